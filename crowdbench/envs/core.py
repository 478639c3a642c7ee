"""Batched replay simulator: B environments, A robots each, M padded humans.

Every tensor is batch-first. One :meth:`CrowdSim.step` advances all environments with
tensor ops; resets take a boolean mask. Humans are replayed from a :class:`Scene` and
never react to the robot (the robot is invisible, SPEC section 3).

Geometry (SPEC section 3):
- clearance ``d`` = centre distance - robot radius - human radius;
- collision: ``d < 0`` at any moment of the step, tested on the linear motion of both
  bodies over the step (closest approach of the relative segment), not only at step ends;
- danger: ``0 <= d < 0.2`` at the end of a step; success: distance to goal < robot radius.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import torch

from crowdbench.data.scenes import Scene

RUNNING, SUCCESS, COLLISION, TIMEOUT = 0, 1, 2, 3
OUTCOMES = {SUCCESS: "success", COLLISION: "collision", TIMEOUT: "timeout"}
_FAR = 1e6  # clearance reported when no human is present
START_CLEARANCE = 0.3  # m: a start point closer than this to a present human is not used


@dataclass
class SimConfig:
    dt: float = 0.25
    v_max: float = 1.0
    robot_radius: float = 0.2
    human_radius: float = 0.1
    danger_dist: float = 0.2
    sensing_range: float = 5.0
    time_limit: int = 100  # steps (25 s at dt = 0.25)
    r_reach: float = 1.0
    r_fail: float = -0.25
    danger_dt_scaling: bool = False  # CrowdNav multiplies the danger penalty by dt
    frame: str = "rotate"  # observation frame: rotate | translate | world
    start_radius: float = 4.0
    time_base: str = "true"  # ETH row period: true (2/3 s) or 0.4

    @classmethod
    def fields_of(cls, mapping) -> dict:
        """The entries of ``mapping`` (e.g. the ``env`` config) that are simulator settings."""
        names = {f.name for f in fields(cls)}
        # YAML reads "true" as a bool: the time base is a string option
        return {k: (str(v).lower() if k == "time_base" else v) for k, v in dict(mapping).items() if k in names}

    def __post_init__(self):
        if self.frame not in ("rotate", "translate", "world"):
            raise ValueError(f"unknown frame {self.frame!r}; valid: rotate, translate, world")


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


def to_local(vec: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Rotate ``[..., K, 2]`` world vectors into the frame whose x-axis is ``heading`` ``[..., 2]``.

    Elementwise rather than ``vec @ R``: batched 2x2 matmuls cost ~20x more per call on CPU.
    """
    c, s = heading[..., 0:1], heading[..., 1:2]
    x, y = vec[..., 0], vec[..., 1]
    return torch.stack((c * x + s * y, c * y - s * x), -1)


