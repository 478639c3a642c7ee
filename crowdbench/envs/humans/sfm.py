r"""Batched social-force model (SFM) of the humans, in torch.

The extended social-force model as implemented by PySocialForce (Gao & Kitani, github:yuxiang-gao/
PySocialForce, ``DesiredForce`` + ``SocialForce``; itself a port of pedsim_ros / libpedsim), i.e. the
Helbing & Molnar (1995) relaxation towards a desired velocity plus the pedestrian interaction of Moussaid,
Helbing, Garnier, Johansson, Combe & Theraulaz (2009), "Experimental study of the behavioural mechanisms
underlying self-organization in human crowds", Proc. R. Soc. B 276:2755-2762. Accelerations in m/s^2
(unit mass: every "force" below is a force per mass), lengths in m, speeds in m/s, times in s.

Goal attraction (Helbing & Molnar 1995, eq. 2), for human i at p_i with velocity v_i::

    e_i   = (g_i - p_i) / |g_i - p_i|
    F_i^0 = (v_pref_i e_i - v_i) / tau          if |g_i - p_i| > goal_threshold, else  -v_i / tau

Human-human interaction (Moussaid et al. 2009, eqs. 2-3), for each other present human j::

    d_ij  = |p_j - p_i|,   e_ij = (p_j - p_i) / d_ij                   (centre distance, i -> j)
    D_ij  = lambda (v_i - v_j) + e_ij,   t_ij = D_ij / |D_ij|           (interaction direction)
    n_ij  = t_ij rotated by +90 deg                                     (its left normal)
    theta = signed angle from t_ij to e_ij, wrapped to (-pi, pi]
    B     = gamma |D_ij|
    f_ij  = -A exp(-d_ij / B) [ exp(-(n' B theta)^2) t_ij + sign(theta) exp(-(n B theta)^2) n_ij ]

The first term brakes along the interaction direction, the second turns i away from the side j is on.

Human-robot interaction: each body in ``others_*`` (the robot) acts on the humans through the same
Moussaid force ``f_ij`` as a pedestrian j with its own velocity -- which is what PySocialForce does when
the robot is put into its state as one more pedestrian, and keeps the anticipation (a robot moving
towards a human is avoided earlier than a standing one). On top of it comes the circular exponential
repulsion of Helbing, Farkas & Vicsek (2000, "Simulating dynamical features of escape panic", Nature
407:487) on the surface distance::

    f_iR^body = A_body exp((r_i + r_R - d_iR) / B_body) (-e_iR)

because Moussaid's force ignores body size: for a human that has slowed down next to a standing robot
|D| -> 1, B -> gamma = 0.35 m, and ``A exp(-d/B)`` balances the goal force only at d ~ 0.14 m, well inside
the robot's disc. The body term (25 m/s^2 at contact, decaying over 8 cm) keeps the human out without
changing anything beyond ~0.5 m of clearance. ``body_strength = 0`` gives the pure PySocialForce model.

Integration (PySocialForce ``PedState.step``, semi-implicit Euler)::

    v_i <- v_i + dt (F_i^0 + sum_j f_ij + sum_R f_iR)
    v_i <- v_i min(1, v_max_i / |v_i|),   v_max_i = max_speed_factor * v_pref_i  (1.3, PySocialForce)

The caller then moves the humans with ``p += v dt``.

Differences from PySocialForce, and why:

- Desired speed. PySocialForce's ``DesiredForce`` relaxes towards ``max_speeds`` = 1.3 x the initial
  speed, so its pedestrians walk at their speed cap; here the desired speed is ``v_pref`` itself (Helbing
  & Molnar's v^0) and 1.3 v_pref is only the cap, so a human walks at its preferred speed.
- theta is wrapped to (-pi, pi] (computed as atan2(cross, dot)). PySocialForce subtracts two atan2
  angles without wrapping: when t_ij and e_ij straddle the -x axis, theta comes out near +-2 pi and both
  exponentials vanish, so the force drops to ~0 for that pair (libpedsim, which it ports, wraps).
- No obstacle, group, or field-of-view forces; no "stop when less than 0.5 m from the goal" in the step
  (arrival and goal re-sampling are the environment's business). The goal-threshold braking of
  ``DesiredForce`` is kept.
- The robot body term above (absent in PySocialForce).
- Per-human ``radius`` / ``v_pref`` and any number of worlds at once; padded humans (``valid`` False)
  exert no force and get a zero velocity. There is no interaction cutoff (nor in PySocialForce): the force
  decays as exp(-d / (gamma |D|)), ~1e-8 m/s^2 at 20 m for walking speeds.

With the same parameters (body term off, cap = desired speed) one step agrees with PySocialForce 1.1.2 to
1e-9 for every human none of whose pairs hits its unwrapped theta, and for all humans once that unwrapped
theta is emulated (tests/test_sfm_model.py). Cost: all pairs at once, O(N M (M + R)) memory and time;
eager torch spends its time in ~40 elementwise passes over [N, M, M + R], so callers with fixed shapes gain
~3x from ``torch.compile(social_force_velocities, dynamic=False)`` (benchmarks/bench_sfm_model.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

_EPS = 1e-9  # guards the divisions by zero-length vectors; those pairs are masked out or get no direction


@dataclass(frozen=True)
class SFMParams:
    # Relaxation time tau [s]: Helbing & Molnar 1995 (tau = 0.5 s); PySocialForce default.toml
    # [desired_force] relaxation_time = 0.5.
    tau: float = 0.5
    # Distance to the goal [m] under which the desired velocity is zero (the human brakes):
    # PySocialForce default.toml [desired_force] goal_threshold = 0.2.
    goal_threshold: float = 0.2
    # Speed cap as a multiple of v_pref: PySocialForce default.toml [scene] max_speed_multiplier = 1.3
    # (Helbing & Molnar 1995 also cap at 1.3 v^0).
    max_speed_factor: float = 1.3
    # Interaction strength A [m/s^2]: PySocialForce default.toml [social_force] factor = 5.1 (from
    # pedsim_ros); Moussaid et al. 2009 fitted A = 4.5 m/s^2 to their experiments.
    A: float = 5.1
    # Weight of the relative velocity in the interaction direction, lambda [s/m]: Moussaid et al. 2009
    # (lambda = 2.0); PySocialForce lambda_importance = 2.0.
    lam: float = 2.0
    # Range of the interaction per unit |D|, gamma [m]: Moussaid et al. 2009 (gamma = 0.35);
    # PySocialForce gamma = 0.35.
    gamma: float = 0.35
    # Angular decay of the turning term, n: Moussaid et al. 2009 (n = 2.0); PySocialForce n = 2.
    n: float = 2.0
    # Angular decay of the braking term, n': Moussaid et al. 2009 (n' = 3.0); PySocialForce n_prime = 3.
    n_prime: float = 3.0
    # Robot body repulsion strength [m/s^2]: Helbing, Farkas & Vicsek 2000, A_i = 2000 N on a pedestrian of
    # m = 80 kg -> 25 m/s^2. Set to 0 for the pure PySocialForce model.
    body_strength: float = 25.0
    # Robot body repulsion range [m]: Helbing, Farkas & Vicsek 2000, B_i = 0.08 m.
    body_range: float = 0.08


def _as_field(x: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """A per-body scalar as a [N, K] tensor (a float is broadcast)."""
    if isinstance(x, torch.Tensor):
        return x.to(like.dtype).expand(like.shape[:-1])
    return torch.full(like.shape[:-1], float(x), dtype=like.dtype, device=like.device)


def _moussaid_sum(
    pos: torch.Tensor,
    vel: torch.Tensor,
    src_pos: torch.Tensor,
    src_vel: torch.Tensor,
    weight: torch.Tensor,
    p,
) -> torch.Tensor:
    """Sum over j of ``weight_ij * f_ij`` on each i of ``pos/vel`` [N, M, 2] from ``src_*`` [N, K, 2].

    weight [N, M, K] is 0 for absent and self pairs. Every pairwise quantity is kept as separate x / y
    [N, M, K] tensors: reductions and stacks over a trailing dim of size 2 cost ~10x an elementwise op.
    """
    # lambda is applied to the [N, M] / [N, K] velocities before broadcasting: one big multiply fewer.
    lv, lsv = p.lam * vel, p.lam * src_vel
    px, py, vx, vy = (t.unsqueeze(2) for t in (pos[..., 0], pos[..., 1], lv[..., 0], lv[..., 1]))
    sx, sy, svx, svy = (t.unsqueeze(1) for t in (src_pos[..., 0], src_pos[..., 1], lsv[..., 0], lsv[..., 1]))
    ex, ey = sx - px, sy - py  # i -> j
    d = torch.hypot(ex, ey)
    inv = 1.0 / d.clamp_min(_EPS)
    ex, ey = ex * inv, ey * inv
    Dx = (vx - svx) + ex
    Dy = (vy - svy) + ey
    d_len = torch.hypot(Dx, Dy)
    # Angle from D (hence t) to e straight from cross and dot: one atan2, already wrapped to (-pi, pi].
    theta = torch.atan2(Dx * ey - Dy * ex, Dx * ex + Dy * ey)
    B = (p.gamma * d_len).clamp_min(_EPS)
    neg_dist = -d / B
    bt2 = (B * theta).square()
    w = weight * (-p.A / d_len.clamp_min(_EPS))  # 1/|D| turns D into t below
    along = w * torch.exp(neg_dist - p.n_prime**2 * bt2)
    turn = w * torch.sign(theta) * torch.exp(neg_dist - p.n**2 * bt2)
    # along * t + turn * leftnormal(t), leftnormal(x, y) = (-y, x)
    fx = (along * Dx - turn * Dy).sum(dim=2)
    fy = (along * Dy + turn * Dx).sum(dim=2)
    return torch.stack((fx, fy), dim=-1)


def _clean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Padding rows set to 0, so that garbage (NaN, inf) in them cannot leak through a zero weight."""
    return torch.where(valid.unsqueeze(-1), x, torch.zeros((), dtype=x.dtype, device=x.device))


