"""The environments as a library: reset options and actions are checked as the PettingZoo env checks
them (one line naming the option or the action), never truncated, ignored or silently promoted."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crowdbench.cli import compose
from crowdbench.envs.crowdnav_cases import CROWDNAV
from crowdbench.envs.factory import make_parallel_env, replay_env, replay_parallel_env

GROUP = "agents"


@pytest.mark.parametrize("t0", [float("nan"), "abc", [1, 2, 3], 2.5, True])
def test_replay_t0_option_names_itself(t0):
    """L12: ``cannot convert float NaN to integer``, ``invalid literal for int()``, a TypeError."""
    env = replay_parallel_env("hotel")
    with pytest.raises(ValueError, match=r"options\['t0'\]"):
        env.reset(seed=0, options={"t0": t0})
    env.reset(seed=0, options={"t0": np.int64(12)})  # numpy integers stay valid
    assert env.agents


@pytest.mark.parametrize("angle", ["abc", [1.0], None])
def test_replay_angle_option_names_itself(angle):
    with pytest.raises(ValueError, match=r"options\['angle'\]"):
        replay_parallel_env("hotel").reset(seed=0, options={"angle": angle})


def test_selfplay_start_needs_one_point_per_agent():
    """L12: 3 points for 4 agents gave ``RuntimeError: shape '[1, 4, 2]' is invalid``."""
    env = make_parallel_env(compose(["env=selfplay", "env.n_agents=4"]).env)
    for bad in ([[0.0, 0.0]] * 3, [[0.0, 0.0, 0.0]] * 4, "here"):
        with pytest.raises(ValueError, match=r"options\['start'\] must be 4 points"):
            env.reset(seed=0, options={"start": bad})
    with pytest.raises(ValueError, match=r"options\['t0'\]"):
        env.reset(seed=0, options={"t0": 1.5})


@pytest.mark.parametrize("case", [-1, 2.5, CROWDNAV.test_size, "3"])
def test_crowdnav_case_is_a_test_case_number(case):
    """L12: ``case=-1`` gave a shape-mismatch RuntimeError and ``case=2.5`` was read as 2."""
    env = make_parallel_env(compose(["env=crowdnav"]).env)
    with pytest.raises(ValueError, match=rf"options\['case'\] must be an integer in \[0, {CROWDNAV.test_size}\)"):
        env.reset(seed=0, options={"case": case})
    env.reset(seed=0, options={"case": np.int32(2)})


@pytest.mark.parametrize("shape", [(2, 1, 3), (2, 1, 1), (2, 1, 2, 1)])  # (batch dims: tensordict checks them)
def test_torchrl_action_of_the_wrong_shape_is_refused(shape):
    """L13: ``[B, A, 3]`` was accepted (third component ignored), ``[B, A, 1]`` an IndexError."""
    env = replay_env("hotel", batch=2, seed=0)
    td = env.reset()
    td[GROUP, "action"] = torch.zeros(shape)
    with pytest.raises(ValueError, match=r"action must have shape \[2, 1, 2\]"):
        env.step(td)


def test_torchrl_float64_actions_act_as_their_float32_values():
    """L13: a float64 action promoted the world's state to float64 for good (off the spec, another path)."""
    runs = []
    for dtype in (torch.float32, torch.float64):
        env = replay_env("hotel", batch=2, seed=0)
        td = env.reset()
        gen = torch.Generator().manual_seed(1)
        for _ in range(5):
            td[GROUP, "action"] = torch.rand(2, 1, 2, generator=gen).to(dtype)
            td = env.step(td)["next"]
        assert env.world.pos.dtype == torch.float32
        assert env.observation_spec.is_in(td.select(*env.observation_spec.keys(True, True)))
        runs.append(env.world.pos.clone())
    assert torch.equal(runs[0], runs[1])
