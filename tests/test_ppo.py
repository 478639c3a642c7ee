"""PPO (crowdbench/algos/ppo.py): GAE and the clipped objective against values computed by hand, every
encoder end to end, self-play, resume."""

import math

import pytest
import torch
from torchrl.collectors import Collector

from crowdbench.algos.actors import LOG_PROB
from crowdbench.algos.checkpoint import load_checkpoint, policy_from_checkpoint
from crowdbench.algos.ppo import ADVANTAGE, PPO, VALUE, VALUE_TARGET
from crowdbench.algos.train import train
from crowdbench.cli import compose
from crowdbench.envs.factory import make_env
from crowdbench.envs.observation import ACTION, GROUP
from crowdbench.protocols.replay import evaluate

SMALL = ["train.pretrain=null", "algo=ppo", "encoder=mlp", "encoder.dim=16", "encoder.hidden=[32]", "env.batch=4"]


def collected(cfg, frames: int = 128):
    env = make_env(cfg)
    torch.manual_seed(0)
    algo = PPO(cfg, env.n_agents)
    batch = next(iter(Collector(env, algo.collection_policy(), frames_per_batch=frames, total_frames=frames,
                                auto_register_policy_transforms=False)))
    return algo, batch


@pytest.mark.parametrize("env", ["replay", "selfplay"])
def test_gae_equals_a_loop_over_time(env):
    """delta_t = r_t + gamma V(s_t+1) (1 - terminated_t) - V(s_t); A_t = delta_t + gamma lambda (1 - done_t) A_t+1,
    per environment and agent, the batch's last step bootstrapping from its next state."""
    extra = ["env=selfplay", "env.n_agents=3"] if env == "selfplay" else []
    cfg = compose([*SMALL, "algo.gamma=0.9", "algo.lmbda=0.8", *extra])
    algo, batch = collected(cfg, 128 if env == "replay" else 512)
    value = algo.loss.critic_network
    with torch.no_grad():
        v = value(batch.clone())[VALUE]  # [B, T, A, 1]
        v_next = value(batch["next"].clone())[VALUE]
        algo.loss.value_estimator(batch)
    r, done, term = (batch["next", GROUP, k].float() for k in ("reward", "done", "terminated"))
    assert done.any() and not done.all()  # episodes end inside the batch: the cut is exercised
    B, T = batch.batch_size
    expected = torch.zeros_like(v)
    for b in range(B):
        for i in range(v.shape[2]):
            adv = 0.0
            for t in reversed(range(T)):
                delta = r[b, t, i] + 0.9 * v_next[b, t, i] * (1 - term[b, t, i]) - v[b, t, i]
                adv = delta + (0.9 * 0.8 * (1 - done[b, t, i]) * adv if t < T - 1 else 0.0)
                expected[b, t, i] = adv
    torch.testing.assert_close(batch[ADVANTAGE], expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(batch[VALUE_TARGET], expected + v, rtol=1e-5, atol=1e-5)


def test_clipped_objective_and_value_loss_by_hand():
    """On a minibatch whose old log-probabilities are set so that the ratios are known (inside and
    outside the clip range, for positive and negative advantages)."""
    eps = 0.2
    cfg = compose([*SMALL, f"algo.clip_epsilon={eps}", "algo.normalize_advantage=false", "algo.entropy_coef=0",
                   "algo.critic_coef=0.5"])
    algo, batch = collected(cfg)
    with torch.no_grad():
        algo.loss.value_estimator(batch)
    td = batch.reshape(-1)[:8].clone()
    with torch.no_grad():
        logp = algo.actor.get_dist(td).log_prob(td[ACTION])  # [8, 1]
    ratios = torch.tensor([0.5, 0.9, 1.0, 1.1, 1.5, 0.7, 1.3, 2.0]).view(8, 1)
    adv = torch.tensor([1.0, -1.0, 2.0, 0.5, -0.5, 1.0, 1.5, -2.0]).view(8, 1, 1)
    td.set(LOG_PROB, logp - ratios.log())
    td.set(ADVANTAGE, adv)
    out = algo.loss(td)
    a = adv.view(-1)
    rho = ratios.view(-1)
    expected = -torch.minimum(rho * a, rho.clamp(1 - eps, 1 + eps) * a).mean()
    assert out["loss_objective"].item() == pytest.approx(expected.item(), rel=1e-4)
    with torch.no_grad():
        v = algo.loss.critic_network(td.clone())[VALUE]
    expected_v = 0.5 * ((v - td[VALUE_TARGET]) ** 2).mean()
    assert out["loss_critic"].item() == pytest.approx(expected_v.item(), rel=1e-4)
    clipped = ((rho - 1).abs() > eps).float().mean().item()
    assert out["clip_fraction"].item() == pytest.approx(clipped)
    assert 0 < clipped < 1 and not math.isclose(expected.item(), -(rho * a).mean().item())  # the clip binds


@pytest.mark.parametrize("encoder", ["gatedgcn", "gcn", "mlp", "sarl", "lstm_rl", "rgl", "gat", "dsrnn"])
def test_every_encoder_trains_and_checkpoints(encoder, tmp_path):
    small = ["encoder.dim=16"] + (["encoder.hidden=[32]"] if encoder == "mlp" else [])
    cfg = compose(["train.pretrain=null", "algo=ppo", f"encoder={encoder}", *small, "env.batch=8", "train.frames_per_batch=128",
                   "algo.minibatch_size=64", "algo.epochs=2", "train.total_frames=256", "train.checkpoint_every=128"])
    stats = train(cfg, tmp_path, progress=False)
    assert stats["frames"] == 256 and stats["updates"] == 2 * 2 * 2
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["config"]["algo"]["name"] == "ppo" and state["updates"] == 8
    res = evaluate(policy_from_checkpoint(tmp_path / "checkpoint.pt"), ["hotel"], episodes=2)
    assert res["scenes"]["hotel"]["success_rate"]["n"] == 2


def test_self_play_trains_every_agent_on_the_shared_policy(tmp_path):
    """Each agent's own transitions enter the update: the minibatch count follows agents x steps."""
    cfg = compose(["train.pretrain=null", "algo=ppo", "env=selfplay", "env.n_agents=4", "encoder=gatedgcn", "encoder.dim=16",
                   "env.batch=8", "train.frames_per_batch=64", "algo.minibatch_size=64", "algo.epochs=1",
                   "train.total_frames=128"])
    stats = train(cfg, tmp_path, progress=False)
    # 64 env steps x 4 agents = 256 agent transitions per batch at most (fewer once agents are done)
    assert stats["frames"] == 128 and 2 < stats["updates"] <= 2 * 4
