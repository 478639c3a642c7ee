"""``exp`` and ``atan2`` in plain double arithmetic (fdlibm's algorithms and coefficients: ``e_exp.c``,
``s_atan.c``, ``e_atan2.c`` of Sun's freely distributable fdlibm 5.3, as in Java's ``StrictMath``), for the
compiled social-force kernel.

Why not the C library's: glibc picks an FMA or a non-FMA variant of ``exp``/``atan2`` by the CPU it runs on
(ifuncs), so the same machine code gives different last bits on different x86 CPUs. These functions use
only ``+ - * /``, comparisons and ``ldexp`` (exact), so compiled without ``fastmath`` they give the same
bytes everywhere. Accuracy: under one unit in the last place (tests/test_sfm_kernel.py checks them
against Python's ``math`` on a million arguments each). Plain Python functions until :func:`compiled`.

The reductions' thresholds are written as the doubles fdlibm's high-word tests stand for (fdlibm
compares the high 32 bits only, which differs from these for a handful of arguments per threshold;
either way the result is within one ulp).
"""

from __future__ import annotations

import math

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


def exp(x: float) -> float:
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


def atan(x: float) -> float:
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


def atan2(y: float, x: float) -> float:
    """The angle of (x, y) in [-pi, pi] (fdlibm ``__ieee754_atan2`` for finite arguments, signed zeros
    as C's: atan2(+-0, -0 or x < 0) = +-pi, atan2(+-0, +0 or x > 0) = +-0)."""
    if y == 0.0:
        if x > 0.0 or (x == 0.0 and math.copysign(1.0, x) > 0.0):
            return y
        return math.copysign(PI, y)
    if x == 0.0:
        return math.copysign(ATAN_HI[3], y)
    z = atan(abs(y / x))
    if x > 0.0:
        return math.copysign(z, y)
    return math.copysign(PI - (z - PI_LO), y)


_compiled = None


def compiled(options: dict):
    """(exp, atan2) compiled by numba with ``options`` (no fastmath); ``atan`` is compiled in place, since
    atan2 calls it by its global name."""
    global _compiled, atan
    if _compiled is None:
        import numba

        atan = numba.njit(**options)(atan)
        _compiled = numba.njit(**options)(exp), numba.njit(**options)(atan2)
    return _compiled


__all__ = ["atan", "atan2", "compiled", "exp"]
