"""One metric table (crowdbench/metric_table.py): every key an evaluation writes is declared there, once;
adding an entry reaches the aggregation and every table (the CLI's, the leaderboard's, the site's); intervals
stay within each metric's range, while the leaderboard's statistics still read the unclipped spread."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
import torch

from crowdbench import metric_table
from crowdbench.envs.rules import SUCCESS, SimConfig
from crowdbench.metric_table import (
    COUNT,
    IN_AVERAGE,
    IN_DOCS,
    IN_README,
    IN_SELFPLAY,
    IN_TRACKS,
    METRICS,
    SELFPLAY,
    UNIT,
    V1,
    V2,
    Z95,
    Metric,
    clip,
    in_table,
    metric,
    of_protocol,
    spread,
)
from crowdbench.protocols.engine import aggregate, episode_metrics, format_table, summarise

REPO = Path(__file__).resolve().parents[1]
TABLES = {IN_AVERAGE, IN_README, IN_DOCS, IN_TRACKS, IN_SELFPLAY}


def test_protocol_names_are_the_evaluations():
    from crowdbench.envs import protocol
    from crowdbench.protocols import crowdnav as eval_crowdnav
    from crowdbench.protocols import selfplay as eval_selfplay

    assert (metric_table.V1, metric_table.V2) == (protocol.PROTOCOL_VERSION, protocol.V2)
    assert (metric_table.CROWDNAV, metric_table.SELFPLAY) == (eval_crowdnav.PROTOCOL, eval_selfplay.PROTOCOL)


def test_every_entry_is_well_formed():
    keys = [m.key for m in METRICS]
    assert len(keys) == len(set(keys))
    protocols = {metric_table.V1, metric_table.V2, metric_table.CROWDNAV, metric_table.SELFPLAY}
    for m in METRICS:
        assert m.interval in ("wilson", "normal") and m.protocols and set(m.protocols) <= protocols, m.key
        assert set(m.shown_in) <= TABLES and m.range[0] < m.range[1], m.key
        assert m.interval == "normal" or m.range == UNIT, m.key  # a rate lies in [0, 1]
        assert m.paper_title is None or IN_README in m.shown_in, m.key


def episodes(dangers: list[int]) -> dict[str, torch.Tensor]:
    """Per-episode values of successful straight 1 m runs, episode ``b`` with ``dangers[b]`` steps ending
    within the danger distance."""
    T, B = 4, len(dangers)
    xy = torch.stack([torch.tensor([[0.25 * t, 0.0]] * B, dtype=torch.float64) for t in range(T + 1)])
    clear = torch.full((T, B), 5.0, dtype=torch.float64)
    for b, k in enumerate(dangers):
        clear[:k, b] = 0.1
    none = torch.zeros(T, B, 0, 2)
    tr = {"xy": xy, "clearance": clear, "swept": clear, "reward": torch.zeros(T, B),
          "active": torch.ones(T, B, dtype=torch.bool), "outcome": torch.full((B,), SUCCESS), "clearance0": clear[0],
          "start": xy[0], "goal": xy[-1], "humans_xy": none, "humans_vel": none,
          "humans_present": torch.zeros(T, B, 0, dtype=torch.bool)}
    return episode_metrics(tr, SimConfig())


def test_a_count_interval_stops_at_zero_hand_values():
    """5 episodes, one with a danger step: mean 0.2, sd sqrt(0.2), so the normal interval is
    0.2 -+ 1.96 * sqrt(0.2 / 5) = 0.2 -+ 0.392: [-0.192, 0.592], clipped to [0, 0.592]."""
    agg = aggregate(episodes([0, 0, 0, 0, 1]))
    d = agg["dangers_per_episode"]
    assert d["mean"] == pytest.approx(0.2) and d["n"] == 5 and d["sd"] == pytest.approx(math.sqrt(0.2))
    assert d["ci95"] == [0.0, pytest.approx(0.2 + Z95 * 0.2)]
    assert spread(d) == (pytest.approx(0.2 - Z95 * 0.2), pytest.approx(0.2 + Z95 * 0.2))
    # steps ending >= 0.45 m away: 1, 1, 1, 1, 0.75: 0.95 -+ 0.098, clipped at 1
    assert agg["personal_space_compliance"]["ci95"] == [pytest.approx(0.95 - Z95 * math.sqrt(0.0125 / 5)), 1.0]
    assert summarise(metric("min_clearance"), torch.tensor([-0.1, 0.0, 0.1, 0.2, 3.0]))["ci95"][0] < 0  # unbounded
    # as the CLI and the leaderboard print it
    assert "0.200 [0.000,0.592]" in format_table({"policy": "p", "protocol": V1, "scenes": {"hotel": agg}})
    from crowdbench.leaderboard.stats import scene_cell

    assert scene_cell({"scenes": {"hotel": agg}}, "hotel", "dangers_per_episode", 3)[1] == "0.200 [0.000, 0.592]"


def test_the_leaderboards_statistics_read_the_unclipped_spread():
    """A result with the clipped interval and ``sd`` gives the same paper-scene average and the same seeds'
    bootstrap interval as one holding the unclipped interval (a result written before clipping)."""
    from crowdbench.envs.protocol import PAPER_SCENES
    from crowdbench.leaderboard.stats import average_stat, seeds_interval

    new = aggregate(episodes([0, 0, 0, 0, 1]))["dangers_per_episode"]
    old = {"mean": new["mean"], "ci95": list(spread(new)), "n": 5}
    assert old["ci95"][0] < 0.0 == new["ci95"][0]
    run = lambda v: {"scenes": {s: {"dangers_per_episode": v} for s in PAPER_SCENES}}
    assert average_stat(run(new), "dangers_per_episode") == average_stat(run(old), "dangers_per_episode")
    assert average_stat(run(new), "dangers_per_episode")[1][0] == pytest.approx(0.2 - Z95 * 0.2 / 2)
    assert seeds_interval([[new]] * 3, "dangers_per_episode") == seeds_interval([[old]] * 3, "dangers_per_episode")


def keys_of(res: dict) -> list[set[str]]:
    units = res["scenes"].values() if "scenes" in res else res["settings"].values()
    return [set(u) - {"episode"} | set(u.get("episode", {})) for u in units]


def test_every_key_an_evaluation_writes_is_in_the_table():
    """Both ways: a protocol's results hold exactly the metrics the table gives it, within their ranges."""
    from crowdbench.baselines.straight import StraightToGoal
    from crowdbench.envs.crowdnav import CrowdNavConfig
    from crowdbench.envs.selfplay import SelfPlayConfig
    from crowdbench.protocols.crowdnav import PROTOCOL, evaluate_crowdnav
    from crowdbench.protocols.replay import evaluate
    from crowdbench.protocols.selfplay import evaluate_selfplay

    runs = {V1: evaluate(StraightToGoal(), ["hotel"], episodes=3), V2: evaluate(StraightToGoal(), ["hotel"], 3, humans="sfm"),
            PROTOCOL: evaluate_crowdnav(StraightToGoal(), CrowdNavConfig(), episodes=3),
            SELFPLAY: evaluate_selfplay(StraightToGoal(), SelfPlayConfig(n_agents=3), ["circle"], [3], episodes=3)}
    for protocol, res in runs.items():
        assert res["protocol"] == protocol
        declared = {m.key for m in of_protocol(protocol)}
        for keys, unit in zip(keys_of(res), (res.get("scenes") or res["settings"]).values(), strict=True):
            assert keys == declared, (protocol, keys ^ declared)
            flat = {**unit, **unit.get("episode", {})}
            for k in keys:
                lo, hi = flat[k]["ci95"]
                assert lo is None or (lo, hi) == clip(k, lo, hi), (protocol, k, lo, hi)
    assert list(runs[V1]["average_paper_scenes"]) == [m.key for m in in_table(IN_AVERAGE)]


