"""The batched social-force human model (crowdbench/envs/humans/sfm.py) against independent expectations:
hand computations of the published formulas, symmetries, padding, a robot rollout, and PySocialForce itself
when it is importable (it is not a project dependency)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from crowdbench.envs.humans.sfm import SFMParams, social_force_accelerations, social_force_velocities

P = SFMParams()
DT = 0.25


def t64(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def world(pos, vel, goal, valid=None):
    """One world of humans as [1, M, ...] float64 tensors."""
    pos, vel, goal = t64([pos]), t64([vel]), t64([goal])
    valid = torch.ones(pos.shape[:2], dtype=torch.bool) if valid is None else torch.tensor([valid])
    return pos, vel, goal, valid


def test_goal_force_single_human_hand_computed():
    # At rest, goal 4 m away on +x, v_pref 1.2, tau 0.5 s, dt 0.25 s: v = (1.2 * (1, 0) - 0) / 0.5 * 0.25.
    v = social_force_velocities(*world([[0.0, 0.0]], [[0.0, 0.0]], [[4.0, 0.0]]), 0.3, 1.2, dt=DT, params=P)
    torch.testing.assert_close(v[0, 0], t64([0.6, 0.0]))
    # Moving at (0.2, 0.4): F = ((1.2, 0) - (0.2, 0.4)) / 0.5 = (2.0, -0.8); v + 0.25 F = (0.7, 0.2).
    v = social_force_velocities(*world([[1.0, 1.0]], [[0.2, 0.4]], [[5.0, 1.0]]), 0.3, 1.2, dt=DT, params=P)
    torch.testing.assert_close(v[0, 0], t64([0.7, 0.2]))
    # Speed cap 1.3 * v_pref: from (1.5, 0) towards a goal on -y, v + dt F = (1.5 - 0.75, -0.6) is under the
    # cap 1.56; from (3, 0) it is (1.5, -0.6), |.| = 1.6155 > 1.56, scaled down to 1.56.
    v = social_force_velocities(*world([[0.0, 0.0]], [[3.0, 0.0]], [[0.0, -4.0]]), 0.3, 1.2, dt=DT, params=P)
    torch.testing.assert_close(v[0, 0], t64([1.5, -0.6]) * (1.56 / math.hypot(1.5, 0.6)))
    # Within goal_threshold (0.2 m) of the goal the desired velocity is zero: F = -v / tau.
    v = social_force_velocities(*world([[0.0, 0.0]], [[0.4, 0.0]], [[0.1, 0.0]]), 0.3, 1.2, dt=DT, params=P)
    torch.testing.assert_close(v[0, 0], t64([0.4 - 0.25 * 0.4 / 0.5, 0.0]))


def test_pair_force_hand_computed_moussaid():
    # i at the origin walking +x at 1 m/s, j at (2, 0.5) walking -x at 0.5 m/s. Each walks straight at its
    # goal at exactly v_pref, so the goal force is zero and the acceleration is the Moussaid force alone.
    pos, vel, goal, valid = world(
        [[0.0, 0.0], [2.0, 0.5]], [[1.0, 0.0], [-0.5, 0.0]], [[10.0, 0.0], [-10.0, 0.5]]
    )
    acc = social_force_accelerations(pos, vel, goal, valid, 0.3, t64([[1.0, 0.5]]), params=P)

    def moussaid(pi, vi, pj, vj):
        A, lam, gamma, n, n_prime = 5.1, 2.0, 0.35, 2.0, 3.0  # PySocialForce default.toml / Moussaid 2009
        dx, dy = pj[0] - pi[0], pj[1] - pi[1]
        d = math.hypot(dx, dy)
        ex, ey = dx / d, dy / d  # unit vector i -> j
        Dx, Dy = lam * (vi[0] - vj[0]) + ex, lam * (vi[1] - vj[1]) + ey
        D = math.hypot(Dx, Dy)
        tx, ty = Dx / D, Dy / D  # interaction direction
        theta = math.atan2(ey, ex) - math.atan2(ty, tx)  # angle from t to e (small here: no wrap needed)
        B = gamma * D
        fv = -A * math.exp(-d / B) * math.exp(-((n_prime * B * theta) ** 2))
        fa = -A * math.copysign(1.0, theta) * math.exp(-d / B) * math.exp(-((n * B * theta) ** 2))
        return fv * tx + fa * -ty, fv * ty + fa * tx  # f_v t + f_a (left normal of t)

    fi = moussaid((0.0, 0.0), (1.0, 0.0), (2.0, 0.5), (-0.5, 0.0))
    fj = moussaid((2.0, 0.5), (-0.5, 0.0), (0.0, 0.0), (1.0, 0.0))
    torch.testing.assert_close(acc[0, 0], t64(fi))
    torch.testing.assert_close(acc[0, 1], t64(fj))
    # i brakes and turns right, away from j on its left (the published sense of both terms).
    assert fi[0] < -0.1 and fi[1] < -0.1
    # The step integrates it: v_i + dt f_i (under the cap 1.3).
    v = social_force_velocities(pos, vel, goal, valid, 0.3, t64([[1.0, 0.5]]), dt=DT, params=P)
    torch.testing.assert_close(v[0, 0], t64([1.0 + DT * fi[0], DT * fi[1]]))


def test_head_on_symmetry():
    # Point symmetry through the origin: (p, v, g) -> -(p, v, g) swaps the two humans, forces are negated.
    pos, vel, goal, valid = world(
        [[-1.5, 0.1], [1.5, -0.1]], [[1.0, 0.0], [-1.0, 0.0]], [[5.0, 0.1], [-5.0, -0.1]]
    )
    acc = social_force_accelerations(pos, vel, goal, valid, 0.3, 1.2, params=P)
    torch.testing.assert_close(acc[0, 1], -acc[0, 0])
    assert acc[0, 0, 1] > 0.0  # j is 0.2 m to i's right: i turns left (+y), j turns to its own left (-y)
    # Mirror symmetry about the y axis: both on y = 0.2, facing each other; forces mirror x -> -x.
    pos, vel, goal, valid = world(
        [[-1.5, 0.2], [1.5, 0.2]], [[1.0, 0.0], [-1.0, 0.0]], [[5.0, 0.2], [-5.0, 0.2]]
    )
    acc = social_force_accelerations(pos, vel, goal, valid, 0.3, 1.2, params=P)
    torch.testing.assert_close(acc[0, 1], acc[0, 0] * t64([-1.0, 1.0]))
    assert acc[0, 0, 0] < 0.0 and abs(float(acc[0, 0, 1])) < 1e-12  # on one line: pure braking


def test_far_human_and_padding_change_nothing():
    pos, vel, goal, valid = world(
        [[0.0, 0.0], [1.5, 0.4]], [[1.0, 0.0], [-1.0, 0.0]], [[5.0, 0.0], [-5.0, 0.4]]
    )
    ref = social_force_velocities(pos, vel, goal, valid, 0.3, 1.2, dt=DT, params=P)
    # The model has no cutoff; at 20 m the force is ~A exp(-20 / (gamma |D|)) ~ 1e-8 m/s^2.
    far = world(
        [[0.0, 0.0], [1.5, 0.4], [20.0, 0.0]], [[1.0, 0.0], [-1.0, 0.0], [0.0, 0.0]],
        [[5.0, 0.0], [-5.0, 0.4], [20.0, 5.0]],
    )  # fmt: skip
    v = social_force_velocities(*far, 0.3, 1.2, dt=DT, params=P)
    torch.testing.assert_close(v[:, :2], ref, atol=1e-7, rtol=0)
    # A padded human in contact, with garbage (NaN) state, changes nothing and gets a zero velocity.
    nan = float("nan")
    pad = world(
        [[0.0, 0.0], [0.3, 0.0], [1.5, 0.4]], [[1.0, 0.0], [nan, 2.0], [-1.0, 0.0]],
        [[5.0, 0.0], [nan, nan], [-5.0, 0.4]], valid=[True, False, True],
    )  # fmt: skip
    v = social_force_velocities(*pad, 0.3, 1.2, dt=DT, params=P)
    torch.testing.assert_close(v[:, [0, 2]], ref, atol=0, rtol=0)
    assert torch.equal(v[0, 1], t64([0.0, 0.0]))


def test_batching_matches_one_world_at_a_time():
    g = torch.Generator().manual_seed(0)
    n, m = 5, 7
    pos = torch.rand(n, m, 2, generator=g, dtype=torch.float64) * 8 - 4
    vel = torch.randn(n, m, 2, generator=g, dtype=torch.float64) * 0.7
    goal = torch.rand(n, m, 2, generator=g, dtype=torch.float64) * 8 - 4
    valid = torch.rand(n, m, generator=g) > 0.3
    v_pref = 0.8 + 0.6 * torch.rand(n, m, generator=g, dtype=torch.float64)
    rob = torch.rand(n, 1, 2, generator=g, dtype=torch.float64) * 4 - 2
    rvel = torch.randn(n, 1, 2, generator=g, dtype=torch.float64)
    kw = {"dt": DT, "params": P, "others_pos": rob, "others_vel": rvel, "others_radius": 0.3}
    out = social_force_velocities(pos, vel, goal, valid, 0.3, v_pref, **kw)
    for w in range(n):
        one = social_force_velocities(
            pos[w : w + 1], vel[w : w + 1], goal[w : w + 1], valid[w : w + 1], 0.3, v_pref[w : w + 1],
            dt=DT, params=P, others_pos=rob[w : w + 1], others_vel=rvel[w : w + 1], others_radius=0.3,
        )  # fmt: skip
        torch.testing.assert_close(out[w : w + 1], one)
    assert torch.all(out[~valid] == 0)


def rollout(y0: float, steps: int = 40, with_robot: bool = True):
    """A human from (-4, y0) to (4, y0) at 1.3 m/s past a standing robot at the origin (radius 0.3 each)."""
    pos, vel, goal, valid = world([[-4.0, y0]], [[0.0, 0.0]], [[4.0, y0]])
    rob = t64([[[0.0, 0.0]]]) if with_robot else None
    track = []
    for _ in range(steps):
        vel = social_force_velocities(
            pos, vel, goal, valid, 0.3, 1.3, dt=DT, params=P, others_pos=rob, others_radius=0.3
        )
        pos = pos + vel * DT
        track.append(pos[0, 0].clone())
    return torch.stack(track)


def test_robot_repels_and_is_not_overlapped():
    free = rollout(0.05, with_robot=False)
    assert float((free[:, 1] - 0.05).abs().max()) < 1e-9  # no robot: a straight line
    for y0 in (0.05, 0.0):  # slightly off the line, and dead on it (no turning term: it has to stop)
        track = rollout(y0)
        clearance = track.norm(dim=-1) - 0.6
        assert float(clearance.min()) > 0.0, (y0, float(clearance.min()))
    track = rollout(0.05)
    assert float(track[:, 1].max()) > 0.3  # it deviates (to the side it already was on)...
    assert float(track[-1, 0]) > 2.0  # ...and gets past the robot within the 10 s


# --- PySocialForce, when importable (e.g. PYTHONPATH=<pip --target dir with pysocialforce and numba>) ------


def _pysf_scene(rng, m):
    pos = rng.uniform(-3, 3, (m, 2))
    vel = rng.normal(0, 0.8, (m, 2))
    goal = rng.uniform(-6, 6, (m, 2))
    v_pref = rng.uniform(0.8, 1.5, m)
    return pos, vel, goal, v_pref


def _pysf_unwrapped_theta_bad(pos, vel):
    """Per human: does some pair have |theta| > pi in PySocialForce's unwrapped angle difference?"""
    e = pos[:, None] - pos[None]  # PySocialForce's convention: self - other, and other - self for velocity
    d = np.linalg.norm(e, axis=-1)
    np.fill_diagonal(d, 1.0)
    e = e / d[..., None]
    t = 2.0 * (vel[None] - vel[:, None]) + e
    theta = np.arctan2(t[..., 1], t[..., 0]) - np.arctan2(e[..., 1], e[..., 0])
    np.fill_diagonal(theta, 0.0)
    return (np.abs(theta) > np.pi).any(axis=1)


