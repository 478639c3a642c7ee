"""TorchRL EnvBase: spec checks, partial resets and agreement with the core."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs
from worlds import replay_sim, reset_v1

from crowdbench.envs.factory import replay_env
from crowdbench.envs.transforms import HumanDropout, HumanThinning, ProgressReward


@pytest.mark.parametrize("batch", [1, 4])
def test_check_env_specs(batch):
    check_env_specs(replay_env("students001", batch, seed=0))


def test_rollout_autoresets_done_envs():
    env = replay_env("hotel", 6, seed=1)
    td = env.rollout(150, break_when_any_done=False)  # [B, T]
    done = td["next", "done"].squeeze(-1)
    assert done.any(1).all()  # every env finished an episode within 150 steps (time limit 100)
    r = td["next", "agents", "reward"][..., 0, 0]
    assert (r[done] != 0).all()  # the final step carries r_reach or r_fail
    b, k = done.nonzero()[0].tolist()
    # the step after a done starts a new episode: robot at the start, zero velocity, goal 8 m away
    robot = td["agents", "observation", "robot"][b, k + 1, 0]
    assert robot[2:4].abs().sum() == 0 and robot[4:6].norm().item() == pytest.approx(8.0, abs=1e-4)


def test_same_seed_same_rollout():
    a = replay_env("zara2", 3, seed=5)
    b = replay_env("zara2", 3, seed=5)
    torch.manual_seed(0)
    ra = a.rollout(40, break_when_any_done=False)
    torch.manual_seed(0)
    rb = b.rollout(40, break_when_any_done=False)
    assert torch.equal(ra["next", "agents", "observation", "humans"], rb["next", "agents", "observation", "humans"])
    assert torch.equal(ra["next", "agents", "reward"], rb["next", "agents", "reward"])


def test_fixed_episode_list_and_world_agreement():
    t0, angle = torch.tensor([30, 60]), torch.tensor([0.3, 2.0])
    env = replay_env("students003", 2, episodes=(t0, angle))
    td = env.reset()
    sim = replay_sim(env.world.scene, 2)
    reset_v1(sim, torch.ones(2, dtype=torch.bool), t0, angle)
    assert torch.equal(td["agents", "observation", "humans"], sim.observe()["humans"])
    action = torch.tensor([[[0.6, 0.1]], [[0.2, -0.4]]])
    td["agents", "action"] = action
    out = env.step(td)["next"]
    info = sim.step(action)
    assert torch.equal(out["agents", "reward"][..., 0], info.reward)
    assert torch.equal(out["agents", "observation", "robot"], sim.observe()["robot"])


def test_nan_action_raises():
    env = replay_env("eth", 1)
    td = env.reset()
    td["agents", "action"] = torch.full((1, 1, 2), math.nan)
    with pytest.raises(ValueError, match="NaN"):
        env.step(td)
    td["agents", "action"] = torch.full((1, 1, 2), math.inf)  # would be NaN after the frame rotation
    with pytest.raises(ValueError, match="inf"):
        env.step(td)


def test_progress_reward_pays_per_metre_towards_the_goal():
    """Rotated frame: action (0.6, 0.8) moves 0.15 m towards the goal and 0.2 m sideways in 0.25 s."""
    t0, angle = torch.tensor([30, 60]), torch.tensor([0.3, 2.0])
    plain = replay_env("students003", 2, episodes=(t0, angle))
    shaped = TransformedEnv(replay_env("students003", 2, episodes=(t0, angle)), ProgressReward(0.5))
    check_env_specs(shaped)
    action = torch.tensor([[[0.6, 0.8]], [[0.0, 0.0]]])
    rewards = []
    for env in (plain, shaped):
        td = env.reset()
        td["agents", "action"] = action
        rewards.append(env.step(td)["next", "agents", "reward"][:, 0, 0])
    # distance to goal 8 m before; after: sqrt((8 - 0.15)^2 + 0.2^2)
    progress = 8.0 - math.hypot(8.0 - 0.15, 0.2)
    assert rewards[1][0] - rewards[0][0] == pytest.approx(0.5 * progress, abs=1e-5)
    assert rewards[1][1] == rewards[0][1]  # standing still earns nothing


def test_human_dropout_hides_humans_for_a_whole_episode():
    base = replay_env("students001", 64, seed=0)
    env = TransformedEnv(base, HumanDropout(1.0, seed=0, n_slots=base.world.M, n_humans=base.world.Mh))
    td = env.reset()
    keep = env.transform.keep
    valid = base.world.scene.valid[base.world.t]
    kept = (keep & valid).sum(1).float() / valid.sum(1).clamp_min(1)
    assert 0.3 < kept.mean().item() < 0.7  # E[1 - u] = 0.5 for u ~ U(0, 1)
    assert kept.std().item() > 0.1  # the density varies between episodes
    for _ in range(5):
        seen = td["agents", "observation", "humans_mask"][:, 0]
        assert not (seen & ~keep).any()  # a hidden human is never observed ...
        assert (td["agents", "observation", "humans"][:, 0][~keep] == 0).all()
        assert seen.any()  # ... while the kept ones are
        td["agents", "action"] = torch.zeros(64, 1, 2)
        td = env.step(td)["next"]
    assert torch.equal(env.transform.keep, keep)  # no env was reset: the same humans stay hidden
    _, _, hvalid = base.world.humans()
    assert (hvalid & ~keep).any()  # ... but they are still in the world (they can be hit)
    with pytest.raises(ValueError, match="human_dropout"):
        HumanDropout(1.5, seed=0, n_slots=3, n_humans=3)


def test_human_thinning_removes_humans_from_the_world_per_episode():
    base = replay_env("students001", 64, seed=0)
    env = TransformedEnv(base, HumanThinning(1.0, seed=0))
    td = env.reset()
    crowd = base.world.crowd
    keep = crowd.keep.clone()
    valid = base.world.scene.valid[crowd.t]
    kept = (keep & valid).sum(1).float() / valid.sum(1).clamp_min(1)
    assert 0.3 < kept.mean().item() < 0.7  # E[1 - u] = 0.5 for u ~ U(0, 1)
    for _ in range(5):
        _, _, hvalid = base.world.humans()
        assert not (hvalid & ~keep).any()  # a removed human is not in the world (cannot be hit) ...
        assert (hvalid & keep).any()
        seen = td["agents", "observation", "humans_mask"][:, 0]
        assert seen.any() and not (seen & ~keep).any()  # ... nor seen
        td["agents", "action"] = torch.zeros(64, 1, 2)
        td = env.step(td)["next"]
    assert torch.equal(crowd.keep, keep)  # no env was reset: the same humans stay removed
    reset = torch.zeros(64, 1, dtype=torch.bool)
    reset[:3] = True
    env.reset(TensorDict({"_reset": reset}, batch_size=[64]))
    assert torch.equal(crowd.keep[3:], keep[3:])  # a partial reset redraws only the envs it starts anew
    assert not torch.equal(crowd.keep[:3], keep[:3])
    with pytest.raises(ValueError, match="human_thinning"):
        HumanThinning(-0.1, seed=0)