def to_world(vec: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    c, s = heading[..., 0:1], heading[..., 1:2]
    x, y = vec[..., 0], vec[..., 1]
    return torch.stack((c * x - s * y, s * x + c * y), -1)


def clip_speed(action: torch.Tensor, v_max: float) -> torch.Tensor:
    """Each component clamped to ``[-v_max, v_max]``, then the speed clipped to ``v_max`` (SPEC section 3)."""
    a = action.clamp(-v_max, v_max)
    return a * (v_max / a.norm(dim=-1, keepdim=True).clamp_min(v_max))


def heading_to(goal: torch.Tensor, pos: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Unit vector from ``pos`` to ``goal``; at the goal the direction is undefined: keep ``heading``."""
    to_goal = goal - pos
    dist = to_goal.norm(dim=-1, keepdim=True)
    return torch.where(dist > 1e-6, to_goal / dist.clamp_min(1e-6), heading)


def step_reward(cfg, end: torch.Tensor, success: torch.Tensor, failure: torch.Tensor,
                active: torch.Tensor) -> torch.Tensor:
    """The paper's reward (Eq. 1-2) of one step: danger term on the end clearance ``end``, ``r_reach``
    on success, ``r_fail`` on collision or timeout (``failure``); zero for inactive agents."""
    danger = -0.1 + end.clamp_min(0.0) / 2
    if cfg.danger_dt_scaling:
        danger = danger * cfg.dt
    return (torch.where(end < cfg.danger_dist, danger, 0.0) + cfg.r_reach * success + cfg.r_fail * failure) * active


def outcome_of(success: torch.Tensor, collision: torch.Tensor, timeout: torch.Tensor) -> torch.Tensor:
    return torch.where(success, SUCCESS, torch.where(collision, COLLISION, torch.where(timeout, TIMEOUT, RUNNING)))


def free_start(scene: Scene, t0: torch.Tensor, start: torch.Tensor, margin: float, radius_sum: float) -> torch.Tensor:
    """``[n]`` bool: no human present at grid index ``t0`` is within ``margin`` clearance of ``start`` ``[n, 2]``.

    An episode that starts inside (or touching) a pedestrian is a collision no policy can avoid.
    """
    pos, valid = scene.pos[t0].to(start.dtype), scene.valid[t0]
    gap = (pos - start.unsqueeze(-2)).norm(dim=-1) - radius_sum
    return ((gap >= margin) | ~valid).all(-1)


class CrowdSim:
    """``B`` environments replaying one scene; ``A`` = 1 robot per environment."""

    def __init__(self, scene: Scene, batch_size: int, cfg: SimConfig | None = None, n_agents: int = 1):
        self.scene = scene
        self.cfg = cfg or SimConfig()
        if abs(self.cfg.dt - scene.dt) > 1e-9:
            raise ValueError(f"scene resampled at dt={scene.dt}, simulator dt={self.cfg.dt}")
        if scene.n_steps <= self.cfg.time_limit + 1:
            raise ValueError(f"scene {scene.name} is shorter than the time limit ({self.cfg.time_limit} steps)")
        self.B, self.A, self.M = batch_size, n_agents, scene.max_humans
        B, A = batch_size, n_agents
        self.t = torch.zeros(B, dtype=torch.long)  # scene grid index
        self.steps = torch.zeros(B, dtype=torch.long)
        self.pos = torch.zeros(B, A, 2)
        self.vel = torch.zeros(B, A, 2)
        self.goal = torch.zeros(B, A, 2)
        self.start = torch.zeros(B, A, 2)
        self.heading = torch.zeros(B, A, 2)
        self.heading[..., 0] = 1.0
        self.outcome = torch.full((B, A), TIMEOUT, dtype=torch.long)  # not started = finished
        self.radius_sum = self.cfg.robot_radius + self.cfg.human_radius
        self.keep = torch.ones(B, self.M, dtype=torch.bool)  # humans present in each env's episode (training dropout)

    # ------------------------------------------------------------------ episodes
    @property
    def last_start(self) -> int:
        return self.scene.last_start(self.cfg.time_limit)

    def start_goal(self, angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Start and goal on the ``start_radius`` circle around the scene centre, diametrically opposed."""
        u = torch.stack((torch.cos(angle), torch.sin(angle)), -1)
        c = self.scene.centre
        return c + self.cfg.start_radius * u, c - self.cfg.start_radius * u

    def start_is_free(self, t0: torch.Tensor, angle: torch.Tensor, margin: float = START_CLEARANCE) -> torch.Tensor:
        return free_start(self.scene, t0, self.start_goal(angle.to(torch.float32))[0], margin, self.radius_sum)

    def reset(self, mask: torch.Tensor, t0: torch.Tensor, angle: torch.Tensor, keep: torch.Tensor | None = None) -> None:
        """Reset the environments where ``mask`` ([B] bool) is set.

        ``t0`` and ``angle`` are ``[B]`` (only the masked entries are used): the scene grid
        index at which the episode starts and the start angle on the circle. ``keep``
        ``[B, M]`` (training only): the humans that exist in the new episode; the others are
        absent for its whole length (not observed, no collisions). Default: all of them.
        """
        self.keep = torch.where(mask.view(-1, 1), True if keep is None else keep, self.keep)
        if (t0[mask] < 0).any() or (t0[mask] > self.last_start).any():
            raise ValueError(f"start index outside [0, {self.last_start}] for scene {self.scene.name}")
        start, goal = self.start_goal(angle.to(torch.float32))
        m2 = mask.view(-1, 1, 1)
        self.t = torch.where(mask, t0, self.t)
        self.steps = torch.where(mask, 0, self.steps)
        self.start = torch.where(m2, start.unsqueeze(1), self.start)
        self.pos = torch.where(m2, start.unsqueeze(1), self.pos)
        self.goal = torch.where(m2, goal.unsqueeze(1), self.goal)
        self.vel = torch.where(m2, 0.0, self.vel)
        self.outcome = torch.where(mask.view(-1, 1), RUNNING, self.outcome)
        self._update_heading()

    def _update_heading(self) -> None:
        self.heading = heading_to(self.goal, self.pos, self.heading)

    # ------------------------------------------------------------------ humans
    def humans(self, t: torch.Tensor | None = None):
        """Humans at grid index ``t`` ([B]): position, velocity ``[B, M, 2]``, valid ``[B, M]``."""
        t = self.t if t is None else t
        return self.scene.pos[t], self.scene.vel[t], self.scene.valid[t] & self.keep

    def clearance(self, pos: torch.Tensor, hpos: torch.Tensor, hvalid: torch.Tensor) -> torch.Tensor:
        """Per-human clearance ``[B, A, M]`` (``_FAR`` on padding)."""
        gap = (hpos.unsqueeze(1) - pos.unsqueeze(2)).norm(dim=-1) - self.radius_sum
        return gap.masked_fill(~hvalid.unsqueeze(1), _FAR)

    def min_clearance(self) -> torch.Tensor:
        """Current clearance to the nearest human, ``[B, A]``."""
        hpos, _, hvalid = self.humans()
        return self.clearance(self.pos, hpos, hvalid).amin(-1)

    # ------------------------------------------------------------------ step
    def clip_action(self, action: torch.Tensor) -> torch.Tensor:
        return clip_speed(action, self.cfg.v_max)

    def step(self, action: torch.Tensor, frame: str | None = None) -> StepInfo:
        """Advance every running environment by one step.

        ``action`` is ``[B, A, 2]`` velocity in the observation frame (``frame``, default
        the config's) and is converted to world coordinates here. Finished environments
        stay frozen until reset and receive zero reward.
        """
        if torch.isnan(action).any():
            raise ValueError("action contains NaN")
        cfg = self.cfg
        frame = frame or cfg.frame
        act = to_world(action.unsqueeze(-2), self.heading).squeeze(-2) if frame == "rotate" else action
        vel = self.clip_action(act)
        active = self.outcome == RUNNING  # [B, A]
        vel = vel * active.unsqueeze(-1)
        new_pos = self.pos + vel * cfg.dt
        env_active = active.any(-1)
        t1 = torch.where(env_active, self.t + 1, self.t)

        # swept test: humans present at t1, moving from their previous position
        h1, hv1 = self.scene.pos[t1], self.scene.valid[t1]
        h0 = self.scene.prev[t1]
        rel0 = h0.unsqueeze(1) - self.pos.unsqueeze(2)  # [B, A, M, 2]
        rel1 = h1.unsqueeze(1) - new_pos.unsqueeze(2)
        swept = segment_min_distance(rel0, rel1) - self.radius_sum
        swept = swept.masked_fill(~hv1.unsqueeze(1), _FAR).amin(-1)  # M >= 1 (see pack_slots)
        end = self.clearance(new_pos, h1, hv1).amin(-1)

        steps = self.steps + env_active.long()
        collision = active & (swept < 0)
        success = active & ~collision & ((self.goal - new_pos).norm(dim=-1) < cfg.robot_radius)
        timeout = active & ~collision & ~success & (steps >= cfg.time_limit).unsqueeze(-1)

        reward = step_reward(cfg, end, success, collision | timeout, active)
        outcome = outcome_of(success, collision, timeout)
        self.outcome = torch.where(active, outcome, self.outcome)
        self.pos, self.vel, self.t, self.steps = new_pos, vel, t1, steps
        self._update_heading()
        return StepInfo(
            reward=reward,
            terminated=success | collision,
            truncated=timeout,
            outcome=outcome,
            clearance=end,
            swept_clearance=swept,
            active=active,
        )

    # ------------------------------------------------------------------ observation
    def observe(self, frame: str | None = None) -> dict[str, torch.Tensor]:
        """Observation in the robot-relative frame (SPEC section 3).

        - ``robot`` ``[B, A, 6]``: ``[px, py, vx, vy, gx, gy]`` (position 0 in relative frames);
        - ``humans`` ``[B, A, M, 4]``: ``[px, py, vx, vy]`` of every human, zero where unobserved;
        - ``humans_mask`` ``[B, A, M]``: present and within the sensing range (centre distance).
        """
        frame = frame or self.cfg.frame
        hpos, hvel, hvalid = self.humans()
        B, A, M = self.B, self.A, self.M
        rel = hpos.unsqueeze(1) - self.pos.unsqueeze(2)  # [B, A, M, 2]
        seen = hvalid.unsqueeze(1) & ((rel * rel).sum(-1) <= self.cfg.sensing_range**2)
        if frame == "world":
            rel = hpos.unsqueeze(1).expand(B, A, M, 2)
        # rows: every human's (position, velocity) pair plus the robot's (velocity, goal)
        pairs = torch.cat((torch.stack((rel, hvel.unsqueeze(1).expand(B, A, M, 2)), -2).reshape(B, A, 2 * M, 2),
                           torch.stack((self.vel, self.goal - self.pos if frame != "world" else self.goal), -2)), -2)
        if frame == "rotate":
            pairs = to_local(pairs, self.heading)
        humans = pairs[:, :, : 2 * M].reshape(B, A, M, 4) * seen.unsqueeze(-1)
        pos = self.pos if frame == "world" else torch.zeros_like(self.pos)
        robot = torch.cat((pos, pairs[:, :, 2 * M :].reshape(B, A, 4)), -1)
        return {"robot": robot, "humans": humans, "humans_mask": seen}