def committed(track: str, names=None) -> list[dict]:
    name = "results" if track == "v1" else track
    return [json.loads(p.read_text()) for p in sorted((REPO / "leaderboard" / "results").glob(f"*/{name}.json"))
            if names is None or p.parent.name in names]


def test_a_metric_added_to_the_table_reaches_every_table(monkeypatch, tmp_path):
    """One entry: aggregated from its per-episode value, a section of README.md and docs/results.md, a
    column of TRACKS.md, of the site and of `crowdbench eval`'s table."""
    from crowdbench.envs.protocol import EVAL_SCENES
    from crowdbench.leaderboard.render import render_docs_block, render_readme
    from crowdbench.leaderboard.site import write_site
    from crowdbench.leaderboard.track_tables import render_tracks

    new = Metric("steps_taken", "Steps taken per episode", "steps taken", 1, COUNT, source="steps",
                 shown_in=(IN_README, IN_DOCS, IN_TRACKS))
    monkeypatch.setattr(metric_table, "METRICS", (*METRICS, new))
    assert aggregate(episodes([0, 1]))["steps_taken"]["mean"] == 4.0
    by_track = {t: committed(t, ("orca", "straight", "gatedgcn_td3_s0")) for t in ("v1", "v2-orca")}
    assert len(by_track["v1"]) == 3 and len(by_track["v2-orca"]) == 3
    for results in by_track.values():
        for r in results:
            for scene in r["scenes"].values():
                scene["steps_taken"] = {"mean": 40.0, "ci95": [39.0, 41.0], "n": 250}
    scenes = list(EVAL_SCENES)
    assert "\n## Steps taken per episode\n" in render_readme(by_track["v1"], [], scenes, None, [])
    assert "\n### Steps taken per episode\n" in render_docs_block(by_track["v1"], scenes, None)
    tracks = render_tracks(by_track, scenes, None, [], [])
    assert tracks.count("| steps taken |") == 2 and "| 40.0 [39.5, 40.5] |" in tracks  # paper scenes: 1 / 2
    cli = format_table(by_track["v2-orca"][0])
    assert re.search(r"crowd deviation m\s+steps taken\n", cli) and "40.000 [39.000,41.000]" in cli
    index = write_site(tmp_path / "site", REPO / "leaderboard", by_track, scenes, None, figures=0,
                       log=lambda *a: None).read_text()
    assert index.count(">steps taken</th>") == 2 and index.count("<summary>Steps taken per episode</summary>") == 2


