"""Reactive crowd models: humans that walk to their own goals and avoid each other (and the robot
when ``robot_visible``), integrated by the world step after step.

State per environment: position, velocity and goal of ``M`` humans. Each step, every human's new
velocity is decided from the state at the start of the step (as CrowdNav does: all human actions
first, then everybody moves), then ``p += v * dt``. An environment whose agents are all done is
frozen. The preferred velocity is CrowdNav's (``crowd_sim/envs/policy/orca.py``): towards the goal
at ``v_pref``, and ``goal - p`` itself (per step of one second) within ``v_pref`` metres of it, so a
human slows down near its goal and stays there; goals never change and nobody respawns.

Episode keys: ``human_start``, ``human_goal`` ``[n, M, 2]``; optional ``human_valid`` ``[n, M]``
(padding for fewer humans; an absent human is never seen and never moves).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from crowdbench.envs.humans import Agents, orca, orca_kernel, sfm, sfm_kernel
from crowdbench.envs.humans.sfm import SFMParams


@dataclass(frozen=True)
class OrcaParams:
    """ORCA settings of the humans; defaults are CrowdNav's (``crowd_sim/envs/policy/orca.py`` l.60-66)."""

    neighbor_dist: float = 10.0  # m
    max_neighbors: int = 10
    time_horizon: float = 5.0  # s
    radius_margin: float = 0.01  # m added to every body's radius, as CrowdNav does (safety_space 0)
    # numba: the compiled solver (orca_kernel), equal to the torch one (orca, the reference) value for value
    backend: str = "numba"


ORCA_BACKENDS = {"numba": orca_kernel.orca_velocities, "torch": orca.orca_velocities}
# torch: the reference (the default); numba: compiled, within a few float32 ulps of it (not bit-identical)
SFM_BACKENDS = {"torch": sfm.social_force_velocities, "numba": sfm_kernel.social_force_velocities}


class ReactiveCrowd:
    """Humans moved by a reactive model (:meth:`velocities`); subclasses: :class:`OrcaCrowd`, :class:`SfmCrowd`."""

    name = "reactive"

    def __init__(self, batch: int, n_humans: int, radius: float, v_pref: float, dt: float,
                 robot_visible: bool, robot_radius: float):
        self.M = int(n_humans)
        self.radius, self.v_pref, self.dt = float(radius), float(v_pref), float(dt)
        self.robot_visible, self.robot_radius = bool(robot_visible), float(robot_radius)
        self.pos = torch.zeros(batch, self.M, 2)
        self.vel = torch.zeros(batch, self.M, 2)
        self.goal = torch.zeros(batch, self.M, 2)
        self.valid = torch.zeros(batch, self.M, dtype=torch.bool)
        self.t = torch.zeros(batch, dtype=torch.long)  # steps since the episode started

    def reset(self, mask: torch.Tensor, idx: torch.Tensor, episode: dict) -> None:
        start = episode["human_start"].to(self.pos.dtype)
        self.pos[idx] = start
        self.vel[idx] = 0.0
        self.goal[idx] = episode["human_goal"].to(self.pos.dtype)
        self.valid[idx] = episode.get("human_valid", torch.ones(start.shape[:2], dtype=torch.bool))
        self.t[idx] = 0

    def observe(self):
        return self.pos, self.vel, self.valid

    def preferred_velocity(self) -> torch.Tensor:
        to_goal = self.goal - self.pos
        dist = to_goal.norm(dim=-1, keepdim=True)
        return to_goal * (self.v_pref / dist.clamp_min(1e-12)).clamp(max=1.0)

    def velocities(self, agents: Agents | None) -> torch.Tensor:
        raise NotImplementedError

    def advance(self, env_active: torch.Tensor, agents: Agents | None):
        new_vel = self.velocities(agents) * self.valid.unsqueeze(-1)
        moving = (env_active.unsqueeze(-1) & self.valid).unsqueeze(-1)
        prev = self.pos
        self.vel = torch.where(moving, new_vel, self.vel)
        self.pos = torch.where(moving, prev + new_vel * self.dt, prev)
        self.t = torch.where(env_active, self.t + 1, self.t)
        return prev, self.pos, self.valid


