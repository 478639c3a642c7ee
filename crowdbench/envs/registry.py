"""Envs by name, as Gymnasium and PettingZoo name theirs (docs/api.md).

``make("replay", scene="students003")``, ``make("reactive_replay")``, ``make("crowdnav", n_humans=20)``,
``make("selfplay", n_agents=16)``: the TorchRL env (``batch`` environments), or with ``api="pettingzoo"``
the PettingZoo ``ParallelEnv`` (one environment), or with ``api="gymnasium"`` a single-robot Gymnasium
env. Keyword arguments are keys of the env's config group (``crowdbench/conf/env/<name>.yaml``); an
unknown one is a one-line error listing the valid keys. Importing this module registers the Gymnasium
ids :data:`GYM_IDS` (``gymnasium.make("crowdbench/CrowdNav-v0")``).

This module is not on the evaluation path (the leaderboard hashes that code into its cache), so that
adding a name here leaves the cached leaderboard results valid.
"""

from __future__ import annotations

import functools
from pathlib import Path

from crowdbench.envs.factory import make_env, make_parallel_env

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
# name -> (config group option, fixed overrides)
NAMES = {
    "replay": ("replay", {}),  # protocol v1's world: one robot among the recorded ETH/UCY pedestrians
    "reactive_replay": ("replay", {"humans": "reactive_replay"}),  # protocol v2: they yield (ORCA / social force)
    "crowdnav": ("crowdnav", {}),  # CrowdNav's circle / square crossing among ORCA or social-force humans
    "selfplay": ("selfplay", {}),  # n learning agents, one shared-weight policy
}
APIS = ("torchrl", "pettingzoo", "gymnasium")
GYM_IDS = {"crowdbench/Replay-v0": "replay", "crowdbench/ReactiveReplay-v0": "reactive_replay",
           "crowdbench/CrowdNav-v0": "crowdnav"}  # single robot: not self-play


@functools.cache
def _group_config(group: str) -> dict:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return OmegaConf.to_container(compose(config_name="config", overrides=[f"env={group}"]), resolve=True)


def config(name: str, seed: int = 0, batch: int = 1, **env):
    """The composed config (an OmegaConf ``DictConfig``) of env ``name`` with ``env`` keys replaced."""
    from omegaconf import OmegaConf

    if name not in NAMES:
        raise ValueError(f"unknown env {name!r}; valid: {', '.join(NAMES)}")
    group, fixed = NAMES[name]
    cfg = OmegaConf.create(_group_config(group))
    unknown = sorted(set(env) - set(cfg.env))
    if unknown:
        raise ValueError(f"unknown {name} env key(s) {', '.join(unknown)}; valid: {', '.join(sorted(cfg.env))}")
    for key, value in {**fixed, **env, "batch": batch}.items():
        cfg.env[key] = value
    cfg.seed = seed
    return cfg


def make(name: str, api: str = "torchrl", seed: int = 0, batch: int = 1, **env):
    """Env ``name`` (:data:`NAMES`) through ``api`` (:data:`APIS`); ``env``: its config keys."""
    if api not in APIS:
        raise ValueError(f"unknown api {api!r}; valid: {', '.join(APIS)}")
    if api == "gymnasium":
        return gym_env(name, **env)
    cfg = config(name, seed=seed, batch=batch, **env)
    return make_env(cfg) if api == "torchrl" else make_parallel_env(cfg.env)


def gym_env(name: str = "replay", render_mode: str | None = None, **env):
    """The single-robot Gymnasium env of ``name`` (``gymnasium.make``'s entry point)."""
    from crowdbench.envs.gym_env import CrowdGymEnv

    if name == "selfplay":
        raise ValueError("the Gymnasium env holds one robot; self-play (n agents): api='pettingzoo' or 'torchrl'")
    if render_mode is not None:
        raise ValueError(f"render_mode {render_mode!r} not supported; valid: None")
    return CrowdGymEnv(make(name, api="pettingzoo", **env))


def register_gymnasium() -> None:
    """Register :data:`GYM_IDS` with Gymnasium (once; ``gymnasium.make(id, scene=..., ...)`` passes env keys)."""
    import gymnasium

    for gym_id, name in GYM_IDS.items():
        if gym_id not in gymnasium.registry:
            gymnasium.register(gym_id, entry_point="crowdbench.envs.registry:gym_env", kwargs={"name": name},
                               max_episode_steps=None, disable_env_checker=False)


register_gymnasium()
