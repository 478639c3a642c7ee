"""The PettingZoo ParallelEnv view: API compliance, seeding, and equivalence with the core."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test, parallel_seed_test
from worlds import replay_sim, reset_v1

from crowdbench.data.scenes import load_scene
from crowdbench.envs.factory import replay_parallel_env
from crowdbench.envs.rules import SimConfig

AGENT = "robot_0"


def test_parallel_api():
    env = replay_parallel_env()
    parallel_api_test(env, num_cycles=300)  # > time_limit: episodes run to their end


def test_parallel_seed():
    # note: parallel_seed_test only compares the first step (its `any(terminations)` is over
    # the dict's keys), hence the longer determinism check below
    parallel_seed_test(lambda: replay_parallel_env("students001"), num_cycles=50)


def test_parallel_seed_test_catches_an_env_that_ignores_its_seed():
    """The suite call above can fail: an env whose reset draws its own seed is refused."""

    def unseeded():
        env = replay_parallel_env("students001")
        seeded_reset = env.reset
        env.reset = lambda seed=None, options=None: seeded_reset(seed=None, options=options)
        return env

    with pytest.raises(AssertionError):
        parallel_seed_test(unseeded, num_cycles=5)


def rollout(env, seed, n=40):
    obs, infos = env.reset(seed=seed)
    env.action_space(AGENT).seed(seed)
    trace = [(obs, infos)]
    while env.agents and n:
        out = env.step({a: env.action_space(a).sample() for a in env.agents})
        trace.append(out)
        n -= 1
    return trace


def assert_same(x, y):
    if isinstance(x, dict):
        assert x.keys() == y.keys()
        for k in x:
            assert_same(x[k], y[k])
    elif isinstance(x, tuple | list):
        assert len(x) == len(y)
        for a, b in zip(x, y, strict=True):
            assert_same(a, b)
    elif isinstance(x, np.ndarray):
        assert x.dtype == y.dtype and np.array_equal(x, y)
    else:
        assert x == y


def test_reset_seed_reproducible():
    env = replay_parallel_env()
    a = rollout(env, 7)
    b = rollout(env, 7)  # same env object, re-seeded
    c = rollout(replay_parallel_env(), 7)
    assert_same(a, b)
    assert_same(a, c)
    env.reset(seed=7)
    ep7 = env.episode
    env.reset(seed=8)
    assert env.episode != ep7
    env.reset()  # unseeded reset continues the stream: a new episode
    assert env.episode != ep7


def test_spaces_and_observation_layout():
    env = replay_parallel_env()
    assert env.metadata["name"] == "crowdbench_v1"
    assert env.possible_agents == [AGENT]
    assert env.observation_space(AGENT) is env.observation_space(AGENT)
    assert env.action_space(AGENT) is env.action_space(AGENT)
    m = env.world.M
    obs, infos = env.reset(seed=0)
    assert env.agents == [AGENT]
    o = obs[AGENT]
    assert o["robot"].shape == (6,) and o["humans"].shape == (m, 4) and o["humans_mask"].shape == (m,)
    assert all(v.dtype == np.float32 for v in o.values())
    assert env.observation_space(AGENT).contains(o)
    assert infos[AGENT]["outcome"] == "running"
    act = env.action_space(AGENT)
    assert act.dtype == np.float32 and act.shape == (2,)
    assert np.all(act.low == -1.0) and np.all(act.high == 1.0)
    for _ in range(10):
        obs, rew, term, trunc, info = env.step({AGENT: act.sample()})
        assert env.observation_space(AGENT).contains(obs[AGENT])
        assert type(rew[AGENT]) is float and type(term[AGENT]) is bool and type(trunc[AGENT]) is bool
        assert isinstance(info[AGENT]["outcome"], str) and type(info[AGENT]["clearance"]) is float


def test_reset_options_pick_episode():
    env = replay_parallel_env()
    _, infos = env.reset(options={"t0": 123, "angle": 0.5})
    assert env.episode == {"t0": 123, "angle": 0.5}
    assert infos[AGENT]["t0"] == 123 and infos[AGENT]["angle"] == 0.5
    assert env.world.t.item() == 123
    start = env.world.start[0, 0]
    c = env.world.scene.centre
    expected = c + 4.0 * torch.tensor([math.cos(0.5), math.sin(0.5)])
    assert torch.allclose(start, expected, atol=1e-5)
    with pytest.raises(ValueError, match="start index"):
        env.reset(options={"t0": 10**6})


@pytest.mark.parametrize("frame", ["rotate", "world"])
def test_same_core_as_direct_sim(frame):
    """The PettingZoo view and a direct B=1 world give identical observations and rewards."""
    cfg = SimConfig(frame=frame)
    env = replay_parallel_env("students001", cfg=cfg)
    sim = replay_sim(load_scene("students001", cfg.dt, cfg.time_base), 1, cfg)
    t0, angle = 200, 2.0
    obs, _ = env.reset(options={"t0": t0, "angle": angle})
    reset_v1(sim, torch.ones(1, dtype=torch.bool), torch.tensor([t0]), torch.tensor([angle]))

    def check(o_env, o_sim):
        for k in ("robot", "humans", "humans_mask"):
            ref = o_sim[k][0, 0].to(torch.float32).numpy()
            np.testing.assert_array_equal(o_env[AGENT][k], ref)

    check(obs, sim.observe())
    rng = np.random.default_rng(0)
    n = 0
    while env.agents:
        a = rng.uniform(-1.3, 1.3, 2).astype(np.float32)  # partly out of the Box: clipped by the core
        obs, rew, term, trunc, info = env.step({AGENT: a})
        ref = sim.step(torch.from_numpy(a).view(1, 1, 2))
        check(obs, sim.observe())
        assert rew[AGENT] == ref.reward[0, 0].item()
        assert term[AGENT] == ref.terminated[0, 0].item()
        assert trunc[AGENT] == ref.truncated[0, 0].item()
        assert info[AGENT]["clearance"] == ref.clearance[0, 0].item()
        n += 1
    assert n == env.world.steps.item() and n <= cfg.time_limit


def test_agent_removed_after_termination():
    env = replay_parallel_env()
    obs, _ = env.reset(seed=3, options={"angle": 1.0})
    done = False
    for _ in range(env.cfg.time_limit):
        # straight to the goal (rotate frame: goal direction is the x-axis of the observation)
        g = obs[AGENT]["robot"][4:6]
        a = g / max(np.linalg.norm(g), 1e-9) * min(np.linalg.norm(g) / env.cfg.dt, 1.0)
        obs, _, term, trunc, info = env.step({AGENT: a.astype(np.float32)})
        if term[AGENT] or trunc[AGENT]:
            done = True
            break
        assert env.agents == [AGENT]
    assert done
    assert env.agents == []
    assert info[AGENT]["outcome"] in ("success", "collision", "timeout")
    assert (info[AGENT]["outcome"] == "timeout") == trunc[AGENT]
    with pytest.raises(RuntimeError, match="reset"):
        env.step({AGENT: np.zeros(2, np.float32)})
    env.reset()
    assert env.agents == [AGENT]


def test_timeout_truncates():
    env = replay_parallel_env(cfg=SimConfig(time_limit=5))
    env.reset(seed=0)  # a standing robot meets nobody within 5 steps in this episode
    for _ in range(4):
        _, rew, term, trunc, info = env.step({AGENT: np.zeros(2, np.float32)})
        assert not term[AGENT] and not trunc[AGENT] and env.agents == [AGENT]
    _, rew, term, trunc, info = env.step({AGENT: np.zeros(2, np.float32)})
    assert info[AGENT]["outcome"] == "timeout"
    assert trunc[AGENT] and not term[AGENT] and env.agents == []
    assert rew[AGENT] == -0.25


def test_nan_action_raises():
    env = replay_parallel_env()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="robot_0.*not finite"):
        env.step({AGENT: np.array([np.nan, 0.0], np.float32)})
    with pytest.raises(ValueError, match="robot_0.*not finite"):
        env.step({AGENT: np.array([np.inf, np.inf], np.float32)})
    env.step({AGENT: np.zeros(2, np.float32)})  # the env is still usable


def test_bad_actions_raise():
    env = replay_parallel_env()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="missing action"):
        env.step({})
    with pytest.raises(ValueError, match="unknown agents"):
        env.step({AGENT: np.zeros(2), "robot_9": np.zeros(2)})
    with pytest.raises(ValueError, match="2 elements"):
        env.step({AGENT: np.zeros(3)})


def test_unknown_scene_names_valid_scenes():
    with pytest.raises(ValueError, match="unknown scene 'atlantis'.*students001.*zara2"):
        replay_parallel_env("atlantis")


def test_render_mode_none_only():
    with pytest.raises(ValueError, match="render_mode"):
        replay_parallel_env(render_mode="human")
