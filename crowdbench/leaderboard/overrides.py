"""Bounds on a baseline's or the oracle's ``overrides`` in a submission (docs/submitting.md section 2).

Why here and not in ``crowdbench.policies``: these policies run in the harness process, not in a
worker, so a submission's ``{beam: 4096, headings: 1024}`` would be the harness's memory (7.7 GB in
100 s); ``crowdbench eval`` on one's own machine keeps the registry's looser checks. The bounds
allow every value the published configs use with room to explore (the oracle's planning grid
``beam x headings x chunk`` up to 4x the default's).
"""

from __future__ import annotations

import math

# parameter -> (type, low, high); lists: (list, item type, low, high, max items)
BOUNDS = {
    "orca": {"safety_margin": (float, 0.0, 2.0), "time_horizon": (float, 0.05, 20.0), "max_neighbors": (int, 1, 100),
             "neighbor_dist": (float, 0.1, 50.0), "perturb": (float, 0.0, 0.1)},
    "oracle": {"headings": (int, 1, 64), "beam": (int, 1, 128), "chunk": (int, 1, 64), "cell": (float, 0.01, 1.0),
               "danger_cost": (float, 0.0, 100.0), "speeds": (list, float, 0.0, 1.0, 8)},
}
SEED = (int, 0, 2 ** 63 - 1)
MAX_GRID = 4 * 32 * 16 * 64  # beam x headings x chunk: 4x the default oracle's


def _number_problem(v, typ, lo, hi) -> str | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (typ is int and not isinstance(v, int)):
        return f"must be {'an integer' if typ is int else 'a number'}"
    if not math.isfinite(v) or not lo <= v <= hi:
        return f"must lie in [{lo:g}, {hi:g}]"
    return None


def override_problem(policy: str, overrides: dict) -> tuple[str, str] | None:
    """``(key, problem)`` of the first override of ``policy`` out of its bounds, or None (unknown keys
    are the registry's to refuse)."""
    bounds = {**BOUNDS.get(policy, {}), "seed": SEED}
    for key, v in overrides.items():
        k = key.split(".", 1)[1] if key.startswith(f"{policy}.") else key
        b = bounds.get(k)
        if b is None:
            continue
        if b[0] is list:
            _, typ, lo, hi, n = b
            if not isinstance(v, list) or not 0 < len(v) <= n:
                return key, f"must be a list of 1 to {n} numbers"
            problems = [p for p in (_number_problem(x, typ, lo, hi) for x in v) if p]
            if problems:
                return key, f"items {problems[0][5:]}"
            continue
        problem = _number_problem(v, *b)
        if problem:
            return key, f"{problem}, got {v!r}"[:120]
    if policy == "oracle":
        grid = [overrides.get(k, d) for k, d in (("beam", 32), ("headings", 16), ("chunk", 64))]
        if all(isinstance(x, int) for x in grid) and math.prod(grid) > MAX_GRID:
            return "beam", f"beam x headings x chunk must be at most {MAX_GRID}, got {math.prod(grid)}"
    return None
