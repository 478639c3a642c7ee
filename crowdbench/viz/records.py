"""``episodes.jsonl`` records as ``crowdbench viz`` reads them: every field drawing uses is checked
first, so that a malformed or oversized record is a one-line error naming it (never a traceback, or
minutes and GBs of drawing)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def load_rows(path: Path) -> tuple[list[dict], Path, str]:
    """Rows of ``episodes.jsonl`` (``path`` is the file or a results dir), the file, the ETH time base."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"no such file or directory: {path}")
    if path.is_dir():
        if not (path / "episodes.jsonl").is_file():
            raise ValueError(f"no episodes.jsonl in {path} (evaluate with eval.save_episodes=true)")
        path = path / "episodes.jsonl"
    rows = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            raise ValueError(f"{path} line {i}: not valid JSON") from None
        missing = [k for k in ("scene", "episode", "start_time_s", "dt", "start", "goal", "robot_xy", "outcome")
                   if not isinstance(row, dict) or k not in row]
        if missing:
            raise ValueError(f"{path} line {i}: not an episode record (missing {', '.join(missing)})")
        rows.append(row)
    if not rows:
        raise ValueError(f"{path} holds no episodes")
    sim = {}
    results = path.parent / "results.json"
    if results.is_file():
        try:
            sim = json.loads(results.read_text()).get("sim_config") or {}
        except (json.JSONDecodeError, AttributeError):
            pass
    limit = sim.get("time_limit")
    limit = limit if isinstance(limit, int) and 0 < limit <= MAX_STEPS else MAX_STEPS
    for i, row in enumerate(rows, 1):
        check_record(row, limit, f"{path} episode record {i}")
    return rows, path, str(sim.get("time_base", "true"))


MAX_STEPS = 10_000  # an episode's steps without its results.json (the protocols' limit is 100)


def check_record(row: dict, limit: int, where: str) -> None:
    """The fields drawing reads, checked: a bad one is a one-line error naming it, and a path longer than
    the time limit (``limit`` steps) is refused before drawing it would take minutes and GBs."""
    def number(key: str, lo: float, strict: bool) -> None:
        v = row[key]
        ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and (v > lo if strict else v >= lo)
        if not ok:
            raise ValueError(f"{where}: {key} must be a finite number {'>' if strict else '>='} {lo:g}, got {v!r}")

    number("dt", 0, True)
    number("start_time_s", 0, False)
    for key in ("start", "goal", "robot_xy"):
        value = row[key]
        if key == "robot_xy" and isinstance(value, list) and len(value) > limit + 1:
            raise ValueError(f"{where}: robot_xy has {len(value) - 1} steps, more than the time limit ({limit})")
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            a = None
        shape_ok = a is not None and (a.shape == (2,) if key != "robot_xy" else a.ndim == 2 and a.shape[1:] == (2,))
        if not shape_ok or a.size == 0 or not np.isfinite(a).all():
            want = "[x, y]" if key != "robot_xy" else "a non-empty list of [x, y]"
            raise ValueError(f"{where}: {key} must be {want} with finite numbers")
