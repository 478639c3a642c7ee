"""RVO2's 2-D linear programs (``linearProgram1/2/3``), batched over independent problems.

Every problem ``b`` has up to ``L`` directed lines ``point + t * direction`` (unit
``direction``); the feasible side of a line is on its left, i.e. ``det(direction, point - v)
<= 0``. Lines are given as separate x/y tensors of shape ``[B, L]`` with a ``[B, L]`` mask
of the lines that exist (absent lines are ignored everywhere, as if RVO2 had never pushed
them). All radii and optimisation velocities are ``[B]`` tensors.

The incremental structure of RVO2 is kept line by line, because results that are exactly
equal to RVO2's (not merely another optimum) are needed where the optimum is not unique
(``linearProgram3``). What is batched:

- the loop over line ``i`` runs once for all problems; only the problems whose current result
  violates line ``i`` go through ``linearProgram1``, compacted by one ``nonzero`` per line
  (violations are a small fraction of problem-lines in practice, so solving ``linearProgram1``
  for every problem under a mask would cost several times more);
- ``linearProgram1``'s loop over the earlier lines ``j < i`` is one reduction: ``tLeft`` only
  grows and ``tRight`` only shrinks, so RVO2's early ``tLeft > tRight`` exit fails exactly
  when the final interval is empty, and the order of the ``j`` does not matter.
"""

from __future__ import annotations

import torch

# RVO2's RVO_EPSILON: below it, two line directions count as parallel.
EPS = 1e-5


def _lp1(pxi, pyi, dxi, dyi, px, py, dx, dy, mask, radius, optx, opty, direction_opt: bool):
    """RVO2's ``linearProgram1`` for line ``i`` (``[S]``) bounded by earlier lines (``[S, J]``).

    Returns ``(ok, x, y)``: whether the line has a feasible segment inside the circle, and the
    optimum on it (meaningless where not ``ok``).
    """
    dot = pxi * dxi + pyi * dyi
    disc = dot * dot + radius * radius - (pxi * pxi + pyi * pyi)
    ok = disc >= 0.0
    sq = disc.clamp_min(0.0).sqrt()
    t_left = -dot - sq
    t_right = -dot + sq
    if px.shape[1] > 0:
        den = dxi[:, None] * dy - dyi[:, None] * dx
        num = dx * (pyi[:, None] - py) - dy * (pxi[:, None] - px)
        par = den.abs() <= EPS
        ok = ok & ~(mask & par & (num < 0.0)).any(dim=1)
        t = num / torch.where(par, 1.0, den)
        use = mask & ~par
        inf = torch.tensor(float("inf"), dtype=t.dtype)
        t_right = torch.minimum(t_right, torch.where(use & (den >= 0.0), t, inf).amin(dim=1))
        t_left = torch.maximum(t_left, torch.where(use & (den < 0.0), t, -inf).amax(dim=1))
        ok = ok & (t_left <= t_right)
    if direction_opt:
        t = torch.where(optx * dxi + opty * dyi > 0.0, t_right, t_left)
    else:
        t = dxi * (optx - pxi) + dyi * (opty - pyi)
        t = torch.where(t < t_left, t_left, torch.where(t > t_right, t_right, t))
    return ok, pxi + t * dxi, pyi + t * dyi


def linear_program2(px, py, dx, dy, mask, radius, optx, opty, direction_opt: bool, rx=None, ry=None):
    """RVO2's ``linearProgram2``: the point of the circle of ``radius`` satisfying all lines that
    is closest to ``opt`` (or, with ``direction_opt``, furthest along the unit vector ``opt``).

    Returns ``(x, y, fail)`` where ``fail`` is the index of the first line RVO2 found
    infeasible (``L`` if none); where it failed, ``(x, y)`` is the result before that line, as
    in RVO2. ``rx, ry`` may be given to skip the start-value computation.
    """
    if rx is None:
        if direction_opt:
            rx, ry = optx * radius, opty * radius
        else:
            n2 = optx * optx + opty * opty
            scale = torch.where(n2 > radius * radius, radius / n2.sqrt(), 1.0)
            rx, ry = optx * scale, opty * scale
    n_lines = px.shape[1]
    fail = torch.full(rx.shape, n_lines, dtype=torch.long)
    alive = torch.ones(rx.shape, dtype=torch.bool)
    for i in range(n_lines):
        pxi, pyi, dxi, dyi = px[:, i], py[:, i], dx[:, i], dy[:, i]
        bad = alive & mask[:, i] & (dxi * (pyi - ry) - dyi * (pxi - rx) > 0.0)
        idx = bad.nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        ok, nx, ny = _lp1(
            pxi[idx], pyi[idx], dxi[idx], dyi[idx],
            px[idx, :i], py[idx, :i], dx[idx, :i], dy[idx, :i], mask[idx, :i],
            radius[idx], optx[idx], opty[idx], direction_opt,
        )  # fmt: skip
        rx = rx.index_put((idx,), torch.where(ok, nx, rx[idx]))
        ry = ry.index_put((idx,), torch.where(ok, ny, ry[idx]))
        failed = idx[~ok]
        alive[failed] = False
        fail[failed] = i
    return rx, ry, fail


def linear_program3(px, py, dx, dy, mask, begin, radius, rx, ry):
    """RVO2's ``linearProgram3`` (no obstacle lines): from line ``begin`` on, the result that
    minimises the maximum penetration of the lines, found by re-solving, at each line ``i``
    that is violated by more than the current penetration, a ``linearProgram2`` over the
    bisectors of line ``i`` with every earlier line, pushing as far as possible into ``i``.
    """
    distance = torch.zeros_like(rx)
    n_lines = px.shape[1]
    start = int(begin.min()) if begin.numel() else n_lines
    for i in range(start, n_lines):
        pxi, pyi, dxi, dyi = px[:, i], py[:, i], dx[:, i], dy[:, i]
        hit = mask[:, i] & (begin <= i) & (dxi * (pyi - ry) - dyi * (pxi - rx) > distance)
        idx = hit.nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        pxi, pyi, dxi, dyi = pxi[idx, None], pyi[idx, None], dxi[idx, None], dyi[idx, None]
        pxj, pyj, dxj, dyj = px[idx, :i], py[idx, :i], dx[idx, :i], dy[idx, :i]
        det = dxi * dyj - dyi * dxj
        par = det.abs() <= EPS
        # Parallel lines pointing the same way add no bisector: RVO2 skips them.
        keep = mask[idx, :i] & ~(par & (dxi * dxj + dyi * dyj > 0.0))
        s = (dxj * (pyi - pyj) - dyj * (pxi - pxj)) / torch.where(par, 1.0, det)
        qx = torch.where(par, 0.5 * (pxi + pxj), pxi + s * dxi)
        qy = torch.where(par, 0.5 * (pyi + pyj), pyi + s * dyi)
        ex, ey = dxj - dxi, dyj - dyi
        norm = (ex * ex + ey * ey).sqrt()
        norm = torch.where(norm > 0.0, norm, 1.0)
        nx, ny, fail = linear_program2(
            qx, qy, ex / norm, ey / norm, keep, radius[idx], -dyi[:, 0], dxi[:, 0], True
        )
        # A failure is float round-off (the old result is feasible by construction): keep it.
        okay = fail == i
        nx = torch.where(okay, nx, rx[idx])
        ny = torch.where(okay, ny, ry[idx])
        rx = rx.index_put((idx,), nx)
        ry = ry.index_put((idx,), ny)
        distance = distance.index_put((idx,), dxi[:, 0] * (pyi[:, 0] - ny) - dyi[:, 0] * (pxi[:, 0] - nx))
    return rx, ry
