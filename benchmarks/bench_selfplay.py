"""Self-play throughput: env-steps/s (and agent-steps/s) at n = 8 and 32 agents, B = 256.

Usage: python benchmarks/bench_selfplay.py [--threads 2] [--seconds 3] [--batch 256]
       python benchmarks/bench_selfplay.py --scale [--batch 64]   # 32-256 agents, every slot vs 16 nearest

``--scale``: each configuration in its own process, reporting env-steps/s of the TorchRL env with the shared
gatedgcn actor, the process's peak resident memory, that peak above the baseline (a process that imports
torch and crowdbench and builds nothing), the rate and peak of the env alone (another process stepping it
with a fixed action, no actor), and the most tensor memory one env step (step and observation, after a
reset) and one decision of the actor for every agent each hold at once (torch.profiler's allocation events,
without the allocator's cached memory); circle crossing on a circle of radius n / 8 m (the agents must fit),
``env.obs_slots`` = 0 (every agent and human is a slot: the view grows as n^2) or 16 (the 16 nearest bodies:
linear in n).

An env-step advances one environment (all its n agents) by one step; agent-steps = env-steps x n.
Every figure includes one ``observe`` per ``step`` (each agent's view of the other agents and
the background); "TorchRL" is the self-play :class:`CrowdEnv` (``selfplay_env``) through ``step_and_maybe_reset`` (partial
resets included); "+ actor" adds the shared-weight MP-GatedGCN (D = 32) deciding for every agent.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import torch

from crowdbench.algos.actors import build_actor
from crowdbench.envs.factory import selfplay_env, selfplay_world
from crowdbench.envs.selfplay import SelfPlayConfig


def timed(fn, seconds: float) -> tuple[int, float]:
    for _ in range(3):
        fn()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        fn()
        n += 1
    return n, time.perf_counter() - t0


def core_rate(cfg: SelfPlayConfig, batch: int, seconds: float) -> float:
    world, scenario = selfplay_world(cfg, batch)
    sampler = scenario.sampler(0)
    world.reset(torch.ones(batch, dtype=torch.bool), sampler(batch))
    action = torch.full((batch, cfg.n_agents, 2), 0.7)

    def step():
        world.observe()
        world.step(action)
        done = (world.outcome != 0).all(-1)
        if done.any():
            world.reset(done, sampler(int(done.sum())))

    n, dt = timed(step, seconds)
    return n * batch / dt


def torchrl_rate(cfg: SelfPlayConfig, batch: int, seconds: float, actor=None, env=None) -> float:
    env = env or selfplay_env(batch, cfg, seed=0)
    state = {"td": env.reset()}
    fixed = torch.full((batch, cfg.n_agents, 2), 0.7)

    @torch.no_grad()
    def step():
        td = state["td"]
        if actor is None:
            td["agents", "action"] = fixed
        else:
            actor(td)
        _, state["td"] = env.step_and_maybe_reset(td)

    n, dt = timed(step, seconds)
    return n * batch / dt


def gatedgcn():
    return build_actor("td3", {"name": "gatedgcn", "dim": 32, "layers": 2, "k": 8}, 1.0)


def peak_rss() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MB (Linux reports kB)


def held(fn) -> float:
    """MB: the most tensor memory ``fn()`` allocates and holds at once (torch.profiler's memory events)."""
    from torch.profiler import ProfilerActivity, profile

    err, null = os.dup(2), os.open(os.devnull, os.O_WRONLY)  # kineto logs its start and stop on stderr
    try:
        os.dup2(null, 2)
        with torch.no_grad(), profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
            fn()
    finally:
        os.dup2(err, 2)
        os.close(err), os.close(null)
    events = sorted((e for e in prof.profiler.kineto_results.events() if e.name() == "[memory]"),
                    key=lambda e: e.start_ns())
    live = top = 0
    for e in events:
        live += e.nbytes()
        top = max(top, live)
    return top / 2**20


def one_scale(n: int, slots: int, batch: int, seconds: float, with_actor: bool) -> None:
    """One configuration in this process: its rate, peak RSS and (with the actor) the tensors one env step
    and one decision of the actor hold, as JSON for :func:`scale`."""
    cfg = SelfPlayConfig(n_agents=n, circle_radius=max(4.0, n / 8), obs_slots=slots)
    env, actor = selfplay_env(batch, cfg, seed=0), gatedgcn() if with_actor else None
    out = {"rate": torchrl_rate(cfg, batch, seconds, actor, env), "rss": peak_rss()}
    if actor is not None:
        with torch.no_grad():
            td = env.reset()
            out["actor"] = held(lambda: actor(td))  # (writes the action the step takes into td)
            out["step"] = held(lambda: env.step_and_maybe_reset(td))  # from the state after a reset
    print(json.dumps(out))


def scale(args) -> None:
    def child(*one: str) -> dict:
        cmd = [sys.executable, __file__, "--batch", str(args.batch), "--threads", str(args.threads),
               "--seconds", str(args.seconds), "--one", ",".join(map(str, one))]
        return json.loads(subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True).stdout)

    base = child("base")["rss"]
    print(f"torch {torch.__version__}, threads {args.threads}, B = {args.batch}, circle crossing, "
          f"TorchRL env + shared gatedgcn (D=32) actor; baseline (imports only) {base:,.0f} MB")
    print("| n agents | slots per agent | env-steps/s | agent-steps/s | env alone: env-steps/s "
          "| peak RSS (MB) | above baseline (MB) | env alone: above baseline (MB) | env step tensors (MB) "
          "| actor tensors (MB) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in (32, 64, 128, 256):
        for slots in (0, 16):
            full, alone = child(n, slots, 1), child(n, slots, 0)
            r, rss, view = full["rate"], full["rss"], slots or f"all ({n - 1})"
            print(f"| {n} | {view} | {r:,.0f} | {r * n:,.0f} | {alone['rate']:,.0f} | {rss:,.0f} "
                  f"| {rss - base:,.0f} | {alone['rss'] - base:,.0f} | {full['step']:,.1f} "
                  f"| {full['actor']:,.0f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--scale", action="store_true")
    ap.add_argument("--one", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.one == "base":  # the baseline: imports only
        return print(json.dumps({"rss": peak_rss()}))
    if args.one:
        n, slots, with_actor = map(int, args.one.split(","))
        return one_scale(n, slots, args.batch, args.seconds, bool(with_actor))
    if args.scale:
        return scale(args)
    B = args.batch
    actor = gatedgcn()
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, B = {B}, circle crossing")
    print("| path | n agents | background | env-steps/s | agent-steps/s | ms per step call |")
    print("|---|---|---|---|---|---|")
    for n in (8, 32):
        for bg in ("", "students001"):
            cfg = SelfPlayConfig(n_agents=n, background=bg)
            rows = [("batched core (observe + step)", core_rate(cfg, B, args.seconds)),
                    ("TorchRL CrowdEnv (self-play)", torchrl_rate(cfg, B, args.seconds))]
            if not bg:
                rows.append(("TorchRL + shared gatedgcn (D=32) actor", torchrl_rate(cfg, B, args.seconds, actor)))
            for name, r in rows:
                print(f"| {name} | {n} | {bg or 'none'} | {r:,.0f} | {r * n:,.0f} | {B / r * 1e3:.2f} |")


if __name__ == "__main__":
    main()
