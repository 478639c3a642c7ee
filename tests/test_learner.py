"""PER importance-sampling weights in the losses (``algo.per_weights``)."""

import pytest
import torch
from torchrl.collectors import Collector

from crowdbench.algos.multiagent import agent_transitions
from crowdbench.algos.offpolicy import KEEP
from crowdbench.algos.registry import component
from crowdbench.algos.train import train
from crowdbench.cli import compose

SMALL = ["encoder=mlp", "encoder.dim=16", "encoder.hidden=[32]", "env.batch=8", "algo.batch_size=16"]
# no target smoothing noise (TD3): a loss is a function of its batch alone
SMOOTHING = {"td3": ["algo.policy_noise=0.0"], "ddpg": []}


def sampled_batch(cfg):
    """A PER sample of 16 transitions collected by a random-init policy on students001."""
    from crowdbench.envs.factory import make_env

    env = make_env(cfg)
    torch.manual_seed(1)
    learner = component(cfg.algo.name)(cfg, env.n_agents)
    rb, policy = learner.rb, learner.collection_policy()
    for batch in Collector(env, policy, frames_per_batch=128, total_frames=128, auto_register_policy_transforms=False):
        rb.extend(agent_transitions(batch, KEEP))
    return rb.sample()


def critic_loss(cfg, sample) -> float:
    """``loss_critic`` of one critic-only update (step 1 of policy delay 2) from the same initial weights."""
    torch.manual_seed(0)
    return component(cfg.algo.name)(cfg, 1).update(sample.clone(), 1)["loss_critic"]


@pytest.mark.parametrize("algo", ["td3", "ddpg"])
def test_weighted_loss_is_the_weighted_mean(algo):
    """With weights one-hot at k the weighted critic loss is transition k's own loss; with uniform
    weights it is the plain mean; without per_weights the weights are ignored."""
    cfg_w = compose([f"algo={algo}", *SMALL, *SMOOTHING[algo], "algo.replay=prioritized", "algo.per_weights=true"])
    cfg_plain = compose([f"algo={algo}", *SMALL, *SMOOTHING[algo], "algo.replay=prioritized"])
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
        component("td3")(compose([*SMALL, "algo.per_weights=true", "algo.replay=uniform"]), 1)
