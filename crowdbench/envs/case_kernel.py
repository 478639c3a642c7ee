"""CrowdNav's rejection sampler (:mod:`crowdbench.envs.crowdnav_cases`) compiled with numba: the same
uniform draws in the same order, the same accept/reject decisions, the same values.

The draws are made by numpy (``RandomState.random_sample(k)``, the same doubles in the same order as
``k`` scalar calls) into a buffer the kernel reads from its start; when the buffer runs out the kernel
returns, the caller appends more draws and the kernel resumes at the human it was placing (that human's
candidates are tested again from its first draw: same decisions). The kernel only reads draws, so how
many were consumed is where its pointer stops.

Values: the candidate positions are CrowdNav's scalar operations in CrowdNav's order (IEEE double, no
``fastmath``, so no contraction into FMA). Circle crossing needs ``cos`` and ``sin`` of each candidate's
angle: they are computed by numpy on the whole buffer (the ufunc CrowdNav calls, whatever its SIMD
implementation on this CPU), not by the kernel's libm.

Decisions: CrowdNav rejects a candidate closer than ``radius + r + discomfort`` to another agent, the
distance being ``numpy.linalg.norm`` of a 2-tuple, i.e. ``sqrt`` of a BLAS ``ddot`` (which may round
``dx*dx + dy*dy`` once, with FMA, or twice). The kernel computes ``sqrt(dx*dx + dy*dy)``; a candidate
none of whose distances is certainly too close and one of which is within ``margin`` (1e-9 m) of its
threshold is returned undecided, the caller decides it with CrowdNav's own test and resumes with that
decision given (``forced``). Such candidates are rare (none in the 1,500 published cases).
"""

from __future__ import annotations

DONE, MORE, UNDECIDED = 0, 1, 2  # kernel status
CIRCLE, SQUARE_START, SQUARE_GOAL = 0, 1, 2  # which rejection loop a candidate belongs to

_kernels = None


def _verdict(x, y, ox, oy, lo2, hi2, k, p, forced_at, forced_ok):
    """1: accepted, 0: rejected, -1: undecided, for the candidate ``(x, y)`` drawn at ``p`` against the
    first ``k`` others. Squared distances: rejected for certain below ``lo2`` = (threshold - margin)^2,
    accepted for certain from ``hi2``; in between, the decision is ``forced``'s or none. The loop counts
    without branching (so that LLVM can vectorise it: integer sums, no float reassociation)."""
    close = 0
    near = 0
    for j in range(k):
        dx = x - ox[j]
        dy = y - oy[j]
        h2 = dx * dx + dy * dy
        close += h2 < lo2[j]
        near += h2 < hi2[j]
    if close:
        return 0
    if not near:
        return 1
    for f in range(forced_at.shape[0]):
        if forced_at[f] == p:
            return 1 if forced_ok[f] else 0
    return -1


def _put(ox, oy, lo2, hi2, j, x, y, thr, margin):
    ox[j], oy[j] = x, y
    lo2[j], hi2[j] = (thr - margin) ** 2, (thr + margin) ** 2


def _circle(d, cos_a, sin_a, radius_c, v, thr, ox, oy, lo2, hi2, n, i0, p0, margin, forced_at, forced_ok, acc):
    """Circle crossing from human ``i0`` at draw ``p0``. The others are the robot's start and goal (slots
    0, 1) and each placed human's start and goal (slots ``2 i + 2``, ``2 i + 3``); the order of the others
    changes no decision. ``acc[i]``: the draws of human ``i``'s accepted candidate. Returns (status, human, draw to resume from, undecided candidate's draw or -1,
    loop); circle crossing resumes at the candidate where it stopped."""
    p = p0
    for i in range(i0, n):
        k = 2 * (i + 1)
        while True:
            if p + 3 > d.shape[0]:  # resumed at this candidate (the placed humans are kept)
                return MORE, i, p, -1, CIRCLE
            c = p // 3
            x = radius_c * cos_a[c] + (d[p + 1] - 0.5) * v
            y = radius_c * sin_a[c] + (d[p + 2] - 0.5) * v
            ok = _verdict(x, y, ox, oy, lo2, hi2, k, p, forced_at, forced_ok)
            if ok < 0:
                return UNDECIDED, i, p, p, CIRCLE
            p += 3
            if ok == 1:
                break
        _put(ox, oy, lo2, hi2, k, x, y, thr, margin)
        _put(ox, oy, lo2, hi2, k + 1, -x, -y, thr, margin)
        acc[i, 0], acc[i, 1], acc[i, 2] = d[p - 3], d[p - 2], d[p - 1]
    return DONE, n, p, -1, CIRCLE


def _square_loop(d, p, width, sign, ox, oy, lo2, hi2, k, forced_at, forced_ok):
    """One of square crossing's loops from draw ``p``: (status, draw after the accepted one or the
    undecided one's, x, y)."""
    while True:
        if p + 2 > d.shape[0]:
            return MORE, p, 0.0, 0.0
        x = d[p] * width * 0.5 * sign
        y = (d[p + 1] - 0.5) * width
        ok = _verdict(x, y, ox, oy, lo2, hi2, k, p, forced_at, forced_ok)
        if ok < 0:
            return UNDECIDED, p, x, y
        p += 2
        if ok == 1:
            return DONE, p, x, y


def _square(d, width, thr, s, g, n, i0, p0, margin, forced_at, forced_ok, signs):
    """Square crossing from human ``i0`` at draw ``p0``: one sign draw, then starts tested against the
    starts so far (``s``: rows x, y, lo2, hi2; the robot's in slot 0), then goals against the goals (``g``). Returns as
    :func:`_circle`."""
    p = p0
    for i in range(i0, n):
        begin = p
        if p + 1 > d.shape[0]:
            return MORE, i, begin, -1, SQUARE_START
        sign = -1.0 if d[p] > 0.5 else 1.0
        st, p, x, y = _square_loop(d, p + 1, width, sign, s[0], s[1], s[2], s[3], i + 1, forced_at, forced_ok)
        if st != DONE:
            return st, i, begin, p, SQUARE_START
        st, p, x_g, y_g = _square_loop(d, p, width, -sign, g[0], g[1], g[2], g[3], i + 1, forced_at, forced_ok)
        if st != DONE:
            return st, i, begin, p, SQUARE_GOAL
        _put(s[0], s[1], s[2], s[3], i + 1, x, y, thr, margin)
        _put(g[0], g[1], g[2], g[3], i + 1, x_g, y_g, thr, margin)
        signs[i] = sign
    return DONE, n, p, -1, SQUARE_START


def kernels():
    """(circle, square), compiled on first use (importing this module does not import numba)."""
    global _kernels
    if _kernels is None:
        import numba

        opts = {"cache": True, "fastmath": False, "error_model": "numpy"}
        g = globals()
        for name in ("_verdict", "_put", "_square_loop"):
            g[name] = numba.njit(**opts)(g[name])
        _kernels = numba.njit(**opts)(_circle), numba.njit(**opts)(_square)
    return _kernels
