"""The leaderboard's ranked plots: ``leaderboard/leaderboard.png`` (protocol v1: success and dangers per
episode averaged over the paper scenes) and ``leaderboard/plots/<track>.png`` (each track's headline
success, and success against dangers per episode). One horizontal bar (or point) per entry, in the tables'
rank order (best at the top), with its 95% interval as the tables compute it (:func:`~.render.group_stat`); each method has its own colour,
the same in every plot (:func:`colour_map` over every entry shown, no colour recycled)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from crowdbench.envs.protocol import PAPER_SCENES, PROTOCOL_VERSION
from crowdbench.leaderboard.render import group_results, group_stat, label, success_score
from crowdbench.leaderboard.stats import ranked
from crowdbench.metric_table import metric
from crowdbench.viz.palette import distinct_colours


def colour_map(results: list[dict]) -> dict[str, tuple]:
    """Entry label -> its colour: every label of ``results`` a different one (alphabetical order)."""
    labels = sorted({label([r], escape=False) for r in results}, key=lambda s: (s.lower(), s))
    return dict(zip(labels, distinct_colours(len(labels)), strict=True))


def _bars(ax, rows: list[tuple], title: str, xlabel: str, xlim=None) -> None:
    """``rows``: (label, mean, lo, hi, colour) in rank order, drawn top to bottom."""
    for y, (_, m, lo, hi, c) in enumerate(rows):
        if m is None:
            continue
        err = [[max(m - lo, 0.0)], [max(hi - m, 0.0)]] if lo is not None else None
        ax.barh(y, m, color=c, height=0.72, xerr=err, error_kw={"elinewidth": 0.9, "capsize": 2})
        ax.text(m if lo is None else hi, y, f" {m:.3f}", va="center", fontsize=6.5)
    ax.set_yticks(range(len(rows)), [r[0] for r in rows], fontsize=7.5)
    ax.set_ylim(max(len(rows), 1) - 0.5, -0.5)  # an empty track: a blank panel, not a singular axis
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.tick_params(axis="x", labelsize=7)
    ax.grid(axis="x", alpha=0.3)
    if xlim:
        ax.set_xlim(*xlim)


def _rows(order, cols_of, metric: str, colours: dict) -> list[tuple]:
    rows = []
    for rank, g in order:
        name = label(g, escape=False)
        m, lo, hi = group_stat(g, cols_of(g), metric)
        rows.append((f"{rank or '—'}. {name}".replace("$", r"\$"), m, lo, hi, colours.get(name, (0.5, 0.5, 0.5))))
    return rows


def _save(fig, out: Path) -> None:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)


def v1_plot(results: list[dict], scenes: list[str], out: Path, colours: dict | None = None) -> None:
    groups = group_results(results)
    colours = colours or colour_map(results)
    order = ranked(groups, lambda g: success_score(g, scenes))
    paper = all(s in scenes for s in PAPER_SCENES)

    def cols(g):
        return list(PAPER_SCENES) if paper else list(scenes)

    where = "average over the paper scenes" if paper else f"mean over {', '.join(scenes)} (unofficial)"
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 0.24 * len(groups) + 1.3), sharey=True,
                               gridspec_kw={"width_ratios": (3, 2)})
    _bars(a, _rows(order, cols, "success_rate", colours), f"success rate, {where}", "success (95% interval)",
          (0, 1.08))
    _bars(b, _rows(order, cols, "dangers_per_episode", colours), "dangers per episode", "steps with 0 <= d < 0.2 m")
    b.tick_params(axis="y", left=False)
    fig.suptitle(f"crowdbench leaderboard, protocol {PROTOCOL_VERSION}: ranked by success "
                 "(the oracle is a privileged upper bound)", fontsize=10)
    fig.tight_layout()
    _save(fig, out)


def metric_title(key: str) -> str:
    return metric(key).title


def _tradeoff(ax, success: list[tuple], dangers: list[tuple], metric: str = "dangers_per_episode") -> None:
    """Success against dangers (``metric``: per episode; self-play: between agents, per agent), one point per
    entry (its rank number) with both intervals: the safest successful entries sit top left."""
    for rank, (s, d) in enumerate(zip(success, dangers, strict=True), 1):
        if s[1] is None or d[1] is None:
            continue
        xerr = [[max(d[1] - d[2], 0.0)], [max(d[3] - d[1], 0.0)]] if d[2] is not None else None
        yerr = [[max(s[1] - s[2], 0.0)], [max(s[3] - s[1], 0.0)]] if s[2] is not None else None
        ax.errorbar(d[1], s[1], xerr=xerr, yerr=yerr, fmt="o", color=s[4], ms=4, elinewidth=0.8, capsize=1.5)
        ax.annotate(str(rank), (d[1], s[1]), textcoords="offset points", xytext=(3, 3), fontsize=6.5)
    ax.set_xlabel("dangers per episode (steps with 0 <= d < 0.2 m)" if metric == "dangers_per_episode" else
                  f"{metric_title(metric).lower()} (steps with 0 <= d < 0.2 m)", fontsize=8)
    ax.set_ylabel("success", fontsize=8)
    ax.set_ylim(-0.03, 1.05)
    ax.set_xlim(left=0)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.set_title("success against dangers (95% intervals)", fontsize=9)


def track_plot(track, results: list[dict], out: Path, colours: dict | None = None) -> None:
    """Track ``track``'s ranked success (the entries of its table) and each entry's success against its
    dangers per episode, to ``out``."""
    from crowdbench.leaderboard.track_tables import at_home, group_cell, headline_scenes

    groups = group_results([r for r in results if at_home(r, track)])
    colours = colours or colour_map(results)
    order = ranked(groups, lambda g: group_cell(g, track, "success_rate", 3)[0])
    rows = _rows(order, lambda g: headline_scenes(g[0], track), "success_rate", colours)
    dangers = _rows(order, lambda g: headline_scenes(g[0], track), track.evaluator.danger_metric, colours)
    fig, (ax, tr) = plt.subplots(1, 2, figsize=(11, max(0.24 * len(groups) + 1.1, 3.2)),
                                 gridspec_kw={"width_ratios": (3, 2)})
    where = "average over the paper scenes" if track.replay else f"{track.evaluator.short} {track.setting}"
    _bars(ax, rows, f"{track.name}: {track.title}\nsuccess, {where}, ranked", "success (95% interval)", (0, 1.08))
    _tradeoff(tr, rows, dangers, track.evaluator.danger_metric)
    fig.tight_layout()
    _save(fig, out)