class OrcaCrowd(ReactiveCrowd):
    """ORCA humans (van den Berg et al. 2011), solved batched (:func:`orca_velocities`, validated against RVO2).

    Every human solves ORCA among all humans within ``neighbor_dist`` (the nearest ``max_neighbors``)
    and, when ``robot_visible``, the robots: a robot enters as an agent with its current velocity, so
    the human takes its reciprocal half of the avoidance. The robots' own ORCA answers are discarded.
    """

    name = "orca"

    def __init__(self, *args, params: OrcaParams | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.params = params or OrcaParams()

    def velocities(self, agents: Agents | None) -> torch.Tensor:
        p, M = self.params, self.M
        pos, vel, valid = self.pos, self.vel, self.valid
        radius = torch.full(valid.shape, self.radius + p.radius_margin)
        pref = self.preferred_velocity()
        if self.robot_visible:
            pos, vel = torch.cat((pos, agents.pos), 1), torch.cat((vel, agents.vel), 1)
            pref = torch.cat((pref, agents.vel), 1)
            valid = torch.cat((valid, agents.present), 1)
            radius = torch.cat((radius, torch.full(agents.present.shape, self.robot_radius + p.radius_margin)), 1)
        new = ORCA_BACKENDS[p.backend](pos, vel, pref, valid, radius, self.v_pref, time_horizon=p.time_horizon, dt=self.dt,
                              neighbor_dist=p.neighbor_dist, max_neighbors=p.max_neighbors)
        # RVO2's fallback program can leave the speed limit when half-planes are nearly opposite (22 m/s
        # measured in a 50-human crossing); a human is not that fast: cap it (RVO2 and CrowdNav do not)
        new = new[:, :M]
        return new * (self.v_pref / new.norm(dim=-1, keepdim=True).clamp_min(self.v_pref))


class SfmCrowd(ReactiveCrowd):
    """Social-force humans (Helbing & Molnar 1995; Moussaid et al. 2009, as PySocialForce): see
    :mod:`crowdbench.envs.humans.sfm`. When ``robot_visible``, the robots repel them as pedestrians
    moving at their own velocity, plus a short-range body force."""

    name = "sfm"

    def __init__(self, *args, params: SFMParams | None = None, backend: str = "torch", **kwargs):
        super().__init__(*args, **kwargs)
        if backend not in SFM_BACKENDS:
            raise ValueError(f"unknown env.sfm_backend {backend!r}; valid: {', '.join(SFM_BACKENDS)}")
        self.params, self.backend = params or SFMParams(), backend

    def velocities(self, agents: Agents | None) -> torch.Tensor:
        others = {}
        if self.robot_visible:
            others = {"others_pos": agents.pos, "others_vel": agents.vel, "others_valid": agents.present,
                      "others_radius": self.robot_radius}
        return SFM_BACKENDS[self.backend](self.pos, self.vel, self.goal, self.valid, self.radius, self.v_pref,
                                          dt=self.dt, params=self.params, **others)


CROWDS = {"orca": OrcaCrowd, "sfm": SfmCrowd}


def reactive_crowd(cfg, batch: int, orca: OrcaParams | None = None) -> ReactiveCrowd:
    """``cfg.n_humans`` humans of model ``cfg.humans`` for ``batch`` environments, from a simulator config
    with the humans' fields (``human_radius``, ``human_v_pref``, ``robot_visible``; CrowdNav, self-play; an
    ``sfm_backend`` field if it has one)."""
    if cfg.humans == "orca":
        kwargs = {"params": orca}
    else:
        kwargs = {"backend": getattr(cfg, "sfm_backend", "torch")}
    return CROWDS[cfg.humans](batch, cfg.n_humans, cfg.human_radius, cfg.human_v_pref, cfg.dt,
                              robot_visible=cfg.robot_visible, robot_radius=cfg.robot_radius, **kwargs)
