"""Time to result: wall time until the held-out probe first reaches a target success, per recipe and seed.

    python benchmarks/time_to_success.py                                  # every recipe, seeds 0 1 2
    python benchmarks/time_to_success.py --recipes td3 ppo --seeds 0 --minutes 10
    python benchmarks/time_to_success.py --plot docs/img/time_to_success.png --summary runs/tts/summary.json
    python benchmarks/time_to_success.py --load runs/tts/summary*.json --plot docs/img/time_to_success.png

Each run trains with ``crowdbench.algos.train.train`` exactly as ``crowdbench run`` does, with ``cpus``
threads, for at most ``--minutes`` of training wall time. Every ``--probe-every`` frames the held-out
probe evaluates the current actor on all four paper scenes (``--episodes`` protocol episodes each,
deterministic actions) and records their average success. The probe's own time is subtracted from the
wall time (it is the measurement, not training); an imitation warm start's is counted. Reported per run:
the training time at which the average first reached ``--target`` (or "not reached"), and the final
probe's average success.

Runs execute one after the other, so a run has the machine to itself only if nothing else runs:
the load average is recorded with each run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

# overrides and frames between probes (PPO collects ~10x more frames per minute than TD3)
RECIPES = {
    # the default recipe (crowdbench run algo=td3 encoder=gatedgcn): the ORCA warm start, 28,672 frames; the
    # recipes below, measured when sigma 0.3 was the default, pin the exploration sigma they were measured with (0.3)
    "td3": ([], 3584),
    # RL from scratch, the default recipe before the warm start (143,360 frames)
    "td3_scratch": (["train=scratch", "algo.exploration_sigma=0.3"], 7168),
    "sac": (["train=scratch", "method=gatedgcn_sac"], 7168),
    "ppo": (["experiment=ppo"], 40960),
    # PPO's recipe ends its 409,600 frames in ~3 minutes on 2 idle cores: the same, held to the wall-time budget
    "ppo_long": (["experiment=ppo", "train.total_frames=4096000"], 204800),
    # the ORCA warm start with its cloning term held over the first 10,000 updates
    "td3_orca": (["train=scratch", "train.pretrain=orca", "train.pretrain_bc_weight=1", "train.pretrain_bc_updates=10000",
                  "algo.exploration_sigma=0.3"],
                 7168),
    # RGL with its bounded similarity at the from-scratch recipe (experiment=leaderboard_scratch: 28,672 frames;
    # 0.935 ± 0.013 on v1)
    "rgl": (["experiment=baselines", "method=rgl_td3", "algo.exploration_sigma=0.3"], 3584),
    # the same with the ORCA warm start and cloning term of td3_orca: the named experiment
    "rgl_orca": (["experiment=warmstart", "algo.exploration_sigma=0.3"], 3584),
    # the card's command, crowdbench run algo=td3 encoder=gatedgcn: the default config (a residual on ORCA)
    "default": ([], 3584),
    # MP-GatedGCN with the same warm start at the from-scratch recipe (experiment=leaderboard_scratch: prioritized
    # replay, 28,672 frames); with algo.replay=uniform it is the default recipe's training config
    "gatedgcn_orca": (["experiment=warmstart", "method=gatedgcn_td3", "algo.exploration_sigma=0.3"], 3584),
}


def probe_all(cfg, scenes, episodes: int, spent: list[float]):
    from crowdbench.algos.checkpoint import LearnedPolicy
    from crowdbench.envs.rules import SimConfig
    from crowdbench.protocols.replay import evaluate

    def probe(actor) -> dict[str, float]:
        t = time.perf_counter()
        res = evaluate(LearnedPolicy(actor, frame=cfg.env.frame), list(scenes), episodes,
                       sim_overrides=SimConfig.fields_of(cfg.env))
        avg = sum(res["scenes"][s]["success_rate"]["mean"] for s in scenes) / len(scenes)
        spent.append(time.perf_counter() - t)
        # the loop's train.max_minutes counts wall time: give it back what the probe took
        cfg.train.max_minutes = float(cfg.train.max_minutes) + spent[-1] / 60
        return {"probe_paper_success": avg}

    return probe


def timed_warm_start(train_module, cfg) -> list[float]:
    """Count the imitation warm start as training time: the loop's ``wall_time_s`` starts after it, so
    its duration is taken off the run's ``train.max_minutes`` and added to every probe's time. (A wrapper
    rather than a flag of ``train``: the loop's own clock is the resumable RL time, which a warm start
    that never repeats on resume does not belong to.)"""
    took = [0.0]
    inner = train_module.warm_start

    def warm_start(*a, **kw):
        t = time.perf_counter()
        logs = inner(*a, **kw)
        took[0] = time.perf_counter() - t
        cfg.train.max_minutes = float(cfg.train.max_minutes) - took[0] / 60
        return logs

    warm_start.__wrapped__ = inner
    train_module.warm_start = warm_start
    return took


def one_run(recipe: str, seed: int, args) -> dict:
    import torch

    from crowdbench.algos import train as train_module
    from crowdbench.algos.checkpoint import load_checkpoint, policy_from_checkpoint
    from crowdbench.algos.train import train
    from crowdbench.cli import compose
    from crowdbench.envs.protocol import PAPER_SCENES

    recipe_overrides, probe_every = RECIPES[recipe]
    overrides = [*recipe_overrides, f"seed={seed}", f"cpus={args.cpus}",
                 f"train.probe_every={args.probe_every or probe_every}",
                 f"train.max_minutes={args.minutes}", "train.save_buffer=false", *args.overrides]
    cfg = compose(overrides)
    torch.set_num_threads(cfg.cpus)
    spent: list[float] = []
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep / f"{recipe}_s{seed}" if args.keep else Path(tmp) / "run"
        cfg.train.max_minutes = float(args.minutes)  # raised by each probe's duration (probe_all)
        probe = probe_all(cfg, PAPER_SCENES, args.episodes, spent)
        pretrain_s = timed_warm_start(train_module, cfg)
        try:
            stats = train(cfg, out, progress=False, probe=probe)
        finally:
            train_module.warm_start = train_module.warm_start.__wrapped__
        rows = [line.split(",") for line in (out / "logs" / "scalars" / "probe_paper_success.csv").read_text().split()]
        walls = dict(line.split(",") for line in (out / "logs" / "scalars" / "wall_time_s.csv").read_text().split())
        state = load_checkpoint(out / "checkpoint.pt")
        if int(rows[-1][0]) != stats["frames"]:  # the budget ended between probes: probe the final actor
            rows.append([str(stats["frames"]), str(probe(policy_from_checkpoint(out / "checkpoint.pt").actor)
                                                   ["probe_paper_success"])])
            walls[str(stats["frames"])] = str(state["wall_time_s"])
    curve, budget = [], 60 * args.minutes
    for i, (frames, success) in enumerate(rows):
        # the loop reads the wall time before it probes: subtract the probes before this one
        train_s = float(walls[frames]) - sum(spent[:i]) + pretrain_s[0]
        if train_s > budget + 30 and curve:  # past the budget (a run stops at the first batch after it)
            break
        curve.append((int(float(frames)), train_s, float(success)))
    return {"recipe": recipe, "seed": seed, "overrides": overrides, "curve": curve,
            "time_to_target_s": time_to_target(curve, args.target),
            "final_success": curve[-1][2] if curve else None, "probe_s": sum(spent), "pretrain_s": pretrain_s[0],
            "load_avg_start": load0, "load_avg_end": os.getloadavg()[0]}


def plot(runs: list[dict], target: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    colours = dict(zip(RECIPES, plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False))
    for r in runs:
        _, t, s = zip(*r["curve"], strict=True) if r["curve"] else ((), (), ())
        ax.plot([x / 60 for x in t], s, color=colours.get(r["recipe"]), alpha=0.8,
                label=r["recipe"] if r["seed"] == min(q["seed"] for q in runs if q["recipe"] == r["recipe"]) else None)
    ax.axhline(target, color="grey", ls="--", lw=1)
    ax.set_xlabel("training wall time (min, probes excluded)")
    ax.set_ylabel("average success, 4 paper scenes")
    ax.set_ylim(0, 1)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def time_to_target(curve: list, target: float) -> float | None:
    """Training seconds at the first probe whose success reaches ``target``; None if none does."""
    return next((t for _, t, success in curve if success >= target), None)


def report(r: dict, target: float) -> str:
    t = r["time_to_target_s"]
    return (f"{r['recipe']:10s} seed {r['seed']}: {'%.1f min' % (t / 60) if t is not None else 'not reached':>12s} to "
            f"{target:.2f}; final {r['final_success']:.3f} after {r['curve'][-1][0]:,} frames; "
            f"load {r['load_avg_start']:.2f}/{r['load_avg_end']:.2f}")


def per_recipe(runs: list[dict], target: float) -> list[str]:
    """One line per recipe: seeds reaching the target, their times, the final success's mean and sd."""
    import statistics

    lines = []
    for recipe in dict.fromkeys(r["recipe"] for r in runs):
        rs = [r for r in runs if r["recipe"] == recipe]
        times = sorted(r["time_to_target_s"] / 60 for r in rs if r["time_to_target_s"] is not None)
        finals = [r["final_success"] for r in rs]
        sd = statistics.stdev(finals) if len(finals) > 1 else 0.0
        lines.append(f"{recipe:10s} {len(times)}/{len(rs)} seeds reach {target:.2f}"
                     f"{' (' + ', '.join(f'{t:.1f}' for t in times) + ' min)' if times else ''}; "
                     f"final {statistics.mean(finals):.3f} +- {sd:.3f}")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--minutes", type=float, default=10.0, help="training wall time per run")
    p.add_argument("--probe-every", type=int, default=0, help="frames between probes (default: the recipe's)")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--target", type=float, default=0.90)
    p.add_argument("--cpus", type=int, default=2)
    p.add_argument("--overrides", nargs="*", default=[])
    p.add_argument("--summary", type=Path)
    p.add_argument("--keep", type=Path, help="keep each run's directory here (RECIPE_sSEED/), e.g. to submit it")
    p.add_argument("--plot", type=Path)
    p.add_argument("--load", nargs="+", type=Path, default=[],
                   help="report and plot the runs of earlier --summary files instead of training")
    args = p.parse_args(argv)
    runs = []
    for path in args.load:
        for r in json.loads(path.read_text()):
            # the target may differ from the one the run was reported against
            r["time_to_target_s"] = time_to_target(r["curve"], args.target)
            runs.append(r)
            print(report(r, args.target))
    for recipe in args.recipes if not args.load else []:
        for seed in args.seeds:
            r = one_run(recipe, seed, args)
            runs.append(r)
            print(report(r, args.target), flush=True)
            if args.summary:
                args.summary.parent.mkdir(parents=True, exist_ok=True)
                args.summary.write_text(json.dumps(runs, indent=1) + "\n")
    print("\n".join(per_recipe(runs, args.target)))
    if args.plot:
        plot(runs, args.target, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
