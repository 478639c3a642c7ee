"""The social-navigation metrics the field reports, per episode, from the evaluation's traces.

SPL, STL, personal-space compliance at 0.5 m, minimum time-to-collision, path irregularity and one
composite score (definitions, units and citations: docs/protocol.md, "Metrics"). Every function is
batched: ``[T, B]`` step traces, ``[T, B, M]`` human traces, ``[B]`` results; float64 throughout.
:func:`episode_social_metrics` is what :func:`crowdbench.protocols.engine.episode_metrics` adds to protocol v1's
metrics (which it leaves untouched).
"""

from __future__ import annotations

import math

import torch

PERSONAL_SPACE_50CM = 0.5  # m, surface gap (the 0.45 m one is crowdbench.protocols.engine.PERSONAL_SPACE)
TTC_HORIZON = 10.0  # s: a minimum time-to-collision is reported capped here (no collision course = the cap)
SCORE_TTC = 3.0  # s: the composite's TTC term, min(TTC, 3 s) / 3 s (pedestrians' interaction horizon)


def spl(success: torch.Tensor, straight: torch.Tensor, path: torch.Tensor) -> torch.Tensor:
    """Success weighted by path length (Anderson et al. 2018): ``S * l / max(p, l)``."""
    straight = straight.double()
    return success.double() * straight / torch.maximum(path.double(), straight)


def stl(success: torch.Tensor, straight: torch.Tensor, nav_time: torch.Tensor, v_max: float) -> torch.Tensor:
    """Success weighted by time length: ``S * t* / max(t, t*)``, ``t* = l / v_max`` (free-space time)."""
    t_star = straight.double() / v_max
    return success.double() * t_star / torch.maximum(nav_time.double(), t_star)


def compliance(clearance: torch.Tensor, active: torch.Tensor, threshold: float) -> torch.Tensor:
    """Fraction of active steps ending with a clearance ``>= threshold`` (``[T, B]`` -> ``[B]``)."""
    steps = active.double().sum(0)
    return ((clearance.double() >= threshold) & active).sum(0) / steps.clamp_min(1)


def time_to_collision(rel_pos: torch.Tensor, rel_vel: torch.Tensor, radius: float) -> torch.Tensor:
    """First ``t >= 0`` with ``|rel_pos + t rel_vel| = radius`` (``[..., 2]`` -> ``[...]``, float64):
    0 if the discs already overlap, ``inf`` if they never meet."""
    p, v = rel_pos.double(), rel_vel.double()
    c = (p * p).sum(-1) - radius**2
    b = (p * v).sum(-1)
    disc = b * b - (v * v).sum(-1) * c
    approaching = (b < 0) & (disc >= 0)
    # the smaller root (-b - sqrt(disc)) / |v|^2, written as c / (-b + sqrt(disc)): no cancellation, no 0/0
    t = c / (-b + disc.clamp_min(0).sqrt()).clamp_min(1e-300)
    return torch.where(c <= 0, 0.0, torch.where(approaching, t, math.inf))


def min_ttc(xy: torch.Tensor, humans_xy: torch.Tensor, humans_vel: torch.Tensor, present: torch.Tensor,
            active: torch.Tensor, dt: float, radius: float, horizon: float = TTC_HORIZON) -> torch.Tensor:
    """Per episode ``[B]``: the smallest time-to-collision at the end of any active step, over the humans
    present then, extrapolating robot and humans at constant velocity (the robot's: its last step),
    capped at ``horizon``. ``xy`` ``[T + 1, B, 2]``, humans ``[T, B, M, 2]``, ``present`` ``[T, B, M]``."""
    vel = (xy[1:] - xy[:-1]).double() / dt  # [T, B, 2]
    ttc = time_to_collision(humans_xy.double() - xy[1:].double().unsqueeze(-2),
                            humans_vel.double() - vel.unsqueeze(-2), radius)
    ttc = ttc.masked_fill(~(present & active.unsqueeze(-1)), math.inf)  # [T, B, M]
    if ttc.numel() == 0:  # no human slots
        return torch.full(active.shape[1:], horizon, dtype=torch.float64)
    return ttc.amin(-1).amin(0).clamp_max(horizon)


def path_irregularity(xy: torch.Tensor, active: torch.Tensor, start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """Guzzi et al. (2013): total rotation of the direction of motion per metre of path (rad/m), from
    the start-goal direction (the robot's initial heading; reaching the goal straight needs no turn).
    Steps without motion keep the last direction; a path of length 0 gives 0."""
    step = (xy[1:] - xy[:-1]).double()  # [T, B, 2]
    length = step.norm(dim=-1)
    moving = active & (length > 0)
    dirs = torch.cat([(goal - start).double().unsqueeze(0), step])  # [T + 1, B, 2]; entry 0: initial heading
    T = step.shape[0]
    idx = torch.where(moving, torch.arange(1, T + 1).view(T, *[1] * (moving.dim() - 1)), 0)
    last = torch.cat([torch.zeros_like(idx[:1]), idx]).cummax(0).values[:-1]  # [T, B]: last direction before step k
    prev = dirs.gather(0, last.unsqueeze(-1).expand(*last.shape, 2))
    cross = prev[..., 0] * step[..., 1] - prev[..., 1] * step[..., 0]
    turn = torch.atan2(cross, (prev * step).sum(-1)).abs() * moving
    path = (length * active).sum(0)
    return torch.where(path > 0, turn.sum(0) / path.clamp_min(1e-300), 0.0)


def social_nav_score(success, spl_, stl_, personal_space, ttc, tau: float = SCORE_TTC) -> torch.Tensor:
    """The composite: the mean of five per-episode terms in [0, 1], higher is better: success, SPL, STL,
    personal-space compliance at 0.5 m and ``min(min TTC, tau) / tau``."""
    terms = [success.double(), spl_, stl_, personal_space, ttc.clamp_max(tau) / tau]
    return sum(terms) / len(terms)


def episode_social_metrics(tr: dict, cfg, success: torch.Tensor, path: torch.Tensor,
                           nav_time: torch.Tensor) -> dict[str, torch.Tensor]:
    """The new per-episode metrics ``[B]`` from the traces of :func:`crowdbench.protocols.engine.robot_traces`
    (``humans_xy``, ``humans_vel`` ``[T, B, M, 2]``, ``humans_present`` ``[T, B, M]`` at every step's end)."""
    straight = (tr["goal"] - tr["start"]).double().norm(dim=-1)
    act = tr["active"]
    out = {"spl": spl(success, straight, path), "stl": stl(success, straight, nav_time, cfg.v_max),
           "personal_space_50cm": compliance(tr["clearance"], act, PERSONAL_SPACE_50CM),
           "path_irregularity": path_irregularity(tr["xy"], act, tr["start"], tr["goal"]),
           "min_ttc": min_ttc(tr["xy"], tr["humans_xy"], tr["humans_vel"], tr["humans_present"], act, cfg.dt,
                              cfg.robot_radius + cfg.human_radius)}
    out["social_nav_score"] = social_nav_score(success, out["spl"], out["stl"], out["personal_space_50cm"],
                                               out["min_ttc"])
    return out
