"""``train.playback_speeds``: the training scene replayed faster, checked against the annotation rows themselves."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crowdbench.cli import compose, main
from crowdbench.data.scenes import FRAMES_PER_ROW, load_scene, playback_scene, read_rows, row_period
from crowdbench.envs.factory import make_env, training_world

TINY = ["train.pretrain=null", "train.total_frames=128", "train.frames_per_batch=64", "algo.warmup=64", "encoder.dim=8", "env.batch=4",
        "train.probe_every=1000000", "train.checkpoint_every=1000000", "train.utd=0.0625",
        "eval.episodes=1", "eval.scenes=[hotel]"]


def recorded(pid: int, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Pedestrian ``pid`` of students001 at recording time ``t`` s, from its rows: linear between rows."""
    rows = read_rows("students001")
    period = row_period("students001")
    mine = rows[rows[:, 1] == pid]
    tau = (mine[:, 0] - rows[:, 0].min()) / FRAMES_PER_ROW * period
    i = int(np.searchsorted(tau, t, side="right")) - 1
    i = min(i, len(tau) - 2)
    a = (t - tau[i]) / (tau[i + 1] - tau[i])
    return mine[i, 2:4] + a * (mine[i + 1, 2:4] - mine[i, 2:4]), (mine[i + 1, 2:4] - mine[i, 2:4]) / period


@pytest.mark.parametrize("speed", [1.5, 2.0])
def test_a_faster_part_shows_the_recording_at_speed_times_the_time(speed):
    dt, steps = 0.25, 100
    scene = playback_scene("students001", dt, (1.0, speed), steps)
    first = load_scene("students001", dt)
    offset = first.n_steps + steps + 1  # where the second part starts
    checked = 0
    for k in (40, 41, 200, 333):
        g = offset + k
        for slot in torch.nonzero(scene.valid[g]).flatten()[:6].tolist():
            pid = int(scene.ped_id[g, slot])
            p, v = recorded(pid, speed * k * dt)
            assert np.allclose(scene.pos[g, slot].numpy(), p, atol=1e-4)
            # the velocity is the segment's at that time, walked `speed` times faster (at a row boundary the
            # resampler takes the next segment's, as recorded() does)
            assert np.allclose(scene.vel[g, slot].numpy(), speed * v, atol=1e-4)
            checked += 1
    assert checked >= 12
    # the first part is the recording as the protocol replays it, then empty steps
    assert torch.equal(scene.pos[: first.n_steps, : first.max_humans], first.pos)
    assert torch.equal(scene.vel[: first.n_steps, : first.max_humans], first.vel)
    assert not scene.valid[first.n_steps:offset].any()


def test_episodes_start_where_they_stay_inside_one_part():
    cfg = compose(["train.playback_speeds=[1.0,2.0,1.5]"])
    world, scenario = training_world(cfg.env, 4, cfg.train.playback_speeds)
    scene, limit = world.crowd.scene, int(cfg.env.time_limit)
    lengths = [load_scene("students001", 0.25 * f).n_steps for f in (1.0, 2.0, 1.5)]
    ends = np.cumsum([n + limit + 1 for n in lengths])
    part_start = np.concatenate([[0], ends[:-1]])
    t0 = scenario.sampler(seed=3)(3000)["t0"].numpy()
    part = np.searchsorted(ends, t0, side="right")
    assert np.all(t0 + limit <= part_start[part] + np.array(lengths)[part] - 1)  # the whole episode inside its part
    assert set(part.tolist()) == {0, 1, 2}  # every speed is drawn
    assert scene.valid[t0].any(-1).all()


def test_as_recorded_is_the_protocol_scene_itself():
    cfg = compose([])
    assert list(cfg.train.playback_speeds) == [1.0]
    env = make_env(cfg, playback_speeds=cfg.train.playback_speeds)
    assert env.world.crowd.scene is load_scene("students001", 0.25, "true")  # (the cache key of replay_scene)
    assert env.world.crowd.scene.starts is None


def test_a_run_trains_with_playback_speeds_and_records_them(tmp_path):
    assert main(["run", *TINY, "train.playback_speeds=[1.0,2.0]", f"out={tmp_path}"]) == 0
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert list(state["config"]["train"]["playback_speeds"]) == [1.0, 2.0]


@pytest.mark.parametrize(("overrides", "message"), [
    (["train.playback_speeds=[0]"], "train.playback_speeds"),
    (["train.playback_speeds=[1.0,5.0]"], "train.playback_speeds"),
    (["env=crowdnav", "train.playback_speeds=[1.0,2.0]"], "train.playback_speeds: env.name=crowdnav replays no recording"),
])
def test_bad_playback_speeds_are_one_line_errors(tmp_path, capsys, overrides, message):
    assert main(["run", *TINY, *overrides, f"out={tmp_path / 'x'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any(message in line for line in err), err
