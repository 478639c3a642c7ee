"""The social-navigation metrics (crowdbench/social_metrics.py) on hand-computed trajectories, protocol v1's
metrics unchanged by them (bit for bit, against the code from before they existed), and their tables."""

from __future__ import annotations

import itertools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from crowdbench.envs.rules import COLLISION, SUCCESS, SimConfig
from crowdbench.metric_table import UNIT, clip, metric_range, spread
from crowdbench.protocols.engine import aggregate, episode_metrics, format_table, mean_ci
from crowdbench.social_metrics import (
    SCORE_TTC,
    TTC_HORIZON,
    min_ttc,
    path_irregularity,
    social_nav_score,
    time_to_collision,
)

REPO = Path(__file__).resolve().parents[1]
CFG = SimConfig()  # dt 0.25 s, v_max 1 m/s, radii 0.2 + 0.1 m
R = CFG.robot_radius + CFG.human_radius


def polyline(*corners, step: float) -> torch.Tensor:
    """Positions ``[T + 1, 2]`` (float64) along straight legs between ``corners``, ``step`` metres apart."""
    pts = [torch.tensor(corners[0], dtype=torch.float64)]
    for a, b in itertools.pairwise(corners):
        a, b = torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)
        n = round(float((b - a).norm()) / step)
        pts += [a + (b - a) * (k / n) for k in range(1, n + 1)]
    return torch.stack(pts)


def traces(paths: list[torch.Tensor], goals, outcomes, clearance: torch.Tensor | None = None, humans=None) -> dict:
    """Traces ``[T, B]`` as :func:`crowdbench.protocols.engine.robot_traces` returns them, for hand-made robot paths
    (shorter ones padded with the finished robot standing still: inactive steps) and humans
    ``(xy, vel, present)`` ``[T, B, M, ...]`` (default: nobody)."""
    T = max(len(p) for p in paths) - 1
    B = len(paths)
    xy = torch.stack([torch.cat([p, p[-1:].expand(T + 1 - len(p), 2)]) for p in paths], 1)
    active = torch.stack([torch.arange(T) < len(p) - 1 for p in paths], 1)
    clear = torch.full((T, B), 5.0, dtype=torch.float64) if clearance is None else clearance
    hxy, hvel, present = humans or (torch.zeros(T, B, 0, 2), torch.zeros(T, B, 0, 2), torch.zeros(T, B, 0, dtype=torch.bool))
    return {"xy": xy, "clearance": clear, "swept": clear, "reward": torch.zeros(T, B), "active": active,
            "outcome": torch.tensor(outcomes), "clearance0": clear[0], "start": xy[0],
            "goal": torch.tensor(goals, dtype=torch.float64), "humans_xy": hxy, "humans_vel": hvel,
            "humans_present": present}


def test_straight_path_and_right_angle_detour_hand_values():
    straight = polyline((0, 0), (8, 0), step=0.125)  # 8 m at 0.5 m/s: 64 steps, 16 s; free-space time 8 s
    detour = polyline((0, 0), (4, 0), (4, 4), step=0.25)  # 4 m + 4 m at 1 m/s towards a goal 4*sqrt(2) m away
    stop = torch.cat([detour[:17], detour[16:17].expand(4, 2), detour[17:]])  # the same, waiting 1 s at the corner
    m = episode_metrics(traces([straight, detour, stop, detour], [(8, 0), (4, 4), (4, 4), (4, 4)],
                               [SUCCESS, SUCCESS, SUCCESS, COLLISION]), CFG)
    assert m["spl"][0] == 1.0 and m["path_irregularity"][0] == 0.0
    assert m["stl"][0] == 0.5  # t* / t = 8 s / 16 s
    assert m["spl"][1].item() == pytest.approx(4 * math.sqrt(2) / 8, abs=1e-15)
    assert m["stl"][1].item() == pytest.approx(4 * math.sqrt(2) / 8, abs=1e-15)  # 5.66 s free-space over 8 s
    # from the start-goal direction: pi/4 to the first leg, pi/2 at the corner, over 8 m
    assert m["path_irregularity"][1].item() == pytest.approx(3 * math.pi / 4 / 8, abs=1e-12)
    assert m["path_irregularity"][2].item() == pytest.approx(3 * math.pi / 4 / 8, abs=1e-12)  # a stop turns nothing
    assert m["stl"][2].item() == pytest.approx(4 * math.sqrt(2) / 9, abs=1e-15)  # 9 s with the wait; SPL unchanged
    assert m["spl"][2].item() == pytest.approx(4 * math.sqrt(2) / 8, abs=1e-15)
    assert m["spl"][3] == m["stl"][3] == 0.0  # failed: 0, whatever the path
    assert (m["min_ttc"] == TTC_HORIZON).all()  # nobody there


