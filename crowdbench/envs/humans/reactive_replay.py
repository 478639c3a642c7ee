r"""Reactive replay (protocol v2): the recorded ETH/UCY pedestrians, who now yield to the robot and
then rejoin their recorded tracks.

Each recorded human keeps the recording as a feed-forward and adds a deviation that a crowd model
decides from the robots alone (the humans' interactions with each other stay as recorded)::

    r(t), v_rec = (r(t+1) - r(t)) / dt      recorded position, recorded velocity of the coming step
    e = p - r(t)                             the human's offset from its recording
    v_pref = v_rec - e / horizon             towards where the recording will be ``horizon`` s ahead
    v = model(v_pref; robots)                ORCA or social force against the robots only
    p(t+1) = r(t+1) + e + (v - v_rec) dt     i.e. p + v dt, kept in offset form

On its track (``e = 0``) the preferred velocity is exactly the recorded one; while no robot is near,
``v = v_pref`` bit for bit, so a human that never met a robot is replayed exactly and one that was
pushed aside returns to its track with the offset shrinking by ``1 - dt / horizon`` per step. Humans
appear where and when the recording has them appear (with zero offset) and vanish when their track
ends, wherever they are. A human's observed velocity is the recording's (as in protocol v1) plus its
current deviation ``v - v_rec``.

Models (``params.model``):

- ``orca``: one ORCA half-plane per robot within ``neighbor_dist`` (nearest first), from the human's
  and the robot's current velocities, bodies grown by ``radius_margin``; the human takes
  ``responsibility`` of the avoidance (0.5: RVO2's reciprocal share, as CrowdNav's visible robot).
  Solved with RVO2's linear programs 2 and 3 (:mod:`crowdbench.envs.humans.lp`).
- ``sfm``: the deviation relaxes towards ``-e / horizon`` with the social-force model's relaxation
  time and is pushed by the robots' Moussaid interaction and body force (PySocialForce's
  parameters, :class:`~crowdbench.envs.humans.sfm.SFMParams`), robots within ``neighbor_dist`` only.

Either way the speed is capped at ``max(min_speed, speed_factor * |v_rec|)``: a recorded runner is
never slowed down by the cap, and a standing person can still step aside at walking speed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch

from crowdbench.config_fields import bounded, check_fields
from crowdbench.data.scenes import Scene
from crowdbench.envs.humans import Agents
from crowdbench.envs.humans.lp import _gather, _rows, far_lines, lp2_packed, lp3_packed
from crowdbench.envs.humans.orca import DTYPE, _orca_lines
from crowdbench.envs.humans.reactive import OrcaParams
from crowdbench.envs.humans.sfm import SFMParams, robot_force

MODELS = ("orca", "sfm")


@dataclass(frozen=True)
class ReactiveParams:
    """The ``env.reactive`` settings, with their bounds (also the schema of ``env.reactive``); the ORCA ones
    default to the humans' ORCA of every crowd model (:class:`~crowdbench.envs.humans.reactive.OrcaParams`).
    docs/reactive_replay.md gives the reasons for each default."""

    model: str = bounded("orca", choices=MODELS)
    # s: how far ahead (along the recording) a displaced human aims; the offset decays by dt / horizon per step
    horizon: float = bounded(1.0, gt=0)
    speed_factor: float = bounded(1.3, gt=0)  # cap = speed_factor x recorded speed (Helbing & Molnar 1995's 1.3 v0)...
    min_speed: float = bounded(1.0, ge=0)  # m/s ... but never below this (CrowdNav's human v_pref)
    neighbor_dist: float = bounded(OrcaParams.neighbor_dist, gt=0)  # m: robots farther away are ignored
    time_horizon: float = bounded(OrcaParams.time_horizon, gt=0)  # s, ORCA
    responsibility: float = bounded(0.5, gt=0, le=1)  # ORCA: the human's share of the avoidance (RVO2's 0.5)
    radius_margin: float = bounded(OrcaParams.radius_margin, ge=0)  # m added to each body's radius in ORCA

    def __post_init__(self):
        check_fields(self, "env.reactive.")

    @classmethod
    def of(cls, mapping) -> ReactiveParams:
        """From the ``env.reactive`` mapping; an unknown key is a one-line error naming it."""
        mapping = dict(mapping or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(mapping) - names)
        if unknown:
            raise ValueError(f"unknown env.reactive key(s) {', '.join(unknown)}; valid: {', '.join(sorted(names))}")
        return cls(**mapping)

    def to_dict(self) -> dict:
        return asdict(self)


def track_links(scene: Scene) -> tuple[torch.Tensor, torch.Tensor]:
    """Per grid step, how the slot-packed humans continue: ``src`` ``[T, M]`` the slot at ``t - 1`` of
    the human in slot ``s`` at ``t`` (-1: it appears at ``t``), and ``step`` ``[T, M, 2]`` the recorded
    displacement of slot ``s`` from ``t`` to ``t + 1`` (0 where its track ends)."""
    ped, pos = scene.ped_id, scene.pos
    T, M = ped.shape
    same = (ped[:-1, :, None] == ped[1:, None, :]) & (ped[:-1, :, None] >= 0)  # [T-1, s at t, s' at t+1]
    src = torch.full((T, M), -1, dtype=torch.long)
    src[1:] = torch.where(same.any(1), same.to(torch.uint8).argmax(1), -1)
    nxt = torch.where(same.any(2), same.to(torch.uint8).argmax(2), -1)  # [T-1, M]
    step = torch.zeros_like(pos)
    ahead = torch.gather(pos[1:], 1, nxt.clamp_min(0).unsqueeze(-1).expand(-1, -1, 2))
    step[:-1] = torch.where((nxt >= 0).unsqueeze(-1), ahead - pos[:-1], 0.0)
    return src, step


class ReactiveReplayCrowd:
    """The humans of ``scene`` replayed reactively (module docstring). Episode key: ``t0`` ``[n]``, as replay."""

    name = "reactive_replay"
    robot_visible = True  # the humans yield to the robot (a value lookahead's `query` is refused here)

    def __init__(self, scene: Scene, batch: int, time_limit: int, dt: float, human_radius: float,
                 robot_radius: float, params: ReactiveParams | None = None, sfm: SFMParams | None = None):
        self.scene, self.M = scene, scene.max_humans
        self.params, self.sfm = params or ReactiveParams(), sfm or SFMParams()
        self.dt, self.human_radius, self.robot_radius = float(dt), float(human_radius), float(robot_radius)
        self.last_start = scene.last_start(time_limit)
        self.src, step = track_links(scene)
        self.v_rec = step / self.dt
        self.t = torch.zeros(batch, dtype=torch.long)
        self.offset = torch.zeros(batch, self.M, 2)  # p - r(t), in the slots of step t
        self.dev = torch.zeros(batch, self.M, 2)  # velocity - recorded velocity

    def reset(self, mask: torch.Tensor, idx: torch.Tensor, episode: dict) -> None:
        t0 = episode["t0"].long()
        if (t0 < 0).any() or (t0 > self.last_start).any():
            raise ValueError(f"start index outside [0, {self.last_start}] for scene {self.scene.name}")
        self.t[idx] = t0
        self.offset[idx] = 0.0
        self.dev[idx] = 0.0

    def observe(self):
        t = self.t
        return self.scene.pos[t] + self.offset, self.scene.vel[t] + self.dev, self.scene.valid[t]

    def advance(self, env_active: torch.Tensor, agents: Agents):
        sc, t = self.scene, self.t
        valid = sc.valid[t]
        pos, vel, _ = self.observe()
        v_rec = self.v_rec[t]
        pref = v_rec - self.offset / self.params.horizon
        cap = (v_rec.norm(dim=-1) * self.params.speed_factor).clamp_min(self.params.min_speed)
        robots = agents.pos, agents.vel, agents.present
        if self.params.model == "orca":
            new = self._orca(pos, vel, pref, cap, valid, *robots)
            dev = new - v_rec
        else:
            dev = self._sfm(pos, vel, v_rec, cap, valid, *robots)
        dev = dev * valid.unsqueeze(-1)
        offset = self.offset + dev * self.dt

        # into the slots of t + 1 (humans who appear start on their track; those whose track ends vanish)
        t1 = torch.where(env_active, t + 1, t)
        src = self.src[(t + 1).clamp_max(sc.n_steps - 1)]
        cont = (src >= 0).unsqueeze(-1)
        take = lambda x: torch.gather(x, 1, src.clamp_min(0).unsqueeze(-1).expand(-1, -1, 2)) * cont
        run = env_active.view(-1, 1, 1)
        prev = torch.where(run, torch.where(cont, take(pos), sc.pos[t1]), pos)
        self.offset = torch.where(run, take(offset), self.offset)
        self.dev = torch.where(run, take(dev), self.dev)
        self.t = t1
        return prev, sc.pos[t1] + self.offset, sc.valid[t1]

    def _orca(self, pos, vel, pref, cap, valid, rpos, rvel, rvalid):
        """ORCA against the robots only: ``[B, M, 2]`` new velocities."""
        p = self.params
        B, M, A = pos.shape[0], self.M, rpos.shape[1]
        rel = rpos.unsqueeze(1) - pos.unsqueeze(2)  # [B, M, A, 2]: robot - human
        rv = vel.unsqueeze(2) - rvel.unsqueeze(1)
        d2 = rel.square().sum(-1)
        exists = valid.unsqueeze(2) & rvalid.unsqueeze(1) & (d2 < p.neighbor_dist ** 2)
        if A > 1:  # RVO2's order: nearest neighbour first
            order = d2.masked_fill(~exists, float("inf")).argsort(-1)
            rel, rv = (torch.gather(x, 2, order.unsqueeze(-1).expand(-1, -1, -1, 2)) for x in (rel, rv))
            exists = torch.gather(exists, 2, order)
        line_major = lambda x: x.permute(2, 0, 1).reshape(A, B * M).to(DTYPE)  # [A, B*M]
        v = vel.reshape(B * M, 2).to(DTYPE)
        lines = _orca_lines(line_major(rel[..., 0]), line_major(rel[..., 1]), line_major(rv[..., 0]),
                            line_major(rv[..., 1]), self.human_radius + self.robot_radius + 2 * p.radius_margin,
                            v[:, 0], v[:, 1], 1.0 / p.time_horizon, 1.0 / self.dt, share=p.responsibility)
        lines = torch.where(line_major(exists).bool()[:, None], lines, far_lines(lines))
        speed = cap.reshape(-1).to(DTYPE)
        opt = pref.reshape(-1, 2).to(DTYPE).T
        rx, ry, fail = lp2_packed(lines, speed, opt[0], opt[1])
        lp3 = (fail < A).nonzero().squeeze(1)
        if lp3.numel():
            nx, ny = lp3_packed(_gather(_rows(lines), lp3, A), fail[lp3], speed[lp3], rx[lp3], ry[lp3])
            rx, ry = rx.index_put((lp3,), nx), ry.index_put((lp3,), ny)
        return torch.stack((rx, ry), -1).reshape(B, M, 2).to(pos.dtype)

    def _sfm(self, pos, vel, v_rec, cap, valid, rpos, rvel, rvalid):
        """Social force against the robots only: the new deviation ``[B, M, 2]`` from the recorded velocity."""
        f = robot_force(pos, vel, valid, self.human_radius, rpos, rvel, rvalid, self.robot_radius, self.sfm,
                        cutoff=self.params.neighbor_dist)
        dev = self.dev + self.dt * ((-self.offset / self.params.horizon - self.dev) / self.sfm.tau + f)
        new = v_rec + dev
        scale = (cap / new.norm(dim=-1).clamp_min(1e-9)).clamp(max=1.0).unsqueeze(-1)
        return torch.where(scale < 1.0, new * scale - v_rec, dev)
