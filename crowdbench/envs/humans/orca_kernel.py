"""ORCA compiled with numba: :func:`crowdbench.envs.humans.orca.orca_velocities` as one scalar kernel,
parallel over worlds, equal to the torch solver value for value.

The torch solver stays the reference (and the documentation of the algorithm); this module runs the
same float32 operations in the same order, one agent at a time, so every rounding is the same:

- neighbours: the ``max_neighbors`` nearest valid others strictly within ``neighbor_dist``, by an
  insertion sort over the agents in index order (equal float32 distances keep the lower index first,
  the torch solver's ``(distance, index)`` key);
- half-planes: ``_orca_lines`` term by term (``torch.lerp`` with a 0/1 weight written as torch's
  scalar formula, ``rsqrt`` as ``1 / sqrt``, which is what torch's CPU kernels compute);
- ``linearProgram1/2/3`` in RVO2's sequential form; the torch solver's reductions over earlier lines
  (min/max) and its far-away lines for absent neighbours or skipped bisectors are exact, so leaving
  them out changes no value. Python-float constants are rounded to float32 first, as torch does with
  scalars in float32 arithmetic.

The only possible difference is the sign of a zero (torch's vectorised and scalar ``lerp`` already
disagree there): values compare equal. tests/test_orca_kernel.py checks equality with the torch
solver on thousands of random worlds of each kind, and agreement with RVO2.

Bit-identical on every x86 CPU: no ``fastmath``, so numba emits plain ``fmul``/``fadd`` without the
``contract`` flag and LLVM fuses nothing into FMA whatever the target CPU (its default
``-fp-contract`` fuses only what the IR allows); the only library call is ``sqrt``, correctly
rounded. The kernel is compiled for the host CPU; the tests run it under ``NUMBA_CPU_NAME=generic``
and the host target in two processes and require the same bytes, and look for FMA instructions in
the host code.

Compilation: ``cache=True`` stores the machine code in ``__pycache__`` beside this file, or, when that
is not writable (an installed wheel), in numba's per-user cache directory; a cold compile is ~5 s,
a cached load ~0.3 s, paid at the first call (numba imports lazily too). Threads: as many as torch's
intra-op threads, on numba's workqueue layer (see :func:`_compile`).
"""

from __future__ import annotations

import numpy as np
import torch

from crowdbench.envs.humans.numba_runtime import LOCK, compile_module, set_threads

F0, F1, HALF = np.float32(0.0), np.float32(1.0), np.float32(0.5)
EPS = np.float32(1e-5)  # RVO_EPSILON, as crowdbench.envs.humans.lp.EPS
DROP = np.float32(1e30)  # crowdbench.envs.humans.lp._DROP
TINY = np.float32(np.finfo(np.float32).tiny)

_kernel = None


def _step(x):
    """``[x > 0]`` as float32 0/1 (lp._step)."""
    return F1 if x > F0 else F0


def _lerp(a, b, w):
    """torch.lerp's scalar formula (for 0/1 weights: ``a`` or ``b``)."""
    if w < HALF:
        return a + w * (b - a)
    return b - (b - a) * (F1 - w)


def _violation(lines, i, rx, ry):
    return lines[i, 2] * (lines[i, 1] - ry) - lines[i, 3] * (lines[i, 0] - rx)


def _lp1(lines, i, radius, optx, opty, direction_opt):
    """linearProgram1 for line ``i`` bounded by lines ``0 .. i-1`` (lp._lp1): (ok, x, y)."""
    pxi, pyi, dxi, dyi = lines[i, 0], lines[i, 1], lines[i, 2], lines[i, 3]
    dot = pxi * dxi + pyi * dyi
    disc = dot * dot + radius * radius - (pxi * pxi + pyi * pyi)
    ok = disc >= F0
    sq = np.sqrt(max(disc, F0))
    t_left = -dot - sq
    t_right = sq - dot
    for j in range(i):
        pxj, pyj, dxj, dyj = lines[j, 0], lines[j, 1], lines[j, 2], lines[j, 3]
        den = dxi * dyj - dyi * dxj
        num = dxj * (pyi - pyj) - dyj * (pxi - pxj)
        par = F1 - _step(abs(den) - EPS)
        if par * _step(-num) > F0:
            ok = False
        t = num / (den + par * (F1 - den))
        neg = _step(-den)
        t_right = min(t_right, t + max(par, neg) * DROP)
        t_left = max(t_left, t - max(par, F1 - neg) * DROP)
    if t_left - t_right > F0:
        ok = False
    if direction_opt:
        t = _lerp(t_left, t_right, _step(optx * dxi + opty * dyi))
    else:
        t = dxi * (optx - pxi) + dyi * (opty - pyi)
        t = min(max(t, t_left), t_right)
    return ok, pxi + t * dxi, pyi + t * dyi


