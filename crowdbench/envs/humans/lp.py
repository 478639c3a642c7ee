"""RVO2's 2-D linear programs (``linearProgram1/2/3``), batched over independent problems.

Every problem ``b`` has up to ``L`` directed lines ``point + t * direction`` (unit
``direction``); the feasible side of a line is on its left, i.e. ``det(direction, point - v)
<= 0``. The solvers take the lines packed as one line-major ``[L, 4, B]`` tensor
``(point_x, point_y, direction_x, direction_y)``: one gather per step fetches everything
about the lines, and every elementwise op runs over a contiguous ``B`` (problems) inner
dimension (short inner dimensions such as ``L`` defeat vectorisation on CPU). Radii and
optimisation velocities are ``[B]`` tensors.

Absent lines (``linear_program2``'s mask; neighbours that do not exist) are replaced by
:data:`FAR_LINE`, a line so far away that the whole plane of interest is on its feasible side:
it is never violated and never binds ``linearProgram1``, so it changes nothing, exactly as if
RVO2 had never pushed it. ``linear_program3`` additionally needs the absent lines after all
present ones (as :func:`crowdbench.envs.humans.orca.orca_lines` makes them), because it forms
bisectors with every earlier line.

The incremental structure of RVO2 is kept line by line, because results that are exactly
equal to RVO2's (not merely another optimum) are needed where the optimum is not unique
(``linearProgram3``). What is batched:

- the loop over line ``i`` runs once for all problems; only the problems whose current result
  violates line ``i`` go through ``linearProgram1``, compacted by one ``nonzero`` per line
  (violations are a small fraction of problem-lines in practice, so solving ``linearProgram1``
  for every problem under a mask would cost several times more);
- ``linearProgram1``'s loop over the earlier lines ``j < i`` is one reduction: ``tLeft`` only
  grows and ``tRight`` only shrinks, so RVO2's early ``tLeft > tRight`` exit fails exactly
  when the final interval is empty, and the order of the ``j`` does not matter;
- ``linearProgram3``'s inner ``linearProgram2`` (over the bisectors) runs on the already
  compacted problems under a mask, without compacting again.
"""

from __future__ import annotations

import numpy as np
import torch

# RVO2's RVO_EPSILON: below it, two line directions count as parallel.
EPS = 1e-5
# The line y = -1e15 pointing along +x: everything above it is feasible. Its intersections with
# any line through the speed disc are ~1e15 / |sin| away (finite in float32), never binding.
FAR_LINE = (0.0, -1e15, 1.0, 0.0)


def ieee_sqrt(x: torch.Tensor) -> torch.Tensor:
    """The correctly rounded square root (RVO2's ``std::sqrt``), the same bits on every CPU.

    Why not ``torch.sqrt``: on CPU it is a library routine, not the instruction: within 1 ulp but not
    correctly rounded (17 % of float32 results are the farther neighbour), under every
    ``ATEN_CPU_CAPABILITY`` and MKL setting, so nothing pins its bits to the IEEE ones; the ORCA
    tracks' episodes differed in the last bits between an AVX-512 and an AMD machine while every
    track without ``torch.sqrt`` matched bit for bit. ``torch.rsqrt`` and ``torch.norm`` use the
    instruction already; numpy's ``sqrt`` is the instruction.
    """
    return torch.from_numpy(np.sqrt(x.detach().contiguous().numpy()))


def far_lines(like: torch.Tensor) -> torch.Tensor:
    """:data:`FAR_LINE` as a ``[4, 1]`` tensor of ``like``'s dtype (broadcasts over ``[4, B]``)."""
    return torch.tensor(FAR_LINE, dtype=like.dtype)[:, None]


def _step(x: torch.Tensor) -> torch.Tensor:
    """``[x > 0]`` as 0/1 of ``x``'s dtype (exact; comparisons, bool tensors and ``where`` are
    several times slower than float arithmetic on CPU, so the masks here are floats)."""
    return x.sign().clamp_min(0.0)


# Added to (or subtracted from) a candidate to drop it from a min (max): larger than any
# intersection parameter (those are at most ~1e15 / RVO_EPSILON = 1e20, see FAR_LINE).
_DROP = 1e30


