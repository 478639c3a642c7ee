"""CrowdNav's Table I beside the harness's value rows, read from the committed leaderboard.

Usage: python benchmarks/table_i.py [--write docs/value.md]

Reads the ranked tables of ``leaderboard/TRACKS.md`` (written by ``crowdbench leaderboard``: means over the
seeds with their two-level bootstrap intervals) and prints, per value network, the published cells of
CrowdNav's Table I, the ``query`` (privileged) and ``cv`` rows as success / collision / navigation time, and
``query`` minus ``cv``; then the same without published cells for the other CrowdNav tracks. ``--write``
replaces the generated blocks ``table-i`` and ``value-tracks`` of the given file (the leaderboard's markers,
``<!-- generated:NAME:start -->`` / ``<!-- generated:NAME:end -->``).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from value_rows import PUBLISHED

from crowdbench.leaderboard.render import read_block, splice

ROOT = Path(__file__).resolve().parent.parent
# (published key, the entry's label on the leaderboard, the name in the docs' tables)
NETS = [("cadrl", "CADRL", "CADRL"), ("lstm_rl", "LSTM-RL", "LSTM-RL"), ("sarl", "SARL", "SARL"),
        ("lm_sarl", "LM-SARL", "LM-SARL"), ("gatedgcn", "MP-GatedGCN", "MP-GatedGCN as V"), ("rgl", "RGL", "RGL as V")]
CELLS = ("success", "collision", "nav time s")
OTHER_TRACKS = ("crowdnav-square5", "crowdnav-circle20")
NUM = re.compile(r"^(-?[\d.]+) \[(-?[\d.]+), (-?[\d.]+)\]$")


def track_rows(text: str, track: str) -> dict[str, dict[str, str]]:
    """``{method label: {column: cell}}`` of ``track``'s ranked table in TRACKS.md."""
    lines = [ln for ln in read_block(text, f"track-{track}").splitlines() if ln.startswith("|")]
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    return {row["method"]: row for row in
            (dict(zip(head, (c.strip() for c in ln.strip("|").split("|")))) for ln in lines[2:])}


def entry(rows: dict, label: str, look: str) -> dict | None:
    suffix = " (PRIVILEGED)" if look == "query" else ""
    return rows.get(f"{label} (value, {look} lookahead){suffix}")


def cell(row: dict, col: str, published: float | None = None) -> str:
    """The harness's cell; ✗ where ``published`` (2 decimals) lies outside its interval."""
    m = NUM.match(row[col])
    if published is None or m is None:
        return row[col]
    lo, hi = float(m.group(2)), float(m.group(3))
    return row[col] + (" ✗" if published + 0.005 < lo or published - 0.005 > hi else "")


def success(row: dict | None) -> float | None:
    return float(NUM.match(row["success"]).group(1)) if row else None


def table_i(rows: dict) -> list[str]:
    out = ["| method | published (Table I) | `query` (privileged, as published) | seeds | `cv` | seeds | `query` minus `cv` |",
           "|---|---|---|---|---|---|---|"]
    for key, label, name in NETS:
        q, c = entry(rows, label, "query"), entry(rows, label, "cv")
        if q is None and c is None:
            continue
        pub = PUBLISHED.get(key)
        qs = " / ".join(cell(q, col, pub[i] if pub else None) for i, col in enumerate(CELLS)) if q else "—"
        cs = " / ".join(cell(c, col) for col in CELLS) if c else "—"
        diff = f"{success(q) - success(c):+.3f}" if q and c else "—"
        published = " / ".join(f"{v:.2f}" for v in pub) if pub else "—"
        out.append(f"| {name} | {published} | {qs} | "
                   f"{q['seeds'] if q else '—'} | {cs} | {c['seeds'] if c else '—'} | {diff} |")
    return out


def other_tracks(text: str) -> list[str]:
    out = ["| track | method | lookahead | seeds | success | collision | timeout | nav time s | dangers/ep |",
           "|---|---|---|---|---|---|---|---|---|"]
    for track in OTHER_TRACKS:
        rows = track_rows(text, track)
        for label in ("ORCA", "Oracle (privileged)"):
            r = rows[label]
            out.append(f"| `{track}` | {label} | — | {r['seeds']} | {r['success']} | {r['collision']} | "
                       f"{r['timeout']} | {r['nav time s']} | {r['dangers/ep']} |")
        for _, label, name in NETS:
            for look in ("query", "cv"):
                r = entry(rows, label, look)
                if r and r["trained on"] == track:
                    look_s = "query (privileged)" if look == "query" else "cv"
                    out.append(f"| `{track}` | {name} | {look_s} | {r['seeds']} | {r['success']} | {r['collision']} | "
                               f"{r['timeout']} | {r['nav time s']} | {r['dangers/ep']} |")
    return out


def replace_block(doc: str, name: str, lines: list[str]) -> str:
    """``doc`` with its generated block ``name`` holding ``lines``."""
    return splice(doc, "\n\n" + "\n".join(lines) + "\n\n", name)


def main(argv: list[str]) -> None:
    text = (ROOT / "leaderboard" / "TRACKS.md").read_text()
    blocks = {"table-i": table_i(track_rows(text, "crowdnav-circle5")), "value-tracks": other_tracks(text)}
    if argv[:1] == ["--write"] and len(argv) == 2:
        path = Path(argv[1])
        doc = path.read_text()
        for tag, lines in blocks.items():
            doc = replace_block(doc, tag, lines)
        path.write_text(doc)
        print(f"wrote {', '.join(blocks)} into {path}")
    elif argv:
        raise SystemExit(__doc__)
    else:
        for lines in blocks.values():
            print("\n".join(lines) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
