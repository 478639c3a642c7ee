"""Cost of one call of the batched social-force human model (crowdbench/envs/humans/sfm.py):
N = 1024 worlds, M = 5, 20, 50 humans plus one robot (in ``others_*``), float32, at 1 and 2 threads,
eager and wrapped in ``torch.compile(dynamic=False)`` (one compile per shape, timed separately).

    python benchmarks/bench_sfm_model.py [--worlds 1024] [--reps 50] [--no-compile]

Prints ms per call (median of ``reps`` timed calls after warm-up) and world-steps/s. Run it with nothing
else running on the machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from crowdbench.envs.humans.sfm import SFMParams, social_force_velocities


def scene(n: int, m: int, g: torch.Generator):
    pos = torch.rand(n, m, 2, generator=g) * 10 - 5
    vel = torch.randn(n, m, 2, generator=g) * 0.7
    goal = torch.rand(n, m, 2, generator=g) * 10 - 5
    valid = torch.rand(n, m, generator=g) > 0.1
    rob = torch.rand(n, 1, 2, generator=g) * 4 - 2
    rvel = torch.randn(n, 1, 2, generator=g)
    return pos, vel, goal, valid, rob, rvel


def time_call(n: int, m: int, reps: int, fn=social_force_velocities) -> float:
    pos, vel, goal, valid, rob, rvel = scene(n, m, torch.Generator().manual_seed(0))
    params = SFMParams()

    def call():
        return fn(
            pos, vel, goal, valid, 0.3, 1.3, dt=0.25, params=params,
            others_pos=rob, others_vel=rvel, others_radius=0.3,
        )  # fmt: skip

    with torch.inference_mode():
        for _ in range(5):
            call()
        times = []
        for _ in range(reps):
            t = time.perf_counter()
            call()
            times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", type=int, default=1024)
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--no-compile", action="store_true")
    args = ap.parse_args()
    print(f"torch {torch.__version__}, N = {args.worlds} worlds, one robot, float32")
    variants = [("eager", social_force_velocities)]
    if not args.no_compile:
        compiled = torch.compile(social_force_velocities, dynamic=False)
        for m in (5, 20, 50):  # compile outside the timings
            t = time.perf_counter()
            time_call(args.worlds, m, 1, compiled)
            print(f"torch.compile M={m}: {time.perf_counter() - t:.1f} s to compile")
        variants.append(("compiled", compiled))
    for name, fn in variants:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            for m in (5, 20, 50):
                s = time_call(args.worlds, m, args.reps, fn)
                print(
                    f"{name:8s} threads={threads} M={m:3d}: {s * 1e3:7.2f} ms/call"
                    f"  {args.worlds / s:12,.0f} world-steps/s"
                )


if __name__ == "__main__":
    main()
