"""Protocol lists, metrics and the exported episodes against independent expectations."""

import json
import math

import pytest
import torch
from worlds import replay_sim

from crowdbench.baselines.straight import StraightToGoal
from crowdbench.data.scenes import load_scene
from crowdbench.envs.protocol import (
    EVAL_SCENES,
    ProtocolSpec,
    TrainSampler,
    generate_episodes,
    load_episodes,
    protocol_path,
)
from crowdbench.protocols.engine import mean_ci, rate_ci
from crowdbench.protocols.replay import evaluate

SPEC_KEYS = ["protocol", "scene", "episode", "start_time_s", "dt", "start", "goal", "robot_xy", "outcome",
             "nav_time_s", "danger_steps", "min_clearance"]


@pytest.mark.parametrize("scene", EVAL_SCENES)
def test_saved_lists_match_generator_and_cover_protocol(scene):
    saved = json.loads(protocol_path(scene).read_text())
    assert saved == generate_episodes(scene, ProtocolSpec())
    eps = saved["episodes"]
    assert saved["protocol"] == "v1" and len(eps) >= 250
    s = load_scene(scene)
    last = s.n_steps - 1 - 100
    planned = [round(i * last / (len(eps) - 1)) for i in range(len(eps))]
    shift = [abs(e["t0"] - p) for e, p in zip(eps, planned, strict=True)]
    assert all(0 <= e["t0"] <= last for e in eps)  # every episode fits its 100 steps
    # evenly spread, nudged to a free start: at most 25% moved, by at most 20 s (students003, the densest)
    assert sum(d > 0 for d in shift) <= len(eps) // 4 and max(shift) <= 80
    for e in eps:  # the start point is free at t0 (>= 0.3 m clearance from every human present)
        h = s.pos[e["t0"]][s.valid[e["t0"]]].double()
        assert ((h - torch.tensor(e["start"], dtype=torch.float64)).norm(dim=-1) - 0.3 >= 0.3 - 1e-5).all()
    sectors = torch.tensor([int(e["angle"] / (2 * math.pi) * 8) for e in eps]).bincount(minlength=8)
    assert sectors.min() >= 28  # golden-ratio angles cover the circle (250 / 8 = 31.25)
    e = eps[7]
    c = s.centre.double()
    assert e["start"] == pytest.approx((c + 4 * torch.tensor([math.cos(e["angle"]), math.sin(e["angle"])])).tolist(),
                                       abs=1e-5)
    assert math.dist(e["start"], e["goal"]) == pytest.approx(8.0, abs=1e-5)


def test_seed_changes_angles_same_seed_same_list():
    a = generate_episodes("hotel", ProtocolSpec(seed=1))
    b = generate_episodes("hotel", ProtocolSpec(seed=2))
    assert a["episodes"][0]["angle"] != b["episodes"][0]["angle"]
    assert generate_episodes("hotel", ProtocolSpec(seed=1)) == a


def test_stale_saved_list_rejected(tmp_path, monkeypatch):
    import crowdbench.envs.protocol as proto

    saved = json.loads(protocol_path("eth").read_text())
    saved["episodes"][3]["t0"] += 1
    (tmp_path / "eth.json").write_text(json.dumps(saved))
    monkeypatch.setattr(proto, "PROTOCOL_DIR", tmp_path)
    with pytest.raises(ValueError, match="does not match its generator"):
        load_episodes("eth")


def test_train_sampler_reproducible():
    a, b = TrainSampler(500, seed=3), TrainSampler(500, seed=3)
    ta, aa = a(64)
    tb, ab = b(64)
    assert torch.equal(ta, tb) and torch.equal(aa, ab) and ta.max() <= 500 and ta.min() >= 0