def test_time_to_collision_hand_values():
    robot_v = torch.tensor([1.0, 0.0], dtype=torch.float64)
    def ttc(h_pos, h_vel, robot=(0.0, 0.0)):
        rel = torch.tensor(h_pos, dtype=torch.float64) - torch.tensor(robot, dtype=torch.float64)
        return time_to_collision(rel, torch.tensor(h_vel, dtype=torch.float64) - robot_v, R).item()

    assert ttc((5, 0), (-1, 0)) == pytest.approx((5 - R) / 2, abs=1e-15)  # head-on, closing at 2 m/s: 2.35 s
    assert ttc((5, 0), (0, 0)) == pytest.approx(5 - R, abs=1e-15)  # a standing human ahead
    assert ttc((3, -3), (0, 1)) == pytest.approx(3 - R / math.sqrt(2), abs=1e-14)  # crossing: meets head-on in relative frame
    assert ttc((5, 0), (2, 0)) == math.inf  # diverging: never
    assert ttc((-5, 0), (0, 0)) == math.inf  # behind, the robot moving away
    assert ttc((5, 1), (-1, 0)) == math.inf  # passes 1 m aside > 0.3 m
    assert ttc((0.2, 0), (-1, 0)) == 0.0  # already overlapping
    assert ttc((5, 0), (1, 0)) == math.inf  # same velocity: the gap never changes


def test_min_ttc_over_steps_present_humans_and_the_cap():
    """Robot at 1 m/s along x; human 0 head-on at 1 m/s from 10 m, human 1 overlapping but absent, human 2
    diverging. Step ends k = 1..4: gap 10 - 2k m at 2 m/s. The robot stops after step 3 (inactive step 4)."""
    T, dt = 4, 0.25
    xy = torch.tensor([[[0.25 * k, 0.0]] for k in range(T + 1)], dtype=torch.float64)  # [T + 1, 1, 2]
    k = torch.arange(1, T + 1, dtype=torch.float64)
    h0 = torch.stack([10 - 0.25 * k, torch.zeros(T)], -1)
    h1 = xy[1:, 0] + torch.tensor([0.1, 0.0], dtype=torch.float64)
    h2 = torch.stack([-5 - 0.25 * k, torch.zeros(T)], -1)
    hxy = torch.stack([h0, h1, h2], 1).unsqueeze(1)  # [T, 1, 3, 2]
    hvel = torch.tensor([[-1.0, 0], [1, 0], [-1, 0]], dtype=torch.float64).expand(T, 1, 3, 2)
    present = torch.tensor([True, False, True]).expand(T, 1, 3)
    active = torch.tensor([[True], [True], [True], [False]])
    gap3 = (10 - 0.25 * 3) - 0.25 * 3  # centre distance after step 3
    assert min_ttc(xy, hxy, hvel, present, active, dt, R)[0].item() == pytest.approx((gap3 - R) / 2, abs=1e-14)
    assert min_ttc(xy, hxy, hvel, present.clone().fill_(True), active, dt, R)[0] == 0.0  # human 1 present: overlap
    only_diverging = present.clone()
    only_diverging[..., 0] = False
    assert min_ttc(xy, hxy, hvel, only_diverging, active, dt, R)[0] == TTC_HORIZON  # infinite -> the cap
    far = hxy.clone()
    far[..., 0, 0] += 100  # 100 m further: 52 s away, capped
    assert min_ttc(xy, far, hvel, present, active, dt, R)[0] == TTC_HORIZON


