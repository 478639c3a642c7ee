"""Episode by episode against a reference: where a row fails that the reference solves, and the reverse.

    python benchmarks/paired_outcomes.py gatedgcn_td3_residual_sigma045_s0 gatedgcn_td3_residual_sigma045_s1
    python benchmarks/paired_outcomes.py ROW... --reference orca --track v1 --scenes hotel eth

Reads the committed harness results (``leaderboard/results/<name>/<track>.json``: each episode's outcome,
S / C / T for success / collision / timeout, in the order of the track's episode lists) of each row and of the
reference, and prints per scene and row: the row's collisions and timeouts, the episodes only the reference
solves (with the row's outcome in them), those only the row solves, those both fail, and the exact two-sided
McNemar p-value of the discordant pairs (are the two success rates different on these same episodes?).
Rows and reference must have been evaluated on the same episodes (their ``episode_ids`` are compared).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "leaderboard" / "results"
PAPER = ("students003", "zara2", "hotel", "eth")


def load(name: str, track: str) -> dict:
    from crowdbench.leaderboard.tracks import TRACKS

    if track not in TRACKS:
        raise SystemExit(f"paired_outcomes: unknown --track {track!r}; valid: {', '.join(TRACKS)}")
    path = ROOT / name / TRACKS[track].results_file
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise SystemExit(f"paired_outcomes: no results for {name!r} on track {track!r}: {path} ({e.strerror})") from None


def mcnemar_p(only_ref: int, only_row: int) -> float:
    """Exact two-sided McNemar test: the discordant pairs are Binomial(n, 1/2) under equal success rates."""
    n, k = only_ref + only_row, min(only_ref, only_row)
    if n == 0:
        return 1.0
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n)


def paired(ref: str, row: str) -> dict:
    """Counts of two equally long outcome strings (S / C / T per episode)."""
    if len(ref) != len(row):
        raise ValueError(f"{len(ref)} reference episodes against {len(row)}")
    only_ref = [b for a, b in zip(ref, row, strict=True) if a == "S" and b != "S"]
    only_row = sum(1 for a, b in zip(ref, row, strict=True) if a != "S" and b == "S")
    both = sum(1 for a, b in zip(ref, row, strict=True) if a != "S" and b != "S")
    return {"collisions": row.count("C"), "timeouts": row.count("T"), "only_reference": "".join(only_ref),
            "only_row": only_row, "both_fail": both, "p": mcnemar_p(len(only_ref), only_row)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rows", nargs="+", help="submission names (e.g. the seeds of one entry)")
    p.add_argument("--reference", default="orca")
    p.add_argument("--track", default="v1")
    p.add_argument("--scenes", nargs="+", default=list(PAPER))
    args = p.parse_args(argv)
    ref = load(args.reference, args.track)
    print(f"| scene | row | collisions | timeouts | only {args.reference} solves (the row's outcome) | only the row "
          f"solves | both fail | McNemar p |\n|---|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        r_out = ref["episode_outcomes"][scene]
        print(f"| {scene} | {args.reference} | {r_out.count('C')} | {r_out.count('T')} | | | | |")
        for name in args.rows:
            res = load(name, args.track)
            if res["episode_ids"].get(scene) != ref["episode_ids"].get(scene):
                raise SystemExit(f"paired_outcomes: {name} and {args.reference} were evaluated on other {scene} episodes")
            c = paired(r_out, res["episode_outcomes"][scene])
            shown = c["only_reference"] or "—"
            print(f"| {scene} | {name} | {c['collisions']} | {c['timeouts']} | {len(c['only_reference'])} ({shown}) | "
                  f"{c['only_row']} | {c['both_fail']} | {c['p']:.3g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