def _lp1(li, lj, radius, optx, opty, direction_opt: bool):
    """RVO2's ``linearProgram1`` for line ``i`` (``li``: ``[4, S]``) bounded by the earlier lines
    ``lj`` (``[J, 4, S]``).

    Returns ``(ok, x, y)``: whether (1.0, else 0.0) the line has a feasible segment inside the
    circle, and the optimum on it (meaningless where not ``ok``).
    """
    pxi, pyi, dxi, dyi = li.unbind(0)
    dot = pxi * dxi + pyi * dyi
    disc = dot * dot + radius * radius - (pxi * pxi + pyi * pyi)
    ok = 1.0 - _step(-disc)  # disc >= 0
    sq = ieee_sqrt(disc.clamp_min(0.0))
    t_left = -dot - sq
    t_right = sq - dot
    if lj.shape[0] > 0:
        pxj, pyj, dxj, dyj = lj.unbind(1)
        den = dxi * dyj - dyi * dxj
        num = dxj * (pyi - pyj) - dyj * (pxi - pxj)
        par = 1.0 - _step(den.abs() - EPS)  # |den| <= EPS
        # Parallel with the feasible side away from line i: no segment at all.
        ok = ok * (1.0 - (par * _step(-num)).amax(dim=0))
        t = num / (den + par * (1.0 - den))  # parallel: divide by ~1, the t is dropped
        neg = _step(-den)  # den < 0: bounds t from the left, else from the right
        t_right = torch.minimum(t_right, (t + torch.maximum(par, neg) * _DROP).amin(dim=0))
        t_left = torch.maximum(t_left, (t - torch.maximum(par, 1.0 - neg) * _DROP).amax(dim=0))
        ok = ok * (1.0 - _step(t_left - t_right))  # t_left <= t_right
    if direction_opt:
        t = torch.lerp(t_left, t_right, _step(optx * dxi + opty * dyi))
    else:
        t = dxi * (optx - pxi) + dyi * (opty - pyi)
        t = torch.minimum(torch.maximum(t, t_left), t_right)
    return ok, pxi + t * dxi, pyi + t * dyi


def _rows(lines):
    """``[L, 4, B]`` lines as contiguous ``[B, L * 4]`` rows: gathering problems is a row copy."""
    return lines.permute(2, 0, 1).contiguous().reshape(lines.shape[2], -1)


def _gather(rows, idx, n: int):
    """The first ``n`` lines of problems ``idx`` as ``[n, 4, S]``."""
    return rows[:, : 4 * n].index_select(0, idx).reshape(-1, n, 4).permute(1, 2, 0).contiguous()


def _violation(li, rx, ry):
    """``det(direction, point - r)`` of lines ``li`` ``[4, S]`` at ``r``: > 0 where violated."""
    return li[2] * (li[1] - ry) - li[3] * (li[0] - rx)


def lp2_packed(lines, radius, optx, opty):
    """``linearProgram2`` (closest to ``opt``) on packed ``[L, 4, B]`` lines without absent ones
    (use :data:`FAR_LINE`). Returns ``(rx, ry, fail)`` as :func:`linear_program2`."""
    n2 = optx * optx + opty * opty
    scale = torch.where(n2 > radius * radius, radius / ieee_sqrt(n2), 1.0)
    rx, ry = optx * scale, opty * scale
    n_lines = lines.shape[0]
    fail = torch.full(rx.shape, n_lines, dtype=torch.long)
    alive = torch.ones(rx.shape, dtype=torch.bool)
    rows = _rows(lines)
    for i in range(n_lines):
        bad = (_violation(lines[i], rx, ry) > 0.0) & alive
        idx = bad.nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        sub = _gather(rows, idx, i + 1)
        ok, nx, ny = _lp1(sub[i], sub[:i], radius[idx], optx[idx], opty[idx], False)
        rx = rx.index_put((idx,), torch.lerp(rx[idx], nx, ok))
        ry = ry.index_put((idx,), torch.lerp(ry[idx], ny, ok))
        failed = idx[ok == 0.0]
        alive[failed] = False
        fail[failed] = i
    return rx, ry, fail


def _lp2_direction_masked(lines, radius, optx, opty):
    """``linearProgram2`` pushing furthest along unit ``opt`` (``directionOpt``), every problem
    under a mask (no compaction; for the small sets of ``linearProgram3``). Returns ``(rx, ry,
    ok)``, ``ok`` false where some line was infeasible."""
    rx, ry = optx * radius, opty * radius
    alive = torch.ones_like(rx)
    for i in range(lines.shape[0]):
        li = lines[i]
        bad = _step(_violation(li, rx, ry)) * alive
        if not bool(bad.any()):
            continue
        ok, nx, ny = _lp1(li, lines[:i], radius, optx, opty, True)
        take = bad * ok
        rx = torch.lerp(rx, nx, take)
        ry = torch.lerp(ry, ny, take)
        alive = alive - bad * (1.0 - ok)
    return rx, ry, alive