def _lp2_lines(lines, n_lines, radius, optx, opty, rx, ry, direction):
    """linearProgram2's loop from ``(rx, ry)``: each violated line projects the point onto it (linearProgram1);
    (x, y, index of the failing line or n_lines)."""
    for i in range(n_lines):
        if _violation(lines, i, rx, ry) > F0:
            ok, nx, ny = _lp1(lines, i, radius, optx, opty, direction)
            if not ok:
                return rx, ry, i
            rx, ry = nx, ny
    return rx, ry, n_lines


def _lp2(lines, n_lines, radius, optx, opty):
    """linearProgram2, closest to ``opt`` (lp.lp2_packed): (x, y, index of the failing line or n_lines)."""
    n2 = optx * optx + opty * opty
    scale = radius / np.sqrt(n2) if n2 > radius * radius else F1
    return _lp2_lines(lines, n_lines, radius, optx, opty, optx * scale, opty * scale, False)


def _lp2_direction(lines, n_lines, radius, optx, opty):
    """linearProgram2 pushing along unit ``opt`` (lp._lp2_direction_masked): (x, y, ok)."""
    rx, ry, fail = _lp2_lines(lines, n_lines, radius, optx, opty, optx * radius, opty * radius, True)
    return rx, ry, fail == n_lines


def _lp3(lines, n_lines, begin, radius, rx, ry, bis):
    """linearProgram3 from line ``begin`` (lp.lp3_packed); ``bis`` is scratch for the bisectors.
    Same-direction parallel pairs add no bisector (the torch solver's far line never binds)."""
    distance = F0
    for i in range(begin, n_lines):
        if _violation(lines, i, rx, ry) <= distance:
            continue
        pxi, pyi, dxi, dyi = lines[i, 0], lines[i, 1], lines[i, 2], lines[i, 3]
        n_bis = 0
        for j in range(i):
            pxj, pyj, dxj, dyj = lines[j, 0], lines[j, 1], lines[j, 2], lines[j, 3]
            det = dxi * dyj - dyi * dxj
            par = F1 - _step(abs(det) - EPS)
            if par * _step(dxi * dxj + dyi * dyj) > F0:
                continue
            s = (dxj * (pyi - pyj) - dyj * (pxi - pxj)) / (det + par * (F1 - det))
            ex, ey = dxj - dxi, dyj - dyi
            norm = np.sqrt(ex * ex + ey * ey)
            inv = F1 / (norm + (F1 - _step(norm)))
            bis[n_bis, 0] = _lerp(pxi + s * dxi, HALF * (pxi + pxj), par)
            bis[n_bis, 1] = _lerp(pyi + s * dyi, HALF * (pyi + pyj), par)
            bis[n_bis, 2] = ex * inv
            bis[n_bis, 3] = ey * inv
            n_bis += 1
        nx, ny, ok = _lp2_direction(bis, n_bis, radius, -dyi, dxi)
        if ok:  # a failure is round-off (the old result is feasible by construction): keep the old one
            rx, ry = nx, ny
        distance = _violation(lines, i, rx, ry)
    return rx, ry


def _neighbors(pos, valid, a, m, range_sq, nb, nb_d2):
    """The ``m`` nearest valid others of agent ``a`` strictly within range, nearest first, ties by
    index: their indices in ``nb``; returns how many."""
    count = 0
    for b in range(pos.shape[0]):
        if b == a or not valid[b]:
            continue
        rx, ry = pos[b, 0] - pos[a, 0], pos[b, 1] - pos[a, 1]
        d2 = rx * rx + ry * ry
        if not d2 < range_sq or (count == m and not d2 < nb_d2[m - 1]):
            continue
        slot = min(count, m - 1)
        while slot > 0 and nb_d2[slot - 1] > d2:
            nb_d2[slot], nb[slot] = nb_d2[slot - 1], nb[slot - 1]
            slot -= 1
        nb_d2[slot], nb[slot] = d2, b
        count = min(count + 1, m)
    return count


