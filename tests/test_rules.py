"""Simulator geometry and episode logic against hand-computed cases."""

import math

import pytest
import torch
from worlds import replay_sim, reset_v1

from crowdbench.data.scenes import Scene, load_scene
from crowdbench.envs.rules import (
    COLLISION,
    RUNNING,
    SUCCESS,
    TIMEOUT,
    SimConfig,
    segment_min_distance,
)


def toy_scene(tracks, n_steps=12, dt=1.0):
    """A hand-made scene: ``tracks`` = list of per-step positions (None = absent) for each human."""
    m = len(tracks)
    pos = torch.zeros(n_steps, max(m, 1), 2)
    prev = torch.zeros_like(pos)
    valid = torch.zeros(n_steps, max(m, 1), dtype=torch.bool)
    for j, tr in enumerate(tracks):
        for k in range(n_steps):
            p = tr(k)
            if p is not None:
                pos[k, j] = torch.tensor(p)
                valid[k, j] = True
                q = tr(k - 1) if k > 0 else None
                prev[k, j] = torch.tensor(q if q is not None else p)
    vel = torch.zeros_like(pos)
    ped = torch.where(valid, torch.arange(max(m, 1)).expand(n_steps, -1), -1)
    return Scene("toy", dt, dt, pos, prev, vel, valid, ped, torch.zeros(2))


def sim_for(scene, angle=math.pi, radius=0.5, time_limit=5, batch=1, **kw):
    cfg = SimConfig(dt=scene.dt, start_radius=radius, time_limit=time_limit, **kw)
    sim = replay_sim(scene, batch, cfg)
    reset_v1(sim, torch.ones(batch, dtype=torch.bool), torch.zeros(batch, dtype=torch.long), torch.full((batch,), angle))
    return sim


def world_step(sim, vx, vy=0.0):
    return sim.step(torch.tensor([[[vx, vy]]]).expand(sim.B, 1, 2), frame="world")


def test_segment_min_distance_hand_cases():
    a0 = torch.tensor([[-1.0, 0.5], [2.0, 0.0], [0.0, 3.0]])
    a1 = torch.tensor([[1.0, 0.5], [3.0, 0.0], [0.0, 3.0]])
    assert segment_min_distance(a0, a1).tolist() == pytest.approx([0.5, 2.0, 3.0])


def test_swept_test_catches_pass_through_that_step_ends_miss():
    # static human at the origin; robot goes (-0.5, 0) -> (0.5, 0) in one 1 s step at 1 m/s.
    # Both step ends have clearance 0.5 - 0.3 = 0.2 >= 0, but the robot passes through the human.
    sim = sim_for(toy_scene([lambda k: (0.0, 0.0)]), v_max=1.0)
    assert sim.start.squeeze().tolist() == pytest.approx([-0.5, 0.0], abs=1e-6)
    info = world_step(sim, 1.0)
    assert info.clearance.item() == pytest.approx(0.2, abs=1e-6)
    assert info.swept_clearance.item() == pytest.approx(-0.3, abs=1e-6)
    assert info.outcome.item() == COLLISION and info.terminated.item()
    # collision wins over reaching the goal in the same step; reward = r_fail + r_danger(0.2 -> 0)
    assert info.reward.item() == pytest.approx(-0.25, abs=1e-6)


def test_spawned_human_is_tested_at_its_spawn_point():
    # a human that appears at step 1 at (0, -0.5) has no earlier position: over step 0 -> 1 it is a
    # static disk at its spawn point, so the robot passing along y = 0 keeps 0.5 - 0.3 = 0.2 clearance
    scene = toy_scene([lambda k: (0.0, -0.5 + (k - 1)) if k >= 1 else None])
    sim = sim_for(scene)
    info = world_step(sim, 1.0)
    assert info.swept_clearance.item() == pytest.approx(0.2, abs=1e-6)
    assert info.clearance.item() == pytest.approx(math.hypot(0.5, 0.5) - 0.3, abs=1e-5)
    assert info.outcome.item() == SUCCESS


def test_moving_crossing_detected():
    scene = toy_scene([lambda k: (0.0, -0.5 + 1.0 * k)])  # crosses the x-axis between k=0 and k=1
    sim = sim_for(scene)
    info = world_step(sim, 1.0)
    assert info.outcome.item() == COLLISION
    assert info.swept_clearance.item() == pytest.approx(-0.3, abs=1e-6)  # they meet exactly
    assert info.clearance.item() == pytest.approx(math.hypot(0.5, 0.5) - 0.3, abs=1e-5)


def test_clearance_danger_and_reward_at_known_distance():
    # human at (0.5, 0.4): at the goal (0.5, 0) the centre distance is 0.4 -> clearance 0.1 (danger)
    sim = sim_for(toy_scene([lambda k: (0.5, 0.4)]))
    info = world_step(sim, 1.0)
    assert info.clearance.item() == pytest.approx(0.1, abs=1e-6)
    assert info.outcome.item() == SUCCESS
    # r_reach + r_danger = 1 + (-0.1 + 0.1 / 2)
    assert info.reward.item() == pytest.approx(0.95, abs=1e-6)
    # with CrowdNav's dt scaling the danger term is multiplied by dt (= 1 here, so use dt 1 and compare sign)
    far = sim_for(toy_scene([lambda k: (0.5, 0.55)]))
    info = world_step(far, 1.0)
    assert info.clearance.item() == pytest.approx(0.25, abs=1e-6)
    assert info.reward.item() == pytest.approx(1.0, abs=1e-6)  # no danger beyond 0.2