def test_personal_space_at_050_and_045_on_a_clearance_sequence():
    seq = [0.6, 0.5, 0.47, 0.45, 0.44, 1.0, 0.3, 0.49, 0.0, 0.0]  # the last 2: after the robot finished
    clear = torch.tensor([seq, [1.0] * 10], dtype=torch.float64).T  # [T, 2]
    paths = [polyline((0, 0), (2, 0), step=0.25), polyline((0, 0), (2.5, 0), step=0.25)]  # 8 and 10 steps
    m = episode_metrics(traces(paths, [(8, 0), (8, 0)], [COLLISION, COLLISION], clearance=clear), CFG)
    assert m["personal_space"][0] == 6 / 8  # >= 0.45 m: 0.6, 0.5, 0.47, 0.45, 1.0, 0.49
    assert m["personal_space_50cm"][0] == 3 / 8  # >= 0.5 m: 0.6, 0.5, 1.0
    agg = aggregate(m)
    assert agg["personal_space_compliance"]["mean"] == (6 / 8 + 1) / 2
    assert agg["personal_space_compliance_50cm"]["mean"] == (3 / 8 + 1) / 2


def test_composite_score_hand_values():
    f = lambda *v: torch.tensor(v, dtype=torch.float64)
    score = social_nav_score(torch.tensor([True, True, False]), f(0.5, 1.0, 0.0), f(0.25, 1.0, 0.0),
                             f(0.75, 1.0, 0.5), f(1.5, 20.0, 0.0))
    assert SCORE_TTC == 3.0
    assert score.tolist() == pytest.approx([(1 + 0.5 + 0.25 + 0.75 + 0.5) / 5, 1.0, 0.5 / 5], abs=1e-15)
    agg = aggregate(episode_metrics(traces([polyline((0, 0), (8, 0), step=0.125)] * 3, [(8, 0)] * 3,
                                           [SUCCESS, SUCCESS, COLLISION]), CFG))
    assert agg["spl"] == mean_ci(f(1, 1, 0), UNIT) and agg["stl"] == mean_ci(f(0.5, 0.5, 0), UNIT)
    assert agg["spl"]["ci95"][1] == 1.0  # the normal interval, 2/3 +- 0.653, clipped to the metric's range
    assert agg["social_nav_score"] == mean_ci(f(0.9, 0.9, 0.4), UNIT) and agg["min_ttc_s"]["mean"] == TTC_HORIZON
    assert metric_range("min_ttc_s") == (0.0, TTC_HORIZON)
    assert agg["path_irregularity"]["mean"] == 0.0


def test_path_irregularity_is_batch_generic():
    """``[T, E, A]`` traces (e.g. self-play's agents) give each column's own value: no mixing across the batch."""
    g = torch.Generator().manual_seed(0)
    xy = torch.randn(7, 2, 3, 2, generator=g, dtype=torch.float64).cumsum(0)
    active = torch.rand(6, 2, 3, generator=g) < 0.8
    goal = torch.randn(2, 3, 2, generator=g, dtype=torch.float64)
    full = path_irregularity(xy, active, xy[0], goal)
    for e in range(2):
        for a in range(3):
            one = path_irregularity(xy[:, e, a, None], active[:, e, a, None], xy[0, e, a, None], goal[e, a, None])
            assert full[e, a] == one[0]


