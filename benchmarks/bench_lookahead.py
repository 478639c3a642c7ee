"""The value lookahead's candidates (``crowdbench.envs.lookahead.lookahead_observation``): milliseconds per
call for B CrowdNav circle-crossing environments x 81 actions, one thread, best of 5 repetitions of 50 calls.

Usage: python benchmarks/bench_lookahead.py [--batch 64] [--humans 5,20] [--model query|cv]
"""

from __future__ import annotations

import argparse
import time

import torch

from crowdbench.envs.crowdnav import CrowdNavConfig
from crowdbench.envs.factory import crowdnav_world
from crowdbench.envs.lookahead import MODELS, action_set, lookahead_observation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--humans", default="5,20")
    ap.add_argument("--model", choices=MODELS, default="query")
    args = ap.parse_args()
    torch.set_num_threads(1)
    acts = action_set(1.0)
    for n in (int(x) for x in args.humans.split(",")):
        world, scen = crowdnav_world(CrowdNavConfig(n_humans=n), args.batch)
        world.reset(torch.ones(args.batch, dtype=torch.bool), scen.cases(list(range(args.batch))))
        for _ in range(3):  # the humans moving
            world.step(torch.full((args.batch, 1, 2), 0.3))
        for _ in range(5):
            lookahead_observation(world, acts, args.model)
        best = float("inf")
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(50):
                lookahead_observation(world, acts, args.model)
            best = min(best, (time.perf_counter() - t) / 50 * 1e3)
        print(f"{n} humans, B={args.batch}, K={len(acts)}, {args.model}: {best:.2f} ms per call")


if __name__ == "__main__":
    main()
