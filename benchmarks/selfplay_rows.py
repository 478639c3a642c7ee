"""Self-play results side by side: one markdown row per policy and setting, seeds pooled.

Usage: python benchmarks/selfplay_rows.py NAME=RUN_DIR[,RUN_DIR...] [NAME=...]

Each RUN_DIR holds the ``results.json`` of ``crowdbench run env=selfplay`` or ``crowdbench eval env=selfplay``
(the ``selfplay-v1`` episode set). With several runs (seeds) a cell is the mean over them and, in brackets,
the lowest and highest seed; with one run, its 95% interval. ``dangers`` is agent-agent danger steps per
agent (0 <= clearance < 0.2 m), ``all arrived`` the share of episodes in which every agent arrived.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

COLS = (("success", "success_rate", 3), ("collision", "collision_rate", 3), ("timeout", "timeout_rate", 3),
        ("nav time s", "nav_time_s", 2), ("dangers / agent", "agent_dangers_per_agent", 3),
        ("all arrived", ("episode", "all_arrived_rate"), 3))


def _value(setting: dict, key) -> dict | None:
    if isinstance(key, tuple):
        return setting.get(key[0], {}).get(key[1])
    return setting.get(key)


def cell(runs: list[dict], name: str, key, digits: int) -> str:
    stats = [_value(r["settings"][name], key) for r in runs if name in r["settings"]]
    means = [s["mean"] for s in stats if s and s.get("mean") is not None]
    if not means:
        return "—"
    mean = sum(means) / len(means)
    if len(runs) == 1:
        lo, hi = stats[0].get("ci95") or (None, None)
        return f"{mean:.{digits}f}" + (f" [{lo:.{digits}f}, {hi:.{digits}f}]" if lo is not None else "")
    return f"{mean:.{digits}f} ({min(means):.{digits}f}-{max(means):.{digits}f})"


def table(groups: dict[str, list[dict]]) -> str:
    settings = sorted({s for runs in groups.values() for r in runs for s in r["settings"]},
                      key=lambda s: (s.split("_n")[0], int(s.split("_n")[1])))
    lines = ["| policy | seeds | setting | " + " | ".join(c[0] for c in COLS) + " |",
             "|---|---|---|" + "---|" * len(COLS)]
    for setting in settings:
        for name, runs in groups.items():
            cells = [cell(runs, setting, key, d) for _, key, d in COLS]
            lines.append(f"| {name} | {len(runs)} | {setting} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    if not argv or any("=" not in a for a in argv):
        print(__doc__.strip().splitlines()[2], file=sys.stderr)
        return 2
    groups = {}
    for arg in argv:
        name, dirs = arg.split("=", 1)
        groups[name] = [json.loads((Path(d) / "results.json").read_text()) for d in dirs.split(",")]
    print(table(groups))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
