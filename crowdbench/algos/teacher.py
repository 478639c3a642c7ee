"""A trained checkpoint as the imitation expert (``train.pretrain=checkpoint``, ``train.pretrain_checkpoint``).

The expert of :func:`crowdbench.algos.pretrain.collect_demonstrations` acts on the training env's
observations. A value-lookahead checkpoint (``algo=value``) also reads its candidates' next states,
which the evaluation loop computes from the world (crowdbench/protocols/engine.py); here they are computed the same
way from the training env's world, before each step. A teacher whose lookahead is privileged (``query``)
is refused: what it knows would pass into the student, which could then not be labelled unprivileged.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase

from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint, policy_from_checkpoint
from crowdbench.envs.lookahead import PRIVILEGED_MODELS, lookahead_observation
from crowdbench.envs.observation import OBS


def _world(env):
    """The batched world under ``env`` (a CrowdEnv, or one inside TorchRL transforms)."""
    while not hasattr(env, "world") and hasattr(env, "base_env"):
        env = env.base_env
    return env.world


class CheckpointExpert:
    """``act(obs) -> action`` of a trained checkpoint on the training env ``env``."""

    def __init__(self, path: str | Path, env, frame: str, v_max: float):
        try:
            cfg = load_checkpoint(Path(path))["config"]
            self.policy = policy_from_checkpoint(Path(path))
        except CheckpointError as e:
            raise ValueError(f"train.pretrain_checkpoint: {e}") from None
        self.look = getattr(self.policy, "lookahead", None)
        if self.look is not None and self.look[0] in PRIVILEGED_MODELS:
            raise ValueError(f"train.pretrain_checkpoint: {path} acts with the privileged lookahead {self.look[0]!r}; "
                             "a teacher must see only what the student sees (train it with algo.lookahead=cv)")
        if cfg["env"]["frame"] != frame or float(cfg["env"]["v_max"]) != float(v_max):
            raise ValueError(f"train.pretrain_checkpoint: {path} was trained with env.frame={cfg['env']['frame']}, "
                             f"env.v_max={cfg['env']['v_max']}; this run has {frame}, {v_max}")
        self.world = _world(env)
        self.name = f"checkpoint {Path(path).name} ({getattr(self.policy, 'name', 'policy')})"

    @torch.no_grad()
    def act(self, td: TensorDictBase) -> torch.Tensor:
        if self.look is not None:  # the candidates of the world's current state: the one ``td`` observes
            td = td.clone(recurse=False)
            obs = td[OBS].clone(recurse=False)
            for key, value in lookahead_observation(self.world, self.look[1], self.look[0]).items():
                obs.set(key, value)
            td.set(OBS, obs)
        return self.policy.act(td)
