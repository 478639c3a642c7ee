"""ORCA (optimal reciprocal collision avoidance) for many independent crowds at once, in torch.

One call computes, for every agent of ``N`` independent worlds of ``K`` agents each, the new
velocity that RVO2 2.0's ``RVOSimulator::doStep`` computes (``Agent::computeNeighbors`` then
``Agent::computeNewVelocity``, no obstacles). Positions are not advanced: integrate with
``pos + v * dt`` yourself, as RVO2's ``Agent::update`` does.

Algorithm, per agent ``a``:

1. Neighbours: the other valid agents ``b`` of the same world with ``|p_b - p_a|^2 <
   neighbor_dist^2`` (strictly), the ``max_neighbors`` nearest kept, nearest first.
2. One ORCA half-plane per neighbour, from the relative position ``P = p_b - p_a``, relative
   velocity ``V = v_a - v_b`` and combined radius ``R = r_a + r_b``. Without collision
   (``|P| > R``), ``V`` is projected on the truncated velocity obstacle (the cone of the two
   legs tangent to the disc ``R`` around ``P``, cut off by the disc ``R / time_horizon``
   around ``P / time_horizon``) onto the cut-off circle or the nearer leg; when the discs
   overlap, onto the circle of radius ``R / dt`` around ``P / dt`` (leave the overlap within
   one step). ``u`` is the vector from ``V`` to that projection; the half-plane passes through
   ``v_a + u / 2`` (each agent takes half of the avoidance) perpendicular to ``u``.
3. ``linearProgram2``: the velocity closest to ``pref`` inside the disc ``max_speed`` that
   satisfies every half-plane, by RVO2's incremental algorithm (lines in neighbour order).
4. If that is infeasible, ``linearProgram3``: from the first infeasible line on, the velocity
   in the disc that minimises the largest penetration of the half-planes.

Parameters: ``time_horizon`` (s) how far ahead collisions with other agents are avoided;
``dt`` (s) the simulation step (used only for overlapping discs); ``neighbor_dist`` (m) and
``max_neighbors`` which agents are taken into account. ``radius`` and ``max_speed`` are per
agent (float or ``[N, K]``), as RVO2's ``add_agent`` arguments; the other parameters are the
same for every agent.

Differences from RVO2 and why:

- Float64 throughout (RVO2 is float32), so that nothing is lost on float64 inputs and
  round-off matters less in the near-degenerate steps. Measured against pyrvo on float32
  inputs (benchmarks/bench_orca_model.py): median difference ~5e-8 m/s; about 0.1 % of
  agents differ by more than 1e-3 m/s, all of them in ``linearProgram3`` (infeasible
  half-planes) where nearly parallel bisectors make the float32 run pick another point of
  (almost) the same largest penetration (equal to ~1e-4; RVO2's point sometimes leaves the
  speed disc there, ours stays in it). RVO_EPSILON (1e-5) is kept as the parallel test.
- Neighbour ties (equal squared distances) are broken by agent index; RVO2 breaks them by
  its k-d tree's traversal order. This only matters for exactly equal distances.
- Invalid (padding) agents are neither neighbours nor solved: their ``vel`` is returned as
  given.
"""

from __future__ import annotations

import torch

from crowdbench.envs.humans.lp import linear_program2, linear_program3


def _per_agent(x, valid: torch.Tensor) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(torch.float64).expand(valid.shape)
    return torch.full(valid.shape, float(x), dtype=torch.float64)


def orca_velocities(
    pos: torch.Tensor,
    vel: torch.Tensor,
    pref: torch.Tensor,
    valid: torch.Tensor,
    radius: float | torch.Tensor,
    max_speed: float | torch.Tensor,
    *,
    time_horizon: float,
    dt: float,
    neighbor_dist: float,
    max_neighbors: int,
) -> torch.Tensor:
    """New velocity ``[N, K, 2]`` of every agent (see the module docstring).

    ``pos, vel, pref``: ``[N, K, 2]`` positions, current and preferred velocities; ``valid``
    ``[N, K]`` bool; ``radius, max_speed``: float or ``[N, K]``. The result has ``vel``'s
    dtype; invalid agents keep ``vel``.
    """
    n, k = valid.shape
    lines = orca_lines(
        pos, vel, valid, radius, time_horizon=time_horizon, dt=dt, neighbor_dist=neighbor_dist,
        max_neighbors=max_neighbors,
    )  # fmt: skip
    m = lines[0].shape[1]
    speed = _per_agent(max_speed, valid).reshape(-1)
    optx, opty = pref[..., 0].to(torch.float64).reshape(-1), pref[..., 1].to(torch.float64).reshape(-1)
    rx, ry, fail = linear_program2(*lines, speed, optx, opty, False)
    lp3 = (fail < m).nonzero().squeeze(1)
    if lp3.numel():
        sub = [x[lp3] for x in lines]
        nx, ny = linear_program3(*sub, fail[lp3], speed[lp3], rx[lp3], ry[lp3])
        rx = rx.index_put((lp3,), nx)
        ry = ry.index_put((lp3,), ny)
    new = torch.stack([rx, ry], dim=-1).reshape(n, k, 2).to(vel.dtype)
    return torch.where(valid[..., None], new, vel)