def test_danger_dt_scaling():
    scene = toy_scene([lambda k: (2.0, 0.35)], dt=0.5)  # far from the goal, robot parked
    sim = sim_for(scene, radius=2.0, danger_dt_scaling=True)  # start (-2, 0), goal (2, 0)
    sim.pos[:] = torch.tensor([2.0, 0.0]) - torch.tensor([0.0, 0.0])
    sim.goal[:] = torch.tensor([5.0, 0.0])
    info = world_step(sim, 0.0)
    assert info.clearance.item() == pytest.approx(0.05, abs=1e-6)
    assert info.reward.item() == pytest.approx((-0.1 + 0.025) * 0.5, abs=1e-6)


def test_timeout_and_frozen_after_done():
    sim = sim_for(toy_scene([]), radius=3.0, time_limit=3)
    for _ in range(2):
        assert world_step(sim, 0.0).outcome.item() == RUNNING
    info = world_step(sim, 0.0)
    assert info.outcome.item() == TIMEOUT and info.truncated.item() and not info.terminated.item()
    assert info.reward.item() == pytest.approx(-0.25)
    pos = sim.pos.clone()
    info = world_step(sim, 1.0)  # finished: frozen, no reward
    assert torch.equal(sim.pos, pos) and info.reward.item() == 0.0 and not info.active.item()


def test_empty_scene_runs():
    sim = sim_for(toy_scene([]), radius=1.0)
    obs = sim.observe()
    assert not obs["humans_mask"].any()
    info = world_step(sim, 1.0)
    assert info.outcome.item() == RUNNING and info.clearance.item() > 1e3
    # and a real empty stretch of ETH
    eth = load_scene("eth")
    k = int((eth.count() == 0).nonzero()[0, 0])
    sim = replay_sim(eth, 1)
    reset_v1(sim, torch.tensor([True]), torch.tensor([k]), torch.tensor([0.0]))
    assert sim.observe()["humans_mask"].sum() == 0
    assert sim.step(torch.zeros(1, 1, 2)).outcome.item() == RUNNING


def test_speed_clip_and_nan():
    sim = sim_for(toy_scene([]), radius=3.0)
    world_step(sim, 5.0, 5.0)
    assert sim.vel.norm().item() == pytest.approx(1.0, abs=1e-6)
    assert sim.vel[0, 0, 0].item() == pytest.approx(sim.vel[0, 0, 1].item())
    with pytest.raises(ValueError, match="NaN"):
        world_step(sim, float("nan"))


def test_rotated_observation_and_action_frame():
    # goal straight "up" from the robot: the rotated frame puts it on +x
    sim = sim_for(toy_scene([lambda k: (0.0, 1.0)]), angle=-math.pi / 2, radius=2.0)  # start (0,-2), goal (0,2)
    obs = sim.observe()
    assert obs["robot"][0, 0].tolist() == pytest.approx([0, 0, 0, 0, 4.0, 0], abs=1e-5)
    # human at (0, 1) is 3 m ahead: (3, 0) in the robot frame
    assert obs["humans"][0, 0, 0, :2].tolist() == pytest.approx([3.0, 0.0], abs=1e-5)
    sim.step(torch.tensor([[[0.5, 0.0]]]))  # "forward" in the robot frame = +y in the world
    assert sim.pos[0, 0].tolist() == pytest.approx([0.0, -1.5], abs=1e-5)


def test_sensing_range():
    sim = sim_for(toy_scene([lambda k: (0.0, 5.0), lambda k: (0.0, 5.6)]), angle=-math.pi / 2, radius=0.5)
    # robot at (0, -0.5): first human 5.5 m away (unseen), second 6.1 m (unseen); move robot up 1 m
    assert not sim.observe()["humans_mask"].any()
    sim.pos[:] = torch.tensor([0.0, 0.5])
    assert sim.observe()["humans_mask"][0, 0].tolist() == [True, False]


def test_partial_reset_by_mask():
    scene = load_scene("students001")
    sim = replay_sim(scene, 3)
    reset_v1(sim, torch.ones(3, dtype=torch.bool), torch.tensor([0, 10, 20]), torch.zeros(3))
    sim.step(torch.ones(3, 1, 2) * 0.5)
    before = sim.pos.clone()
    reset_v1(sim, torch.tensor([False, True, False]), torch.tensor([0, 50, 0]), torch.full((3,), math.pi))
    assert torch.equal(sim.pos[[0, 2]], before[[0, 2]])
    assert sim.t.tolist() == [1, 50, 21] and sim.steps.tolist() == [1, 0, 1]
    with pytest.raises(ValueError, match="start index"):
        reset_v1(sim, torch.tensor([True, False, False]), torch.tensor([10_000, 0, 0]), torch.zeros(3))
