"""The self-play tracks side by side, read from the committed leaderboard.

Usage: python benchmarks/selfplay_table.py [--write docs/selfplay.md]

Reads the ranked self-play tables of ``leaderboard/TRACKS.md`` (written by ``crowdbench leaderboard``: means
over the seeds with their two-level bootstrap intervals) and prints one row per track: ORCA's success and
agent-agent dangers per agent, then the same for every entry trained in self-play, and the best learned
success minus ORCA's. ``--write`` replaces the generated block ``selfplay-tracks`` of the given file (the
leaderboard's markers, ``<!-- generated:NAME:start -->`` / ``<!-- generated:NAME:end -->``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from table_i import replace_block, success, track_rows

from crowdbench.protocols.selfplay_tracks import SETTINGS, track_name

ROOT = Path(__file__).resolve().parent.parent


def learned(rows: dict) -> list[str]:
    """The labels of the entries trained in self-play, in the table's order (ranked)."""
    return [label for label, r in rows.items() if r["trained on"] == "selfplay"]


PREFIX = "MP-GatedGCN-RL self-play ("


def short(label: str) -> str:
    """``MP-GatedGCN-RL self-play (TD3, ORCA warm start)`` -> ``TD3, ORCA warm start``."""
    return label.removeprefix(PREFIX).removesuffix(")") if label.startswith(PREFIX) else label


def orcas(rows: dict) -> list[str]:
    """The ORCA baselines: the protocol's ``ORCA`` first, then its variants (``ORCA (margin 0.3 m, ...)``)."""
    return ["ORCA", *sorted(label for label in rows if label.startswith("ORCA ("))]


def selfplay_table(text: str) -> list[str]:
    tables = {s: track_rows(text, track_name(s)) for s, _ in SETTINGS}
    labels = sorted({label for rows in tables.values() for label in learned(rows)})
    bases = sorted({b for rows in tables.values() for b in orcas(rows)}, key=lambda b: (b != "ORCA", b))
    head = ["track", *(f"success: {b}" for b in bases), *(f"success: {short(label)}" for label in labels),
            *(f"best learned minus {b}" for b in bases),
            *(f"dangers: {b}" for b in bases), *(f"dangers: {short(label)}" for label in labels)]
    caption = ("Success per agent and agent-agent danger steps per agent; learned: MP-GatedGCN-RL self-play, "
               "the mean over seeds [95% interval].")
    out = [caption, "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for setting, _ in SETTINGS:
        rows = tables[setting]
        base = [rows.get(b) for b in bases]
        got = [rows.get(label) for label in labels]
        best = max((success(r) for r in got if r), default=None)
        diffs = [f"{best - success(r):+.3f}" if best is not None and r else "—" for r in base]
        cells = [f"`{track_name(setting)}`", *(r["success"] if r else "—" for r in base),
                 *(f"{r['success']}, {r['seeds']} seed{'s' * (r['seeds'] != '1')}" if r else "—" for r in got), *diffs,
                 *(r["agent dangers"] if r else "—" for r in base), *(r["agent dangers"] if r else "—" for r in got)]
        out.append("| " + " | ".join(cells) + " |")
    return out


def main(argv: list[str]) -> None:
    lines = selfplay_table((ROOT / "leaderboard" / "TRACKS.md").read_text())
    if argv[:1] == ["--write"] and len(argv) == 2:
        path = Path(argv[1])
        path.write_text(replace_block(path.read_text(), "selfplay-tracks", lines))
        print(f"wrote selfplay-tracks into {path}")
    elif argv:
        raise SystemExit(__doc__)
    else:
        print("\n".join(lines))


if __name__ == "__main__":
    main(sys.argv[1:])
