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

- Precision: float32 throughout, as RVO2 (float64 inputs are rounded; the result is
  cast back to ``vel``'s dtype). This reproduces RVO2 more closely than float64 did: in
  ``linearProgram3`` over nearly (anti-)parallel lines, float32 bisector intersections lie
  ~1e4 m away and RVO2's result can leave the speed disc by far (seen: 22 m/s with
  ``max_speed`` 1 in a dense circle crossing); we land on the same point, a float64 solver did
  not. Measured against pyrvo on float32 inputs: benchmarks/bench_orca_model.py's 4 kinds x
  1250 worlds, 37531/37531 agents within 1e-3 m/s (median difference 0, max 8e-4; float64:
  99.93 %); CrowdNav circle crossing (time horizon 5, neighbour distance 10, 150 worlds x 6
  rollout states), 100 % / 99.995 % / 99.97 % for 6 / 21 / 51 agents (float64: 99.98 /
  99.96 / 99.85 %). The remaining disagreements are all in ``linearProgram3``, where nearly
  parallel bisectors make a different operation order pick another point of (almost) the
  same largest penetration. RVO_EPSILON (1e-5) is kept as the parallel test.
- Neighbour ties (equal squared distances) are broken by agent index; RVO2 breaks them by
  its k-d tree's traversal order. This only matters for exactly equal distances.
- Invalid (padding) agents are neither neighbours nor solved: their ``vel`` is returned as
  given.

