"""The built-in policies' constructor arguments, read from a composed config.

A baseline gets the same arguments wherever it is built (``crowdbench eval policy=NAME``, the leaderboard
harness, the ORCA warm start of training): the env config's dynamics (``v_max``, ``dt``, radii), its
section of ``conf/config.yaml`` (``orca.*``, ``oracle.*``), the seed, then the caller's overrides. Kept
here, below the algorithms, so that training (crowdbench/algos/pretrain.py) builds its ORCA expert
without importing the policy registry (crowdbench/policies.py), which sits above it.
"""

from __future__ import annotations

import copy
import functools
from dataclasses import dataclass, field
from pathlib import Path

from crowdbench.config_fields import bounded, check_fields

NAMES = ("orca", "straight", "oracle")  # every built-in policy (anything else must be a checkpoint path)
PRIVILEGED = ("oracle",)  # knows the replayed humans' future: an upper bound, not a navigation policy
BASELINES = tuple(n for n in NAMES if n not in PRIVILEGED)
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
ENV_ARGS = {"orca": ("v_max", "dt", "robot_radius", "human_radius"), "straight": ("v_max", "dt"), "oracle": ()}
SEEDED = ("orca",)  # policies whose constructor takes the run's seed
PREF_RULES = ("reach", "crowdnav")


@dataclass
class OrcaSettings:
    """The robot's ORCA baseline (``policy=orca``, the warm start's demonstrator, a residual actor's base): the
    ``orca`` section of conf/config.yaml, with its bounds (also its schema) and the constructor's defaults
    (crowdbench/baselines/orca.py). The humans' ORCA is another parameter set: envs/humans/reactive.py
    ``OrcaParams`` (CrowdNav's), which the reactive crowds and ``env.reactive`` share."""

    safety_margin: float = bounded(0.2, ge=0)  # m added to the human radius
    time_horizon: float = bounded(2.0, gt=0)  # s
    max_neighbors: int = bounded(10, ge=0)
    neighbor_dist: float = bounded(5.0, gt=0)  # m, the sensing range
    perturb: float = bounded(1.0e-3, ge=0)  # m/s symmetry-breaking perturbation of the preferred velocity
    # near the goal: reach (land on it in one step) | crowdnav (min(dist, 1) m/s, CrowdNav's rule)
    pref_rule: str = bounded("reach", choices=PREF_RULES)

    def __post_init__(self):
        check_fields(self, "orca.")


ORACLE_SPEEDS = (1.0, 0.5)


@dataclass
class OracleSettings:
    """The privileged oracle's search (``policy=oracle``): the ``oracle`` section of conf/config.yaml, with its
    bounds (also its schema) and the constructor's defaults (crowdbench/baselines/oracle.py)."""

    headings: int = bounded(16, ge=1)  # directions, rotations of the direction to the goal
    # fractions of v_max (plus stop and "land on the goal")
    speeds: list[float] = field(default_factory=lambda: list(ORACLE_SPEEDS), metadata={"min_len": 1, "gt": 0, "le": 1})
    beam: int = bounded(32, ge=1)  # positions kept per episode and step
    cell: float = bounded(0.1, gt=0)  # m, de-duplication grid of end positions
    danger_cost: float = bounded(2.0, ge=0)  # steps of cost per danger step (0 <= d < 0.2 m)
    chunk: int = bounded(64, ge=1)  # episodes planned together (memory bound)

    def __post_init__(self):
        check_fields(self, "oracle.")


class PolicyError(ValueError):
    """A policy that cannot be built; ``key`` names the offending override, if any."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key


@functools.cache
def _composed() -> dict:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return OmegaConf.to_container(compose(config_name="config"), resolve=True)


def default_config() -> dict:
    """``conf/config.yaml`` composed without overrides (what ``crowdbench eval`` sees), as a plain dict."""
    return copy.deepcopy(_composed())


def _plain(cfg) -> dict:
    if cfg is None:
        return default_config()
    if isinstance(cfg, dict):
        return cfg
    from omegaconf import OmegaConf  # a Hydra DictConfig: lists inside become plain lists too

    return OmegaConf.to_container(cfg, resolve=True)


def params(name: str, cfg=None, overrides: dict | None = None) -> dict:
    """Constructor arguments of built-in policy ``name``.

    ``cfg`` is a composed config (dict or DictConfig; default: :func:`default_config`).
    ``overrides`` maps ``key`` or ``name.key`` to a value; only keys of the ``name`` section
    (and ``seed`` for seeded policies) are accepted: the dynamics are the protocol's."""
    if name not in NAMES:
        raise PolicyError(f"unknown policy {name!r}; valid: {', '.join(NAMES)} or a checkpoint path")
    cfg = _plain(cfg)
    section = dict(cfg.get(name) or {})
    env = cfg.get("env") or {}
    out = {k: env[k] for k in ENV_ARGS[name] if k in env}
    if name in SEEDED:
        out["seed"] = cfg.get("seed", 0)
    out.update(section)
    tunable = [*sorted(section), *(["seed"] if name in SEEDED else [])]
    for key, value in (overrides or {}).items():
        k = key.split(".", 1)[1] if key.startswith(f"{name}.") else key
        if k not in tunable:
            raise PolicyError(f"unknown {name} parameter {key!r}; valid: {', '.join(tunable) or 'none'}", key=key)
        out[k] = value
    return out
