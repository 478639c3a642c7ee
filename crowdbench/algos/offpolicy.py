"""Off-policy actor-critic on a replay buffer: what TD3, DDPG and SAC share (Algorithm 1 of the paper).

Each collected batch goes into a prioritised (or uniform) replay buffer as per-agent transitions
(n-step if ``algo.n_steps > 1``), then ``train.utd * frames`` gradient updates follow: the critics
every update, the actor and the target networks every ``policy_delay`` updates. The losses are
TorchRL's own modules with the keys of the ``agents`` group; a subclass names its loss and its two
loss terms (:meth:`OffPolicyAlgorithm.make_loss`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, TensorDictPrioritizedReplayBuffer, TensorDictReplayBuffer
from torchrl.modules import AdditiveGaussianModule, OrnsteinUhlenbeckProcessModule
from torchrl.objectives import SoftUpdate, ValueEstimators

from crowdbench.algos.actors import BASES, OrcaResidual, leaf_action_spec
from crowdbench.algos.base import Algorithm
from crowdbench.algos.multiagent import agent_transitions
from crowdbench.algos.nstep import STEPS, n_step
from crowdbench.algos.pretrain import DemoCloning, imitate, sync_targets
from crowdbench.algos.resume import compact_storage, remove_stale_buffers, restore_buffer, save_buffer
from crowdbench.config_fields import bounded
from crowdbench.envs.observation import ACTION, GROUP
from crowdbench.models import make_encoder
from crowdbench.models.heads import (
    BASE_ACTION,
    OBS_KEYS,
    STATE_ACTION_VALUE,
    Critic,
    actor_module,
    critic_module,
    prepare_batch,
)

# the keys the losses read; everything else the env emits stays out of the replay buffer
KEEP = [(GROUP, "observation"), (GROUP, "action"), ("next", GROUP, "observation"), ("next", GROUP, "reward"),
        ("next", GROUP, "done"), ("next", GROUP, "terminated")]
REPLAY_KIND = ("replay", "per_alpha", "per_beta", "buffer_size")


@dataclass
class OffPolicyConfig:
    """The keys TD3, DDPG and SAC share."""

    name: str = bounded("td3")
    gamma: float = bounded(0.99, gt=0, le=1)
    lr_actor: float = bounded(1.0e-3, gt=0)
    lr_critic: float = bounded(1.0e-3, gt=0)
    tau: float = bounded(0.005, gt=0, le=1)  # soft target update
    critic_lookahead: float = bounded(0.25, ge=0)  # s; 0 = the paper's critic (models/heads.py Critic)
    n_steps: int = bounded(1, ge=1)  # 1 = TD(0) as Algorithm 1 (algos/nstep.py)
    loss_function: str = bounded("l2", choices=("l2", "l1", "smooth_l1"))
    batch_size: int = bounded(100, ge=1)
    buffer_size: int = bounded(100000, ge=1)
    warmup: int = bounded(2000, ge=0)  # frames of random actions before the first update
    replay: str = bounded("uniform", choices=("uniform", "prioritized"))
    per_alpha: float = bounded(0.6, ge=0, le=1)
    per_beta: float = bounded(0.4, ge=0, le=1)
    per_weights: bool = False  # PER's importance-sampling weights in the losses
    # orca: a deterministic actor adds a learned residual to ORCA's velocity (algos/actors.py OrcaResidual)
    actor_base: str = bounded("none", choices=BASES)
    actor_residual: float = bounded(0.15, gt=0)  # m/s, the residual's largest speed (actor_base=orca)


@dataclass
class NoisyActorConfig(OffPolicyConfig):
    """A deterministic actor explored by added noise (TD3, DDPG)."""

    exploration_sigma: float = bounded(0.3, ge=0)  # a = pi(G) + N(0, sigma); the paper: 0.1
    exploration: str = bounded("gaussian", choices=("gaussian", "ou"))
    ou_theta: float = bounded(0.125, gt=0, le=1)  # OU mean reversion per step
    actor_squash: str = bounded("radial", choices=("radial", "box"))


def make_buffer(a, generator: torch.Generator):
    """PER (the paper) or uniform replay, sampling from ``generator``.

    The generator is not optional: without one TorchRL's prioritized sampler draws from numpy's
    global RNG, which nothing seeds, and two runs with the same seed diverge at the first update."""
    storage = LazyTensorStorage(a.buffer_size)
    if a.replay == "prioritized":
        rb = TensorDictPrioritizedReplayBuffer(alpha=a.per_alpha, beta=a.per_beta, storage=storage,
                                               batch_size=a.batch_size, priority_key="td_error",
                                               generator=generator)
    elif a.replay == "uniform":
        rb = TensorDictReplayBuffer(storage=storage, batch_size=a.batch_size, generator=generator)
    else:
        raise ValueError(f"unknown replay {a.replay!r}; valid: prioritized, uniform")
    compact_storage(rb)  # a saved buffer holds its transitions, not its capacity
    return rb


def exploration_policy(actor, n_agents: int, v_max: float, sigma: float, noise: str = "gaussian",
                       theta: float = 0.125):
    """Algorithm 1, line 7: ``a = pi(G) + N(0, sigma)``.

    ``noise="ou"``: temporally correlated noise instead, TorchRL's Ornstein-Uhlenbeck module in
    steps (``x' = (1 - theta) x + s * N(0, 1)``, reset where the env's ``is_init`` is set, which
    needs an ``InitTracker``); ``s`` is chosen so that the stationary std is ``sigma``, the same
    scale as the Gaussian. Why: a lateral step of 0.25 m does not avoid anyone, a deviation held
    for ~1/theta steps (2 s at theta = 0.125) does."""
    spec = leaf_action_spec(n_agents, v_max)
    if noise == "gaussian":
        module = AdditiveGaussianModule(spec=spec, sigma_init=sigma, sigma_end=sigma, action_key=ACTION, safe=True)
    elif noise == "ou":
        if not 0 < theta <= 1:
            raise ValueError(f"algo.ou_theta must be in (0, 1], got {theta}")
        module = OrnsteinUhlenbeckProcessModule(spec, eps_init=1.0, eps_end=1.0, theta=theta,
                                                sigma=sigma * (2 * theta - theta**2) ** 0.5, dt=1.0,
                                                action_key=ACTION, is_init_key="is_init", safe=True)
    else:
        raise ValueError(f"unknown algo.exploration {noise!r}; valid: gaussian, ou")
    return TensorDictSequential(actor, module)


def per_transition(err: torch.Tensor, n: int) -> torch.Tensor:
    """One priority per sampled transition: the largest error over twin critics and agents."""
    if err.shape[0] != n:  # twin critics are stacked first: [2, n, ...]
        err = err.amax(0)
    return err.reshape(n, -1).amax(-1)


def params_of(tree) -> list[torch.Tensor]:
    return list(tree.flatten_keys().values(True, True))


class OffPolicyAlgorithm(Algorithm):
    """Replay buffer, critics and the update; subclasses build the TorchRL loss."""

    resume_fields = ("loss", "opt_actor", "opt_critic", "replay_rng")
    replays = True
    policy_delay = 1
    prepared = True  # the loss reads graphs built once per sampled batch (models/heads.py prepare_batch)
    keep = tuple(KEEP)  # what the replay buffer holds of each transition

    def __init__(self, cfg, n_agents: int):
        super().__init__(cfg, n_agents)
        a = self.a
        # PER samples transition i with probability P(i) ~ priority_i^alpha, which biases the expected
        # update towards high-error transitions; the weights w_i = (P(i) / min_j P(j))^-beta (TorchRL's
        # sampler) undo that bias (Schaul et al. 2016). TorchRL's losses average a weighted loss as
        # sum(w l) / sum(w). Off by default: the paper's Algorithm 1 and every shipped run use none.
        if a.per_weights and a.replay != "prioritized":
            raise ValueError(f"algo.per_weights=true needs algo.replay=prioritized, got {a.replay}")
        horizon = float(a.critic_lookahead)  # seconds; 0 = the paper's critic
        if horizon > 0 and cfg.env.frame == "world":
            raise ValueError(f"algo.critic_lookahead needs a robot-relative env.frame (rotate or translate); "
                             f"got {horizon} with frame {cfg.env.frame}")
        critic = self.make_critic(cfg, horizon)
        actor = self.actor
        # TorchRL's losses hand the target critic what they selected of the next state for the target actor:
        # a critic that reads more than the actor's prepared graphs needs it listed among the actor's inputs
        carry = [k for k in critic.in_keys if k != ACTION] if self.critic_reads_raw(horizon) else []
        # a residual's base velocities are stored with each transition (OrcaResidual.store_base)
        self.residual = self.actor.module if isinstance(self.actor.module, OrcaResidual) else None
        if self.residual is not None:
            # ORCA reads the raw observation, so the actor (and then the critics) read it in the losses too
            self.prepared = False
            self.keep = (*self.keep, BASE_ACTION, ("next", *BASE_ACTION))
        if self.prepared:  # ``self.actor`` stays the raw-observation module for acting
            actor = actor_module(self.actor.module, prepared=True, carry=carry)
            critic_in = critic if self.critic_reads_raw(horizon) else critic_module(critic.module, prepared=True)
        else:
            critic_in = critic
        # the buffer holds one agent per transition (self-play flattens agents into the batch: algos/multiagent.py)
        self.loss = loss = self.make_loss(actor, critic_in, leaf_action_spec(1, self.v_max))
        keys = {"reward": (GROUP, "reward"), "done": (GROUP, "done"), "terminated": (GROUP, "terminated"),
                "state_action_value": STATE_ACTION_VALUE, **self.extra_keys()}
        loss.set_keys(**keys)
        loss.make_value_estimator(ValueEstimators.TD0, gamma=a.gamma)
        # n-step transitions (algos/nstep.py) carry their length m: the bootstrap is discounted by gamma^m
        loss.value_estimator.set_keys(steps_to_next_obs=STEPS)
        # graphs built once per sampled batch, for the networks that read them (a lookahead critic builds its own)
        self.encoders = ((self.actor.module.encoder,) + (() if self.critic_reads_raw(horizon) else
                                                         (critic.module.encoder,))
                         if self.prepared else ())
        # a critic that reads no prepared graph: a critic-only step needs the next observation's only
        self.root_every_step = not self.critic_reads_raw(horizon)
        self.target_updater = SoftUpdate(loss, tau=a.tau)
        # fused Adam: one kernel for all parameters (~5x cheaper steps for many small tensors on CPU)
        self.opt_actor = torch.optim.Adam(params_of(loss.actor_network_params), lr=a.lr_actor, fused=True)
        self.opt_critic = torch.optim.Adam(params_of(self.critic_params()), lr=a.lr_critic, fused=True)
        self.rb = make_buffer(a, self.generator)
        self.cloning = None
        # the cloning term draws from the warm start's demonstrations: without one (train.pretrain=null) it has
        # nothing to clone and is off, whatever its weight (the default recipe sets both)
        if cfg.train.get("pretrain") and cfg.train.get("pretrain_bc_weight", 0) > 0:
            self.cloning = DemoCloning(cfg)

    # ---- what a subclass provides
    def make_loss(self, actor, critic, action_spec):
        raise NotImplementedError

    def make_critic(self, cfg, horizon: float):
        """``Q(s, a)`` as a TensorDictModule on the raw observation: the run's encoder (a lookahead critic
        if ``horizon > 0``; models/heads.py)."""
        return critic_module(Critic(make_encoder(**OmegaConf.to_container(cfg.encoder)), None, horizon, self.v_max))

    def critic_reads_raw(self, horizon: float) -> bool:
        """The critic reads its inputs as they were collected, not graphs prepared once per batch (its
        graph depends on the action: the lookahead critic)."""
        return horizon > 0

    def extra_keys(self) -> dict:
        return {"action": ACTION}

    def critic_params(self):
        return self.loss.qvalue_network_params

    def critic_network(self):
        """The loss's parameter-free critic that :meth:`critic_params` run through (DDPG: its value network)."""
        return self.loss.qvalue_network if hasattr(self.loss, "qvalue_network") else self.loss.value_network

    def critic_loss(self, sample):
        return self.loss.value_loss(sample)

    def actor_loss(self, sample):
        return self.loss.actor_loss(sample)

    def after_actor_step(self, meta: dict, out: dict) -> None:
        """After each actor step (SAC: the temperature)."""

    # ---- collection
    def collection_policy(self):
        a = self.a
        return exploration_policy(self.actor, self.n_agents, self.v_max, a.exploration_sigma, a.exploration,
                                  a.ou_theta)

    def random_frames(self, resumed: bool, restored: bool, frames: int) -> int:
        # a resumed run continues the warm-up where it stopped; without its saved buffer it refills one
        # with the policy's actions (no updates until it holds algo.warmup transitions)
        if self.cfg.train.get("pretrain"):
            # the buffer starts with the demonstrations; random actions would then only teach the critic
            # what the imitating actor never does, and updates on them start at once: act with the policy
            return 0
        if not resumed:
            return self.a.warmup
        return max(0, self.a.warmup - frames) if restored else 0

    def expected_updates(self, frames: int) -> int:
        t = self.cfg.train
        waiting = max(0, self.a.warmup - t.pretrain_frames) if t.get("pretrain") else self.a.warmup
        return max(0, int(t.utd * (frames - waiting)))

    # ---- learning
    def learn(self, batch) -> dict[str, float]:
        a = self.a
        if a.n_steps > 1:
            batch = n_step(batch, a.n_steps, a.gamma)
        self.store_base(batch)
        self.rb.extend(agent_transitions(batch, [*self.keep, *[STEPS] * (a.n_steps > 1)]))
        logs: dict[str, float] = {}
        if len(self.rb) >= a.warmup:
            for _ in range(max(1, int(self.cfg.train.utd * batch.numel()))):
                sample = self.rb.sample()
                logs.update(self.update(sample, self.updates))
                self.updates += 1
                if a.replay == "prioritized":
                    self.rb.update_tensordict_priority(sample)
        return logs

    def warm_start(self, demos) -> dict[str, float]:
        """Behaviour cloning of the actor and ``Q(s, a_demo) -> return`` for each critic
        (``crowdbench/algos/pretrain.py``), targets synced, the demonstrations into the replay buffer."""
        prepare = (lambda td: prepare_batch(td, *self.encoders, include_next=False)) if self.prepared else None
        self.store_base(demos)
        critic = (self.critic_network(), self.critic_params(), STATE_ACTION_VALUE)
        logs = imitate(self.cfg, self.actor, self.actor_kind, demos, [critic], prepare)
        sync_targets(self.loss)
        self.rb.extend(demos.select(*self.keep, *[STEPS] * (self.a.n_steps > 1)))
        if self.cloning is not None:  # the cloning term keeps what its minibatches read
            self.cloning = DemoCloning(self.cfg, demos)
        return logs

    def clone_from(self, data) -> None:
        if self.cloning is not None:
            self.cloning = DemoCloning(self.cfg, self.store_base(data))

    def store_base(self, td):
        """A residual actor's base velocities for ``td``'s observations, stored in it (the others: unchanged)."""
        return td if self.residual is None else self.residual.store_base(td)

    def update(self, sample, n: int) -> dict[str, float]:
        """Gradient step ``n`` on a sampled batch: critics always; actor (and temperature) and targets
        every ``policy_delay`` steps. Writes the new priorities to ``sample["td_error"]``."""
        actor_step = n % self.policy_delay == 0
        if self.prepared:
            prepare_batch(sample, *self.encoders, include_root=actor_step or self.root_every_step)
        if self.a.per_weights:  # the buffer's [n] weights, shaped like the per-agent losses [n, 1]
            sample.set("priority_weight", sample["priority_weight"].reshape(sample.batch_size[0], 1))
        q_loss, meta = self.critic_loss(sample)
        self.opt_critic.zero_grad()
        q_loss.backward()
        self.opt_critic.step()
        sample.set("td_error", per_transition(meta["td_error"].detach(), sample.batch_size[0]))
        out = {"loss_critic": q_loss.item()}
        if actor_step:
            pi_loss, pi_meta = self.actor_loss(sample)
            bc = self.cloning.loss(self.actor, self.actor_kind, n) if self.cloning is not None else None
            if bc is not None:
                out["loss_bc"] = bc.item()
                pi_loss = pi_loss + bc
            self.opt_actor.zero_grad()
            pi_loss.backward()
            self.opt_actor.step()
            self.after_actor_step(pi_meta, out)
            self.target_updater.step()
            out["loss_actor"] = pi_loss.item()
        return out

    # ---- state
    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "loss": self.loss.state_dict(),
                "opt_actor": self.opt_actor.state_dict(), "opt_critic": self.opt_critic.state_dict(),
                "replay_rng": self.generator.get_state(),
                **({"bc_rng": self.cloning.generator.get_state()} if self.cloning is not None else {})}

    def load_state_dict(self, state: dict) -> None:
        """From a checkpoint (the ``actor`` entry is part of ``loss`` and not read back)."""
        self.loss.load_state_dict(state["loss"])
        self.opt_actor.load_state_dict(state["opt_actor"])
        self.opt_critic.load_state_dict(state["opt_critic"])
        if self.cloning is not None and "bc_rng" in state:
            self.cloning.generator.set_state(state["bc_rng"])

    def save_extra(self, out_dir: Path, frames: int) -> dict:
        if self.cloning is not None:
            self.cloning.save(out_dir)
        if not self.cfg.train.save_buffer:
            return {"replay": None}
        return {"replay": save_buffer(self.rb, out_dir, frames, self.updates)}

    def restore_extra(self, state: dict, ckpt: Path) -> bool:
        restored = False
        if self.cloning is not None and "bc_rng" in state:  # a run that cloned before it stopped
            self.cloning.restore(ckpt)
        if self.cfg.train.save_buffer:
            saved = OmegaConf.create(state["config"]["algo"])
            same = all(saved.get(k) == self.a.get(k) for k in REPLAY_KIND)
            restored = restore_buffer(self.rb, state, ckpt, same, lambda: make_buffer(saved, torch.Generator()))
            if restored and self.residual is not None:
                self.fill_base()
        self.generator.set_state(state["replay_rng"])
        self.rb.set_rng(self.generator)  # loads() installs a generator of its own: sample from the checkpointed one
        return restored

    def fill_base(self) -> None:
        """A buffer saved before base velocities were stored with the transitions gets them now (a resume);
        the rows past its length (the storage's padding to capacity) get zeros: they are never sampled."""
        stored = self.rb.storage._storage  # TorchRL's storage TensorDict, padded to its capacity
        if BASE_ACTION in stored.keys(True):
            return
        n = len(self.rb)
        # the observations only, as views (no copy of the buffer): store_base adds its keys to this selection
        filled = self.residual.store_base(stored[:n].select(*OBS_KEYS, *[("next", *k) for k in OBS_KEYS]))
        for key in (BASE_ACTION, ("next", *BASE_ACTION)):
            base = filled.get(key)
            full = base.new_zeros(stored.shape[0], *base.shape[1:])
            full[:n] = base
            stored.set(key, full)

    def after_save(self, out_dir: Path, extra: dict) -> None:
        ref = extra.get("replay")
        remove_stale_buffers(out_dir, ref and ref["dir"])