# -------------------------------------------------------------- protocol v1's numbers unchanged
# what NUMBERS printed on the tree of 759d7f7 (the last commit before these metrics), kept as a file so the
# test needs no git history (a shallow clone or a source tarball has none)
BEFORE = REPO / "tests" / "data" / "protocol_v1_hotel5_before_social_metrics.json"
NUMBERS = """
import json
from crowdbench.envs.protocol import PROTOCOL_VERSION, ProtocolSpec, load_episodes
from crowdbench.protocols.engine import aggregate, episode_metrics, select_episodes
from crowdbench.protocols.replay import evaluate, rollout, sim_config_for
from crowdbench.policies import build
out = {}
saved = load_episodes("hotel")
cfg = sim_config_for(ProtocolSpec(**{**saved["spec"], "version": PROTOCOL_VERSION}))
for name in ("straight", "orca"):
    m = episode_metrics(rollout(build(name), "hotel", select_episodes(saved, 5), cfg), cfg)
    out[name] = {"episodes": {k: v.tolist() for k, v in m.items()}, "aggregate": aggregate(m),
                 "results": evaluate(build(name), ["hotel"], episodes=5)["scenes"]}
print(json.dumps(out))
"""


def as_before(v: dict) -> dict:
    """An aggregated metric as it was before intervals were clipped: its unclipped interval, no ``sd``."""
    return {"mean": v["mean"], "ci95": list(spread(v)), "n": v["n"]}


def numbers(root: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", NUMBERS], cwd=root, env=env, capture_output=True, text=True,
                         timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout)


@pytest.mark.slow
def test_protocol_v1_metrics_bit_identical_to_the_code_before():
    """Every key the evaluation had before (per episode, aggregated, in results) keeps its exact value on
    5 hotel episodes of straight and ORCA; the new metrics only add keys. "Before" is what 759d7f7 gave
    (``BEFORE``; JSON floats round-trip exactly). Since then an interval is clipped to its metric's range
    (e.g. straight's dangers per episode, 0.2 [-0.192, 0.592]: [0, 0.592]) and a mean carries its ``sd``,
    from which the unclipped interval is the one from before, bit for bit."""
    before, after = json.loads(BEFORE.read_text()), numbers(REPO)
    new = {"spl", "stl", "personal_space_50cm", "min_ttc", "path_irregularity", "social_nav_score"}
    renamed = {"spl", "stl", "personal_space_compliance_50cm", "min_ttc_s", "path_irregularity", "social_nav_score"}
    for name in ("straight", "orca"):
        b, a = before[name], after[name]
        assert set(a["episodes"]) - set(b["episodes"]) == new
        assert {k: a["episodes"][k] for k in b["episodes"]} == b["episodes"]
        assert set(a["aggregate"]) - set(b["aggregate"]) == renamed
        assert {k: as_before(a["aggregate"][k]) for k in b["aggregate"]} == b["aggregate"]
        assert {k: as_before(a["results"]["hotel"][k]) for k in b["results"]["hotel"]} == b["results"]["hotel"]
        assert {k: a["aggregate"][k]["ci95"] for k in b["aggregate"]} == \
            {k: list(clip(k, *v["ci95"])) for k, v in b["aggregate"].items()}
        assert list(a["results"]["hotel"])[: len(b["results"]["hotel"])] == list(b["results"]["hotel"])  # order too
    assert after["straight"]["episodes"]["spl"][1:] == [1.0] * 4  # 4 straight successes


def test_format_table_prints_the_social_metrics_only_when_present():
    cell = {"mean": 0.5, "ci95": [0.4, 0.6], "n": 10}
    old = {"policy": "p", "protocol": "v1", "scenes": {"hotel": {k: cell for k in (
        "success_rate", "collision_rate", "timeout_rate", "nav_time_s", "dangers_per_episode", "min_clearance")}}}
    assert "SPL" not in format_table(old) and len(format_table(old).splitlines()) == 3
    new = json.loads(json.dumps(old))
    new["scenes"]["hotel"] |= {"spl": cell, "social_nav_score": cell}
    lines = format_table(new).splitlines()
    assert lines[:3] == format_table(old).splitlines() and lines[4].split() == ["scene", "SPL", "score"]
    assert lines[5].count("0.500 [0.400,0.600]") == 2 and "n/a" not in lines[5]  # the metrics the results hold
    new["scenes"]["eth"] = {"spl": cell}
    assert format_table(new).splitlines()[-1].split()[1:] == ["0.500", "[0.400,0.600]", "n/a"]  # missing: n/a


