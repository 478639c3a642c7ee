"""Training speed: actor latency, one TD3 update per encoder preset, and the whole training loop.

    python benchmarks/bench_train.py                      # all sections, 2 threads
    python benchmarks/bench_train.py --sections loop --loop-frames 4096
    python benchmarks/bench_train.py --sections loop --overrides "algo.critic_lookahead=1.0"

- ``latency`` and ``td3``: the sections of ``bench_models.py`` (actor decision at B = 1 on a
  crowded students001 observation; one TD3 update at batch 100 for every encoder preset).
- ``update``: one gradient update exactly as ``crowdbench run`` makes it (``OffPolicyAlgorithm.update``
  on a batch of 100 sampled from a PER buffer of real students001 transitions, then the
  priority write-back), per encoder preset, with the paper's critic and with the leaderboard
  recipe's lookahead critic; TD3 updates the actor every 2nd step, so the mean over 2 steps is
  the cost per update, and the full step (critics + actor + targets) is printed beside it.
- ``loop``: ``crowdbench.algos.train.train`` exactly as ``crowdbench run`` calls it (TD3,
  16 envs, PER, utd 0.5), timed after the warm-up from its own log: env-steps/s and
  updates/s of collection + updates together, for each fast encoder preset.

Timings on a shared machine are noisy: the load average is printed with the figures.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def read_scalar(run: Path, name: str) -> list[tuple[int, float]]:
    rows = csv.reader((run / "logs" / "scalars" / f"{name}.csv").read_text().splitlines())
    return [(int(float(r[0])), float(r[1])) for r in rows if r]


def loop_section(frames: int, encoders: list[str], threads: int, overrides: list[str] = ()) -> None:
    from crowdbench.algos.train import train
    from crowdbench.cli import compose

    print(f"\n## whole training loop (TD3, 16 envs, utd 0.5, PER), {frames} frames after a 2,000-frame warm-up"
          + (f"; {' '.join(overrides)}" if overrides else ""))
    print(f"  {'encoder':16s}{'env-steps/s':>14s}{'updates/s':>12s}{'ms/update':>12s}{'load avg':>10s}")
    for enc in encoders:
        with tempfile.TemporaryDirectory() as tmp:
            cfg = compose([f"encoder={enc}", f"train.total_frames={2048 + frames}", "train.probe_every=100000000",
                           "train.checkpoint_every=100000000", *overrides])
            torch.set_num_threads(threads)
            train(cfg, Path(tmp), progress=False)
            wall = read_scalar(Path(tmp), "wall_time_s")
            upd = read_scalar(Path(tmp), "updates")
            # rows from the first collection that ran updates to the end
            first = next(i for i, (_, u) in enumerate(upd) if u > 0)
            df = wall[-1][0] - wall[first][0]
            dt = wall[-1][1] - wall[first][1]
            du = upd[-1][1] - upd[first][1]
            print(f"  {enc:16s}{df / dt:14.1f}{du / dt:12.1f}{1000 * dt / max(du, 1):12.1f}"
                  f"{os.getloadavg()[0]:10.2f}")


def update_section(encoders: list[str], reps: int, overrides: list[str] = ()) -> None:
    import bench_models as bm
    from torchrl.collectors import Collector

    from crowdbench.algos.multiagent import agent_transitions
    from crowdbench.algos.offpolicy import KEEP
    from crowdbench.algos.registry import component
    from crowdbench.cli import compose
    from crowdbench.envs.factory import make_env

    print("\n## one training update as `crowdbench run` makes it, batch 100 from a PER buffer of 4,096 students001"
          " transitions (ms) — target <= 30 ms for gatedgcn (D=32)"
          + (f"; {' '.join(overrides)}" if overrides else ""))
    print(f"  {'encoder':16s}{'critic':>8s}{'per update (d=2)':>18s}{'critic-only':>13s}{'full step':>11s}")
    for enc in encoders:
        for lookahead in (0.0, 0.25):
            cfg = compose([f"encoder={enc}", f"algo.critic_lookahead={lookahead}", *overrides])
            torch.manual_seed(0)
            env = make_env(cfg)
            learner = component(cfg.algo.name)(cfg, env.n_agents)
            rb, policy = learner.rb, learner.collection_policy()
            for batch in Collector(env, policy, frames_per_batch=1024, total_frames=4096,
                                   auto_register_policy_transforms=False):
                rb.extend(agent_transitions(batch, KEEP))

            def step(n: int, learner=learner, rb=rb):
                """Update ``n``: critic-only unless ``n`` is a multiple of policy_delay (then actor + targets too)."""
                sample = rb.sample()
                learner.update(sample, n)
                rb.update_tensordict_priority(sample)

            tc, tf = bm.bench(lambda: step(1), reps), bm.bench(lambda: step(0), reps)
            label = "lookahead" if lookahead else "paper"
            print(f"  {enc:16s}{label:>8s}{(tc + tf) / 2:18.2f}{tc:13.2f}{tf:11.2f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--sections", default="latency,td3,update,loop")
    ap.add_argument("--loop-frames", type=int, default=4096)
    ap.add_argument("--encoders", default="gatedgcn,gcn,mlp")
    ap.add_argument("--overrides", default="", help="extra training overrides for the loop, e.g. "
                    "'algo.critic_lookahead=1.0 algo.n_steps=5'")
    args = ap.parse_args(argv)
    import bench_models as bm

    from crowdbench.models.perf import tune_allocator

    torch.set_num_threads(args.threads)
    tune_allocator()
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, load average {os.getloadavg()[0]:.2f}")
    sections = args.sections.split(",")
    if "latency" in sections:
        bm.latency_section(args.reps)
    if "td3" in sections:
        o, a, info, o2 = bm.transition("students001", 100)
        bm.td3_section(o, a, info, o2, args.reps, quick=False)
    if "update" in sections:
        update_section(args.encoders.split(","), args.reps, args.overrides.split())
    if "loop" in sections:
        loop_section(args.loop_frames, args.encoders.split(","), args.threads, args.overrides.split())


if __name__ == "__main__":
    main()
