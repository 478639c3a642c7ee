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
(:func:`fd_exp`, :func:`fd_atan2`, in double, then rounded to the inputs' type) and ``hypot`` is
``sqrt(x^2 + y^2)`` in double, rounded: within a few float32 ulps of torch (measured maxima in
docs/humans.md, tested in tests/test_sfm_kernel.py). So ``env.sfm_backend`` defaults to ``torch`` and no
committed number depends on this kernel; reactive replay (the v2-sfm track) always uses the torch model.

Bit-identical on every x86 CPU: no ``fastmath`` (no FMA contraction, no reassociation) and no C library
function but ``sqrt`` (correctly rounded) and ``ldexp`` (exact); glibc's ``exp``/``atan2`` are avoided
because glibc picks their FMA or non-FMA variant by the CPU. The tests compile the kernel for a generic
x86-64 and for the host in two processes and require the same bytes.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from crowdbench.envs.humans.numba_runtime import LOCK, OPTIONS, numba_module, set_threads
from crowdbench.envs.humans.sfm import _EPS, SFMParams

_kernel = None
_prange = range  # numba.prange once compiled (see _compile)

# slots of the constants vector (one array of the inputs' float type)
ONE, EPS, TAU, GOAL_THR, SPEED_F, NEG_A, LAM, GAMMA, N2, NP2, BODY_S, BODY_R, DT = range(13)


# ---------------------------------------------------------------------------------------------------
# exp and atan2 in plain double arithmetic: fdlibm's algorithms and coefficients (e_exp.c, s_atan.c,
# e_atan2.c of Sun's freely distributable fdlibm 5.3, as in Java's StrictMath). Not the C library's: glibc
# picks an FMA or a non-FMA variant by the CPU it runs on, so the same machine code would give different
# last bits on different x86 CPUs; these use only + - * /, comparisons and ldexp (exact), so compiled
# without fastmath they give the same bytes everywhere. Under one ulp (tests/test_sfm_kernel.py, against
# Python's math on ~900,000 arguments each). The reductions' thresholds are the doubles fdlibm's
# high-word tests stand for (fdlibm compares 32 bits only; either way within one ulp). In this file, not
# a module of their own: numba's cache tracks only the file of the function it compiles.

LN2_HI, LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
INV_LN2 = 1.44269504088896338700e00
P1, P2, P3 = 1.66666666666666019037e-01, -2.77777777770155933842e-03, 6.61375632143793436117e-05
P4, P5 = -1.65339022054652515390e-06, 4.13813679705723846039e-08
EXP_MAX, EXP_MIN = 7.09782712893383973096e02, -7.45133219101941108420e02

ATAN_HI = (4.63647609000806093515e-01, 7.85398163397448278999e-01, 9.82793723247329054082e-01,
           1.57079632679489655800e00)
ATAN_LO = (2.26987774529616870924e-17, 3.06161699786838301793e-17, 1.39033110312309984516e-17,
           6.12323399573676603587e-17)
AT = (3.33333333333329318027e-01, -1.99999999998764832476e-01, 1.42857142725034663711e-01,
      -1.11111104054623557880e-01, 9.09088713343650656196e-02, -7.69187620504482999495e-02,
      6.66107313738753120669e-02, -5.83357013379057348645e-02, 4.97687799461593236017e-02,
      -3.65315727442169155270e-02, 1.62858201153657823623e-02)
PI, PI_LO = 3.1415926535897931160e00, 1.2246467991473531772e-16


def fd_exp(x: float) -> float:
    """e ** x (fdlibm ``__ieee754_exp``): x = k ln2 + r, |r| <= ln2 / 2, a rational approximation of e^r
    in r, then 2^k exactly."""
    if math.isnan(x):
        return x
    if x > EXP_MAX:
        return math.inf
    if x < EXP_MIN:
        return 0.0
    ax = abs(x)
    if ax < 3.725290298461914e-09:  # 2^-28
        return 1.0 + x
    k, hi, lo = 0, x, 0.0
    if ax > 0.34657359027997264:  # ln2 / 2
        if ax < 1.0397207708399179:  # 3 ln2 / 2
            k = 1 if x > 0 else -1
            hi = x - LN2_HI if x > 0 else x + LN2_HI
            lo = LN2_LO if x > 0 else -LN2_LO
        else:
            k = int(INV_LN2 * x + (0.5 if x > 0 else -0.5))
            t = float(k)
            hi = x - t * LN2_HI  # exact
            lo = t * LN2_LO
        x = hi - lo
    t = x * x
    c = x - t * (P1 + t * (P2 + t * (P3 + t * (P4 + t * P5))))
    if k == 0:
        return 1.0 - ((x * c) / (c - 2.0) - x)
    return math.ldexp(1.0 - ((lo - (x * c) / (2.0 - c)) - hi), k)


def fd_atan(x: float) -> float:
    """arctan(x) for x >= 0 (fdlibm ``atan``): reduced onto |t| < 7/16 around atan(0.5), atan(1), atan(1.5)
    or infinity, then an odd polynomial in t split into even and odd parts."""
    if x >= 7.378697629483821e19:  # 2^66
        return ATAN_HI[3] + ATAN_LO[3]
    i = -1
    if x < 0.4375:
        if x < 1.862645149230957e-09:  # 2^-29
            return x
    elif x < 1.1875:
        if x < 0.6875:
            i, x = 0, (2.0 * x - 1.0) / (2.0 + x)
        else:
            i, x = 1, (x - 1.0) / (x + 1.0)
    elif x < 2.4375:
        i, x = 2, (x - 1.5) / (1.0 + 1.5 * x)
    else:
        i, x = 3, -1.0 / x
    z = x * x
    w = z * z
    s1 = z * (AT[0] + w * (AT[2] + w * (AT[4] + w * (AT[6] + w * (AT[8] + w * AT[10])))))
    s2 = w * (AT[1] + w * (AT[3] + w * (AT[5] + w * (AT[7] + w * AT[9]))))
    if i < 0:
        return x - x * (s1 + s2)
    return ATAN_HI[i] - ((x * (s1 + s2) - ATAN_LO[i]) - x)


def fd_atan2(y: float, x: float) -> float:
    """The angle of (x, y) in [-pi, pi] (fdlibm ``__ieee754_atan2`` for finite arguments, signed zeros
    as C's: atan2(+-0, -0 or x < 0) = +-pi, atan2(+-0, +0 or x > 0) = +-0)."""
    if y == 0.0:
        if x > 0.0 or (x == 0.0 and math.copysign(1.0, x) > 0.0):
            return y
        return math.copysign(PI, y)
    if x == 0.0:
        return math.copysign(ATAN_HI[3], y)
    z = fd_atan(abs(y / x))
    if x > 0.0:
        return math.copysign(z, y)
    return math.copysign(PI - (z - PI_LO), y)


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
    s[0] = fd_exp(np.float64(x))
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
    s[0] = fd_atan2(np.float64(dx * ey - dy * ex), np.float64(dx * ex + dy * ey))
    theta = s[0]
    b = max(c[GAMMA] * d_len, c[EPS])
    neg_dist = -d / b
    bt = b * theta
    bt2 = bt * bt
    w = (c[ONE] / max(d_len, c[EPS])) * c[NEG_A]
    along = w * _rexp(neg_dist - c[NP2] * bt2, s)
    turn = w * _sign(theta, c) * _rexp(neg_dist - c[N2] * bt2, s)
    return along * dx - turn * dy, along * dy + turn * dx


def _human(w, i, pos, vel, goal, valid, rad, vpref, opos, ovel, ovalid, orad, c, body, pair, s):
    """Human ``i`` of world ``w``: its new velocity (social_force_velocities); ``pair[i, j]``: the force of
    human ``j`` on ``i`` (:func:`_pairs`)."""
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
            mx, my = mx + pair[i, j, 0], my + pair[i, j, 1]
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


def _pairs(w, pos, vel, valid, c, pair, s):
    """Moussaid's force between every two present humans of world ``w`` into ``pair`` (``pair[i, j]``: on
    ``i`` from ``j``). ``pair[j, i] = -pair[i, j]`` is what :func:`_pair` computes for ``(j, i)`` when the
    two differ in both coordinates: every difference it takes changes sign (``a - b = -(b - a)``), so the
    distances, ``|D|``, the angle's cross and dot products (products of two negated factors) and the
    exponentials are the same, and the force is negated: half the pairs to compute. Where a coordinate
    difference is zero (its sign does not flip: ``+0`` both ways), ``(j, i)`` is computed as well."""
    for i in range(pos.shape[1]):
        if not valid[w, i]:
            continue
        px, py, lvx, lvy = pos[w, i, 0], pos[w, i, 1], c[LAM] * vel[w, i, 0], c[LAM] * vel[w, i, 1]
        for j in range(i + 1, pos.shape[1]):
            if valid[w, j]:
                qx, qy, lqx, lqy = pos[w, j, 0], pos[w, j, 1], c[LAM] * vel[w, j, 0], c[LAM] * vel[w, j, 1]
                fx, fy = _pair(px, py, lvx, lvy, qx, qy, lqx, lqy, c, s)
                pair[i, j, 0], pair[i, j, 1] = fx, fy
                if qx != px and qy != py:
                    pair[j, i, 0], pair[j, i, 1] = -fx, -fy
                else:
                    pair[j, i, 0], pair[j, i, 1] = _pair(qx, qy, lqx, lqy, px, py, lvx, lvy, c, s)


def _solve(pos, vel, goal, valid, rad, vpref, opos, ovel, ovalid, orad, c, body, out):
    """Every world (prange): ``out[w]`` = the humans' new velocities, zeros where absent."""
    m = pos.shape[1]
    for w in _prange(pos.shape[0]):
        s = np.empty(1, c.dtype)
        pair = np.empty((m, m, 2), c.dtype)
        _pairs(w, pos, vel, valid, c, pair, s)
        for i in range(m):
            if valid[w, i]:
                out[w, i, 0], out[w, i, 1] = _human(w, i, pos, vel, goal, valid, rad, vpref, opos, ovel, ovalid,
                                                    orad, c, body, pair, s)
            else:
                out[w, i, 0], out[w, i, 1] = 0, 0


def _compile():
    """Compile (or load from the cache) lazily: importing this module does not import numba."""
    global _kernel, _prange
    if _kernel is None:
        numba = numba_module()
        _prange = numba.prange
        g = globals()
        for name in ("fd_exp", "fd_atan", "fd_atan2", "_hyp", "_rexp", "_sign", "_pair", "_pairs", "_human"):
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


__all__ = ["constants", "fd_atan2", "fd_exp", "social_force_velocities"]
