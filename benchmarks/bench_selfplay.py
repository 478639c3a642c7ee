"""Self-play throughput: env-steps/s (and agent-steps/s) at n = 8 and 32 agents, B = 256.

Usage: python benchmarks/bench_selfplay.py [--threads 2] [--seconds 3] [--batch 256]
       python benchmarks/bench_selfplay.py --scale [--batch 64]   # 32, 64, 128 agents, every slot vs 16 nearest

``--scale``: each configuration in its own process, reporting env-steps/s of the TorchRL env with the shared
gatedgcn actor and the process's peak resident memory; circle crossing on a circle of radius n / 8 m (the
agents must fit), ``env.obs_slots`` = 0 (every agent and human is a slot: the view grows as n^2) or 16 (the
16 nearest bodies: linear in n).

An env-step advances one environment (all its n agents) by one step; agent-steps = env-steps x n.
Every figure includes one ``observe`` per ``step`` (each agent's view of the other agents and
the background); "TorchRL" is the self-play :class:`CrowdEnv` (``selfplay_env``) through ``step_and_maybe_reset`` (partial
resets included); "+ actor" adds the shared-weight MP-GatedGCN (D = 32) deciding for every agent.
"""

from __future__ import annotations

import argparse
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


def torchrl_rate(cfg: SelfPlayConfig, batch: int, seconds: float, actor=None) -> float:
    env = selfplay_env(batch, cfg, seed=0)
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


def one_scale(n: int, slots: int, batch: int, seconds: float) -> None:
    cfg = SelfPlayConfig(n_agents=n, circle_radius=max(4.0, n / 8), obs_slots=slots)
    r = torchrl_rate(cfg, batch, seconds, gatedgcn())
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"| {n} | {slots or 'all (' + str(n - 1) + ')'} | {r:,.0f} | {r * n:,.0f} | {rss:,.0f} |", flush=True)


def scale(args) -> None:
    print(f"torch {torch.__version__}, threads {args.threads}, B = {args.batch}, circle crossing, TorchRL env + "
          "shared gatedgcn (D=32) actor")
    print("| n agents | slots per agent | env-steps/s | agent-steps/s | peak RSS (MB) |")
    print("|---|---|---|---|---|")
    for n in (32, 64, 128):
        for slots in (0, 16):
            subprocess.run([sys.executable, __file__, "--one", f"{n},{slots}", "--batch", str(args.batch),
                            "--threads", str(args.threads), "--seconds", str(args.seconds)], check=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--scale", action="store_true")
    ap.add_argument("--one", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.one:
        n, slots = map(int, args.one.split(","))
        return one_scale(n, slots, args.batch, args.seconds)
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
