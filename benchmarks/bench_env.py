"""Environment throughput: robot env-steps/s of the batched core, the TorchRL env and the PettingZoo view.

Usage: python benchmarks/bench_env.py [--threads 2] [--seconds 3]
Observation building is included in every figure (one ``observe`` per ``step``).
"""

from __future__ import annotations

import argparse
import time

import torch

from crowdbench.data.scenes import Scene, load_scene
from crowdbench.envs.factory import replay_env, replay_parallel_env, replay_world
from crowdbench.envs.protocol import TrainSampler


def timed(fn, seconds: float) -> tuple[int, float]:
    """Call ``fn`` repeatedly for about ``seconds``; return (calls, elapsed)."""
    for _ in range(5):
        fn()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(10):
            fn()
        n += 10
    return n, time.perf_counter() - t0


def core_rate(scene: Scene, batch: int, seconds: float) -> float:
    world, scenario = replay_world(scene, batch)
    sampler = TrainSampler(scenario.last_start, 0)  # (t0, angle) draws, no start check: as before the world API
    world.reset(torch.ones(batch, dtype=torch.bool), scenario.episodes(*sampler(batch)))
    action = torch.full((batch, 1, 2), 0.7)

    def step():
        world.observe()
        world.step(action)
        done = (world.outcome != 0).any(-1)
        if done.any():  # partial reset by mask, as the TorchRL env does
            t0, angle = sampler(batch)  # full-batch draws, masked: the same episode stream as before
            world.reset(done, scenario.episodes(t0[done], angle[done]))

    n, dt = timed(step, seconds)
    return n * batch / dt


def torchrl_rate(batch: int, seconds: float) -> float:
    env = replay_env("students001", batch, seed=0)
    td = env.reset()
    td["agents", "action"] = torch.full((batch, 1, 2), 0.7)
    state = {"td": td}

    def step():
        _, nxt = env.step_and_maybe_reset(state["td"])
        nxt["agents", "action"] = td["agents", "action"]
        state["td"] = nxt

    n, dt = timed(step, seconds)
    return n * batch / dt


def pettingzoo_rate(seconds: float) -> float:
    env = replay_parallel_env("students001")
    env.reset(seed=0)
    act = {"robot_0": torch.tensor([0.7, 0.7]).numpy()}

    def step():
        if not env.agents:
            env.reset()
        env.step(act)

    n, dt = timed(step, seconds)
    return n / dt


def humans_scaling(seconds: float) -> list[tuple[int, float]]:
    """Cost per step vs number of humans: students001 with humans subsampled to M slots."""
    full = load_scene("students001")
    out = []
    for m in (1, 10, 25, 50, 75):
        s = Scene(full.name, full.dt, full.row_period, full.pos[:, :m].contiguous(), full.prev[:, :m].contiguous(),
                  full.vel[:, :m].contiguous(), full.valid[:, :m].contiguous(), full.ped_id[:, :m].contiguous(),
                  full.centre)
        out.append((m, core_rate(s, 1024, seconds)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    scene = load_scene("students001")
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, scene students001 (M = {scene.max_humans})")
    print("| path | B | env-steps/s | ms per step call |")
    print("|---|---|---|---|")
    for b in (1, 64, 1024):
        r = core_rate(scene, b, args.seconds)
        print(f"| batched core (observe + step) | {b} | {r:,.0f} | {b / r * 1e3:.3f} |")
    for b in (1, 1024):
        r = torchrl_rate(b, args.seconds)
        print(f"| TorchRL CrowdEnv (step_and_maybe_reset) | {b} | {r:,.0f} | {b / r * 1e3:.3f} |")
    r = pettingzoo_rate(args.seconds)
    print(f"| PettingZoo CrowdParallelEnv | 1 | {r:,.0f} | {1 / r * 1e3:.3f} |")
    print("\nCost vs humans per env (core, B = 1024):")
    print("| humans M | env-steps/s | us per env-step |")
    print("|---|---|---|")
    for m, r in humans_scaling(args.seconds):
        print(f"| {m} | {r:,.0f} | {1e6 / r:.2f} |")


if __name__ == "__main__":
    main()
