"""RVO2 (the ``pyrvo`` wheel) as the reference for :func:`crowdbench.envs.humans.orca.orca_velocities`,
plus random test configurations of several kinds. Used by the tests and the benchmark.

A fresh ``pyrvo.RVOSimulator`` is built per world: ``clear_agents`` leaves dangling k-d
tree pointers (see ``crowdbench.baselines.orca``).
"""

from __future__ import annotations

import math

import numpy as np
import pyrvo
import torch

KINDS = ("sparse", "dense", "overlap", "infeasible")


def rvo2_velocities(pos, vel, pref, valid, radius, max_speed, *, time_horizon, dt, neighbor_dist, max_neighbors):
    """RVO2's new velocities for the same arguments as ``orca_velocities`` (``[N, K]`` radius and
    max_speed); returns a float64 numpy ``[N, K, 2]`` array, invalid agents keep ``vel``."""
    pos, vel, pref = (np.asarray(a, dtype=np.float64) for a in (pos, vel, pref))
    valid = np.asarray(valid, dtype=bool)
    n, k = valid.shape
    radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n, k))
    max_speed = np.broadcast_to(np.asarray(max_speed, dtype=np.float64), (n, k))
    out = vel.copy()
    for w in range(n):
        sim = pyrvo.RVOSimulator(dt, neighbor_dist, max_neighbors, time_horizon, time_horizon, 0.1, 1.0)
        ids = np.flatnonzero(valid[w])
        for a in ids:
            sim.add_agent(
                (float(pos[w, a, 0]), float(pos[w, a, 1])), neighbor_dist, max_neighbors, time_horizon,
                time_horizon, float(radius[w, a]), float(max_speed[w, a]),
                (float(vel[w, a, 0]), float(vel[w, a, 1])),
            )  # fmt: skip
        for j, a in enumerate(ids):
            sim.set_agent_pref_velocity(j, (float(pref[w, a, 0]), float(pref[w, a, 1])))
        sim.do_step()
        for j, a in enumerate(ids):
            out[w, a] = sim.get_agent_velocity(j).to_tuple()
    return out


def random_configs(kind: str, n: int, k: int, seed: int) -> dict[str, torch.Tensor]:
    """``n`` random worlds of up to ``k`` agents (trailing ones padded out at random), inputs
    rounded to float32 so RVO2 sees exactly the same numbers.

    - ``sparse``: a 12 m box, few neighbours in range; mostly the no-collision cases.
    - ``dense``: a 3 m box; many neighbours, cut-off circle and both legs.
    - ``overlap``: as dense, plus a few agents dropped onto another one (discs overlap: the
      collision case).
    - ``infeasible``: agents packed around the origin, fast and converging, with small
      maximum speeds, so that ``linearProgram2`` fails and ``linearProgram3`` runs.
    """
    g = np.random.default_rng(seed)
    size = {"sparse": 12.0, "dense": 3.0, "overlap": 3.0, "infeasible": 1.2}[kind]
    pos = g.uniform(-size / 2, size / 2, (n, k, 2))
    radius = g.uniform(0.1, 0.4, (n, k))
    vel = _in_disc(g, (n, k), 1.5)
    pref = _in_disc(g, (n, k), 2.0)
    max_speed = g.uniform(0.5, 2.0, (n, k))
    if kind == "overlap":
        hit = g.random((n, k)) < 0.3
        host = g.integers(0, k, (n, k))
        near = pos[np.arange(n)[:, None], host] + _in_disc(g, (n, k), 0.3)
        pos = np.where(hit[..., None], near, pos)
    if kind == "infeasible":
        vel = -pos / np.linalg.norm(pos, axis=-1, keepdims=True) * g.uniform(0.5, 2.0, (n, k, 1))
        max_speed = g.uniform(0.05, 0.5, (n, k))
        radius = g.uniform(0.15, 0.3, (n, k))
    counts = g.integers(max(2, k // 2), k + 1, n)
    valid = np.arange(k)[None, :] < counts[:, None]
    f32 = lambda a: torch.from_numpy(a.astype(np.float32).astype(np.float64))
    return {
        "pos": f32(pos), "vel": f32(vel), "pref": f32(pref), "valid": torch.from_numpy(valid),
        "radius": f32(radius), "max_speed": f32(max_speed),
    }  # fmt: skip


def _in_disc(g: np.random.Generator, shape, r: float) -> np.ndarray:
    ang = g.uniform(0.0, 2 * np.pi, shape)
    rad = r * np.sqrt(g.random(shape))
    # The C library's cos/sin (math), not numpy's: numpy's float64 kernels for AVX-512 machines differ in
    # the last bit, which made the worlds, and so what the tests check, depend on the machine.
    cos, sin = (np.array([f(a) for a in ang.ravel()]).reshape(shape) for f in (math.cos, math.sin))
    return np.stack([rad * cos, rad * sin], axis=-1)