def lp3_packed(lines, begin, radius, rx, ry):
    """``linearProgram3`` (no obstacle lines) on packed ``[L, 4, B]`` lines, absent ones last
    and :data:`FAR_LINE`. See :func:`linear_program3`."""
    distance = torch.zeros_like(rx)
    n_lines = lines.shape[0]
    start = int(begin.min()) if begin.numel() else n_lines
    rows = _rows(lines)
    for i in range(start, n_lines):
        hit = (_violation(lines[i], rx, ry) > distance) & (begin <= i)
        idx = hit.nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        sub = _gather(rows, idx, i + 1)
        li = sub[i]
        pxi, pyi, dxi, dyi = li.unbind(0)
        pxj, pyj, dxj, dyj = sub[:i].unbind(1)
        det = dxi * dyj - dyi * dxj
        par = 1.0 - _step(det.abs() - EPS)  # |det| <= EPS
        # Parallel lines pointing the same way add no bisector: RVO2 skips them.
        skip = par * _step(dxi * dxj + dyi * dyj)
        s = (dxj * (pyi - pyj) - dyj * (pxi - pxj)) / (det + par * (1.0 - det))
        qx = torch.lerp(pxi + s * dxi, 0.5 * (pxi + pxj), par)
        qy = torch.lerp(pyi + s * dyi, 0.5 * (pyi + pyj), par)
        ex, ey = dxj - dxi, dyj - dyi
        norm = ieee_sqrt(ex * ex + ey * ey)
        inv = 1.0 / (norm + (1.0 - _step(norm)))  # norm = 0 (same direction, skipped): 1 / 1
        bis = torch.stack([qx, qy, ex * inv, ey * inv], dim=1)
        keep = 1.0 - skip[:, None]
        bis = bis * keep + far_lines(bis) * (1.0 - keep)  # finite, so exact
        nx, ny, okay = _lp2_direction_masked(bis, radius[idx], -dyi, dxi)
        # A failure is float round-off (the old result is feasible by construction): keep it.
        nx = torch.lerp(rx[idx], nx, okay)
        ny = torch.lerp(ry[idx], ny, okay)
        rx = rx.index_put((idx,), nx)
        ry = ry.index_put((idx,), ny)
        distance = distance.index_put((idx,), _violation(li, nx, ny))
    return rx, ry


def pack_lines(px, py, dx, dy, mask):
    """Separate ``[B, L]`` line tensors and mask -> packed ``[L, 4, B]`` with :data:`FAR_LINE`
    for absent lines."""
    lines = torch.stack([px.T, py.T, dx.T, dy.T], dim=1)
    return torch.where(mask.T[:, None], lines, far_lines(lines))


def linear_program2(px, py, dx, dy, mask, radius, optx, opty, direction_opt: bool, rx=None, ry=None):
    """RVO2's ``linearProgram2``: the point of the circle of ``radius`` satisfying all lines that
    is closest to ``opt`` (or, with ``direction_opt``, furthest along the unit vector ``opt``).

    Returns ``(x, y, fail)`` where ``fail`` is the index of the first line RVO2 found
    infeasible (``L`` if none); where it failed, ``(x, y)`` is the result before that line, as
    in RVO2. ``rx, ry`` are accepted for compatibility and ignored.
    """
    lines = pack_lines(px, py, dx, dy, mask)
    if not direction_opt:
        return lp2_packed(lines, radius, optx, opty)
    # Reference path (not used by the solver): per-line failure index from the masked solver.
    n_lines = lines.shape[0]
    fail = torch.full(radius.shape, n_lines, dtype=torch.long)
    rx, ry = optx * radius, opty * radius
    for i in range(n_lines):
        bad = (_violation(lines[i], rx, ry) > 0.0) & (fail == n_lines)
        ok, nx, ny = _lp1(lines[i], lines[:i], radius, optx, opty, True)
        ok = ok > 0.0
        rx = torch.where(bad & ok, nx, rx)
        ry = torch.where(bad & ok, ny, ry)
        fail = torch.where(bad & ~ok, i, fail)
    return rx, ry, fail


def linear_program3(px, py, dx, dy, mask, begin, radius, rx, ry):
    """RVO2's ``linearProgram3`` (no obstacle lines): from line ``begin`` on, the result that
    minimises the maximum penetration of the lines, found by re-solving, at each line ``i``
    that is violated by more than the current penetration, a ``linearProgram2`` over the
    bisectors of line ``i`` with every earlier line, pushing as far as possible into ``i``.
    Absent lines (``~mask``) must come after every present line of their problem.
    """
    return lp3_packed(pack_lines(px, py, dx, dy, mask), begin, radius, rx, ry)
