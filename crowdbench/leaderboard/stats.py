"""The statistics of the generated tables: each metric's range (intervals are clipped to it), the 95%
interval of an entry with several training seeds (a two-level bootstrap: seeds, then each seed's
episodes), and the ranking of the entries by the headline metric.

Several seeds: ``B`` times, draw the seeds with replacement, and for each drawn seed a value of each of its
scenes from that scene's own sampling distribution (a rate: a binomial count of its ``n`` episodes; a mean:
normal with the standard error its 95% interval implies); the interval is the 2.5 and 97.5 percentiles of
the means. It holds both the seed-to-seed and the episode-to-episode variation (a plain bootstrap over 3
seeds has 10 distinct resamples and ignores the episodes). The draws come from numpy's legacy
``RandomState(0)``, whose streams numpy keeps fixed across versions: a fresh render equals the committed
tables on any machine (``crowdbench leaderboard --check``).
"""

from __future__ import annotations

import math

import numpy as np

BOOTSTRAP = 2000  # resamples per cell
SEED = 0
# metric -> (low, high) of its values; a metric not listed is unbounded (e.g. min_clearance: negative on contact)
UNIT = ("success_rate", "collision_rate", "timeout_rate", "spl", "stl", "personal_space_compliance",
        "personal_space_compliance_50cm", "social_nav_score")
NON_NEGATIVE = ("nav_time_s", "dangers_per_episode", "danger_events", "jerk", "mean_speed", "path_length",
                "path_length_ratio", "path_irregularity", "crowd_offset_max_m", "crowd_deviation_m")
RANGES = {**{m: (0.0, 1.0) for m in UNIT}, **{m: (0.0, math.inf) for m in NON_NEGATIVE}, "min_ttc_s": (0.0, 10.0)}


def metric_range(metric: str) -> tuple[float, float]:
    if metric.endswith("_rate"):
        return 0.0, 1.0
    return RANGES.get(metric, (-math.inf, math.inf))


def clip(metric: str, lo: float, hi: float) -> tuple[float, float]:
    """An interval within ``metric``'s range (a normal approximation can leave it: a count below 0)."""
    a, b = metric_range(metric)
    return min(max(lo, a), b), min(max(hi, a), b)


def _draws(v: dict, metric: str, rs: np.random.RandomState) -> np.ndarray:
    """``BOOTSTRAP`` draws of one run's value on one scene from its sampling distribution."""
    if metric.endswith("_rate") and v.get("n"):
        return rs.binomial(int(v["n"]), min(max(float(v["mean"]), 0.0), 1.0), BOOTSTRAP) / int(v["n"])
    lo, hi = v.get("ci95") or (None, None)
    se = (hi - lo) / (2 * 1.959963984540054) if lo is not None and hi is not None else 0.0
    return float(v["mean"]) + se * rs.standard_normal(BOOTSTRAP)


def seeds_interval(runs: list[list[dict]], metric: str) -> tuple[float, float]:
    """The 95% two-level bootstrap interval (module docstring) of the mean over seeds of each run's mean
    over its ``parts`` (the scenes of a cell: one, or the four paper scenes of an average), clipped."""
    rs = np.random.RandomState(SEED)
    per_run = np.stack([np.mean([_draws(v, metric, rs) for v in parts], axis=0) for parts in runs])  # [S, B]
    pick = rs.randint(0, len(runs), size=(BOOTSTRAP, len(runs)))
    means = per_run[pick, np.arange(BOOTSTRAP)[:, None]].mean(1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return clip(metric, float(lo), float(hi))


def ranked(groups: list[list[dict]], score, digits: int = 3) -> list[tuple[int | None, list[dict]]]:
    """``groups`` by ``score(g)`` (the headline metric, higher first; None last) as shown with ``digits``,
    ties by label; with their rank (1, 2, ...; equal shown scores share a rank; None: no score)."""
    scores = [score(g) for g in groups]
    shown = [None if s is None else round(s, digits) for s in scores]  # ties as the tables show them
    order = sorted(range(len(groups)), key=lambda i: (shown[i] is None, -(shown[i] or 0.0),
                                                      groups[i][0]["meta"]["entry"].lower()))
    out, rank, last = [], 0, None
    for pos, i in enumerate(order, 1):
        if shown[i] is not None and shown[i] != last:
            rank, last = pos, shown[i]
        out.append((rank if shown[i] is not None else None, groups[i]))
    return out
