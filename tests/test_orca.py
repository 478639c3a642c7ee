"""ORCA baseline (RVO2 via pyrvo): behaviour on hand-built observations and in the simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from worlds import replay_sim, reset_v1

from crowdbench.baselines.orca import ORCA
from crowdbench.baselines.straight import StraightToGoal
from crowdbench.data import load_scene
from crowdbench.envs.observation import obs_tensordict
from crowdbench.envs.rules import COLLISION, RUNNING, SUCCESS

DT, V_MAX, RADII = 0.25, 1.0, 0.2 + 0.1


def make_obs(robot, humans=(), observed=None, m: int | None = None):
    """One environment, one robot: ``robot`` = [px, py, vx, vy, gx, gy], humans = [[px, py, vx, vy], ...]."""
    humans = [list(h) for h in humans]
    m = m or max(len(humans), 1)
    h = torch.zeros(1, 1, m, 4)
    mask = torch.zeros(1, 1, m, dtype=torch.bool)
    for j, row in enumerate(humans):
        h[0, 0, j] = torch.tensor(row)
        mask[0, 0, j] = True if observed is None else observed[j]
    robot_t = torch.tensor(robot, dtype=torch.float32).view(1, 1, 6)
    return obs_tensordict({"robot": robot_t, "humans": h * mask.unsqueeze(-1), "humans_mask": mask}, 1)


def random_crowd_obs(batch: int, m: int, seed: int):
    """A batch of plausible rotate-frame observations with a random subset of humans observed."""
    g = torch.Generator().manual_seed(seed)
    robot = torch.zeros(batch, 1, 6)
    robot[..., 2:4] = (torch.rand(batch, 1, 2, generator=g) - 0.5) * 1.2  # current velocity
    robot[..., 4] = 0.5 + 7.5 * torch.rand(batch, 1, generator=g)  # goal on the +x axis
    pos = (torch.rand(batch, 1, m, 2, generator=g) - 0.5) * 8.0
    vel = (torch.rand(batch, 1, m, 2, generator=g) - 0.5) * 3.0
    mask = (torch.rand(batch, 1, m, generator=g) < 0.8) & (pos.norm(dim=-1) > 0.35)
    humans = torch.cat((pos, vel), -1) * mask.unsqueeze(-1)
    return obs_tensordict({"robot": robot, "humans": humans, "humans_mask": mask}, batch)


def swept_clearance(p0, p1, h0, h1) -> float:
    """Surface gap at the closest approach of two bodies moving linearly over one step."""
    a, b = h0 - p0, h1 - p1
    d = b - a
    s = float(np.clip(-(a @ d) / max(d @ d, 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(a + s * d)) - RADII


def rot(vec, c, s):
    """World vector -> frame whose x-axis is (c, s)."""
    return np.array([c * vec[0] + s * vec[1], -s * vec[0] + c * vec[1]])


def toy_episode(policy, human_pos, human_vel, robot_vel=(0.0, 0.0), steps=100):
    """Integrate robot and one constant-velocity human by hand, observing in the rotate frame.

    Returns (reached goal, min swept clearance, max |lateral offset| from the straight path).
    """
    p, v = np.zeros(2), np.array(robot_vel, dtype=float)
    goal = np.array([8.0, 0.0])
    hp, hv = np.array(human_pos, dtype=float), np.array(human_vel, dtype=float)
    min_clear, max_lateral = math.inf, 0.0
    for _ in range(steps):
        to_goal = goal - p
        c, s = to_goal / np.linalg.norm(to_goal)
        robot = [0.0, 0.0, *rot(v, c, s), *rot(to_goal, c, s)]
        td = make_obs(robot, [[*rot(hp - p, c, s), *rot(hv, c, s)]])
        a_local = policy.act(td)[0, 0].double().numpy()
        a = np.array([c * a_local[0] - s * a_local[1], s * a_local[0] + c * a_local[1]])
        assert np.linalg.norm(a) <= V_MAX + 1e-5
        p1, hp1 = p + a * DT, hp + hv * DT
        min_clear = min(min_clear, swept_clearance(p, p1, hp, hp1))
        max_lateral = max(max_lateral, abs(p1[1]))
        p, v, hp = p1, a, hp1
        if np.linalg.norm(goal - p) < 0.2:
            return True, min_clear, max_lateral
    return False, min_clear, max_lateral


# --------------------------------------------------------------------------- single decisions
def test_no_humans_heads_straight_to_goal_at_v_max():
    policy = ORCA()
    for vel in ((0.0, 0.0), (0.3, -0.4), (1.0, 0.0)):
        a = policy.act(make_obs([0, 0, *vel, 8.0, 0.0]))[0, 0]
        assert a[0].item() == pytest.approx(V_MAX, abs=2e-3)
        assert abs(a[1].item()) < 2e-3
    # close to the goal it slows down so as not to overshoot: dist / dt = 0.1 / 0.25
    a = policy.act(make_obs([0, 0, 1.0, 0.0, 0.1, 0.0]))[0, 0]
    assert a.norm().item() == pytest.approx(0.4, abs=2e-3)
    assert a[0].item() > 0.39


def test_unobserved_humans_are_ignored():
    # a human right on the path but flagged unobserved changes nothing
    policy = ORCA()
    free = policy.act(make_obs([0, 0, 1.0, 0.0, 8.0, 0.0]))
    hidden = policy.act(make_obs([0, 0, 1.0, 0.0, 8.0, 0.0], [[1.0, 0.0, -1.0, 0.0]], observed=[False], m=3))
    assert torch.equal(free, hidden)


def test_standing_human_on_the_path_causes_a_lateral_deviation():
    a = ORCA().act(make_obs([0, 0, 1.0, 0.0, 8.0, 0.0], [[1.5, 0.0, 0.0, 0.0]]))[0, 0]
    assert abs(a[1].item()) > 0.1, f"no lateral avoidance: {a.tolist()}"
    assert a[0].item() < V_MAX - 0.05  # and it does not keep charging at full speed


@pytest.mark.parametrize("robot_vel", [(0.0, 0.0), (1.0, 0.0)])
def test_passes_a_standing_human_on_the_path_without_contact(robot_vel):
    reached, min_clear, max_lateral = toy_episode(ORCA(), (4.0, 0.0), (0.0, 0.0), robot_vel)
    assert reached, "the robot got stuck behind the human"
    assert min_clear >= 0.0
    assert max_lateral > RADII  # it went around, not through
    # a straight-line robot on the same course would have hit the human
    _, straight_clear, _ = toy_episode(StraightToGoal(), (4.0, 0.0), (0.0, 0.0), robot_vel)
    assert straight_clear < 0.0


def test_symmetry_breaking_is_what_unlocks_the_head_on_case():
    # without the perturbation a robot starting at rest stops in front of the human for good
    reached, min_clear, max_lateral = toy_episode(ORCA(perturb=0.0), (4.0, 0.0), (0.0, 0.0))
    assert not reached and max_lateral < 1e-3 and min_clear >= 0.0


def test_head_on_walker_is_avoided():
    reached, min_clear, _ = toy_episode(ORCA(), (7.0, 0.0), (-1.0, 0.0), (1.0, 0.0))
    assert reached and min_clear >= 0.0


def test_human_moving_away_faster_than_the_robot_is_no_obstacle():
    policy = ORCA()
    a = policy.act(make_obs([0, 0, 1.0, 0.0, 8.0, 0.0], [[1.0, 0.0, 1.5, 0.0]]))[0, 0]
    assert a[0].item() > V_MAX - 0.02 and abs(a[1].item()) < 0.02
    reached, min_clear, max_lateral = toy_episode(policy, (1.0, 0.0), (1.5, 0.0), (1.0, 0.0))
    assert reached and min_clear > 0.5 and max_lateral < 0.05


# --------------------------------------------------------------------------- interface
def test_shape_dtype_and_speed_limit():
    td = random_crowd_obs(batch=32, m=25, seed=1)
    a = ORCA().act(td)
    assert a.shape == (32, 1, 2) and a.dtype == torch.float32
    assert torch.isfinite(a).all()
    assert (a.norm(dim=-1) <= V_MAX + 1e-5).all()


def test_several_robots_per_environment():
    td = random_crowd_obs(batch=6, m=10, seed=2)
    obs = {k: v.view(3, 2, *v.shape[2:]) for k, v in td["agents", "observation"].items()}
    a = ORCA().act(obs_tensordict(obs, 3))
    assert a.shape == (3, 2, 2)
    assert torch.equal(a.view(6, 1, 2), ORCA().act(td))


def test_deterministic():
    td = random_crowd_obs(batch=16, m=30, seed=3)
    first = ORCA(seed=7).act(td)
    assert torch.equal(first, ORCA(seed=7).act(td))  # fresh instance
    policy = ORCA(seed=7)
    assert torch.equal(policy.act(td), policy.act(td.clone()))  # same instance, repeated


def test_batch_equals_single_calls():
    td = random_crowd_obs(batch=4, m=20, seed=4)
    policy = ORCA()
    batched = policy.act(td)
    singles = torch.cat([policy.act(td[i : i + 1]) for i in range(4)])
    assert torch.equal(batched, singles)


def test_actions_follow_the_observation_frame():
    # the same situation observed in the world frame and in the rotate frame gives the same world velocity
    sim = replay_sim(load_scene("students003"), 4)
    reset_v1(sim, 
        torch.ones(4, dtype=torch.bool), torch.tensor([40, 200, 400, 600]), torch.tensor([0.3, 1.9, 3.5, 5.0])
    )
    rotate = ORCA(perturb=0.0).act(obs_tensordict(sim.observe("rotate"), 4))
    world = ORCA(perturb=0.0, frame="world").act(obs_tensordict(sim.observe("world"), 4))
    c, s = sim.heading[..., 0], sim.heading[..., 1]  # world components of the rotate frame's x-axis
    x, y = rotate[..., 0], rotate[..., 1]
    rotated_back = torch.stack((c * x - s * y, s * x + c * y), -1)
    assert (world.norm(dim=-1) > 0.1).all()  # a real decision, not a trivial zero
    torch.testing.assert_close(rotated_back, world, atol=2e-3, rtol=0)


def test_rejects_bad_parameters():
    with pytest.raises(ValueError, match="frame"):
        ORCA(frame="polar")
    with pytest.raises(ValueError):
        ORCA(time_horizon=0.0)


# --------------------------------------------------------------------------- end to end
def run_episodes(policy, sim, t0, angle, steps=100):
    batch = sim.B
    reset_v1(sim, torch.ones(batch, dtype=torch.bool), t0, angle)
    min_clear = torch.full((batch,), math.inf)
    for _ in range(steps):
        running = (sim.outcome == RUNNING).squeeze(-1)
        if not running.any():
            break
        info = sim.step(policy.act(obs_tensordict(sim.observe(policy.frame), batch)), frame=policy.frame)
        swept = info.swept_clearance.squeeze(-1)
        min_clear = torch.where(running, torch.minimum(min_clear, swept), min_clear)
    return sim.outcome.squeeze(-1).clone(), min_clear


def test_end_to_end_students003_fewer_collisions_than_straight():
    batch = 16
    sim = replay_sim(load_scene("students003"), batch)
    t0 = torch.linspace(0, sim.scenario.last_start, batch + 2).long()[1:-1]  # fixed, spread over the recording
    angle = torch.arange(batch) * 2.399963  # golden-angle sequence around the circle
    orca_out, orca_clear = run_episodes(ORCA(), sim, t0, angle)
    straight_out, _ = run_episodes(StraightToGoal(), sim, t0, angle)

    for out in (orca_out, straight_out):
        assert (out != RUNNING).all()  # every episode ended with a recorded outcome within 100 steps
    orca_coll = int((orca_out == COLLISION).sum())
    straight_coll = int((straight_out == COLLISION).sum())
    assert orca_coll < straight_coll, (orca_coll, straight_coll)
    assert int((orca_out == SUCCESS).sum()) > int((straight_out == SUCCESS).sum())
    # ORCA's recorded outcome agrees with the clearance it actually kept
    assert torch.equal(orca_out == COLLISION, orca_clear < 0)
