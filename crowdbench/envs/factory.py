"""One place that turns the ``env`` config into a TorchRL env: replay (single robot) or self-play."""

from __future__ import annotations

from crowdbench.envs.core import SimConfig


def is_selfplay(env_cfg) -> bool:
    return str(env_cfg.get("name", "replay")) == "selfplay"


def selfplay_config(env_cfg, **overrides):
    from crowdbench.envs.selfplay import SelfPlayConfig

    return SelfPlayConfig(**{**SelfPlayConfig.fields_of(env_cfg), **overrides})


def make_env(cfg, progress_reward: float = 0.0, human_dropout: float = 0.0):
    """``CrowdEnv`` on ``env.scene`` (``env=replay``) or ``SelfPlayEnv`` (``env=selfplay``), ``env.batch`` wide.

    ``progress_reward``: the training-only shaping of both envs (``train.progress_reward``);
    ``human_dropout``: the replay env's training-only density randomisation (``train.human_dropout``).
    """
    if is_selfplay(cfg.env):
        from crowdbench.envs.selfplay_env import SelfPlayEnv

        if human_dropout:
            raise ValueError("train.human_dropout applies to the replay env only (self-play has env.background)")

        return SelfPlayEnv(cfg.env.batch, selfplay_config(cfg.env), seed=cfg.seed, progress_reward=progress_reward)
    from crowdbench.envs.torchrl_env import CrowdEnv

    return CrowdEnv(cfg.env.scene, cfg.env.batch, SimConfig(**SimConfig.fields_of(cfg.env)), seed=cfg.seed,
                    progress_reward=progress_reward, human_dropout=human_dropout)
