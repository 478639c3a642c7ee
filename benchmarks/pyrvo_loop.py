"""A plain Python loop over RVO2 simulators (the ``pyrvo`` wheel), one per environment: the baseline the
batched crowd is compared with in benchmarks/bench_crowd.py (``--pyrvo``).

Per env-step: every agent's preferred velocity set (CrowdNav's rule: towards the goal at ``v_pref``, ``goal -
p`` within ``v_pref`` of it; the robot is one more agent heading straight for its goal), one ``do_step``,
and every agent's position and velocity read back (the observation). Episodes last ``episode_steps`` steps
and restart on the next pool case with a fresh simulator (``clear_agents`` leaves dangling k-d tree
pointers). ``procs`` processes share the environments, one per core, as the batched world uses threads.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np


def _sim(pyrvo, starts, radius, v_pref, dt, orca):
    nd, mn, th = orca.neighbor_dist, orca.max_neighbors, orca.time_horizon
    sim = pyrvo.RVOSimulator(dt, nd, mn, th, th, radius, v_pref)
    for p in starts:
        sim.add_agent((float(p[0]), float(p[1])), nd, mn, th, th, radius, v_pref, (0.0, 0.0))
    return sim


def _one_process(starts, goals, n_sims, seconds, dt, radius, v_pref, episode_steps, orca) -> tuple[int, float]:
    import pyrvo

    pool = len(starts)
    k = starts.shape[1]
    sims = [_sim(pyrvo, starts[i % pool], radius, v_pref, dt, orca) for i in range(n_sims)]
    case = list(range(n_sims))
    steps, t0, t = 0, time.perf_counter(), 0
    while steps == 0 or time.perf_counter() - t0 < seconds:
        for s, sim in enumerate(sims):
            goal = goals[case[s] % pool]
            for j in range(k):
                px, py = sim.get_agent_position(j).to_tuple()
                gx, gy = goal[j, 0] - px, goal[j, 1] - py
                d = math.hypot(gx, gy)
                f = v_pref / d if d > v_pref else 1.0
                sim.set_agent_pref_velocity(j, (gx * f, gy * f))
            sim.do_step()
            [(sim.get_agent_position(j).to_tuple(), sim.get_agent_velocity(j).to_tuple()) for j in range(k)]
        t += 1
        steps += n_sims
        if t % episode_steps == 0:  # every environment starts its next case
            for s in range(n_sims):
                case[s] += n_sims
                sims[s] = _sim(pyrvo, starts[case[s] % pool], radius, v_pref, dt, orca)
    return steps, time.perf_counter() - t0


def pyrvo_rate(pool: dict, batch: int, procs: int, seconds: float, dt: float, radius: float, v_pref: float,
               orca, episode_steps: int = 100) -> float:
    """env-steps/s of ``batch`` environments (robot + humans of ``pool``) over ``procs`` processes."""
    starts = np.concatenate([pool["start"].numpy(), pool["human_start"].numpy()], 1).astype(np.float64)
    goals = np.concatenate([pool["goal"].numpy(), pool["human_goal"].numpy()], 1).astype(np.float64)
    share = [batch // procs + (i < batch % procs) for i in range(procs)]
    args = (seconds, dt, radius, v_pref, episode_steps, orca)
    with ProcessPoolExecutor(procs) as ex:
        out = list(ex.map(_one_process, [starts] * procs, [goals] * procs, share, *[[a] * procs for a in args]))
    return sum(n / t for n, t in out)
