"""SAC (Haarnoja et al. 2018): twin critics, a TanhNormal policy and a learned temperature; TorchRL's
``SACLoss`` (its v2 form, no separate value network). The policy samples its own exploration."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torchrl.objectives import SACLoss

from crowdbench.algos.actors import LOG_PROB
from crowdbench.algos.offpolicy import OffPolicyAlgorithm, OffPolicyConfig
from crowdbench.config_fields import bounded
from crowdbench.envs.observation import ACTION


@dataclass
class SACConfig(OffPolicyConfig):
    """``algo=sac``."""

    name: str = bounded("sac", choices=("sac",))
    lr_alpha: float = bounded(3.0e-4, gt=0)  # the temperature's learning rate
    # initial temperature, scaled to this reward (conf/algo/sac.yaml says why 0.005)
    alpha_init: float = bounded(0.005, gt=0)
    # SACLoss reads the log-probability of the action the env received: no residual distribution
    actor_base: str = bounded("none", choices=("none",))


class SAC(OffPolicyAlgorithm):
    name = "sac"
    config = SACConfig
    actor_kind = "tanh_normal"
    prepared = False  # the probabilistic actor reads the raw observation
    resume_fields = (*OffPolicyAlgorithm.resume_fields, "opt_alpha")

    def __init__(self, cfg, n_agents: int):
        super().__init__(cfg, n_agents)
        self.opt_alpha = torch.optim.Adam([self.loss.log_alpha], lr=self.a.lr_alpha)

    def make_loss(self, actor, critic, action_spec):
        a = self.a
        return SACLoss(actor, critic, num_qvalue_nets=2, loss_function=a.loss_function, action_spec=action_spec,
                       alpha_init=a.alpha_init, target_entropy="auto", use_prioritized_weights=bool(a.per_weights))

    def extra_keys(self) -> dict:
        return {"action": ACTION, "log_prob": LOG_PROB}

    def critic_loss(self, sample):
        return self.loss.qvalue_v2_loss(sample)

    def after_actor_step(self, meta: dict, out: dict) -> None:
        alpha_loss = self.loss.alpha_loss(meta["log_prob"]).mean()
        self.opt_alpha.zero_grad()
        alpha_loss.backward()
        self.opt_alpha.step()
        out["alpha"] = self.loss.log_alpha.exp().item()

    def collection_policy(self):
        return self.actor

    def state_dict(self) -> dict:
        return {**super().state_dict(), "opt_alpha": self.opt_alpha.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.opt_alpha.load_state_dict(state["opt_alpha"])


ALGORITHM = SAC
