"""The social-force model compiled with numba: :func:`crowdbench.envs.humans.sfm.social_force_velocities`
as one scalar kernel, parallel over worlds.

The torch model stays the reference (and the documentation of the model); this kernel evaluates the same
formulas term by term, in the same association and in the inputs' float type (constants rounded to it
first, as torch does with Python scalars; ``c / t`` as torch's ``reciprocal(t) * c``), one human at a time:
the goal force, plus Moussaid's interaction summed over the other present humans and then the bodies
(index order), plus the body repulsion summed over the bodies; then the speed cap. Absent humans get
zeros; absent sources are skipped (the reference weighs them by zero: the same sum).

Not bit-identical to the reference: torch's ``exp``, ``atan2`` and ``hypot`` are its vectorised (SLEEF)
ones, and it sums the sources in several partial sums. Here ``exp`` and ``atan2`` are fdlibm's
(:mod:`crowdbench.envs.humans.fdlibm`, in double, then rounded to the inputs' type) and ``hypot`` is
``sqrt(x^2 + y^2)`` in double, rounded: within a few float32 ulps of torch (measured maxima in
docs/humans.md, tested in tests/test_sfm_kernel.py). So ``env.sfm_backend`` defaults to ``torch`` and no
committed number depends on this kernel; reactive replay (the v2-sfm track) always uses the torch model.

Bit-identical on every x86 CPU: no ``fastmath`` (no FMA contraction, no reassociation) and no C library
function but ``sqrt`` (correctly rounded) and ``ldexp`` (exact); glibc's ``exp``/``atan2`` are avoided
because glibc picks their FMA or non-FMA variant by the CPU. The tests compile the kernel for a generic
x86-64 and for the host in two processes and require the same bytes.
"""

from __future__ import annotations

import numpy as np
import torch

from crowdbench.envs.humans import fdlibm
from crowdbench.envs.humans.numba_runtime import LOCK, OPTIONS, numba_module, set_threads
from crowdbench.envs.humans.sfm import _EPS, SFMParams

_kernel = None
_prange = range  # numba.prange once compiled (see _compile)
_exp = _atan2 = None  # fdlibm's, compiled (see _compile)

# slots of the constants vector (one array of the inputs' float type)
ONE, EPS, TAU, GOAL_THR, SPEED_F, NEG_A, LAM, GAMMA, N2, NP2, BODY_S, BODY_R, DT = range(13)


def constants(params: SFMParams, dt: float, dtype) -> np.ndarray:
    """The kernel's constants in ``dtype``, by slot (as torch rounds each Python scalar)."""
    p = params
    return np.array([1.0, _EPS, p.tau, p.goal_threshold, p.max_speed_factor, -p.A, p.lam, p.gamma, p.n ** 2,
                     p.n_prime ** 2, p.body_strength, p.body_range, dt], dtype=dtype)


def _hyp(x, y, s):
    """hypot in double, rounded to the type of the scratch ``s``."""
    xx, yy = np.float64(x), np.float64(y)
    s[0] = np.sqrt(xx * xx + yy * yy)
    return s[0]


def _rexp(x, s):
    s[0] = _exp(np.float64(x))
    return s[0]


def _sign(x, c):
    if x > 0:
        return c[ONE]
    if x < 0:
        return -c[ONE]
    return x * c[ONE]


def _pair(px, py, lvx, lvy, sx, sy, lsvx, lsvy, c, s):
    """Moussaid's force on a human at ``(px, py)`` (``lvx, lvy`` = lambda v) from a source (sfm._moussaid_sum)."""
    ex, ey = sx - px, sy - py
    d = _hyp(ex, ey, s)
    inv = c[ONE] / max(d, c[EPS])
    ex, ey = ex * inv, ey * inv
    dx = (lvx - lsvx) + ex
    dy = (lvy - lsvy) + ey
    d_len = _hyp(dx, dy, s)
    s[0] = _atan2(np.float64(dx * ey - dy * ex), np.float64(dx * ex + dy * ey))
    theta = s[0]
    b = max(c[GAMMA] * d_len, c[EPS])
    neg_dist = -d / b
    bt = b * theta
    bt2 = bt * bt
    w = (c[ONE] / max(d_len, c[EPS])) * c[NEG_A]
    along = w * _rexp(neg_dist - c[NP2] * bt2, s)
    turn = w * _sign(theta, c) * _rexp(neg_dist - c[N2] * bt2, s)
    return along * dx - turn * dy, along * dy + turn * dx


