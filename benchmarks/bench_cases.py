"""Case generation: milliseconds per case.

CrowdNav's test cases: the compiled rejection sampler (crowdnav_case) against the one-candidate loop
transcribed from CrowdNav (reference_case), on the same cases (0 .. cases-1; the compiled sampler also over
all 500, whose mean is what a track's list costs; wall and CPU time, the latter steadier when other
processes share the machine). Self-play placements (torch, vectorised over episodes):
ms per episode when drawn in batches of ``--batch``. The load average is printed with the figures.

    python benchmarks/bench_cases.py [--cases 100] [--batch 256]
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from crowdbench.envs.crowdnav_cases import crowdnav_case, reference_case
from crowdbench.envs.selfplay import SelfPlayConfig, SelfPlayScenario

SETTINGS = [("circle", 5), ("circle", 20), ("square", 5), ("square", 20)]


def ms_per_case(fn, scenario: str, n: int, cases: int, clock=time.perf_counter) -> float:
    t = clock()
    for c in range(cases):
        fn(c, scenario, n)
    return (clock() - t) / cases * 1e3


def ms_per_selfplay_episode(scenario: str, n_humans: int, batch: int, reps: int) -> float:
    scen = SelfPlayScenario(SelfPlayConfig(n_agents=1, n_humans=n_humans, scenario=scenario, circle_radius=6.0,
                                           square_width=12.0))
    gen = torch.Generator().manual_seed(0)
    scen.draw(batch, gen)
    t = time.perf_counter()
    for _ in range(reps):
        scen.draw(batch, gen)
    return (time.perf_counter() - t) / (reps * batch) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=100, help="test cases per setting for the side-by-side columns")
    ap.add_argument("--batch", type=int, default=256, help="self-play episodes drawn per call")
    args = ap.parse_args()
    torch.set_num_threads(1)
    crowdnav_case(0, "circle", 5)  # compile (or load numba's cache) before timing
    crowdnav_case(0, "square", 5)
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    print(f"| setting | crowdnav_case ms/case (cases 0-{args.cases - 1}) | all 500 | all 500, CPU ms | "
          "reference_case ms/case | ratio |")
    print("|---|---|---|---|---|---|")
    for scenario, n in SETTINGS:
        fast = ms_per_case(crowdnav_case, scenario, n, args.cases)
        all500 = ms_per_case(crowdnav_case, scenario, n, 500)
        cpu500 = ms_per_case(crowdnav_case, scenario, n, 500, time.process_time)
        ref = ms_per_case(reference_case, scenario, n, args.cases)
        print(f"| {scenario}_n{n} | {fast:.3f} | {all500:.3f} | {cpu500:.3f} | {ref:.2f} | {ref / fast:.0f}x |")
    print(f"\nself-play placements (1 agent + n humans, batches of {args.batch}), ms per episode:")
    print("| scenario | n_humans | ms/episode |\n|---|---|---|")
    for scenario in ("circle", "square"):
        for n in (5, 20):
            print(f"| {scenario} | {n} | {ms_per_selfplay_episode(scenario, n, args.batch, 10):.4f} |")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
