"""Self-play at 64-128 agents: each agent observes its ``env.obs_slots`` nearest bodies, so the
observation (and the graph an encoder builds from it) grows linearly with the number of agents."""

import torch
from pettingzoo.test import parallel_api_test
from torchrl.envs.utils import check_env_specs

from crowdbench.envs.factory import selfplay_env, selfplay_parallel_env, selfplay_world
from crowdbench.envs.selfplay import SelfPlayConfig


def on_a_line(slots: int):
    """Five agents on the x axis at 0, 1, 2.5, 4 and 9 m, all heading to +x (frame = world axes)."""
    world, _ = selfplay_world(SelfPlayConfig(n_agents=5, obs_slots=slots, scenario="square"), 1)
    start = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.5, 0.0], [4.0, 0.0], [9.0, 0.0]]])
    world.reset(torch.ones(1, dtype=torch.bool), {"start": start, "goal": start + torch.tensor([20.0, 0.0])})
    return world


def test_the_nearest_bodies_nearest_first():
    obs = on_a_line(2).observe()
    assert obs["humans"].shape == (1, 5, 2, 4)
    # agent 0 sees agents 1 and 2 at +1 m and +2.5 m; agent 3 sees 2 (1.5 m) then 1 (3 m); agent 4 sees 3
    # alone within the 5 m sensing range, its second slot empty
    assert obs["humans"][0, 0, :, 0].tolist() == [1.0, 2.5]
    assert obs["humans"][0, 3, :, 0].tolist() == [-1.5, -3.0]
    assert obs["humans_mask"][0, 4].tolist() == [True, False] and obs["humans"][0, 4, 0, 0] == -5.0
    assert not obs["humans"][0, 4, 1].any()


def test_slots_hold_the_full_views_nearest_rows():
    torch.manual_seed(0)
    cfg = SelfPlayConfig(n_agents=24, scenario="square", square_width=12.0, sensing_range=4.0)
    full, _ = selfplay_world(cfg, 6)
    capped, _ = selfplay_world(SelfPlayConfig(**{**cfg.__dict__, "obs_slots": 5}), 6)
    ep = selfplay_world(cfg, 6)[1].sampler(3)(6)
    action = torch.rand(6, 24, 2) - 0.5
    for w in (full, capped):  # the same episodes and one step of the same actions (velocities in the view)
        w.reset(torch.ones(6, dtype=torch.bool), ep)
        w.step(action)
    a, b = full.observe(), capped.observe()
    d2 = (a["humans"][..., :2] ** 2).sum(-1).masked_fill(~a["humans_mask"], float("inf"))
    order = d2.argsort(dim=-1, stable=True)[..., :5]
    want = a["humans"].gather(-2, order.unsqueeze(-1).expand(*order.shape, 4))
    keep = a["humans_mask"].gather(-1, order)
    torch.testing.assert_close(b["humans"], want * keep.unsqueeze(-1))
    assert torch.equal(b["humans_mask"], keep) and keep.any() and not keep.all()
    assert torch.equal(a["robot"], b["robot"])


def test_128_agents_pass_torchrls_and_pettingzoos_api_checks():
    cfg = SelfPlayConfig(n_agents=128, circle_radius=16.0, obs_slots=16)
    env = selfplay_env(2, cfg, seed=0)
    check_env_specs(env)
    assert env.observation_spec["agents", "observation", "humans"].shape == (2, 128, 16, 4)
    parallel_api_test(selfplay_parallel_env(cfg), num_cycles=30)
