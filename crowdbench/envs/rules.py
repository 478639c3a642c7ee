"""Simulator settings, outcomes, rewards and the collision geometry of the world (:mod:`crowdbench.envs.world`;
its kinematics: :mod:`crowdbench.kinematics`).

Geometry (SPEC section 3):
- clearance ``d`` = centre distance - robot radius - human radius;
- collision: ``d < 0`` at any moment of the step, tested on the linear motion of both
  bodies over the step (closest approach of the relative segment), not only at step ends;
- danger: ``0 <= d < 0.2`` at the end of a step; success: distance to goal < robot radius.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field, fields

import torch

from crowdbench.config_fields import SEED_BOUNDS, bounded, check_fields, problem, value_range
from crowdbench.data.scenes import Scene

# the kinematics live in one module that the networks share; re-exported for code that imports them from here
from crowdbench.kinematics import clip_speed, heading_to, to_local, to_world  # noqa: F401

RUNNING, SUCCESS, COLLISION, TIMEOUT = 0, 1, 2, 3
OUTCOMES = {SUCCESS: "success", COLLISION: "collision", TIMEOUT: "timeout"}
_FAR = 1e6  # clearance reported when no human is present
REWARDS = ("paper", "crowdnav")
START_CLEARANCE = 0.3  # m: a start point closer than this to a present human is not used


FRAMES = ("rotate", "translate", "world")


@dataclass
class SimConfig:
    """The simulator settings every env shares; its fields, with their bounds, are also the ``env`` schema's
    (crowdbench/config_schema.py), so a value is refused in the same words from Python and from a config."""

    dt: float = bounded(0.25, gt=0)
    v_max: float = bounded(1.0, gt=0)
    robot_radius: float = bounded(0.2, gt=0)
    human_radius: float = bounded(0.1, ge=0)
    danger_dist: float = bounded(0.2, ge=0)
    sensing_range: float = bounded(5.0, gt=0)
    time_limit: int = bounded(100, ge=1)  # steps (25 s at dt = 0.25)
    r_reach: float = bounded(1.0)
    r_fail: float = bounded(-0.25)
    danger_dt_scaling: bool = False  # CrowdNav multiplies the danger penalty by dt
    # paper (Eq. 1-2) | crowdnav (Chen et al. 2019: discomfort on the swept gap, no timeout penalty)
    reward: str = bounded("paper", choices=REWARDS)
    discomfort_factor: float = bounded(0.5, ge=0)  # crowdnav reward: penalty per metre inside danger_dist, times dt
    frame: str = bounded("rotate", choices=FRAMES)  # observation frame
    start_radius: float = bounded(4.0, gt=0)
    time_base: str = bounded("true", choices=("true", "0.4"), casefold=True)  # ETH row period: true (2/3 s) or 0.4

    @classmethod
    def fields_of(cls, mapping) -> dict:
        """The entries of ``mapping`` (e.g. the ``env`` config) that are simulator settings."""
        names = {f.name for f in fields(cls)}
        # YAML reads "true" as a bool: the time base is a string option
        return {k: (str(v).lower() if k == "time_base" else v) for k, v in dict(mapping).items() if k in names}

    def __post_init__(self):
        check_fields(self, "env.")


def check_seed(seed) -> int:
    """A seed as a Python int in ``[0, 2**63)`` (numpy integers accepted); one-line error naming it otherwise."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or problem(int(seed), SEED_BOUNDS):
        raise ValueError(f"seed must be an integer {value_range(SEED_BOUNDS)}, got {seed!r}")
    return int(seed)


def int_option(options: dict, key: str, lo: int, hi: int) -> int:
    """PettingZoo ``reset`` option ``key`` as an int in ``[lo, hi)`` (numpy integers accepted; a float,
    even integral, is refused rather than truncated); one-line error naming it otherwise."""
    v = options[key]
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or not lo <= int(v) < hi:
        raise ValueError(f"options[{key!r}] must be an integer in [{lo}, {hi}), got {v!r}")
    return int(v)


@dataclass
class StepInfo:
    reward: torch.Tensor  # [B, A]
    terminated: torch.Tensor  # [B, A] success or collision
    truncated: torch.Tensor  # [B, A] timeout
    outcome: torch.Tensor  # [B, A] RUNNING/SUCCESS/COLLISION/TIMEOUT decided this step
    clearance: torch.Tensor  # [B, A] min clearance at the end of the step
    swept_clearance: torch.Tensor  # [B, A] min clearance over the step's motion
    active: torch.Tensor  # [B, A] the robot moved during this step
    extra: dict = field(default_factory=dict)


def segment_min_distance(a0: torch.Tensor, a1: torch.Tensor) -> torch.Tensor:
    """Min norm of the relative vector moving linearly from ``a0`` to ``a1`` (``[..., 2]``).

    Both bodies move at constant velocity over the step, so their offset is linear in
    time and the closest approach is the point of the segment nearest to the origin.
    """
    d = a1 - a0
    dd = (d * d).sum(-1)
    s = (-(a0 * d).sum(-1) / dd.clamp_min(1e-12)).clamp(0.0, 1.0)
    return (a0 + s.unsqueeze(-1) * d).norm(dim=-1)


def step_reward(cfg, end: torch.Tensor, swept: torch.Tensor, success: torch.Tensor, collision: torch.Tensor,
                timeout: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    """The reward of one step, zero for inactive agents.

    ``paper`` (Eq. 1-2): danger term ``-0.1 + d/2`` on the end clearance ``end`` when ``d < danger_dist``,
    ``r_reach`` on success, ``r_fail`` on collision or timeout. ``crowdnav`` (CrowdNav's ``CrowdSim.step``):
    ``r_fail`` on collision, else ``r_reach`` on success, else ``(d - danger_dist) * discomfort_factor * dt``
    on the step's minimum (swept) clearance ``d < danger_dist``; a timeout earns nothing.
    """
    if cfg.reward == "crowdnav":
        discomfort = torch.where(swept < cfg.danger_dist, (swept - cfg.danger_dist) * cfg.discomfort_factor * cfg.dt, 0.0)
        return torch.where(collision, cfg.r_fail, torch.where(success, cfg.r_reach, discomfort)) * active
    danger = -0.1 + end.clamp_min(0.0) / 2
    if cfg.danger_dt_scaling:
        danger = danger * cfg.dt
    failure = collision | timeout
    return (torch.where(end < cfg.danger_dist, danger, 0.0) + cfg.r_reach * success + cfg.r_fail * failure) * active


def outcome_of(success: torch.Tensor, collision: torch.Tensor, timeout: torch.Tensor) -> torch.Tensor:
    return torch.where(success, SUCCESS, torch.where(collision, COLLISION, torch.where(timeout, TIMEOUT, RUNNING)))


def free_start(scene: Scene, t0: torch.Tensor, start: torch.Tensor, margin: float, radius_sum: float) -> torch.Tensor:
    """``[n]`` bool: no human present at grid index ``t0`` is within ``margin`` clearance of ``start`` ``[n, 2]``.

    An episode that starts inside (or touching) a pedestrian is a collision no policy can avoid. A scene with
    ``starts`` (several parts, :func:`~crowdbench.data.scenes.playback_scene`) also refuses the indices it does not admit.
    """
    pos, valid = scene.pos[t0].to(start.dtype), scene.valid[t0]
    gap = (pos - start.unsqueeze(-2)).norm(dim=-1) - radius_sum
    free = ((gap >= margin) | ~valid).all(-1)
    return free if scene.starts is None else free & scene.starts[t0]