def test_the_how_to_lists_the_files_and_no_other_module_declares_a_label():
    """docs/architecture.md's "How to add a metric" names files that exist; the table's labels appear in
    no other module of crowdbench/ (a second table would)."""
    text = (REPO / "docs" / "architecture.md").read_text()
    section = text.split("## How to add a metric", 1)[1].split("\n## ", 1)[0]
    files = re.findall(r"`(crowdbench/[\w/]+\.py|docs/[\w.]+\.md)`", section)
    assert "crowdbench/metric_table.py" in files and all((REPO / f).is_file() for f in files), files
    labels = {x for m in METRICS for x in (m.title, m.column, m.paper_title) if x and re.search(r"[ /.]", x)}
    for path in (REPO / "crowdbench").rglob("*.py"):
        if path.name != "metric_table.py":
            source = path.read_text()
            assert not [x for x in labels if f'"{x}"' in source], path


@pytest.mark.parametrize("track", ["v1", "v2-sfm", "crowdnav-circle5"])
def test_committed_results_hold_the_tables_metrics(track):
    from crowdbench.leaderboard.tracks import TRACKS

    declared = {m.key for m in of_protocol(TRACKS[track].label)}
    for r in committed(track):
        assert all(keys == declared for keys in keys_of(r)), r["meta"]["submission"]
