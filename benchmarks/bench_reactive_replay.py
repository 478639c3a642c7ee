"""Reactive replay throughput (protocol v2's world): env-steps/s on an ETH/UCY scene, recorded humans
as recorded (v1), or yielding to the robot through ORCA or social force (v2).

    python benchmarks/bench_reactive_replay.py                     # students001, B = 1024, 1 and 2 threads
    python benchmarks/bench_reactive_replay.py --batch 64 --seconds 0.5 --threads 1   # quick

An env-step advances one environment by one step. "world" = ``observe`` + ``step`` + partial reset of
the finished environments by mask (the training distribution of episodes); "CrowdEnv" = the TorchRL
env through ``step_and_maybe_reset``. The robot drives straight to its goal (``--robot random``:
uniform in the speed disc), so it meets the humans and the reactive models have work to do.
"""

from __future__ import annotations

import argparse
import math
import os

import torch
from bench_crowd import timed  # (run as a script: benchmarks/ is on the path)

from crowdbench.envs.factory import replay_world
from crowdbench.envs.humans.reactive_replay import ReactiveParams
from crowdbench.envs.rules import RUNNING, SimConfig
from crowdbench.envs.torchrl_env import CrowdEnv


def robot_action(kind: str, world, gen: torch.Generator) -> torch.Tensor:
    """``[B, 1, 2]`` world-frame velocities: towards the goal at v_max, or uniform in the speed disc."""
    v_max = world.cfg.v_max
    if kind == "straight":
        d = world.goal - world.pos
        return d * (v_max / d.norm(dim=-1, keepdim=True).clamp_min(1e-9))
    r = v_max * torch.rand(world.B, 1, 1, generator=gen).sqrt()
    a = 2 * math.pi * torch.rand(world.B, 1, 1, generator=gen)
    return torch.cat((r * a.cos(), r * a.sin()), -1)


def world_rate(scene: str, batch: int, humans: str, seconds: float, robot: str) -> float:
    reactive = None if humans == "replay" else ReactiveParams(model=humans)
    world, scenario = replay_world(scene, batch, SimConfig(), reactive)
    draw = scenario.sampler(0)
    world.reset(torch.ones(batch, dtype=torch.bool), draw(batch))
    gen = torch.Generator().manual_seed(0)

    def step():
        world.observe()
        world.step(robot_action(robot, world, gen), frame="world")
        done = (world.outcome != RUNNING).any(-1)
        if done.any():
            world.reset(done, draw(int(done.sum())))

    n, dt = timed(step, seconds)
    return n * batch / dt


def env_rate(scene: str, batch: int, humans: str, seconds: float, robot: str) -> float:
    reactive = None if humans == "replay" else ReactiveParams(model=humans)
    world, scenario = replay_world(scene, batch, SimConfig(frame="world"), reactive)
    env = CrowdEnv(world, scenario, seed=0)
    gen = torch.Generator().manual_seed(0)
    state = {"td": env.reset()}

    def step():
        td = state["td"]
        td["agents", "action"] = robot_action(robot, world, gen)
        _, state["td"] = env.step_and_maybe_reset(td)

    n, dt = timed(step, seconds)
    return n * batch / dt


def ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="students001")
    ap.add_argument("--humans", default="replay,orca,sfm", help="replay (v1) and/or the reactive models")
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--threads", type=ints, default=[1, 2])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--robot", choices=("straight", "random"), default="straight")
    ap.add_argument("--paths", default="world,env")
    args = ap.parse_args(argv)
    load = os.getloadavg()
    print(f"torch {torch.__version__}, cores {os.cpu_count()}, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
          f"scene {args.scene}, robot {args.robot}, timed {args.seconds} s per figure")
    fns = {"world": world_rate, "env": env_rate}
    names = {"world": "world (observe + step + masked reset)", "env": "TorchRL CrowdEnv (step_and_maybe_reset)"}
    print("\n| humans | path | threads | B | env-steps/s | us per env-step |")
    print("|---|---|---|---|---|---|")
    for h in args.humans.split(","):
        for p in args.paths.split(","):
            for t in args.threads:
                torch.set_num_threads(t)
                r = fns[p](args.scene, args.batch, h, args.seconds, args.robot)
                label = "recorded (v1)" if h == "replay" else f"reactive {h} (v2)"
                print(f"| {label} | {names[p]} | {t} | {args.batch} | {r:,.0f} | {1e6 / r:.1f} |", flush=True)
    load = os.getloadavg()
    print(f"\nload average at the end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
