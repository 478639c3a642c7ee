"""CrowdNav value-based runs side by side with CrowdNav's Table I: one markdown row per run, one per method.

Usage: python benchmarks/value_rows.py NAME=RUN_DIR[,RUN_DIR...] [NAME=...]

Each RUN_DIR is a finished ``crowdbench run experiment=value_crowdnav ...`` (``results.json`` and
``train_stats.json``). A run row: success, collision, timeout with their 95% intervals (Wilson, 500 cases),
navigation time, training wall time (imitation + deep V-learning, without the final evaluation), RL episodes
and the network kept (``imitation`` or the episode whose validation selected it). A NAME row: the mean over
its runs, the lowest and highest run in brackets, and against the published success (rounded to 2 decimals:
1.00 stands for [0.995, 1]) how many runs' 95% intervals it meets and the pooled interval (all runs' cases).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

# Chen et al. 2019 (CrowdNav, arXiv:1809.08835), Table I: invisible robot, 5 humans, circle crossing,
# 500 test cases; success, collision, navigation time (s)
PUBLISHED = {"cadrl": (0.78, 0.22, 10.80), "lstm_rl": (0.95, 0.03, 11.82), "sarl": (0.99, 0.01, 10.55),
             "lm_sarl": (1.00, 0.00, 10.46)}


def wilson(k: float, n: int, z: float = 1.96) -> tuple[float, float]:
    if n == 0:
        return math.nan, math.nan
    p = k / n
    centre, half = p + z * z / (2 * n), z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (centre - half) / (1 + z * z / n), (centre + half) / (1 + z * z / n)


def load(run: Path) -> dict:
    res = json.loads((run / "results.json").read_text())
    stats = json.loads((run / "train_stats.json").read_text())
    (scene,) = res["scenes"].values()
    rl = stats.get("rl", {})
    kept = rl.get("selected_episode")
    return {"run": run.name, "scene": scene, "n": int(scene["success_rate"]["n"]),
            "lookahead": res.get("lookahead"), "minutes": (stats["wall_time_s"]) / 60,
            "episodes": rl.get("episodes", 0), "kept": "imitation" if kept in (0, None) else f"episode {kept}"}


def fmt(stat: dict, digits: int) -> str:
    lo, hi = stat.get("ci95") or (None, None)
    return f"{stat['mean']:.{digits}f}" + (f" [{lo:.{digits}f}, {hi:.{digits}f}]" if lo is not None else "")


def run_row(r: dict) -> str:
    s = r["scene"]
    return (f"| {r['run']} | {r['lookahead']} | {fmt(s['success_rate'], 3)} | {fmt(s['collision_rate'], 3)} | "
            f"{fmt(s['timeout_rate'], 3)} | {fmt(s['nav_time_s'], 2)} | {r['minutes']:.1f} min, "
            f"{r['episodes']} RL episodes; kept: {r['kept']} |")


def group_row(name: str, runs: list[dict]) -> str:
    def pooled(key: str, digits: int) -> str:
        xs = [r["scene"][key]["mean"] for r in runs]
        return f"{sum(xs) / len(xs):.{digits}f} ({min(xs):.{digits}f}-{max(xs):.{digits}f})"

    method = name.split(":")[0]
    published = PUBLISHED.get(method)
    verdict = "—"
    if published is not None:  # the paper rounds to 2 decimals: 1.00 stands for [0.995, 1]
        p = published[0]
        meets = sum(r["scene"]["success_rate"]["ci95"][0] <= p + 0.005 and p - 0.005 <= r["scene"]["success_rate"]["ci95"][1]
                    for r in runs)
        n = sum(r["n"] for r in runs)
        lo, hi = wilson(sum(r["scene"]["success_rate"]["mean"] * r["n"] for r in runs), n)
        verdict = f"{p:.2f}: within {meets} of {len(runs)} runs' intervals; pooled [{lo:.3f}, {hi:.3f}]"
    return (f"| **{name}** ({len(runs)} runs) | | {pooled('success_rate', 3)} | {pooled('collision_rate', 3)} | "
            f"{pooled('timeout_rate', 3)} | {pooled('nav_time_s', 2)} | published success {verdict} |")


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__)
        return 2
    print("| run | lookahead | success | collision | timeout | nav time s | training |")
    print("|---|---|---|---|---|---|---|")
    for arg in argv:
        name, _, dirs = arg.partition("=")
        runs = [load(Path(d)) for d in dirs.split(",") if (Path(d) / "results.json").is_file()]
        if not runs:
            continue
        for r in runs:
            print(run_row(r))
        print(group_row(name, runs))
    print("\nPublished (CrowdNav Table I): " + "; ".join(
        f"{m} {s:.2f} / {c:.2f} / {t:.2f} s" for m, (s, c, t) in PUBLISHED.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
