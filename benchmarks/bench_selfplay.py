"""Self-play throughput: env-steps/s (and agent-steps/s) at n = 8 and 32 agents, B = 256.

Usage: python benchmarks/bench_selfplay.py [--threads 2] [--seconds 3] [--batch 256]

An env-step advances one environment (all its n agents) by one step; agent-steps = env-steps x n.
Every figure includes one ``observe`` per ``step`` (each agent's view of the other agents and
the background); "TorchRL" is the self-play :class:`CrowdEnv` (``selfplay_env``) through ``step_and_maybe_reset`` (partial
resets included); "+ actor" adds the shared-weight MP-GatedGCN (D = 32) deciding for every agent.
"""

from __future__ import annotations

import argparse
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


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--batch", type=int, default=256)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    B = args.batch
    actor = build_actor("td3", {"name": "gatedgcn", "dim": 32, "layers": 2, "k": 8}, 1.0)
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