def _wrap_pysf_theta(monkeypatch):
    """Make PySocialForce's SocialForce wrap theta: it computes ``vector_angles(t) - vector_angles(e)``, so
    the second call (on e, right after the one on t) returns angle(t) - wrap(angle(t) - angle(e))."""
    from pysocialforce import forces

    orig, last = forces.stateutils.vector_angles, []

    def angles(vecs):
        a = orig(vecs)
        if not last:
            last.append(a)
            return a
        at = last.pop()
        return at - (np.mod(at - a + np.pi, 2 * np.pi) - np.pi)

    monkeypatch.setattr(forces.stateutils, "vector_angles", angles)


@pytest.mark.parametrize("wrap_theta", [False, True], ids=["as-shipped", "theta-wrapped"])
def test_matches_pysocialforce(wrap_theta, monkeypatch):
    psf = pytest.importorskip("pysocialforce")
    if wrap_theta:
        _wrap_pysf_theta(monkeypatch)
    logging.getLogger("numba").setLevel(logging.WARNING)
    params = SFMParams(body_strength=0.0, max_speed_factor=1.0)  # PySocialForce caps at its desired speed
    rng = np.random.default_rng(0)
    agree = clean = total = 0
    worst = 0.0
    for scene in range(20):
        m = 6
        pos, vel, goal, v_pref = _pysf_scene(rng, m)
        robot = scene % 2 == 1  # odd scenes: the last pedestrian is a robot, given to us as others_*
        state = np.concatenate([pos, vel, goal], axis=1)
        sim = psf.Simulator(state.copy())
        sim.peds.max_speeds = v_pref.copy()  # its DesiredForce relaxes towards max_speeds
        sim.peds.step_width = DT
        f_ref = sum(f.get_force() for f in sim.forces)
        sim.step_once()
        v_ref = sim.peds.vel()
        h = m - 1 if robot else m
        kw = {}
        if robot:
            kw = {"others_pos": t64(pos[None, h:]), "others_vel": t64(vel[None, h:])}
        args = (
            t64(pos[None, :h]),
            t64(vel[None, :h]),
            t64(goal[None, :h]),
            torch.ones(1, h, dtype=torch.bool),
        )
        acc = social_force_accelerations(*args, 0.3, t64(v_pref[None, :h]), params=params, **kw)[0].numpy()
        v = social_force_velocities(*args, 0.3, t64(v_pref[None, :h]), dt=DT, params=params, **kw)[0].numpy()
        bad = _pysf_unwrapped_theta_bad(pos, vel)[:h] & (not wrap_theta)
        ok = np.isclose(acc, f_ref[:h], rtol=1e-9, atol=1e-9).all(axis=1)
        far = np.linalg.norm(goal[:h] - pos[:h], axis=1) > 0.5  # PySocialForce zeroes v within 0.5 m of goal
        ok_v = np.isclose(v, v_ref[:h], rtol=1e-9, atol=1e-9).all(axis=1) | ~far
        assert (ok | bad).all() and (ok_v | bad).all(), scene  # every disagreement is PySocialForce's theta
        agree += int(ok.sum())
        clean += int((~bad).sum())
        total += h
        if (~ok).any():
            worst = max(worst, float(np.abs(acc - f_ref[:h])[~ok].max()))
    print(f"PySocialForce (wrap_theta={wrap_theta}): {agree}/{total} humans agree to 1e-9 ({clean} have no pair hit by its unwrapped theta);"
          f" largest force difference elsewhere {worst:.3g} m/s^2")  # fmt: skip
    assert agree >= clean > 0.3 * total