def _line(pos, vel, rad, a, b, inv_tau, inv_diff, lines, row):
    """Agent ``a``'s ORCA half-plane for neighbour ``b`` into ``lines[row]`` (orca._orca_lines)."""
    relx, rely = pos[b, 0] - pos[a, 0], pos[b, 1] - pos[a, 1]
    vx, vy = vel[a, 0], vel[a, 1]
    rvx, rvy = vx - vel[b, 0], vy - vel[b, 1]
    comb_r = rad[a] + rad[b]
    dist_sq = relx * relx + rely * rely
    r_sq = comb_r * comb_r
    collide = F1 if dist_sq <= r_sq else F0
    inv_t = inv_tau + inv_diff * collide
    wx, wy = rvx - inv_t * relx, rvy - inv_t * rely
    w_sq = wx * wx + wy * wy
    dot1 = wx * relx + wy * rely
    circle = max(collide, F1 if dot1 < F0 and dot1 * dot1 > r_sq * w_sq else F0)
    inv_w = F1 / np.sqrt(max(w_sq, TINY))
    ux, uy = wx * inv_w, wy * inv_w
    c_scale = comb_r * inv_t - w_sq * inv_w
    leg = np.sqrt(max(dist_sq - r_sq, F0))
    sleg = leg * ((F1 if relx * wy - rely * wx > F0 else F0) * np.float32(2.0) - F1)
    inv_d = F1 / max(dist_sq, TINY)
    ldx = (relx * sleg - rely * comb_r) * inv_d
    ldy = (rely * sleg + relx * comb_r) * inv_d
    proj = rvx * ldx + rvy * ldy
    lines[row, 2] = _lerp(ldx, uy, circle)
    lines[row, 3] = _lerp(ldy, -ux, circle)
    lines[row, 0] = vx + HALF * _lerp(proj * ldx - rvx, c_scale * ux, circle)
    lines[row, 1] = vy + HALF * _lerp(proj * ldy - rvy, c_scale * uy, circle)


def _solve(pos, vel, pref, valid, rad, speed, inv_tau, inv_diff, range_sq, m, out):
    """Every world ``w`` (prange): ``out[w]`` = new velocities, ``vel[w]`` where invalid."""
    for w in _prange(pos.shape[0]):
        k = pos.shape[1]
        lines = np.empty((max(m, 1), 4), np.float32)
        bis = np.empty((max(m, 1), 4), np.float32)
        nb = np.empty(max(m, 1), np.int64)
        nb_d2 = np.empty(max(m, 1), np.float32)
        for a in range(k):
            if not valid[w, a]:
                out[w, a, 0], out[w, a, 1] = vel[w, a, 0], vel[w, a, 1]
                continue
            count = _neighbors(pos[w], valid[w], a, m, range_sq, nb, nb_d2) if m > 0 else 0
            for row in range(count):
                _line(pos[w], vel[w], rad[w], a, nb[row], inv_tau, inv_diff, lines, row)
            r = speed[w, a]
            rx, ry, fail = _lp2(lines, count, r, pref[w, a, 0], pref[w, a, 1])
            if fail < count:
                rx, ry = _lp3(lines, count, fail, r, rx, ry, bis)
            out[w, a, 0], out[w, a, 1] = rx, ry


_prange = range  # numba.prange once compiled (see _compile)


def _compile():
    global _kernel
    if _kernel is None:
        _kernel = compile_module(globals(), ("_step", "_lerp", "_violation", "_lp1", "_lp2_lines", "_lp2",
                                             "_lp2_direction", "_lp3", "_neighbors", "_line"), _solve)
    return _kernel


def _per_agent(x, valid: torch.Tensor) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return np.ascontiguousarray(x.to(torch.float32).expand(valid.shape).numpy())
    return np.full(valid.shape, np.float32(float(x)), dtype=np.float32)


def _f32(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to(torch.float32).numpy())


def orca_velocities(pos, vel, pref, valid, radius, max_speed, *, time_horizon: float, dt: float,
                    neighbor_dist: float, max_neighbors: int) -> torch.Tensor:
    """:func:`crowdbench.envs.humans.orca.orca_velocities` (same arguments, same values), compiled."""
    kernel = _compile()
    set_threads()
    n, k = valid.shape
    m = max(min(int(max_neighbors), k - 1), 0)
    out = np.empty((n, k, 2), np.float32)
    valid_np = np.ascontiguousarray(valid.numpy())
    args = (_f32(pos), _f32(vel), _f32(pref), valid_np, _per_agent(radius, valid), _per_agent(max_speed, valid),
            np.float32(1.0 / float(time_horizon)), np.float32(1.0 / float(dt) - 1.0 / float(time_horizon)),
            np.float32(float(neighbor_dist) ** 2), m, out)
    with LOCK:
        kernel(*args)
    new = torch.from_numpy(out)
    if vel.dtype == torch.float32:
        return new
    return torch.where(valid[..., None], new.to(vel.dtype), vel)
