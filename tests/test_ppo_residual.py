"""PPO, IPPO and MAPPO on an ORCA base (``algo.actor_base=orca``, crowdbench/algos/actors.py): the TanhNormal
actor samples a residual of at most ``algo.actor_residual`` per component, the action is ``P(ORCA(s) + r)``,
and the clipped objective reads the log-probability of the residual."""

from __future__ import annotations

import math

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType, set_exploration_type

from crowdbench.algos.actors import LOG_PROB, RESIDUAL, residual_distribution
from crowdbench.algos.checkpoint import load_checkpoint, policy_from_checkpoint
from crowdbench.algos.registry import component as algorithm_class
from crowdbench.algos.train import train
from crowdbench.cli import compose
from crowdbench.envs.factory import make_env
from crowdbench.envs.observation import ACTION
from crowdbench.kinematics import clip_speed
from crowdbench.models.heads import OBS_KEYS
from crowdbench.policies import build

SMALL = ["train.pretrain=null", "encoder=gatedgcn", "encoder.dim=16", "env.batch=4", "algo.actor_base=orca"]
SELFPLAY = ["env=selfplay", "env.n_agents=4"]


def _collected(cfg, frames: int):
    env = make_env(cfg)
    torch.manual_seed(0)
    algo = algorithm_class(cfg.algo.name)(cfg, env.n_agents)
    batch = next(iter(Collector(env, algo.collection_policy(), frames_per_batch=frames, total_frames=frames,
                                auto_register_policy_transforms=False)))
    return algo, batch


@pytest.mark.parametrize("algo", ["ppo", "mappo"])
def test_the_untrained_actor_acts_as_the_orca_baseline(algo):
    cfg = compose([*SMALL, f"algo={algo}", *SELFPLAY])
    _, batch = _collected(cfg, 64)
    obs = batch.reshape(-1).select(*OBS_KEYS)
    assert obs["agents", "observation", "humans_mask"].any()
    actor = algorithm_class(algo)(cfg, 4).actor
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        mine = actor(obs.clone())[ACTION]
    # what the world executes (the speed clipped into the disc, which ORCA's solver can leave by a rounding)
    assert torch.equal(mine, clip_speed(build("orca", cfg).act(obs), cfg.env.v_max))


def test_the_sampled_residual_is_bounded_and_the_action_is_orca_plus_it_in_the_disc():
    cfg = compose([*SMALL, "algo=ppo", "algo.actor_residual=0.4", *SELFPLAY])
    _, batch = _collected(cfg, 64)
    flat = batch.reshape(-1)
    res, act = flat[RESIDUAL], flat[ACTION]
    assert res.abs().max() <= 0.4 and res.abs().max() > 0.2  # explored across the box, inside it
    base = build("orca", cfg).act(flat.select(*OBS_KEYS)).reshape(-1, 2).tolist()
    expected = []
    for (bx, by), (rx, ry) in zip(base, res.reshape(-1, 2).tolist(), strict=True):
        sx, sy = bx + rx, by + ry
        n = math.hypot(sx, sy)
        expected.append([sx / n, sy / n] if n > 1.0 else [sx, sy])
    assert torch.allclose(act.reshape(-1, 2), torch.tensor(expected), atol=1e-6)


def test_the_loss_reads_the_log_probability_of_the_residual():
    """Before any update the policy that collected is the one evaluated: the ratio is 1 on every transition
    (nothing clipped, the approximate KL zero), which holds only if the loss scores the stored residual."""
    cfg = compose([*SMALL, "algo=ppo", *SELFPLAY])
    algo, batch = _collected(cfg, 64)
    assert algo.loss.tensor_keys.action == RESIDUAL and residual_distribution(algo.actor) is algo.loss.actor_network
    with torch.no_grad():
        algo.loss.value_estimator(batch)
        out = algo.loss(batch.reshape(-1))
        dist = residual_distribution(algo.actor).get_dist(batch.reshape(-1).select(*OBS_KEYS))
        lp = dist.log_prob(batch.reshape(-1)[RESIDUAL])
    assert float(out["clip_fraction"]) == 0.0 and abs(float(out["kl_approx"])) < 1e-5
    assert torch.allclose(lp.reshape(-1), batch.reshape(-1)[LOG_PROB].reshape(-1), atol=1e-4)


def test_a_mappo_run_checkpoints_and_its_policy_acts_as_in_training(tmp_path):
    cfg = compose([*SMALL, "algo=mappo", *SELFPLAY, "train.frames_per_batch=64", "train.total_frames=128",
                   "algo.minibatch_size=64", "train.checkpoint_every=64"])
    stats = train(cfg, tmp_path, progress=False)
    assert stats["updates"] > 0
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["config"]["algo"]["actor_base"] == "orca"
    policy = policy_from_checkpoint(tmp_path / "checkpoint.pt")
    _, batch = _collected(cfg, 64)
    obs = batch.reshape(-1).select(*OBS_KEYS)
    algo = algorithm_class("mappo")(cfg, 4)
    algo.actor.load_state_dict(state["actor"])
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        trained = algo.actor(obs.clone())[ACTION]
    assert torch.equal(policy.act(obs.clone()), trained)
    assert not torch.equal(trained, build("orca", cfg).act(obs))  # it learned a residual