# -------------------------------------------------------------- leaderboard tables
def committed_results() -> dict[str, list[dict]]:
    from crowdbench.leaderboard.tracks import TRACK_ORDER

    root = REPO / "leaderboard" / "results"
    return {t: [json.loads(p.read_text()) for p in sorted(root.glob(f"*/{'results' if t == 'v1' else t}.json"))]
            for t in TRACK_ORDER}


@pytest.mark.slow
def test_leaderboard_tables_render_the_metrics_only_from_results_that_hold_them():
    """The committed results hold these metrics: README.md and TRACKS.md re-render byte for byte. Results
    written before the metrics existed (the keys stripped) render the tables as they were: no metric
    sections, no metric columns, every other section unchanged; a result without them shows "—"."""
    import copy

    from crowdbench.envs.protocol import EVAL_SCENES
    from crowdbench.leaderboard.render import render_docs_block, render_readme
    from crowdbench.leaderboard.track_tables import render_tracks, trained_on
    from crowdbench.metric_table import METRICS

    by_track, scenes = committed_results(), list(EVAL_SCENES)
    v1 = [r for r in by_track["v1"] if trained_on(r) in (None, "v1")]
    readme, tracks = (REPO / "leaderboard" / "README.md").read_text(), (REPO / "leaderboard" / "TRACKS.md").read_text()
    from crowdbench.leaderboard.board import unevaluated

    # (entries trained on another track that were never evaluated on v1 are listed under "Not evaluated")
    v1_missing = unevaluated(REPO / "leaderboard", by_track, ["v1"])
    assert render_readme(v1, [], scenes, None, v1_missing) == readme

    assert render_tracks(by_track, scenes, None, unevaluated(REPO / "leaderboard", by_track), []) == tracks
    social = [m for m in METRICS if m.optional]
    titles = [m.title for m in social]
    assert all(f"## {t}\n" in readme for t in titles)

    def strip(results):
        out = copy.deepcopy(results)
        for r in out:
            for sc in r["scenes"].values():
                for m in social:
                    sc.pop(m.key, None)
        return out

    old = render_readme(strip(v1), [], scenes, None, v1_missing)
    assert not any(f"## {t}\n" in old for t in titles)
    sections = [sec for sec in readme.split("\n## ") if sec.split("\n", 1)[0] not in titles]
    assert old.split("\n## ") == sections  # every other section exactly as with the metrics
    assert "### SPL" in render_docs_block(v1, scenes, None) and "### SPL" not in render_docs_block(strip(v1), scenes, None)
    old_board = render_tracks({t: strip(rs) for t, rs in by_track.items()}, scenes, None, [], [])
    assert "| SPL |" not in old_board and "| SPL |" in tracks

    mixed = [strip([r])[0] if r["meta"]["submission"] == "straight" else r for r in v1]
    new = render_readme(mixed, [], scenes, None, [])
    for title in titles:
        section = new.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]
        (row,) = [line for line in section.splitlines() if "| ORCA | 1 |" in line]
        assert "—" not in row
        assert "| Straight to goal | 1 | — | — | — | — | — | — | — | — |" in section  # no metric: "—"


def test_crowdnav_and_protocol_v2_results_hold_the_metrics():
    from crowdbench.baselines.straight import StraightToGoal
    from crowdbench.envs.crowdnav import CrowdNavConfig
    from crowdbench.protocols.crowdnav import evaluate_crowdnav
    from crowdbench.protocols.replay import evaluate

    keys = {"spl", "stl", "personal_space_compliance_50cm", "min_ttc_s", "path_irregularity", "social_nav_score"}
    for res in (evaluate_crowdnav(StraightToGoal(), CrowdNavConfig(), episodes=4),
                evaluate(StraightToGoal(), ["hotel"], episodes=4, humans="sfm")):
        (scene,) = res["scenes"].values()
        assert keys <= set(scene) and all(scene[k]["n"] == 4 for k in keys)
        assert 0 <= scene["social_nav_score"]["mean"] <= 1 and 0 <= scene["min_ttc_s"]["mean"] <= TTC_HORIZON
