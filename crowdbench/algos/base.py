"""What every training algorithm provides to the loop in ``crowdbench/algos/train.py``.

An algorithm is a component (BenchMARL's split): it builds its policy, loss, exploration and update
from the config, and the loop only collects batches from the batched env, hands each to
:meth:`Algorithm.learn`, logs, probes and checkpoints. Off-policy algorithms (TD3, DDPG, SAC) keep a
replay buffer (``crowdbench/algos/offpolicy.py``); on-policy ones (PPO) learn from each batch and
drop it. Registered in ``crowdbench/algos/registry.py``.
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase

from crowdbench.algos.actors import actor_base, build_actor


class Algorithm:
    """One run's networks and learning rule for ``cfg`` (groups ``algo``, ``encoder``, ``env``)."""

    name: ClassVar[str]
    config: ClassVar[type]  # the typed schema of ``cfg.algo`` (a dataclass of ``bounded`` fields)
    actor_kind: ClassVar[str] = "deterministic"  # crowdbench/algos/registry.py ACTOR_KINDS
    # checkpoint fields that resuming reads beyond the actor (a submitted checkpoint has none of them)
    resume_fields: ClassVar[tuple[str, ...]] = ("loss",)
    # keeps transitions across batches (a replay buffer): their observation shape, and so the number of
    # agents, is then fixed for the run (no train.curriculum_agents; crowdbench/algos/curriculum.py)
    replays: ClassVar[bool] = False

    def __init__(self, cfg: DictConfig, n_agents: int):
        self.cfg, self.a, self.n_agents = cfg, cfg.algo, n_agents
        self.v_max = cfg.env.v_max
        self.actor = build_actor(self.name, OmegaConf.to_container(cfg.encoder), self.v_max,
                                 squash=self.a.get("actor_squash", "radial"), base=actor_base(cfg),
                                 residual=self.a.get("actor_residual"))
        self.updates = 0  # gradient steps so far (checkpointed by the loop)
        self.generator = torch.Generator().manual_seed(int(cfg.seed))  # minibatch / replay sampling

    @classmethod
    def env_transforms(cls, cfg: DictConfig) -> tuple:
        """TorchRL transforms the training env needs for this algorithm (a centralised critic's state)."""
        return ()

    # ---- collection
    def collection_policy(self):
        """What the collector runs: the actor with exploration (deterministic actors) or itself."""
        return self.actor

    def random_frames(self, resumed: bool, restored: bool, frames: int) -> int:
        """Frames of uniformly random actions before the policy acts (off-policy warm-up)."""
        return 0

    def expected_updates(self, frames: int) -> int:
        """Gradient steps that ``frames`` collected frames lead to (the duration estimate)."""
        raise NotImplementedError

    # ---- learning
    def learn(self, batch: TensorDictBase) -> dict[str, float]:
        """Learn from one collected ``[B, T]`` batch; returns scalars to log; counts ``self.updates``."""
        raise NotImplementedError

    def warm_start(self, demos: TensorDictBase) -> dict[str, float]:
        """Imitation before RL on demonstrations (``crowdbench/algos/pretrain.py``)."""
        raise NotImplementedError(f"algo={self.name} has no imitation warm start")

    def clone_from(self, data: TensorDictBase) -> None:
        """DAgger's aggregated data (``train.pretrain_dagger_rounds``) replaces the demonstrations that a
        cloning term during RL draws from; an algorithm without such a term ignores it."""

    # ---- state
    def state_dict(self) -> dict:
        raise NotImplementedError

    def load_state_dict(self, state: dict) -> None:
        raise NotImplementedError

    def save_extra(self, out_dir: Path, frames: int) -> dict:
        """Checkpoint fields beyond :meth:`state_dict` written next to it (a replay buffer); called
        before the checkpoint is written."""
        return {}

    def restore_extra(self, state: dict, ckpt: Path) -> bool:
        """Load what :meth:`save_extra` wrote; True if something was restored."""
        return False

    def after_save(self, out_dir: Path, extra: dict) -> None:
        """The checkpoint naming ``extra`` is on disk: remove what it no longer references."""
