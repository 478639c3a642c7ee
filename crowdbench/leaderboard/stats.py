"""The statistics of the generated tables: a table cell's mean and 95% interval (a run's Wilson / normal
interval from its results.json; the paper-scene average; several training seeds: a two-level bootstrap
over seeds, then each seed's episodes), and the ranking of the entries by the headline metric.

Several seeds: ``B`` times, draw the seeds with replacement, and for each drawn seed a value of each of its
scenes from that scene's own sampling distribution (a rate: a binomial count of its ``n`` episodes; a mean:
normal with its standard error, :func:`~crowdbench.metric_table.spread`); the interval is the 2.5 and 97.5
percentiles of the means. It holds both the seed-to-seed and the episode-to-episode variation (a plain bootstrap over 3
seeds has 10 distinct resamples and ignores the episodes). The draws come from numpy's legacy
``RandomState(0)``, whose streams numpy keeps fixed across versions: a fresh render equals the committed
tables on any machine (``crowdbench leaderboard --check``). Every interval is clipped to its metric's range
(crowdbench/metric_table.py).
"""

from __future__ import annotations

import math

import numpy as np

from crowdbench.envs.protocol import PAPER_SCENES
from crowdbench.metric_table import Z95, clip, is_rate, spread
from crowdbench.protocols.engine import rate_ci

BOOTSTRAP = 2000  # resamples per cell
SEED = 0


def _draws(v: dict, metric: str, rs: np.random.RandomState) -> np.ndarray:
    """``BOOTSTRAP`` draws of one run's value on one scene from its sampling distribution."""
    if is_rate(metric) and v.get("n"):
        return rs.binomial(int(v["n"]), min(max(float(v["mean"]), 0.0), 1.0), BOOTSTRAP) / int(v["n"])
    lo, hi = spread(v)
    se = (hi - lo) / (2 * Z95) if lo is not None and hi is not None else 0.0
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


# ------------------------------------------------------------------------------- the tables' cells
def fmt(v, digits: int) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def interval(mean: float, lo: float, hi: float, metric: str, digits: int) -> str:
    """``mean [lo, hi]`` with the interval clipped to the metric's range (crowdbench/metric_table.py)."""
    lo, hi = clip(metric, lo, hi)
    return f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def scene_cell(r: dict, scene: str, metric: str, digits: int) -> tuple[float | None, str]:
    v = r["scenes"].get(scene, {}).get(metric)
    if not v or v["mean"] is None:
        return None, "—"
    return v["mean"], interval(v["mean"], *v["ci95"], metric, digits)


def average_stat(r: dict, metric: str) -> tuple[float | None, list]:
    """Paper-scene average and its interval (unclipped; ``[None, None]``: none): pooled Wilson interval
    for rates (equal episode counts), combined normal interval for means."""
    vals = [r["scenes"].get(s, {}).get(metric) for s in PAPER_SCENES]
    if any(v is None or v["mean"] is None for v in vals):
        return None, [None, None]
    mean = sum(v["mean"] for v in vals) / len(vals)
    if is_rate(metric):
        n = sum(v["n"] for v in vals)
        k = round(sum(v["mean"] * v["n"] for v in vals))
        return mean, rate_ci(k, n)["ci95"] if len({v["n"] for v in vals}) == 1 else [None, None]
    half = math.sqrt(sum(((hi - lo) / 2) ** 2 for lo, hi in map(spread, vals))) / len(vals)
    return mean, [mean - half, mean + half]


def average_cell(r: dict, metric: str, digits: int) -> tuple[float | None, str]:
    mean, ci = average_stat(r, metric)
    if mean is None:
        return None, "—"
    return mean, fmt(mean, digits) if ci[0] is None else interval(mean, *ci, metric, digits)


def group_stat(g: list[dict], cols: list[str], metric: str) -> tuple[float | None, float | None, float | None]:
    """Mean and clipped 95% interval of entry ``g`` over the scenes ``cols`` (one scene, or the four paper
    scenes: their average), as its table cell shows them (numbers for the plots; None: missing)."""
    if len(g) > 1:
        runs = [[r["scenes"].get(s, {}).get(metric) for s in cols] for r in g]
        if any(v is None or v["mean"] is None for parts in runs for v in parts):
            return None, None, None
        m = sum(sum(v["mean"] for v in parts) / len(parts) for parts in runs) / len(runs)
        return (m, *seeds_interval(runs, metric))
    if len(cols) == 1:
        v = g[0]["scenes"].get(cols[0], {}).get(metric)
        return (None, None, None) if not v or v["mean"] is None else (v["mean"], *clip(metric, *v["ci95"]))
    if list(cols) != list(PAPER_SCENES):  # an unofficial subset's plain mean
        vals = [(g[0]["scenes"].get(s, {}).get(metric) or {}).get("mean") for s in cols]
        return (None if None in vals else sum(vals) / len(vals)), None, None
    mean, ci = average_stat(g[0], metric)
    return (mean, None, None) if ci[0] is None else (mean, *clip(metric, *ci))


def seeds_cell(runs: list[list[dict] | None], metric: str, digits: int,
               intervals: bool = True) -> tuple[float | None, str]:
    """Several seeds of one entry: the mean over seeds of each run's mean over its ``parts`` (one scene, or
    the four of the paper-scene average) and, with ``intervals``, its 95% two-level bootstrap interval
    (crowdbench/leaderboard/stats.py)."""
    if not runs or any(not parts or any(not v or v["mean"] is None for v in parts) for parts in runs):
        return None, "—"
    m = sum(sum(v["mean"] for v in parts) / len(parts) for parts in runs) / len(runs)
    if not intervals:
        return m, fmt(m, digits)
    return m, interval(m, *seeds_interval(runs, metric), metric, digits)


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