def _human(w, i, pos, vel, goal, valid, rad, vpref, opos, ovel, ovalid, orad, c, body, s):
    """Human ``i`` of world ``w``: its new velocity (social_force_velocities)."""
    px, py, vx, vy = pos[w, i, 0], pos[w, i, 1], vel[w, i, 0], vel[w, i, 1]
    tx, ty = goal[w, i, 0] - px, goal[w, i, 1] - py
    dist = _hyp(tx, ty, s)
    zero = c[ONE] - c[ONE]
    dsx, dsy = zero, zero
    if dist > c[GOAL_THR]:
        g = max(dist, c[EPS])
        dsx, dsy = tx / g * vpref[w, i], ty / g * vpref[w, i]
    fx, fy = (dsx - vx) / c[TAU], (dsy - vy) / c[TAU]
    lvx, lvy = c[LAM] * vx, c[LAM] * vy
    mx, my = zero, zero
    for j in range(pos.shape[1]):
        if j != i and valid[w, j]:
            ax, ay = _pair(px, py, lvx, lvy, pos[w, j, 0], pos[w, j, 1], c[LAM] * vel[w, j, 0], c[LAM] * vel[w, j, 1],
                           c, s)
            mx, my = mx + ax, my + ay
    for r in range(opos.shape[1]):
        if ovalid[w, r]:
            ax, ay = _pair(px, py, lvx, lvy, opos[w, r, 0], opos[w, r, 1], c[LAM] * ovel[w, r, 0],
                           c[LAM] * ovel[w, r, 1], c, s)
            mx, my = mx + ax, my + ay
    fx, fy = fx + mx, fy + my
    if body:
        bx, by = zero, zero
        for r in range(opos.shape[1]):
            if ovalid[w, r]:
                gx, gy = px - opos[w, r, 0], py - opos[w, r, 1]
                d = _hyp(gx, gy, s)
                mag = c[BODY_S] * _rexp((rad[w, i] + orad[w, r] - d) / c[BODY_R], s) / max(d, c[EPS])
                bx, by = bx + mag * gx, by + mag * gy
        fx, fy = fx + bx, fy + by
    nx, ny = vx + c[DT] * fx, vy + c[DT] * fy
    scale = min(c[SPEED_F] * vpref[w, i] / max(_hyp(nx, ny, s), c[EPS]), c[ONE])
    return nx * scale, ny * scale


def _solve(pos, vel, goal, valid, rad, vpref, opos, ovel, ovalid, orad, c, body, out):
    """Every world (prange): ``out[w]`` = the humans' new velocities, zeros where absent."""
    for w in _prange(pos.shape[0]):
        s = np.empty(1, c.dtype)
        for i in range(pos.shape[1]):
            if valid[w, i]:
                out[w, i, 0], out[w, i, 1] = _human(w, i, pos, vel, goal, valid, rad, vpref, opos, ovel, ovalid,
                                                    orad, c, body, s)
            else:
                out[w, i, 0], out[w, i, 1] = 0, 0


def _compile():
    """Compile (or load from the cache) lazily: importing this module does not import numba."""
    global _kernel, _prange, _exp, _atan2
    if _kernel is None:
        numba = numba_module()
        _prange = numba.prange
        _exp, _atan2 = fdlibm.compiled(OPTIONS)
        g = globals()
        for name in ("_hyp", "_rexp", "_sign", "_pair", "_human"):
            g[name] = numba.njit(**OPTIONS)(g[name])
        _kernel = numba.njit(parallel=True, **OPTIONS)(_solve)
    return _kernel


def _field(x, shape, dtype) -> np.ndarray:
    """A per-body scalar or tensor as a C-contiguous ``shape`` array of ``dtype``."""
    if isinstance(x, torch.Tensor):
        return np.ascontiguousarray(x.detach().to(torch.float64).expand(shape).numpy().astype(dtype))
    return np.full(shape, float(x), dtype=dtype)


def _arr(x: torch.Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(x.detach().numpy().astype(dtype, copy=False))


def social_force_velocities(pos, vel, goal, valid, radius, v_pref, *, dt: float, params: SFMParams | None = None,
                            others_pos=None, others_vel=None, others_valid=None, others_radius=None) -> torch.Tensor:
    """:func:`crowdbench.envs.humans.sfm.social_force_velocities` (same arguments), compiled: the same
    model to within a few ulps (module docstring), in the dtype of ``pos`` (float32 or float64)."""
    params = params or SFMParams()
    kernel = _compile()
    set_threads()
    dtype = np.float64 if pos.dtype == torch.float64 else np.float32
    n, m = valid.shape
    body = others_pos is not None and params.body_strength != 0.0
    if body and others_radius is None:
        raise ValueError("others_radius is needed for the body repulsion (or set params.body_strength=0)")
    if others_pos is None:
        others_pos = torch.zeros(n, 0, 2)
    r = others_pos.shape[1]
    others_vel = torch.zeros_like(others_pos) if others_vel is None else others_vel
    others_valid = torch.ones(n, r, dtype=torch.bool) if others_valid is None else others_valid
    out = np.empty((n, m, 2), dtype)
    args = (_arr(pos, dtype), _arr(vel, dtype), _arr(goal, dtype), np.ascontiguousarray(valid.numpy()),
            _field(radius, (n, m), dtype), _field(v_pref, (n, m), dtype), _arr(others_pos, dtype),
            _arr(others_vel, dtype), np.ascontiguousarray(others_valid.expand(n, r).numpy()),
            _field(0.0 if others_radius is None else others_radius, (n, r), dtype),
            constants(params, dt, dtype), body, out)
    with LOCK:
        kernel(*args)
    return torch.from_numpy(out).to(pos.dtype)


__all__ = ["constants", "social_force_velocities"]