def social_force_accelerations(
    pos: torch.Tensor,
    vel: torch.Tensor,
    goal: torch.Tensor,
    valid: torch.Tensor,
    radius: float | torch.Tensor,
    v_pref: float | torch.Tensor,
    *,
    params: SFMParams = SFMParams(),
    others_pos: torch.Tensor | None = None,
    others_vel: torch.Tensor | None = None,
    others_valid: torch.Tensor | None = None,
    others_radius: float | torch.Tensor | None = None,
) -> torch.Tensor:
    """Total force per mass [N, M, 2] on each human (zero for absent ones); see the module docstring."""
    n_w, m = pos.shape[:2]
    pos, vel, goal = _clean(pos, valid), _clean(vel, valid), _clean(goal, valid)
    v_pref = _as_field(v_pref, pos)

    to_goal = goal - pos
    dist = torch.hypot(to_goal[..., 0], to_goal[..., 1]).unsqueeze(-1)
    desired = to_goal / dist.clamp_min(_EPS) * v_pref.unsqueeze(-1)
    desired = torch.where(dist > params.goal_threshold, desired, torch.zeros_like(desired))
    force = (desired - vel) / params.tau

    src_pos, src_vel, src_valid = pos, vel, valid
    if others_pos is not None:
        r = others_pos.shape[1]
        if others_valid is None:
            others_valid = torch.ones(n_w, r, dtype=torch.bool, device=pos.device)
        others_pos = _clean(others_pos, others_valid)
        others_vel = torch.zeros_like(others_pos) if others_vel is None else _clean(others_vel, others_valid)
        # One pairwise pass over humans and robots together: cheaper than two passes for small R.
        src_pos = torch.cat((pos, others_pos), dim=1)
        src_vel = torch.cat((vel, others_vel), dim=1)
        src_valid = torch.cat((valid, others_valid), dim=1)
    k = src_pos.shape[1]
    not_self = ~torch.eye(m, k, dtype=torch.bool, device=pos.device)
    weight = (valid.unsqueeze(2) & src_valid.unsqueeze(1) & not_self).to(pos.dtype)
    force = force + _moussaid_sum(pos, vel, src_pos, src_vel, weight, params)

    if others_pos is not None and params.body_strength != 0.0:
        if others_radius is None:
            raise ValueError("others_radius is needed for the body repulsion (or set params.body_strength=0)")
        ok = (valid.unsqueeze(2) & others_valid.unsqueeze(1)).to(pos.dtype)
        force = force + body_force(pos, radius, others_pos, others_radius, ok, params)

    return torch.where(valid.unsqueeze(-1), force, torch.zeros_like(force))


