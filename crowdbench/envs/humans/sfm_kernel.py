"""The social-force model compiled with numba: :func:`crowdbench.envs.humans.sfm.social_force_velocities`
as one kernel, parallel over worlds (in chunks of ``CHUNK``).

The torch model stays the reference (and the documentation of the model); this kernel evaluates the same
formulas term by term, in the same association and in the inputs' float type (constants rounded to it
first, as torch does with Python scalars; ``c / t`` as torch's ``reciprocal(t) * c``): per human the goal
force, plus Moussaid's interaction summed over the other present humans and then the bodies (index
order), plus the body repulsion summed over the bodies; then the speed cap. Absent humans get zeros;
absent sources are skipped (the reference weighs them by zero: the same sum). Moussaid's force is
computed for all of a world's pairs ``i < j`` (and human-body pairs) in one branch-free loop that LLVM
vectorises (:func:`_block`), and ``f_ji = -f_ij`` exactly (:func:`_pairs`): half the pairs.

Not bit-identical to the reference: torch's ``exp``, ``atan2`` and ``hypot`` are its vectorised (SLEEF)
ones, and it sums the sources in several partial sums. Here ``exp`` and ``atan2`` are branch-free
versions of fdlibm's (:func:`fd_exp`, :func:`fd_atan2`, in double, then rounded to the inputs' type) and
``hypot`` is ``sqrt(x^2 + y^2)`` in double, rounded: within 4 eps of torch per step (docs/crowdnav.md,
tests/test_sfm_kernel.py). So ``env.sfm_backend`` defaults to ``torch`` and no committed number depends
on this kernel; reactive replay (the v2-sfm track) always uses the torch model.

Bit-identical on every x86 CPU: no ``fastmath`` (no FMA contraction, no reassociation: vectorised lanes
compute what the scalar code does) and no C library function but ``sqrt`` (correctly rounded) and
``floor`` (exact); glibc's ``exp``/``atan2`` are avoided because glibc picks their FMA or non-FMA variant
by the CPU. The tests compile the kernel for a generic x86-64 (SSE2, scalar) and for the host (AVX-512
here) in two processes and require the same bytes.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from crowdbench.envs.humans.numba_runtime import LOCK, compile_module, set_threads
from crowdbench.envs.humans.sfm import _EPS, SFMParams

_kernel = None
CHUNK = 16  # worlds per parallel task (scratch arrays are made per task)
_prange = range  # numba.prange once compiled (see _compile)

# slots of the constants vector (one array of the inputs' float type)
ONE, EPS, TAU, GOAL_THR, SPEED_F, NEG_A, LAM, GAMMA, N2, NP2, BODY_S, BODY_R, DT = range(13)


# ---------------------------------------------------------------------------------------------------
# exp and atan2 in plain double arithmetic, branch-free (so that the pair loop vectorises), from fdlibm's
# algorithms and coefficients (e_exp.c, s_atan.c of Sun's freely distributable fdlibm 5.3, as in Java's
# StrictMath). Not the C library's: glibc picks an FMA or a non-FMA variant by the CPU it runs on, so the
# same machine code would give different last bits on different x86 CPUs; these use only + - * /,
# comparisons, floor and a table of powers of two, so compiled without fastmath they give the same bytes
# everywhere. Within one ulp (tests/test_sfm_kernel.py, against Python's math on ~900,000 arguments
# each). In this file, not a module of their own: numba's cache tracks only the file of the function it
# compiles.

LN2_HI, LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
INV_LN2 = 1.44269504088896338700e00
P1, P2, P3 = 1.66666666666666019037e-01, -2.77777777770155933842e-03, 6.61375632143793436117e-05
P4, P5 = -1.65339022054652515390e-06, 4.13813679705723846039e-08
EXP_MAX = 7.09782712893383973096e02

ATAN_HI = (4.63647609000806093515e-01, 7.85398163397448278999e-01, 9.82793723247329054082e-01,
           1.57079632679489655800e00)
ATAN_LO = (2.26987774529616870924e-17, 3.06161699786838301793e-17, 1.39033110312309984516e-17,
           6.12323399573676603587e-17)
AT = (3.33333333333329318027e-01, -1.99999999998764832476e-01, 1.42857142725034663711e-01,
      -1.11111104054623557880e-01, 9.09088713343650656196e-02, -7.69187620504482999495e-02,
      6.66107313738753120669e-02, -5.83357013379057348645e-02, 4.97687799461593236017e-02,
      -3.65315727442169155270e-02, 1.62858201153657823623e-02)
PI, PI_LO = 3.1415926535897931160e00, 1.2246467991473531772e-16


PIO2_HI, PIO2_LO = ATAN_HI[3], ATAN_LO[3]
POW2 = np.ldexp(1.0, np.arange(-1022, 1024))  # 2^k, k = -1022 .. 1023 (exact)


def fd_exp(x):
    """e ** x, branch-free (fdlibm's reduction and rational approximation): k = floor(x / ln2 + 1/2),
    r = x - k ln2 in two parts, then 2^k from a table. 0 below -708 (the exact value is < 3.3e-308), inf
    above 709.78; NaN propagates."""
    xc = min(max(x, -708.0), 709.0)
    scale = 0.0 if x < -708.0 else (math.inf if x > EXP_MAX else 1.0)
    k = np.floor(xc * INV_LN2 + 0.5)
    hi = xc - k * LN2_HI
    lo = k * LN2_LO
    r = hi - lo
    t = r * r
    c = r - t * (P1 + t * (P2 + t * (P3 + t * (P4 + t * P5))))
    y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
    return y * POW2[np.int64(k) + 1022] * scale + (x - x)


def fd_atan2(y, x):
    """The angle of (x, y) in [-pi, pi], branch-free: atan of min/max(|x|, |y|) in [0, 1] by fdlibm's
    reduction (around atan(0.5) and atan(1)) and polynomial, then pi/2 - a if |y| > |x|, pi - a if x < 0
    (or -0), with y's sign. Signed zeros as C's atan2."""
    ax, ay = abs(x), abs(y)
    swap = ay > ax
    num, den = min(ax, ay), max(ax, ay)
    t = num / den if den > 0.0 else 0.0
    id0 = (t >= 0.4375) & (t < 0.6875)
    id1 = t >= 0.6875
    u = (2.0 * t - 1.0 if id0 else (t - 1.0 if id1 else t)) / (2.0 + t if id0 else (t + 1.0 if id1 else 1.0))
    hi = ATAN_HI[0] if id0 else (ATAN_HI[1] if id1 else 0.0)
    lo = ATAN_LO[0] if id0 else (ATAN_LO[1] if id1 else 0.0)
    z = u * u
    w = z * z
    s1 = z * (AT[0] + w * (AT[2] + w * (AT[4] + w * (AT[6] + w * (AT[8] + w * AT[10])))))
    s2 = w * (AT[1] + w * (AT[3] + w * (AT[5] + w * (AT[7] + w * AT[9]))))
    a = hi - ((u * (s1 + s2) - lo) - u)
    a = PIO2_HI - (a - PIO2_LO) if swap else a
    # x < 0, or x = -0 with y = +-0 (atan2(+-0, -0) = +-pi; atan2(y, -0) = +-pi/2 as for +0)
    neg = (x < 0.0) | ((x == 0.0) & (y == 0.0) & (math.copysign(1.0, x) < 0.0))
    a = PI - (a - PI_LO) if neg else a
    return math.copysign(a, y)


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


def _human(w, i, pos, goal, valid, rad, vpref, opos, ovalid, orad, c, body, pair, rob, vel, s):
    """Human ``i`` of world ``w``: its new velocity (social_force_velocities) from Moussaid's forces on it,
    ``pair[i, j]`` from the humans and ``rob[i, k]`` from the bodies (:func:`_pairs`), summed in index order."""
    px, py, vx, vy = pos[w, i, 0], pos[w, i, 1], vel[w, i, 0], vel[w, i, 1]
    tx, ty = goal[w, i, 0] - px, goal[w, i, 1] - py
    dist = _hyp(tx, ty, s)
    zero = c[ONE] - c[ONE]
    dsx, dsy = zero, zero
    if dist > c[GOAL_THR]:
        g = max(dist, c[EPS])
        dsx, dsy = tx / g * vpref[w, i], ty / g * vpref[w, i]
    fx, fy = (dsx - vx) / c[TAU], (dsy - vy) / c[TAU]
    mx, my = zero, zero
    for j in range(pos.shape[1]):
        if j != i and valid[w, j]:
            mx, my = mx + pair[i, j, 0], my + pair[i, j, 1]
    for k in range(opos.shape[1]):
        if ovalid[w, k]:
            mx, my = mx + rob[i, k, 0], my + rob[i, k, 1]
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


def _block(p, q, n, c, r):
    """:func:`_pair` for the ``n`` pairs ``k``: on a human ``p[0:4, k]`` (x, y, lambda vx, lambda vy) from a
    source ``q[0:4, k]``, the same operations with the same roundings (each stored in a row of ``r``, of the
    inputs' type, as :func:`_pair` stores into its scratch); branch-free and long (all of a world's pairs),
    so LLVM vectorises the loop. The forces go to ``r[6], r[7]``."""
    for k in range(n):
        px, py = p[0, k], p[1, k]
        ex, ey = q[0, k] - px, q[1, k] - py
        exd, eyd = np.float64(ex), np.float64(ey)
        r[0, k] = np.sqrt(exd * exd + eyd * eyd)
        d = r[0, k]
        inv = c[ONE] / max(d, c[EPS])
        ex, ey = ex * inv, ey * inv
        dx = (p[2, k] - q[2, k]) + ex
        dy = (p[3, k] - q[3, k]) + ey
        dxd, dyd = np.float64(dx), np.float64(dy)
        r[1, k] = np.sqrt(dxd * dxd + dyd * dyd)
        d_len = r[1, k]
        r[2, k] = fd_atan2(np.float64(dx * ey - dy * ex), np.float64(dx * ex + dy * ey))
        theta = r[2, k]
        b = max(c[GAMMA] * d_len, c[EPS])
        neg_dist = -d / b
        bt = b * theta
        bt2 = bt * bt
        w = (c[ONE] / max(d_len, c[EPS])) * c[NEG_A]
        r[3, k] = fd_exp(np.float64(neg_dist - c[NP2] * bt2))
        r[4, k] = fd_exp(np.float64(neg_dist - c[N2] * bt2))
        along = w * r[3, k]
        sg = c[ONE] if theta > 0 else (-c[ONE] if theta < 0 else theta * c[ONE])
        turn = w * sg * r[4, k]
        r[6, k] = along * dx - turn * dy
        r[7, k] = along * dy + turn * dx


def _load(p, n, x, y, vx, vy, lam):
    p[0, n], p[1, n], p[2, n], p[3, n] = x, y, lam * vx, lam * vy


def _pairs(w, pos, vel, valid, opos, ovel, ovalid, c, pair, rob, p, q, r, ij, s):
    """Moussaid's forces in world ``w``: ``pair[i, j]`` on human ``i`` from human ``j``, ``rob[i, k]`` on
    ``i`` from body ``k``, all pairs ``i < j`` and (human, body) as one block (:func:`_block`).
    ``pair[j, i] = -pair[i, j]`` is what :func:`_pair` computes for ``(j, i)`` when the two differ in both
    coordinates: every difference it takes changes sign (``a - b = -(b - a)``), so the distances, ``|D|``,
    the angle's cross and dot products (products of two negated factors) and the exponentials are the
    same, and the force is negated: half the pairs to compute. Where a coordinate difference is zero (its
    sign does not flip: ``+0`` both ways), ``(j, i)`` is computed as well."""
    m, lam, n = pos.shape[1], c[LAM], 0
    for i in range(m):
        if not valid[w, i]:
            continue
        for j in range(i + 1, m):
            if valid[w, j]:
                ij[0, n], ij[1, n] = i, j
                _load(p, n, pos[w, i, 0], pos[w, i, 1], vel[w, i, 0], vel[w, i, 1], lam)
                _load(q, n, pos[w, j, 0], pos[w, j, 1], vel[w, j, 0], vel[w, j, 1], lam)
                n += 1
        for k in range(opos.shape[1]):
            if ovalid[w, k]:
                ij[0, n], ij[1, n] = i, -1 - k
                _load(p, n, pos[w, i, 0], pos[w, i, 1], vel[w, i, 0], vel[w, i, 1], lam)
                _load(q, n, opos[w, k, 0], opos[w, k, 1], ovel[w, k, 0], ovel[w, k, 1], lam)
                n += 1
    _block(p, q, n, c, r)
    for k in range(n):
        i, j = ij[0, k], ij[1, k]
        if j < 0:
            rob[i, -1 - j, 0], rob[i, -1 - j, 1] = r[6, k], r[7, k]
            continue
        pair[i, j, 0], pair[i, j, 1] = r[6, k], r[7, k]
        if q[0, k] != p[0, k] and q[1, k] != p[1, k]:
            pair[j, i, 0], pair[j, i, 1] = -r[6, k], -r[7, k]
        else:
            pair[j, i, 0], pair[j, i, 1] = _pair(q[0, k], q[1, k], q[2, k], q[3, k], p[0, k], p[1, k], p[2, k],
                                                 p[3, k], c, s)


def _solve(pos, vel, goal, valid, rad, vpref, opos, ovel, ovalid, orad, c, body, chunk, out):
    """Every world, in chunks of ``chunk`` worlds (prange; the scratch arrays are made once per chunk):
    ``out[w]`` = the humans' new velocities, zeros where absent."""
    n, m = pos.shape[0], pos.shape[1]
    for ch in _prange((n + chunk - 1) // chunk):
        s = np.empty(1, c.dtype)
        k = m * (m - 1) // 2 + m * opos.shape[1]  # pairs i < j and (human, body)
        pair, rob = np.empty((m, m, 2), c.dtype), np.empty((m, opos.shape[1], 2), c.dtype)
        p, q, r, ij = np.empty((4, k), c.dtype), np.empty((4, k), c.dtype), np.empty((8, k), c.dtype), \
            np.empty((2, k), np.int64)
        for w in range(ch * chunk, min(n, (ch + 1) * chunk)):
            _pairs(w, pos, vel, valid, opos, ovel, ovalid, c, pair, rob, p, q, r, ij, s)
            for i in range(m):
                if valid[w, i]:
                    out[w, i, 0], out[w, i, 1] = _human(w, i, pos, goal, valid, rad, vpref, opos, ovalid, orad, c,
                                                        body, pair, rob, vel, s)
                else:
                    out[w, i, 0], out[w, i, 1] = 0, 0


def _compile():
    global _kernel
    if _kernel is None:
        _kernel = compile_module(globals(), ("_hyp", "_rexp", "_sign", "_pair", "_block", "_load", "_pairs", "_human"),
                                 _solve, inline=("fd_exp", "fd_atan2"))
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
            constants(params, dt, dtype), body, CHUNK, out)
    with LOCK:
        kernel(*args)
    return torch.from_numpy(out).to(pos.dtype)


__all__ = ["constants", "fd_atan2", "fd_exp", "social_force_velocities"]
