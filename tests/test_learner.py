"""PER importance-sampling weights in the losses (``algo.per_weights``)."""

import pytest
import torch
from torchrl.collectors import Collector

from crowdbench.algos.builders import exploration_policy
from crowdbench.algos.learner import Learner
from crowdbench.algos.multiagent import agent_transitions
from crowdbench.algos.train import KEEP, make_buffer, train
from crowdbench.cli import compose

SMALL = ["encoder=mlp", "encoder.dim=16", "encoder.hidden=[32]", "env.batch=8", "algo.batch_size=16",
         "algo.policy_noise=0.0"]  # no target smoothing noise: a loss is a function of its batch alone


def sampled_batch(cfg):
    """A PER sample of 16 transitions collected by a random-init policy on students001."""
    from crowdbench.envs.factory import make_env

    env = make_env(cfg)
    torch.manual_seed(1)
    learner = Learner(cfg)
    rb = make_buffer(cfg.algo, torch.Generator().manual_seed(0))
    policy = exploration_policy(cfg.algo.name, learner.actor, env.n_agents, cfg.env.v_max, 0.3)
    for batch in Collector(env, policy, frames_per_batch=128, total_frames=128, auto_register_policy_transforms=False):
        rb.extend(agent_transitions(batch, KEEP))
    return rb.sample()


def critic_loss(cfg, sample) -> float:
    """``loss_critic`` of one critic-only update (step 1 of policy delay 2) from the same initial weights."""
    torch.manual_seed(0)
    return Learner(cfg).update(sample.clone(), 1)["loss_critic"]


@pytest.mark.parametrize("algo", ["td3", "ddpg"])
def test_weighted_loss_is_the_weighted_mean(algo):
    """With weights one-hot at k the weighted critic loss is transition k's own loss; with uniform
    weights it is the plain mean; without per_weights the weights are ignored."""
    cfg_w = compose([f"algo={algo}", *SMALL, "algo.replay=prioritized", "algo.per_weights=true"])
    cfg_plain = compose([f"algo={algo}", *SMALL, "algo.replay=prioritized"])
    sample = sampled_batch(cfg_plain)
    n, k = sample.batch_size[0], 5
    assert sample["priority_weight"].shape == (n,)

    one_hot = sample.clone()
    one_hot["priority_weight"] = torch.zeros(n).index_fill_(0, torch.tensor([k]), 0.7)
    alone = critic_loss(cfg_plain, sample[k : k + 1])
    assert critic_loss(cfg_w, one_hot) == pytest.approx(alone, rel=1e-5)

    flat = sample.clone()
    flat["priority_weight"] = torch.full((n,), 0.3)
    mean = critic_loss(cfg_plain, sample)
    assert critic_loss(cfg_w, flat) == pytest.approx(mean, rel=1e-5)
    assert critic_loss(cfg_plain, one_hot) == pytest.approx(mean, rel=1e-6)  # off: weights not read
    assert abs(alone - mean) > 1e-6 * mean  # the two expectations differ, so the checks above can fail


def test_per_weights_train_and_need_per(tmp_path):
    for algo in ("td3", "sac"):
        cfg = compose([f"algo={algo}", *SMALL, "algo.replay=prioritized", "algo.per_weights=true", "train.frames_per_batch=64",
                       "algo.warmup=128", "train.utd=0.125", "train.total_frames=256"])
        stats = train(cfg, tmp_path / algo, progress=False)
        assert stats["updates"] > 0
    with pytest.raises(ValueError, match="per_weights=true needs algo.replay=prioritized"):
        Learner(compose([*SMALL, "algo.per_weights=true", "algo.replay=uniform"]))