def body_force(pos, radius, others_pos, others_radius, weight, params: SFMParams) -> torch.Tensor:
    """Helbing, Farkas & Vicsek's body repulsion [N, M, 2] on humans ``pos`` [N, M, 2] from bodies
    ``others_pos`` [N, R, 2], each pair weighted by ``weight`` [N, M, R] (0 for absent pairs)."""
    rr = _as_field(others_radius, others_pos)
    gx = pos[..., 0].unsqueeze(2) - others_pos[..., 0].unsqueeze(1)  # [N, M, R], robot -> human
    gy = pos[..., 1].unsqueeze(2) - others_pos[..., 1].unsqueeze(1)
    d = torch.hypot(gx, gy)
    reach = _as_field(radius, pos).unsqueeze(2) + rr.unsqueeze(1)
    mag = weight * params.body_strength * torch.exp((reach - d) / params.body_range) / d.clamp_min(_EPS)
    return torch.stack(((mag * gx).sum(dim=2), (mag * gy).sum(dim=2)), dim=-1)


def robot_force(pos, vel, valid, radius, others_pos, others_vel, others_valid, others_radius,
                params: SFMParams, cutoff: float) -> torch.Tensor:
    """The force per mass [N, M, 2] that bodies ``others_*`` [N, R, ...] (the robots) exert on humans
    ``pos/vel`` [N, M, 2], without the humans' goal force or their forces on each other: Moussaid's
    interaction plus the body repulsion, from the bodies whose centre is within ``cutoff`` m only
    (so that a far robot changes nothing, exactly)."""
    gap2 = (pos.unsqueeze(2) - others_pos.unsqueeze(1)).square().sum(-1)  # [N, M, R]
    near = valid.unsqueeze(2) & others_valid.unsqueeze(1) & (gap2 < cutoff * cutoff)
    pos, vel = _clean(pos, valid), _clean(vel, valid)
    others_pos, others_vel = _clean(others_pos, others_valid), _clean(others_vel, others_valid)
    weight = near.to(pos.dtype)
    force = _moussaid_sum(pos, vel, others_pos, others_vel, weight, params)
    if params.body_strength != 0.0:
        force = force + body_force(pos, radius, others_pos, others_radius, weight, params)
    return torch.where(valid.unsqueeze(-1), force, torch.zeros_like(force))


