"""CrowdNav case generation: milliseconds per case, block-wise rejection (crowdnav_case) against the
one-candidate loop transcribed from CrowdNav (reference_case), on the same cases.

    python benchmarks/bench_cases.py [--cases 100]
"""

from __future__ import annotations

import argparse
import time

from crowdbench.envs.crowdnav_cases import crowdnav_case, reference_case

SETTINGS = [("circle", 5), ("circle", 20), ("square", 5), ("square", 20)]


def ms_per_case(fn, scenario: str, n: int, cases: int) -> float:
    t = time.perf_counter()
    for c in range(cases):
        fn(c, scenario, n)
    return (time.perf_counter() - t) / cases * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=100, help="test cases per setting")
    args = ap.parse_args()
    print("| setting | crowdnav_case ms/case | reference_case ms/case | ratio |")
    print("|---|---|---|---|")
    for scenario, n in SETTINGS:
        fast = ms_per_case(crowdnav_case, scenario, n, args.cases)
        ref = ms_per_case(reference_case, scenario, n, args.cases)
        print(f"| {scenario}_n{n} | {fast:.2f} | {ref:.2f} | {ref / fast:.1f}x |")


if __name__ == "__main__":
    main()
