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
        cfg = compose([f"algo={algo}", *SMALL, "train.pretrain=null", "algo.replay=prioritized", "algo.per_weights=true", "train.frames_per_batch=64",
                       "algo.warmup=128", "train.utd=0.125", "train.total_frames=256"])
        stats = train(cfg, tmp_path / algo, progress=False)
        assert stats["updates"] > 0
    with pytest.raises(ValueError, match="per_weights=true needs algo.replay=prioritized"):
        component("td3")(compose([*SMALL, "algo.per_weights=true", "algo.replay=uniform"]), 1)


@pytest.mark.parametrize("per_weights", [False, True])
def test_td3_actor_term_equals_torchrls_with_critic_1_alone(per_weights):
    """``FirstCriticTD3Loss.actor_loss`` (critic 1 only) against TorchRL's ``TD3Loss.actor_loss`` (both
    critics vmapped, ``[0]`` kept) on the default recipe's gatedgcn lookahead critic: the same loss and the
    same actor gradients, and no gradient reaches the critics."""
    from torchrl.objectives import TD3Loss

    from crowdbench.algos.actors import leaf_action_spec
    from crowdbench.models.heads import prepare_batch

    over = ["encoder=gatedgcn", "encoder.dim=16", "env.batch=8", "algo.batch_size=16", "algo.replay=prioritized"]
    cfg = compose(over + (["algo.per_weights=true"] if per_weights else []))
    sample = sampled_batch(cfg)
    torch.manual_seed(0)
    learner = component("td3")(cfg, 1)
    mine = learner.loss
    prepare_batch(sample, *learner.encoders)
    if per_weights:  # shaped as OffPolicyAlgorithm.update hands them to the losses
        sample.set("priority_weight", sample["priority_weight"].reshape(-1, 1))
    reference = TD3Loss(mine.actor_network, mine.qvalue_network, action_spec=leaf_action_spec(1, learner.v_max),
                        num_qvalue_nets=2, use_prioritized_weights=per_weights)
    reference.load_state_dict(mine.state_dict(), strict=False)  # (no value estimator: the actor term needs none)
    reference.set_keys(**{k: getattr(mine.tensor_keys, k) for k in ("action", "state_action_value", "priority_weight")})

    grads = []
    for loss in (mine, reference):
        for p in loss.parameters():
            p.grad = None
        value, meta = loss.actor_loss(sample.clone())
        value.backward()
        grads.append([None if p.grad is None else p.grad.clone() for p in loss.actor_network_params.values(True, True)])
        assert all(p.grad is None or not p.grad.any() for p in loss.qvalue_network_params.values(True, True))
        if loss is mine:
            ours, q1 = value.detach(), meta["state_action_value_actor"]
    torch.testing.assert_close(ours, value.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(q1, meta["state_action_value_actor"][0], rtol=1e-5, atol=1e-6)
    assert sum(g is not None for g in grads[0]) > 0
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
