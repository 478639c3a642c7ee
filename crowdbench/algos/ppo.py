"""PPO (Schulman et al. 2017) on the batched env: TorchRL's ``ClipPPOLoss`` and ``GAE``, readable top to bottom.

Each collected ``[B, T]`` batch (``B`` environments, hundreds to thousands of them) is used once:
GAE advantages and value targets over its time dimension, per agent, then ``epochs`` passes of
shuffled minibatches of the clipped objective, the value loss and an entropy bonus, then dropped.

Self-play (``env=selfplay``): every agent of the shared-weight policy contributes its own
transitions (algos/multiagent.py drops the frozen steps of agents already done), and the critic
is one shared-weight state-value network over each agent's own graph (MAPPO's parameter sharing,
with the agent's observation as its critic input: each agent is the root of its own graph, which
already holds the agents around it).

The actor is SAC's TanhNormal head (crowdbench/algos/actors.py): it explores by sampling and acts
by its mode when evaluated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from crowdbench.algos.actors import BASES, LOG_PROB, RESIDUAL, residual_distribution
from crowdbench.algos.base import Algorithm
from crowdbench.algos.multiagent import agent_transitions
from crowdbench.config_fields import bounded
from crowdbench.envs.observation import ACTION, GROUP
from crowdbench.models import make_encoder
from crowdbench.models.graph import unpack_obs
from crowdbench.models.heads import OBS_KEYS, mlp

VALUE = (GROUP, "state_value")
ADVANTAGE = (GROUP, "advantage")
VALUE_TARGET = (GROUP, "value_target")
# what a minibatch needs; the next reward only carries the "next" group through agent_transitions
KEEP = [(GROUP, "observation"), ACTION, LOG_PROB, ADVANTAGE, VALUE_TARGET, ("next", GROUP, "reward")]


@dataclass
class PPOConfig:
    """``algo=ppo``."""

    name: str = bounded("ppo", choices=("ppo",))
    gamma: float = bounded(0.99, gt=0, le=1)
    lmbda: float = bounded(0.95, ge=0, le=1)  # GAE's lambda
    lr: float = bounded(3.0e-4, gt=0)  # one Adam over actor and critic
    clip_epsilon: float = bounded(0.2, gt=0, lt=1)
    entropy_coef: float = bounded(1.0e-3, ge=0)
    critic_coef: float = bounded(0.5, ge=0)
    loss_critic_type: str = bounded("l2", choices=("l2", "l1", "smooth_l1"))
    epochs: int = bounded(4, ge=1)  # passes over each collected batch
    minibatch_size: int = bounded(1024, ge=1)  # transitions per gradient step
    max_grad_norm: float = bounded(1.0, gt=0)
    normalize_advantage: bool = True  # per minibatch
    # orca: the actor samples a residual of at most actor_residual m/s added to ORCA's velocity (algos/actors.py)
    actor_base: str = bounded("none", choices=BASES)
    actor_residual: float = bounded(0.15, gt=0)


class ValueNet(nn.Module):
    """``V(s) = MLP(robot_h(s))``: the encoder's agent state, no action (a state-value critic)."""

    def __init__(self, encoder: nn.Module, hidden: list | None = None):
        super().__init__()
        self.encoder = encoder
        hidden = list(hidden) if hidden is not None else [encoder.out_dim]
        self.head = mlp([encoder.out_dim, *hidden, 1])

    def forward(self, robot, humans=None, humans_mask=None):
        _, h = self.encoder(*unpack_obs(robot, humans, humans_mask))
        return self.head(h)


class PPO(Algorithm):
    name = "ppo"
    config = PPOConfig
    actor_kind = "tanh_normal"
    resume_fields = ("loss", "opt", "replay_rng")
    keep = tuple(KEEP)  # what a minibatch reads

    def __init__(self, cfg, n_agents: int):
        super().__init__(cfg, n_agents)
        a = self.a
        critic = self.make_critic(cfg)
        # on an ORCA base (algo.actor_base=orca) the loss sees the distribution over the residual, whose
        # sample is what the log-probability is of; the action the env received follows from it
        dist = residual_distribution(self.actor)
        action = RESIDUAL if dist is not self.actor else ACTION
        if action == RESIDUAL:
            self.keep = (*self.keep, RESIDUAL)
        self.loss = loss = ClipPPOLoss(
            dist, critic, clip_epsilon=a.clip_epsilon, entropy_bonus=a.entropy_coef > 0,
            entropy_coeff=a.entropy_coef, critic_coeff=a.critic_coef, loss_critic_type=a.loss_critic_type,
            normalize_advantage=a.normalize_advantage)
        loss.set_keys(advantage=ADVANTAGE, value_target=VALUE_TARGET, value=VALUE, sample_log_prob=LOG_PROB,
                      action=action, reward=(GROUP, "reward"), done=(GROUP, "done"), terminated=(GROUP, "terminated"))
        loss.make_value_estimator(ValueEstimators.GAE, gamma=a.gamma, lmbda=a.lmbda)
        self.params = list(loss.parameters())
        self.opt = torch.optim.Adam(self.params, lr=a.lr)

    def make_critic(self, cfg) -> TensorDictModule:
        """``V(s)`` of each agent on its own observation (decentralised: IPPO with shared weights)."""
        return TensorDictModule(ValueNet(make_encoder(**OmegaConf.to_container(cfg.encoder))),
                                in_keys=list(OBS_KEYS), out_keys=[VALUE])

    def expected_updates(self, frames: int) -> int:
        fpb = self.cfg.train.frames_per_batch
        per_batch = self.a.epochs * math.ceil(fpb * self.n_agents / self.a.minibatch_size)
        return frames // fpb * per_batch

    def learn(self, batch) -> dict[str, float]:
        a = self.a
        with torch.no_grad():  # advantages and value targets over the batch's time dimension, per agent
            self.loss.value_estimator(batch)
        flat = agent_transitions(batch, self.keep)  # [N] transitions, one agent each, frozen steps dropped
        sums: dict[str, float] = {}
        steps = 0
        for _ in range(a.epochs):
            for idx in torch.randperm(len(flat), generator=self.generator).split(a.minibatch_size):
                out = self.loss(flat[idx])
                total = out["loss_objective"] + out["loss_critic"] + out.get("loss_entropy", 0.0)
                self.opt.zero_grad()
                total.backward()
                out["grad_norm"] = nn.utils.clip_grad_norm_(self.params, a.max_grad_norm)
                self.opt.step()
                self.updates += 1
                steps += 1
                for k in ("loss_objective", "loss_critic", "loss_entropy", "clip_fraction", "kl_approx",
                          "entropy", "grad_norm"):
                    if k in out:
                        sums[k] = sums.get(k, 0.0) + float(out[k].detach().mean())
        logs = {k: v / steps for k, v in sums.items()}
        logs["value_target"] = float(flat[VALUE_TARGET].mean())
        return logs

    def warm_start(self, demos) -> dict[str, float]:
        """``train.pretrain``: the actor's deterministic action cloned to the demonstrations', ``V(s)``
        regressed to their returns (crowdbench/algos/pretrain.py); on-policy, so nothing is stored."""
        from crowdbench.algos.pretrain import imitate

        critic = (self.loss.critic_network, self.loss.critic_network_params, VALUE)
        return imitate(self.cfg, self.actor, self.actor_kind, demos, [critic])

    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "loss": self.loss.state_dict(), "opt": self.opt.state_dict(),
                "replay_rng": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(state["loss"])
        self.opt.load_state_dict(state["opt"])
        self.generator.set_state(state["replay_rng"])


ALGORITHM = PPO
