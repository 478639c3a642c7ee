"""One run's networks, TorchRL loss, optimisers and target updates; ``update`` is one gradient step.

Kept apart from the training loop so that ``benchmarks/bench_train.py`` times exactly the
update that ``crowdbench run`` makes (graph preparation, critics, delayed actor, Polyak).
"""

from __future__ import annotations

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.objectives import SoftUpdate

from crowdbench.algos.builders import (
    actor_parameters,
    build_actor,
    build_critic,
    build_loss,
    critic_parameters,
)
from crowdbench.models.heads import prepare_batch


def per_transition(err: torch.Tensor, n: int) -> torch.Tensor:
    """One priority per sampled transition: the largest error over twin critics and agents."""
    if err.shape[0] != n:  # TD3 stacks its critics first: [2, n, ...]
        err = err.amax(0)
    return err.reshape(n, -1).amax(-1)


class Learner:
    """TD3 / DDPG / SAC learner for ``cfg`` (``algo``, ``encoder``, ``env`` groups)."""

    def __init__(self, cfg: DictConfig):
        a = cfg.algo
        algo = a.name
        self.policy_delay = a.policy_delay
        # PER samples transition i with probability P(i) ~ priority_i^alpha, which biases the expected
        # update towards high-error transitions; the weights w_i = (P(i) / min_j P(j))^-beta (TorchRL's
        # sampler) undo that bias (Schaul et al. 2016). TorchRL's losses average a weighted loss as
        # sum(w l) / sum(w). Off by default: the paper's Algorithm 1 and every shipped run use none.
        self.per_weights = bool(a.per_weights)
        if self.per_weights and a.replay != "prioritized":
            raise ValueError(f"algo.per_weights=true needs algo.replay=prioritized, got {a.replay}")
        v_max = cfg.env.v_max
        self.actor = build_actor(algo, OmegaConf.to_container(cfg.encoder), v_max, squash=a.actor_squash)
        horizon = float(a.critic_lookahead)  # seconds; 0 = the paper's critic
        if horizon < 0 or (horizon > 0 and cfg.env.frame == "world"):
            raise ValueError(f"algo.critic_lookahead must be >= 0 s and needs a robot-relative env.frame (rotate or "
                             f"translate); got {horizon} with frame {cfg.env.frame}")
        critic = build_critic(OmegaConf.to_container(cfg.encoder), lookahead_dt=horizon, v_max=v_max)
        self.prepared = algo != "sac"  # SAC's probabilistic actor reads the raw observation
        # the buffer holds one agent per transition (self-play flattens agents into the batch: algos/multiagent.py)
        self.loss = loss = build_loss(algo, self.actor, critic, 1, v_max, a, prepared=self.prepared)
        # graphs built once per sampled batch, for the networks that read them (a lookahead critic builds its own)
        self.encoders = ((self.actor.module.encoder,) + (() if horizon > 0 else (critic.module.encoder,))
                         if self.prepared else ())
        self.target_updater = SoftUpdate(loss, tau=a.tau)
        # fused Adam: one kernel for all parameters (~5x cheaper steps for many small tensors on CPU)
        self.opt_actor = torch.optim.Adam(actor_parameters(loss), lr=a.lr_actor, fused=True)
        self.opt_critic = torch.optim.Adam(critic_parameters(loss), lr=a.lr_critic, fused=True)
        self.opt_alpha = torch.optim.Adam([loss.log_alpha], lr=a.lr_alpha) if algo == "sac" else None
        # the losses' own critic / actor terms, called separately so the actor is only evaluated when updated
        self.critic_loss = getattr(loss, {"td3": "value_loss", "ddpg": "loss_value", "sac": "qvalue_v2_loss"}[algo])
        self.actor_loss = loss.loss_actor if algo == "ddpg" else loss.actor_loss

    def update(self, sample, n: int) -> dict[str, float]:
        """Gradient step ``n`` on a sampled batch: critics always; actor, temperature and targets
        every ``policy_delay`` steps. Writes the new priorities to ``sample["td_error"]``."""
        if self.prepared:
            prepare_batch(sample, *self.encoders)
        if self.per_weights:  # the buffer's [n] weights, shaped like the per-agent losses [n, 1]
            sample.set("priority_weight", sample["priority_weight"].reshape(sample.batch_size[0], 1))
        q_loss, meta = self.critic_loss(sample)
        self.opt_critic.zero_grad()
        q_loss.backward()
        self.opt_critic.step()
        sample.set("td_error", per_transition(meta["td_error"].detach(), sample.batch_size[0]))
        out = {"loss_critic": q_loss.item()}
        if n % self.policy_delay == 0:
            pi_loss, pi_meta = self.actor_loss(sample)
            self.opt_actor.zero_grad()
            pi_loss.backward()
            self.opt_actor.step()
            if self.opt_alpha is not None:
                alpha_loss = self.loss.alpha_loss(pi_meta["log_prob"]).mean()
                self.opt_alpha.zero_grad()
                alpha_loss.backward()
                self.opt_alpha.step()
                out["alpha"] = self.loss.log_alpha.exp().item()
            self.target_updater.step()
            out["loss_actor"] = pi_loss.item()
        return out

    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "loss": self.loss.state_dict(),
                "opt_actor": self.opt_actor.state_dict(), "opt_critic": self.opt_critic.state_dict(),
                **({"opt_alpha": self.opt_alpha.state_dict()} if self.opt_alpha is not None else {})}

    def load_state_dict(self, state: dict) -> None:
        """From a checkpoint (the ``actor`` entry is part of ``loss`` and not read back)."""
        self.loss.load_state_dict(state["loss"])
        self.opt_actor.load_state_dict(state["opt_actor"])
        self.opt_critic.load_state_dict(state["opt_critic"])
        if self.opt_alpha is not None:
            self.opt_alpha.load_state_dict(state["opt_alpha"])
