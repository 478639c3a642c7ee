"""Reactive replay (protocol v2's humans): exact replay without a robot nearby, yielding and returning,
spawn and despawn as recorded, the ORCA step against RVO2 (pyrvo), the track links against a loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crowdbench.data.scenes import Scene, interpolate_tracks, load_scene, pack_slots
from crowdbench.envs.factory import replay_world
from crowdbench.envs.humans.reactive_replay import ReactiveParams, ReactiveReplayCrowd, track_links
from crowdbench.envs.humans.rvo2_reference import rvo2_velocities
from crowdbench.envs.rules import COLLISION, RUNNING, SimConfig

MODELS = ("orca", "sfm")


def synthetic_scene(tracks: dict[int, list[tuple[float, float, float]]], dt: float = 0.25) -> Scene:
    """A scene from hand-made tracks ``{id: [(t, x, y), ...]}`` (rows every 0.4 s, as ETH/UCY)."""
    rows = np.array([(round(t / 0.4) * 10, pid, x, y) for pid, pts in tracks.items() for t, x, y in pts])
    n_steps, tr = interpolate_tracks(rows, 0.4, dt)
    pos, prev, vel, ped = pack_slots(n_steps, tr)
    f = lambda a: torch.as_tensor(a, dtype=torch.float32)
    return Scene("synthetic", dt, 0.4, f(pos), f(prev), f(vel), torch.as_tensor(ped >= 0), torch.as_tensor(ped),
                 torch.zeros(2))


def line(pid_t0: float, t1: float, p0, p1):
    """Rows every 0.4 s of a straight walk from ``p0`` at ``pid_t0`` s to ``p1`` at ``t1`` s."""
    ts = np.arange(pid_t0, t1 + 1e-9, 0.4)
    a = (ts - pid_t0) / (t1 - pid_t0)
    return [(t, p0[0] + s * (p1[0] - p0[0]), p0[1] + s * (p1[1] - p0[1])) for t, s in zip(ts, a, strict=True)]


def world_on(scene: Scene, batch: int, model: str | None, cfg: SimConfig | None = None):
    params = None if model is None else ReactiveParams(model=model)
    return replay_world(scene, batch, cfg or SimConfig(), params)


def far_episodes(batch: int, t0: torch.Tensor) -> dict:
    far = torch.full((batch, 1, 2), 1e4)
    return {"start": far, "goal": far + 10.0, "t0": t0}


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("scene_name", ["students001", "eth"])
def test_far_robot_replays_the_recording_exactly(model, scene_name):
    scene = load_scene(scene_name)
    B = 8
    world, _ = world_on(scene, B, model)
    recorded, _ = world_on(scene, B, None)
    t0 = torch.linspace(0, scene.last_start(100), B).long()
    for w in (world, recorded):
        w.reset(torch.ones(B, dtype=torch.bool), far_episodes(B, t0))
    for _ in range(100):
        for w in (world, recorded):
            w.step(torch.zeros(B, 1, 2))
        pos, vel, valid = world.humans()
        rpos, rvel, rvalid = recorded.humans()
        assert torch.equal(valid, rvalid) and torch.equal(valid, scene.valid[world.t])  # spawn/despawn as recorded
        assert torch.equal(pos * valid[..., None], rpos * rvalid[..., None])  # bit-identical, well under 1 cm
        assert torch.equal(vel * valid[..., None], rvel * rvalid[..., None])


def test_track_links_match_a_loop_over_pedestrian_ids():
    scene = load_scene("zara1")
    src, step = track_links(scene)
    ped, pos = scene.ped_id.numpy(), scene.pos.numpy()
    T, M = ped.shape
    for t in range(1, T, 37):
        for s in range(M):
            if ped[t, s] < 0:
                continue
            before = np.flatnonzero(ped[t - 1] == ped[t, s])
            assert src[t, s] == (before[0] if len(before) else -1)
            after = np.flatnonzero(ped[t + 1] == ped[t, s]) if t + 1 < T else []
            want = pos[t + 1, after[0]] - pos[t, s] if len(after) else np.zeros(2)
            np.testing.assert_allclose(step[t, s].numpy(), want, atol=1e-6)


def crossing_scene() -> Scene:
    """Human 1 walks (-8, 0.1) -> (8, 0.1) at 1 m/s from t = 0 through a standing robot at the origin
    (0.1 m off centre: exactly head-on, Moussaid's turning term is zero and a social-force human stops);
    human 2 walks far away (y = 30); human 3 appears at t = 4 s at (20, 5) and stands still."""
    return synthetic_scene({1: line(0.0, 16.0, (-8.0, 0.1), (8.0, 0.1)),
                            2: line(0.0, 30.0, (-15.0, 30.0), (15.0, 30.0)),
                            3: line(4.0, 28.0, (20.0, 5.0), (20.0, 5.0))})


def run_crossing(model: str | None):
    scene = crossing_scene()
    world, _ = world_on(scene, 1, model)
    world.reset(torch.ones(1, dtype=torch.bool),
                {"start": torch.zeros(1, 1, 2), "goal": torch.tensor([[[0.0, -50.0]]]), "t0": torch.zeros(1).long()})
    trace = []
    for _ in range(99):
        if world.outcome[0, 0] != RUNNING:
            break
        world.step(torch.zeros(1, 1, 2))
        pos, _, valid = world.humans()
        ids = scene.ped_id[world.t[0]]
        trace.append({int(i): (pos[0, s].clone(), scene.pos[world.t[0], s]) for s, i in enumerate(ids.tolist())
                      if valid[0, s]})
    return world, trace


def test_recorded_humans_walk_through_a_standing_robot():
    world, _ = run_crossing(None)
    assert world.outcome[0, 0] == COLLISION


@pytest.mark.parametrize("model", MODELS)
def test_humans_yield_to_a_standing_robot_and_return_to_their_tracks(model):
    world, trace = run_crossing(model)
    assert world.outcome[0, 0] == RUNNING  # 24.75 s, nobody hit the robot
    h1 = [(p, r) for step in trace if 1 in step for p, r in [step[1]]]
    gap = min(float(p.norm()) for p, _ in h1) - 0.3  # radii 0.1 + 0.2
    offset = [float((p - r).norm()) for p, r in h1]
    assert gap > 0.0
    assert max(offset) > 0.15  # it stepped aside
    past = [o for (p, r), o in zip(h1, offset, strict=True) if float(r[0]) > 5.0]
    assert past[-1] < 0.01 and past[-1] < 0.05 * max(offset)  # and went back to its recorded track
    assert len(h1) == 64  # and vanished when its recording ends (16 s), wherever it was
    for step in trace:  # the far-away humans are replayed exactly
        for pid in (2, 3):
            if pid in step:
                assert torch.equal(step[pid][0], step[pid][1])
    assert sum(3 in step for step in trace) == len(trace) - 15  # from step 16 (4 s) on, as recorded


def random_pairs(n: int, robots: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(n, 1, 2, generator=g) - 0.5) * 6
    rpos = (torch.rand(n, robots, 2, generator=g) - 0.5) * 6
    vel = (torch.rand(n, 1, 2, generator=g) - 0.5) * 2.4
    rvel = (torch.rand(n, robots, 2, generator=g) - 0.5) * 2.4
    pref = (torch.rand(n, 1, 2, generator=g) - 0.5) * 2.4
    cap = 0.3 + 1.5 * torch.rand(n, 1, generator=g)
    return pos, vel, pref, cap, rpos, rvel


@pytest.mark.parametrize("robots", [1, 2])
def test_orca_step_agrees_with_rvo2(robots):
    """The human's ORCA against the robots equals RVO2's answer for a world of that human and the robots."""
    n = 400
    pos, vel, pref, cap, rpos, rvel = random_pairs(n, robots, seed=robots)
    params = ReactiveParams()
    crowd = ReactiveReplayCrowd(crowding := synthetic_scene({1: line(0.0, 30.0, (0.0, 0.0), (1.0, 0.0))}), n, 100,
                                0.25, 0.1, 0.2, params)
    assert crowding.max_humans == 1
    ours = crowd._orca(pos, vel, pref, cap, torch.ones(n, 1, dtype=torch.bool), rpos, rvel,
                       torch.ones(n, robots, dtype=torch.bool))
    m = params.radius_margin
    radius = torch.cat((torch.full((n, 1), 0.1 + m), torch.full((n, robots), 0.2 + m)), 1)
    speed = torch.cat((cap, torch.full((n, robots), 5.0)), 1)
    ref = rvo2_velocities(torch.cat((pos, rpos), 1).double(), torch.cat((vel, rvel), 1).double(),
                          torch.cat((pref, rvel), 1).double(), torch.ones(n, 1 + robots, dtype=torch.bool), radius.double(),
                          speed.double(), time_horizon=params.time_horizon, dt=0.25,
                          neighbor_dist=params.neighbor_dist, max_neighbors=10)[:, 0]
    # RVO2 also makes the robots avoid each other, which does not change the human's answer
    err = (ours[:, 0].double() - torch.from_numpy(ref)).norm(dim=-1)
    moved = (ours[:, 0] - pref[:, 0]).norm(dim=-1) > 1e-3
    assert moved.float().mean() > 0.2  # the robots constrain a good share of the humans
    assert (err < 1e-3).float().mean() >= 0.995, f"max error {err.max():.2e}"


def test_reactive_params_errors_name_the_key():
    with pytest.raises(ValueError, match="env.reactive.model"):
        ReactiveParams(model="rvo")
    with pytest.raises(ValueError, match="env.reactive.horizon"):
        ReactiveParams(horizon=0.0)
    with pytest.raises(ValueError, match="env.reactive key.*speed"):
        ReactiveParams.of({"speed": 2})



def test_reactive_values_are_checked_before_anything_runs(tmp_path, capsys):
    from crowdbench.cli import main

    for cmd in ("eval", "run"):
        assert main([cmd, "env.humans=reactive_replay", "env.reactive.min_speed=fast", f"out={tmp_path / cmd}"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "env.reactive.min_speed: must be a number >= 0 (got 'fast')" in err
        assert not (tmp_path / cmd).exists()


def test_protocol_v2_lists_are_v1_episodes_regenerated_and_compared(tmp_path, monkeypatch):
    import json

    from crowdbench.envs import protocol
    from crowdbench.envs.protocol import EVAL_SCENES, load_episodes, load_episodes_v2, reactive_params

    for scene in EVAL_SCENES:
        v2 = load_episodes_v2(scene)  # regenerated and compared inside
        assert v2["protocol"] == "v2" and v2["episodes"] == load_episodes(scene)["episodes"]
        assert reactive_params(v2, "orca")[0] == ReactiveParams(model="orca")
        assert reactive_params(v2, "sfm")[0] == ReactiveParams(model="sfm")
    # a list edited by hand (or a changed default) is refused
    saved = json.loads(protocol.v2_path("eth").read_text())
    saved["humans"]["orca"]["horizon"] = 2.0
    monkeypatch.setattr(protocol, "V2_DIR", tmp_path)
    (tmp_path / "eth.json").write_text(json.dumps(saved))
    with pytest.raises(ValueError, match="does not match its generator"):
        load_episodes_v2("eth")
    with pytest.raises(FileNotFoundError, match="no saved v2 episode list for scene 'hotel'"):
        load_episodes_v2("hotel")


@pytest.mark.slow
def test_training_with_other_reactive_values_evaluates_on_protocol_v2(tmp_path, capsys):
    """``crowdbench eval`` refuses non-protocol env.reactive values; a training run with them is evaluated
    (and probed) with protocol v2's values instead of failing at its end."""
    import json

    from crowdbench.cli import main

    assert main(["eval", "policy=straight", "env.humans=reactive_replay", "env.reactive.horizon=2"]) == 2
    assert "env.reactive.horizon=2 conflicts with protocol v2 (1.0)" in capsys.readouterr().err
    out = tmp_path / "run"
    assert main(["run", "env.humans=reactive_replay", "env.reactive.horizon=2", "env.reactive.model=sfm",
                 "encoder=mlp", "encoder.dim=8", "train.pretrain=null", "train.total_frames=256", "train.frames_per_batch=128",
                 "algo.warmup=128", "train.utd=0.25", "train.probe_every=128", "train.probe_episodes=2",
                 "eval.episodes=2", "eval.scenes=[hotel]", f"out={out}"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["protocol"] == "v2" and res["humans"] == "sfm" and res["reactive"]["horizon"] == 1.0