def orca_lines(pos, vel, valid, radius, *, time_horizon, dt, neighbor_dist, max_neighbors):
    """Every agent's ORCA half-planes, nearest neighbour first, as five ``[N * K, M]`` tensors
    ``(point_x, point_y, direction_x, direction_y, exists)`` with ``M = min(max_neighbors,
    K - 1)``; velocity ``v`` satisfies a line when ``det(direction, point - v) <= 0``."""
    n, k = valid.shape
    f64 = torch.float64
    px, py = pos[..., 0].to(f64), pos[..., 1].to(f64)
    vx, vy = vel[..., 0].to(f64), vel[..., 1].to(f64)
    rad = _per_agent(radius, valid)
    m = max(min(int(max_neighbors), k - 1), 0)
    if m == 0:
        empty = torch.zeros(n * k, 0, dtype=f64)
        return empty, empty, empty, empty, torch.zeros(n * k, 0, dtype=torch.bool)

    # computeNeighbors: the m nearest valid others strictly within neighbor_dist.
    relx = px[:, None, :] - px[:, :, None]  # [n, a, b] = p_b - p_a
    rely = py[:, None, :] - py[:, :, None]
    d2 = relx * relx + rely * rely
    eye = torch.eye(k, dtype=torch.bool)
    ok = valid[:, :, None] & valid[:, None, :] & ~eye & (d2 < float(neighbor_dist) ** 2)
    key = torch.where(ok, d2, float("inf"))
    # Stable sort: ties go to the lower index (RVO2: k-d tree order, see docstring).
    key, order = key.sort(dim=2, stable=True)
    key, order = key[..., :m], order[..., :m]
    exists = torch.isfinite(key).reshape(n * k, m)
    relx = relx.gather(2, order).reshape(n * k, m)
    rely = rely.gather(2, order).reshape(n * k, m)
    flat = order.reshape(n, k * m)
    ovx = vx.gather(1, flat).reshape(n * k, m)
    ovy = vy.gather(1, flat).reshape(n * k, m)
    orad = rad.gather(1, flat).reshape(n * k, m)
    ax, ay = vx.reshape(-1, 1), vy.reshape(-1, 1)
    dist_sq = relx * relx + rely * rely
    lx, ly, ldx, ldy = _orca_lines(
        relx, rely, ax - ovx, ay - ovy, dist_sq, rad.reshape(-1, 1) + orad, ax, ay,
        1.0 / float(time_horizon), 1.0 / float(dt),
    )  # fmt: skip
    return lx, ly, ldx, ldy, exists


def _orca_lines(relx, rely, rvx, rvy, dist_sq, comb_r, vx, vy, inv_tau: float, inv_dt: float):
    """ORCA half-planes (point x/y, unit direction x/y), all ``[B, M]``, as in
    ``Agent::computeNewVelocity``. Rows of absent neighbours hold garbage (masked later)."""
    # Selections are torch.lerp with 0/1 weights (exact, and several times cheaper than
    # torch.where on CPU); both branches are finite for every existing neighbour.
    collide = (dist_sq <= comb_r * comb_r).to(relx.dtype)
    # Overlapping discs use the cut-off circle of the step instead of the horizon: one w for both.
    inv_t = inv_tau + (inv_dt - inv_tau) * collide
    wx, wy = rvx - inv_t * relx, rvy - inv_t * rely
    w_sq = wx * wx + wy * wy
    dot1 = wx * relx + wy * rely
    r_sq = comb_r * comb_r
    on_cutoff = (dot1 < 0.0) & (dot1 * dot1 > r_sq * w_sq)
    circle = torch.maximum(collide, on_cutoff.to(relx.dtype))

    # Projection on the (cut-off or collision) circle.
    w_len = w_sq.sqrt()
    # w = 0 (only on a leg, never on a circle) would poison the unused branch with NaN.
    inv_w = 1.0 / w_len.clamp_min(1e-300)
    ux, uy = wx * inv_w, wy * inv_w
    c_scale = comb_r * inv_t - w_len

    # Projection on a leg: left leg if w is left of P, else the right one (sign -1 mirrors it).
    leg = (dist_sq - r_sq).clamp_min(0.0).sqrt()
    sleg = leg * ((relx * wy - rely * wx > 0.0).to(relx.dtype) * 2.0 - 1.0)
    ldx = (relx * sleg - rely * comb_r) / dist_sq
    ldy = (rely * sleg + relx * comb_r) / dist_sq
    proj = rvx * ldx + rvy * ldy

    dx = torch.lerp(ldx, uy, circle)
    dy = torch.lerp(ldy, -ux, circle)
    ux = torch.lerp(proj * ldx - rvx, c_scale * ux, circle)
    uy = torch.lerp(proj * ldy - rvy, c_scale * uy, circle)
    return vx + 0.5 * ux, vy + 0.5 * uy, dx, dy
