"""The crowd models' cost per call, compiled (numba) against torch, in CPU time (one thread): robust to
other processes sharing the machine, unlike wall-clock env-steps/s (benchmarks/bench_crowd.py).

States: CrowdNav circle crossing, B worlds of M humans (M <= 20: CrowdNav test cases; 50: an even ring,
as bench_crowd.py) after ``--warm`` steps of the torch model, robot visible and standing at its start.
Per model and backend: the minimum CPU time of one call of the velocity function over ``--reps`` calls
(the two backends alternating), as ms per call and as env-steps per CPU-second (B / time). The load average is printed beside each row.

    python benchmarks/bench_kernels.py [--batch 1024] [--n-humans 20,50] [--reps 10]
"""

from __future__ import annotations

import argparse
import os
import time

import torch
from bench_crowd import episode_pool

from crowdbench.envs.crowdnav import CrowdNavConfig
from crowdbench.envs.factory import crowdnav_world


def crowd_state(model: str, n_humans: int, batch: int, warm: int):
    """A world whose crowd has walked ``warm`` steps (torch backends) from CrowdNav-like starts."""
    pool, _, _ = episode_pool(n_humans, 32, 20)
    cfg = CrowdNavConfig(humans=model, n_humans=n_humans, robot_visible=True, orca_backend="torch",
                         sfm_backend="torch")
    world, _ = crowdnav_world(cfg, batch)
    idx = torch.arange(batch) % len(pool["start"])
    world.reset(torch.ones(batch, dtype=torch.bool), {k: v[idx] for k, v in pool.items()})
    for _ in range(warm):
        world.step(torch.zeros(batch, 1, 2))
    return world


def _use(world, model: str, backend: str) -> None:
    crowd = world.crowd
    if model == "orca":
        crowd.params = type(crowd.params)(**{**crowd.params.__dict__, "backend": backend})
    else:
        crowd.backend = backend


def cpu_per_call(world, model: str, reps: int) -> dict[str, float]:
    """Minimum CPU time of one call per backend, the backends alternating call by call (so that a change
    of the machine's load hits both alike)."""
    best = {"numba": float("inf"), "torch": float("inf")}
    agents = world.agents()  # the crowd's whole view of the world, outside the timed calls
    for backend in best:  # compile / load the cache, warm up
        _use(world, model, backend)
        world.crowd.velocities(agents)
    for _ in range(reps):
        for backend in ("numba", "torch"):
            _use(world, model, backend)
            t = time.process_time()
            world.crowd.velocities(agents)
            best[backend] = min(best[backend], time.process_time() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--n-humans", default="20,50")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--warm", type=int, default=8, help="steps walked before timing")
    ap.add_argument("--models", default="orca,sfm")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"B = {args.batch}, 1 thread, CPU time per call (min of {args.reps}); load average "
          f"{os.getloadavg()[0]:.2f} at the start")
    print("| model | humans | backend | ms per call (CPU) | env-steps per CPU-second | vs torch | load |")
    print("|---|---|---|---|---|---|---|")
    for model in args.models.split(","):
        for n in (int(x) for x in args.n_humans.split(",")):
            world = crowd_state(model, n, args.batch, args.warm)
            t = cpu_per_call(world, model, args.reps)
            for be in ("numba", "torch"):
                print(f"| {model} | {n} | {be} | {t[be] * 1e3:.1f} | {args.batch / t[be]:,.0f} | "
                      f"{t['torch'] / t[be]:.2f}x | {os.getloadavg()[0]:.1f} |", flush=True)


if __name__ == "__main__":
    main()