def social_force_velocities(
    pos: torch.Tensor,
    vel: torch.Tensor,
    goal: torch.Tensor,
    valid: torch.Tensor,
    radius: float | torch.Tensor,
    v_pref: float | torch.Tensor,
    *,
    dt: float,
    params: SFMParams = SFMParams(),
    others_pos: torch.Tensor | None = None,
    others_vel: torch.Tensor | None = None,
    others_valid: torch.Tensor | None = None,
    others_radius: float | torch.Tensor | None = None,
) -> torch.Tensor:
    """The humans' velocity [N, M, 2] after one semi-implicit Euler step of ``dt`` seconds.

    pos, vel, goal: [N, M, 2] humans of N independent worlds; valid: [N, M] bool (False = padding).
    radius, v_pref: float or [N, M]. others_pos/vel [N, R, 2], others_valid [N, R], others_radius float or
    [N, R]: bodies (the robot) that repel the humans and are not moved; vel defaults to standing, valid to
    all present; radius is required unless ``params.body_strength == 0``.
    The speed is capped at ``params.max_speed_factor * v_pref``; absent humans get zeros.
    """
    acc = social_force_accelerations(
        pos, vel, goal, valid, radius, v_pref, params=params,
        others_pos=others_pos, others_vel=others_vel, others_valid=others_valid, others_radius=others_radius,
    )  # fmt: skip
    new_vel = vel + dt * acc
    v_max = params.max_speed_factor * _as_field(v_pref, pos)
    speed = torch.hypot(new_vel[..., 0], new_vel[..., 1])
    scale = torch.clamp(v_max / speed.clamp_min(_EPS), max=1.0)
    new_vel = new_vel * scale.unsqueeze(-1)
    return torch.where(valid.unsqueeze(-1), new_vel, torch.zeros_like(new_vel))


__all__ = ["SFMParams", "body_force", "robot_force", "social_force_accelerations", "social_force_velocities"]