def test_confidence_intervals_hand_values():
    r = rate_ci(50, 100)  # Wilson at p = 0.5, n = 100: 0.5 -/+ 0.0960 (approximately)
    assert r["ci95"] == pytest.approx([0.4038, 0.5962], abs=1e-3)
    assert rate_ci(0, 250)["ci95"][0] == pytest.approx(0.0, abs=1e-12) and rate_ci(0, 250)["ci95"][1] == pytest.approx(0.0151, abs=1e-3)
    m = mean_ci(torch.tensor([1.0, 2.0, 3.0, 4.0]))
    assert m["mean"] == 2.5
    assert m["ci95"][1] - 2.5 == pytest.approx(1.959964 * math.sqrt(5 / 3) / 2, abs=1e-6)


def test_straight_evaluation_exports_spec_rows_and_is_reproducible(tmp_path):
    r1 = evaluate(StraightToGoal(), ["zara2"], 40, out_dir=tmp_path / "a", save_episodes=True)
    r2 = evaluate(StraightToGoal(), ["zara2"], 40, out_dir=tmp_path / "b", save_episodes=True)
    assert (tmp_path / "a" / "results.json").read_text() == (tmp_path / "b" / "results.json").read_text()
    rows = [json.loads(x) for x in (tmp_path / "a" / "episodes.jsonl").read_text().splitlines()]
    assert len(rows) == 40 and list(rows[0]) == SPEC_KEYS
    assert r1 == r2
    n_success = 0
    for row in rows:
        xy = torch.tensor(row["robot_xy"])
        steps = len(xy) - 1
        step_len = (xy[1:] - xy[:-1]).norm(dim=-1)
        assert (step_len <= 0.25 + 1e-4).all()  # 1 m/s x 0.25 s
        assert xy[0].tolist() == pytest.approx(row["start"], abs=1e-4)
        if row["outcome"] == "success":
            n_success += 1
            assert math.dist(xy[-1].tolist(), row["goal"]) < 0.2
            assert row["nav_time_s"] == pytest.approx(steps * 0.25)
            assert steps == 32  # straight line: 7.8 m to within 0.2 m of the goal at 0.25 m per step
        elif row["outcome"] == "collision":
            assert row["min_clearance"] < 0 and row["nav_time_s"] is None
    assert n_success / 40 == pytest.approx(r1["scenes"]["zara2"]["success_rate"]["mean"])


def test_collisions_recheckable_from_raw_positions(tmp_path):
    """Re-derive every outcome from the exported positions and the data file alone."""
    evaluate(StraightToGoal(), ["students003"], 25, out_dir=tmp_path, save_episodes=True)
    s = load_scene("students003")
    for line in (tmp_path / "episodes.jsonl").read_text().splitlines():
        row = json.loads(line)
        xy = torch.tensor(row["robot_xy"])
        k0 = round(row["start_time_s"] / row["dt"])
        hit = False
        for k in range(1, len(xy)):
            h1, h0, v = s.pos[k0 + k], s.prev[k0 + k], s.valid[k0 + k]
            # dense sub-sampling of the step instead of the closed form: an independent check
            for a in torch.linspace(0, 1, 101):
                p = xy[k - 1] + a * (xy[k] - xy[k - 1])
                h = h0 + a * (h1 - h0)
                if ((h - p).norm(dim=-1)[v] < 0.3 - 1e-3).any():
                    hit = True
            if hit:
                break
        assert hit == (row["outcome"] == "collision"), row["episode"]


def test_train_sampler_avoids_occupied_starts():
    
    scene = load_scene("students001")
    sim = replay_sim(scene, 1)

    def occupied(t0, angle):
        c = scene.centre.double()
        start = c + 4 * torch.stack((torch.cos(angle.double()), torch.sin(angle.double())), -1)
        gaps = [(scene.pos[t][scene.valid[t]].double() - s).norm(dim=-1) - 0.3 for t, s in zip(t0.tolist(), start)]
        return torch.tensor([bool((g < 0.3 - 1e-4).any()) for g in gaps])

    raw = TrainSampler(sim.scenario.last_start, seed=1)(1000)
    assert occupied(*raw).sum() >= 30  # the dense training scene really has occupied starts
    t0, angle = TrainSampler(sim.scenario.last_start, seed=1, is_free=sim.scenario.start_is_free)(1000)
    assert not occupied(t0, angle).any()
