"""A leaderboard that reads like one: the committed tables ranked by success with it first, every
interval within its metric's range, seeds as a two-level bootstrap interval (deterministic), privileged
and unofficial rows marked, and one colour per method in the plots."""

from __future__ import annotations

import copy
import json
import math
import re
from pathlib import Path

import pytest

from crowdbench.leaderboard.render import group_results, label, scene_cell, seeds_cell
from crowdbench.leaderboard.stats import ranked, seeds_interval
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS
from crowdbench.metric_table import METRICS, clip, metric_range
from crowdbench.viz.palette import distinct_colours

BOARD = Path(__file__).resolve().parents[1] / "leaderboard"
CELL = re.compile(r"^(-?\d+\.\d+)(?: \[(-?\d+\.\d+), (-?\d+\.\d+)\])?$")


def tables(text: str) -> list[tuple[str, list[str], list[list[str]]]]:
    """(section title, header, rows) of every markdown table of ``text``."""
    out, section, lines = [], "", text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("#"):
            section = line.lstrip("# ").strip()
        if line.startswith("| ") and (i == 0 or not lines[i - 1].startswith("|")):
            rows = []
            for ln in lines[i + 2:]:
                if not ln.startswith("|"):
                    break
                rows.append([c.strip() for c in ln.strip().strip("|").split("|")])
            out.append((section, [c.strip() for c in line.strip().strip("|").split("|")], rows))
    return out


def value(cell: str) -> tuple[float, float | None, float | None] | None:
    m = CELL.match(cell.strip("*"))
    if not m:
        return None
    v, lo, hi = m.groups()
    return float(v), (float(lo) if lo else None), (float(hi) if hi else None)


def check_ranked(rows: list[list[str]], col: int, where: str) -> None:
    """Rank column 1, 2, ... (equal shown values share one), ``col`` not increasing down the table."""
    shown = [value(r[col]) for r in rows]
    scored = [s[0] for s in shown if s is not None]
    assert scored == sorted(scored, reverse=True), where
    for k, (r, s) in enumerate(zip(rows, shown, strict=True)):
        if s is None:
            assert r[0] == "—", where
            continue
        first = next(j for j, t in enumerate(shown) if t is not None and t[0] == s[0])
        assert r[0] == str(first + 1), (where, k, r[:3])


def test_committed_tables_are_ranked_by_success_first():
    readme, tracks = (BOARD / "README.md").read_text(), (BOARD / "TRACKS.md").read_text()
    ranked_tables = 0
    for section, head, rows in tables(readme):
        if head[0] != "#":
            continue
        assert head[1:4] == ["method", "seeds", "AVG (paper scenes)"], section
        ranked_tables += 1
        if section.startswith("Success rate"):
            check_ranked(rows, 3, section)
        # every metric's table in the success table's order
        assert [r[1] for r in rows] == [r[1] for r in next(t[2] for t in tables(readme) if t[0].startswith("Success"))]
    assert ranked_tables >= 5
    track_tables = [t for t in tables(tracks) if t[1][:5] == ["#", "method", "trained on", "seeds", "success"]]
    assert len(track_tables) == len(TRACK_ORDER)
    for section, _, rows in track_tables:
        check_ranked(rows, 4, section)
    # privileged entries say so wherever they are ranked
    assert all("(PRIVILEGED)" in r[1] or "privileged" in r[1].lower()
               for _, _, rows in track_tables for r in rows if "query lookahead" in r[1] or "Oracle" in r[1])


def test_committed_intervals_lie_in_each_metrics_range():
    """Each cell's metric is found by its section's title or its column's label (crowdbench/metric_table.py)."""
    by_label = {x: m for m in METRICS for x in (m.title, m.column, m.paper_title) if x}
    checked, bounded = 0, 0
    for f in ("README.md", "TRACKS.md"):
        for section, head, rows in tables((BOARD / f).read_text()):
            for r in rows:
                for name, cell in zip(head, r, strict=True):
                    v = value(cell)
                    if v is None or v[1] is None:
                        continue
                    mean, lo, hi = v
                    assert lo <= mean + 1e-3 and mean <= hi + 1e-3, (f, section, r[1], name, cell)
                    m = by_label.get(name) or by_label.get(section)
                    if m is not None and m.range != (-math.inf, math.inf):
                        assert m.range[0] <= lo and hi <= m.range[1], (f, section, r[1], name, cell)
                        bounded += 1
                    checked += 1
    assert checked > 2000 and bounded > 2000


def run(success: float, n: int = 250, dangers=(0.5, 0.4, 0.6), name: str = "x", official: bool = True) -> dict:
    scene = {"success_rate": {"mean": success, "ci95": [max(success - 0.05, 0), min(success + 0.05, 1)], "n": n},
             "dangers_per_episode": {"mean": dangers[0], "ci95": [dangers[1], dangers[2]], "n": n}}
    return {"scenes": {"hotel": scene}, "meta": {"submission": name, "kind": "learned", "entry": name.split("_")[0]},
            "submission": {}, "harness": {"official": official}}