Speed (N = 1024 worlds, CrowdNav parameters, one thread, machine load ~5 on 2 cores, same
process A/B): 6 / 21 / 51 agents 18 / 126 / 343 ms per call, was 24 / 202 / 683 ms in float64.
What helped: float32; line-major ``[M, 4, B]`` packing (every elementwise op runs over a long
contiguous dimension) with far-away lines for absent neighbours (no masks in the LPs);
float 0/1 masks and ``lerp`` instead of bool masks and ``torch.where`` in the LPs (bool
comparisons and ``where`` are ~5x slower than float arithmetic in this torch build);
problems gathered as rows of a contiguous copy. What did not: chunking worlds (no cache
gain), float masks in the half-plane and neighbour-key code (more passes, slower),
``torch.compile`` of a mask-based whole solve (190 s cold compile, slower than eager) or of
``linearProgram1`` alone (25 s, ~10 % faster): not shipped. Half of the time is the
half-planes (``topk`` over the ``[N, K, K]`` keys alone ~13 ms at K = 21), the rest the
``linearProgram3`` line loops, which are bound by the number of small ops.
"""

from __future__ import annotations

import torch

from crowdbench.envs.humans.lp import _gather, _rows, far_lines, ieee_sqrt, lp2_packed, lp3_packed

# Internal precision (RVO2 computes in float32; see the module docstring).
DTYPE = torch.float32


def _per_agent(x, valid: torch.Tensor) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(DTYPE).expand(valid.shape)
    return torch.full(valid.shape, float(x), dtype=DTYPE)


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
    lines, _ = packed_lines(
        pos, vel, valid, radius, time_horizon=time_horizon, dt=dt, neighbor_dist=neighbor_dist,
        max_neighbors=max_neighbors,
    )  # fmt: skip
    m = lines.shape[0]
    speed = _per_agent(max_speed, valid).reshape(-1)
    opt = pref.to(DTYPE).reshape(-1, 2).T
    rx, ry, fail = lp2_packed(lines, speed, opt[0], opt[1])
    lp3 = (fail < m).nonzero().squeeze(1)
    if lp3.numel():
        nx, ny = lp3_packed(_gather(_rows(lines), lp3, m), fail[lp3], speed[lp3], rx[lp3], ry[lp3])
        rx = rx.index_put((lp3,), nx)
        ry = ry.index_put((lp3,), ny)
    new = torch.stack([rx, ry], dim=-1).reshape(n, k, 2).to(vel.dtype)
    return torch.where(valid[..., None], new, vel)


def orca_lines(pos, vel, valid, radius, *, time_horizon, dt, neighbor_dist, max_neighbors):
    """Every agent's ORCA half-planes, nearest neighbour first, as five ``[N * K, M]`` tensors
    ``(point_x, point_y, direction_x, direction_y, exists)`` with ``M = min(max_neighbors,
    K - 1)``; velocity ``v`` satisfies a line when ``det(direction, point - v) <= 0``. Absent
    neighbours come last and hold :data:`crowdbench.envs.humans.lp.FAR_LINE`."""
    lines, exists = packed_lines(
        pos, vel, valid, radius, time_horizon=time_horizon, dt=dt, neighbor_dist=neighbor_dist,
        max_neighbors=max_neighbors,
    )  # fmt: skip
    return (*lines.permute(1, 2, 0), exists.T)


def packed_lines(pos, vel, valid, radius, *, time_horizon, dt, neighbor_dist, max_neighbors):
    """:func:`orca_lines` packed line-major (as :mod:`crowdbench.envs.humans.lp` takes them):
    ``([M, 4, N * K] lines, [M, N * K] exists)``."""
    n, k = valid.shape
    b = n * k
    m = max(min(int(max_neighbors), k - 1), 0)
    if m == 0:
        return torch.zeros(0, 4, b, dtype=DTYPE), torch.zeros(0, b, dtype=torch.bool)
    pos, vel = pos.to(DTYPE), vel.to(DTYPE)
    rad = _per_agent(radius, valid)
    # [5, N * K]: x, y, vx, vy, radius of every agent; one gather fetches all of a neighbour.
    agents = torch.cat([pos.reshape(b, 2).T, vel.reshape(b, 2).T, rad.reshape(1, b)])

    # computeNeighbors: the m nearest valid others strictly within neighbor_dist.
    px, py = pos[..., 0], pos[..., 1]
    relx = px[:, None, :] - px[:, :, None]  # [n, a, b] = p_b - p_a
    rely = py[:, None, :] - py[:, :, None]
    d2 = relx * relx + rely * rely
    ok = valid[:, :, None] & valid[:, None, :] & (d2 < float(neighbor_dist) ** 2)
    ok.diagonal(dim1=1, dim2=2).fill_(False)
    key, order = _neighbor_key(d2, ok).topk(m, dim=2, largest=False, sorted=True)
    exists = (key < _NO_KEY).reshape(b, m).T
    # Line-major [m, N * K] global neighbour indices.
    order = (order + (torch.arange(n) * k)[:, None, None]).reshape(b, m).T
    nb = agents.index_select(1, order.reshape(-1)).reshape(5, m, b)
    ax, ay = agents[2], agents[3]
    lines = _orca_lines(
        nb[0] - agents[0], nb[1] - agents[1], ax - nb[2], ay - nb[3], agents[4] + nb[4], ax, ay,
        1.0 / float(time_horizon), 1.0 / float(dt),
    )  # fmt: skip
    return torch.where(exists[:, None], lines, far_lines(lines)), exists


_NO_KEY = torch.iinfo(torch.int64).max


def _neighbor_key(d2: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """Distinct int64 sort keys ordered by ``d2`` then by neighbour index (RVO2's insertion
    sort keeps the first-found of equal distances first; we break ties by index), so that a
    (non-stable) ``topk`` is deterministic. Non-neighbours get :data:`_NO_KEY`."""
    k = d2.shape[-1]
    # d2 >= 0, so its float32 bit pattern is monotone in it (float64 distances are rounded to
    # float32 for the order: ties at float32 resolution go by index).
    bits = d2.to(torch.float32).view(torch.int32).to(torch.int64)
    key = bits * k + torch.arange(k)
    return key.masked_fill(~ok, _NO_KEY)


def _orca_lines(relx, rely, rvx, rvy, comb_r, vx, vy, inv_tau: float, inv_dt: float, share: float = 0.5):
    """ORCA half-planes as ``[M, 4, B]`` (point x/y, unit direction x/y), as in
    ``Agent::computeNewVelocity``. Rows of absent neighbours hold garbage (masked later).
    ``share``: the part of the avoidance this agent takes (RVO2: 0.5, reciprocal)."""
    # Selections are torch.lerp with 0/1 weights (exact, and several times cheaper than
    # torch.where on CPU); both branches are finite for every existing neighbour.
    dist_sq = relx * relx + rely * rely
    r_sq = comb_r * comb_r
    collide = (dist_sq <= r_sq).to(relx.dtype)
    # Overlapping discs use the cut-off circle of the step instead of the horizon: one w for both.
    inv_t = inv_tau + (inv_dt - inv_tau) * collide
    wx, wy = rvx - inv_t * relx, rvy - inv_t * rely
    w_sq = wx * wx + wy * wy
    dot1 = wx * relx + wy * rely
    on_cutoff = (dot1 < 0.0) & (dot1 * dot1 > r_sq * w_sq)
    circle = torch.maximum(collide, on_cutoff.to(relx.dtype))

    # Projection on the (cut-off or collision) circle.
    tiny = torch.finfo(relx.dtype).tiny
    inv_w = w_sq.clamp_min(tiny).rsqrt()
    # w = 0 (only on a leg, never on a circle) would poison the unused branch with NaN.
    ux, uy = wx * inv_w, wy * inv_w
    c_scale = comb_r * inv_t - w_sq * inv_w

    # Projection on a leg: left leg if w is left of P, else the right one (sign -1 mirrors it).
    leg = ieee_sqrt((dist_sq - r_sq).clamp_min(0.0))
    sleg = leg * ((relx * wy - rely * wx > 0.0).to(relx.dtype) * 2.0 - 1.0)
    inv_d = 1.0 / dist_sq.clamp_min(tiny)
    ldx = (relx * sleg - rely * comb_r) * inv_d
    ldy = (rely * sleg + relx * comb_r) * inv_d
    proj = rvx * ldx + rvy * ldy

    dx = torch.lerp(ldx, uy, circle)
    dy = torch.lerp(ldy, -ux, circle)
    ux = torch.lerp(proj * ldx - rvx, c_scale * ux, circle)
    uy = torch.lerp(proj * ldy - rvy, c_scale * uy, circle)
    return torch.stack([vx + share * ux, vy + share * uy, dx, dy], dim=1)