def test_seeds_interval_is_a_deterministic_two_level_bootstrap():
    runs = [[run(p)["scenes"]["hotel"]["success_rate"]] for p in (0.6, 0.7, 0.8)]
    a, b = seeds_interval(runs, "success_rate"), seeds_interval(copy.deepcopy(runs), "success_rate")
    assert a == b  # RandomState(0): the same cell on every machine
    lo, hi = a
    assert lo < 0.7 < hi and 0.0 <= lo and hi <= 1.0
    assert hi - lo > 0.15  # the seeds disagree: wider than any one run's episode interval (~0.11)
    same = [[run(0.7)["scenes"]["hotel"]["success_rate"]] for _ in range(3)]
    lo2, hi2 = seeds_interval(same, "success_rate")
    assert 0.02 < hi2 - lo2 < 0.1  # equal seeds: the episodes' variation remains
    perfect = [[run(1.0)["scenes"]["hotel"]["success_rate"]] for _ in range(3)]
    assert seeds_interval(perfect, "success_rate") == (1.0, 1.0)
    m, text = seeds_cell(runs, "success_rate", 3)
    assert m == pytest.approx(0.7) and text == f"0.700 [{lo:.3f}, {hi:.3f}]"


def test_intervals_are_clipped_to_the_metric_range():
    assert metric_range("collision_rate") == (0.0, 1.0) and metric_range("min_clearance")[0] < -1e9
    assert clip("dangers_per_episode", -0.004, 0.01) == (0.0, 0.01)
    assert clip("social_nav_score", 0.95, 1.002) == (0.95, 1.0)
    assert clip("min_clearance", -0.2, 0.3) == (-0.2, 0.3)  # negative on contact: unbounded
    r = run(0.5, dangers=(0.003, -0.004, 0.01))
    assert scene_cell(r, "hotel", "dangers_per_episode", 3)[1] == "0.003 [0.000, 0.010]"


def test_ranking_ties_and_missing():
    groups = [[run(0.9, name="b")], [run(0.9004, name="a")], [run(0.95, name="c")], [run(0.1, name="d")]]
    groups.append([{**run(0.1, name="e"), "scenes": {}}])

    def score(g):
        return g[0]["scenes"].get("hotel", {}).get("success_rate", {}).get("mean")

    order = ranked(groups, score)
    assert [(k, g[0]["meta"]["entry"]) for k, g in order] == [(1, "c"), (2, "a"), (2, "b"), (4, "d"), (None, "e")]


def test_unofficial_rows_among_official_ones_are_marked():
    groups = group_results([run(0.9, name="full"), run(0.8, name="subset", official=False)])
    labels = sorted(label(g, escape=False) for g in groups)
    assert labels == ["full", "subset (UNOFFICIAL)"]
    only_subset = group_results([run(0.8, name="subset", official=False)])  # the page says it is a subset
    assert label(only_subset[0], escape=False) == "subset"


@pytest.mark.parametrize("n", [1, 5, 10, 11, 20, 21, 24, 40, 80])
def test_distinct_colours_never_repeat(n):
    colours = distinct_colours(n)
    assert len(colours) == n and len({tuple(round(c, 4) for c in col) for col in colours}) == n


def test_every_committed_method_has_its_own_colour():
    from crowdbench.leaderboard.plots import colour_map

    results = [json.loads(p.read_text()) for t in TRACK_ORDER
               for p in sorted((BOARD / "results").glob(f"*/{TRACKS[t].results_file}"))]
    colours = colour_map(results)
    assert len(colours) > 20 and len(set(colours.values())) == len(colours)
    assert all((BOARD / "plots" / f"{t}.png").is_file() for t in TRACK_ORDER)


def test_track_plot_places_each_entry_at_its_dangers_and_success():
    import matplotlib.pyplot as plt

    from crowdbench.leaderboard.plots import _tradeoff

    success = [("1. a", 0.9, 0.8, 1.0, (1, 0, 0)), ("2. b", 0.5, 0.4, 0.6, (0, 1, 0)),
               ("3. c", None, None, None, (0, 0, 1))]
    dangers = [("1. a", 0.2, 0.1, 0.3, (1, 0, 0)), ("2. b", 3.0, 2.0, 4.5, (0, 1, 0)),
               ("3. c", 1.0, 0.5, 1.5, (0, 0, 1))]
    fig, ax = plt.subplots()
    _tradeoff(ax, success, dangers)
    points = [tuple(line.get_xydata()[0]) for line in ax.lines if line.get_marker() == "o"]
    assert points == [(0.2, 0.9), (3.0, 0.5)]  # an entry without a success figure is not drawn
    assert [t.get_text() for t in ax.texts] == ["1", "2"]
    caps = sorted(round(float(x), 6) for line in ax.lines if line.get_marker() != "o"
                  for x in line.get_xdata())
    assert 2.0 in caps and 4.5 in caps  # b's dangers interval
    plt.close(fig)
