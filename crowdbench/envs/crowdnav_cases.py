"""CrowdNav's test cases, reproduced bit for bit: the same start positions and goals for case ``i``.

What is reproduced
------------------
The initial state that CrowdNav's ``CrowdSim.reset(phase, test_case=i)`` builds (Chen et al., ICRA 2019,
"Crowd-Robot Interaction", github.com/vita-epfl/CrowdNav at commit
``20d678085c06831e658a65b9e20c8bb6f6ecdc10``) with the default ``crowd_nav/configs/env.config``:
the robot's start and goal and every human's start and goal (and, with ``randomize_attributes``, each
human's radius and preferred speed). Read from ``crowd_sim/envs/crowd_sim.py`` (``reset`` lines 251-312,
``generate_random_human_position`` 84-153, ``generate_circle_crossing_human`` 155-176,
``generate_square_crossing_human`` 178-207), ``crowd_sim/envs/utils/agent.py``
(``sample_random_attributes`` 39-45) and ``crowd_nav/configs/env.config``. The humans' motion (ORCA) and
the episode itself are not reproduced here; only the draws of ``reset``.

CrowdNav draws from numpy's legacy global RNG after ``np.random.seed(seed)``; here a private
``np.random.RandomState(seed)`` makes the same scalar draws in the same order, and every float is
computed with the same operations in the same order, so the values are identical: checked once against
CrowdNav's own ``reset`` (gym and rvo2 stubbed) for all 500 test cases of circle and square crossing with
5 humans, 20 cases with 20 / 12 humans, val and train cases, the debug case and 50 randomized-attribute
cases; ``tests/test_crowdnav_cases.py`` keeps a sample of those values.

Quirks (all from ``crowd_sim/envs/crowd_sim.py`` unless named otherwise)
------------------------------------------------------------------------
- Seed: ``np.random.seed(counter_offset[phase] + case_counter[phase])`` (line 276) with
  ``counter_offset = {'val': 0, 'test': 1000, 'train': 2000}`` (lines 272-273; ``test`` is
  ``case_capacity['val'] = 1000``, ``train`` is ``case_capacity['val'] + case_capacity['test']``, line 61).
  So test case ``i`` is seed ``1000 + i``, validation case ``i`` seed ``i``, training episode ``k`` seed
  ``2000 + k``. The seed does not depend on the number of humans or the scenario.
- ``test_case`` vs the counter: ``reset(phase, test_case=i)`` sets ``case_counter[phase] = i``
  (line 260) and is used as given (no modulo, no bound check: test case 1000 is seed 2000, the same as
  training episode 0). Afterwards the counter becomes ``(i + 1) % case_size[phase]`` (line 283), with
  ``case_size`` = test_size 500, val_size 100, train ``uint32 max - 2000`` (lines 62-63).
  ``Explorer.run_k_episodes`` (``crowd_nav/utils/explorer.py`` line 36) calls ``reset(phase)`` without
  ``test_case``, so a test run of 500 episodes from a fresh env plays cases 0..499 in order, and episode
  ``k`` of a longer run is case ``k % 500``; :func:`case_list` numbers episodes the same way.
- ``test_case = -1`` (test phase only) is a fixed debugging case that ignores the RNG: 3 humans at
  (0, -6)->(0, 5), (-5, -5)->(-5, 5), (5, -5)->(5, 5) (lines 286-292); CrowdNav also overwrites its
  ``human_num`` with 3 for the rest of the run. Other negative cases raise ``NotImplementedError`` there
  and ``ValueError`` here.
- The robot is always placed at (0, -circle_radius) with goal (0, +circle_radius) and heading pi/2
  (line 274), for square crossing too; it draws nothing. Its goal is fixed for every case.
- Number of humans: ``human_num`` from ``[sim]`` (line 68) for the test phase (line 281). For train/val
  with a robot policy whose ``multiagent_training`` is false (CADRL) CrowdNav uses 1 human and forces
  circle crossing (lines 266-267, 278); pass ``n_humans=1, scenario="circle"`` for that. Humans are
  generated one after another and each is rejection-sampled against the robot and the humans before
  it only, so the first ``k`` humans of a case with ``n > k`` humans equal the ``k``-human case.
- Circle crossing, per human (lines 155-176): repeat { ``angle = u * pi * 2``,
  ``noise_x = (u - 0.5) * v_pref``, ``noise_y = (u - 0.5) * v_pref``,
  ``start = circle_radius * (cos angle, sin angle) + noise`` } until, for the robot and every human
  already placed, the start is at least ``human.radius + agent.radius + discomfort_dist`` (0.3 + 0.3 + 0.2
  = 0.8 m; rejected if ``<``) from that agent's start AND from that agent's goal. The goal is exactly
  ``-start`` (the point opposite through the origin, noise included), so the humans' goals are also
  0.8 m apart from each other and from the robot's start and goal. The noise is uniform in
  ``[-v_pref/2, v_pref/2)`` per axis: the start is within 0.5 m per axis of the circle, not on it.
- Square crossing, per human (lines 178-207): one draw ``u > 0.5`` -> ``sign = -1`` else ``+1`` (made
  once, before the start loop); start: repeat { ``x = u * square_width * 0.5 * sign``,
  ``y = (u - 0.5) * square_width`` } until the start is >= 0.8 m from every agent's START only; goal:
  repeat { ``x = u * square_width * 0.5 * -sign``, ``y = (u - 0.5) * square_width`` } until the goal is
  >= 0.8 m from every agent's GOAL only (the robot's goal (0, 4) included). A start may thus lie near
  another agent's goal (even the robot's) and a goal near another's start. Start and goal are on
  opposite sides of the y axis, within [-w/2, w/2]^2 (w = 10).
- ``randomize_attributes`` (false in env.config): each human first draws ``v_pref = uniform(0.5, 1.5)``
  then ``radius = uniform(0.3, 0.5)`` (``agent.py`` lines 44-45) before its position draws; the circle
  noise scales with that v_pref and the separation uses that radius.
- Distances are ``numpy.linalg.norm`` of a 2-tuple, as in CrowdNav, so accept/reject decisions match.
- The ``mixed`` rule (lines 103-151, not used by the configs) is not reproduced.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from crowdbench.envs.case_kernel import CIRCLE, DONE, MORE, SQUARE_START, kernels

__all__ = ["CROWDNAV", "CrowdNavFacts", "case_list", "crowdnav_case", "reference_case"]


@dataclass(frozen=True)
class CrowdNavFacts:
    """CrowdNav's settings (commit ``commit``), each from the file named in its comment."""

    commit: str = "20d678085c06831e658a65b9e20c8bb6f6ecdc10"  # github.com/vita-epfl/CrowdNav HEAD
    human_radius: float = 0.3  # crowd_nav/configs/env.config [humans] radius
    human_v_pref: float = 1.0  # crowd_nav/configs/env.config [humans] v_pref
    robot_radius: float = 0.3  # crowd_nav/configs/env.config [robot] radius
    robot_v_pref: float = 1.0  # crowd_nav/configs/env.config [robot] v_pref
    robot_visible: bool = False  # crowd_nav/configs/env.config [robot] visible (humans ignore the robot)
    robot_theta: float = np.pi / 2  # crowd_sim/envs/crowd_sim.py reset, robot.set(..., np.pi / 2)
    dt: float = 0.25  # crowd_nav/configs/env.config [env] time_step
    time_limit: float = 25.0  # crowd_nav/configs/env.config [env] time_limit
    success_reward: float = 1.0  # crowd_nav/configs/env.config [reward] success_reward
    collision_penalty: float = -0.25  # crowd_nav/configs/env.config [reward] collision_penalty
    discomfort_dist: float = 0.2  # crowd_nav/configs/env.config [reward] discomfort_dist
    discomfort_penalty_factor: float = 0.5  # crowd_nav/configs/env.config [reward] discomfort_penalty_factor
    circle_radius: float = 4.0  # crowd_nav/configs/env.config [sim] circle_radius
    square_width: float = 10.0  # crowd_nav/configs/env.config [sim] square_width
    human_num: int = 5  # crowd_nav/configs/env.config [sim] human_num
    randomize_attributes: bool = False  # crowd_nav/configs/env.config [env] randomize_attributes
    val_offset: int = 0  # crowd_sim/envs/crowd_sim.py reset, counter_offset['val']
    test_offset: int = 1000  # crowd_sim/envs/crowd_sim.py reset, counter_offset['test'] = case_capacity['val']
    train_offset: int = 2000  # crowd_sim/envs/crowd_sim.py reset, counter_offset['train'] = val + test capacity
    val_size: int = 100  # crowd_nav/configs/env.config [env] val_size (crowd_sim.py case_size['val'])
    test_size: int = 500  # crowd_nav/configs/env.config [env] test_size (crowd_sim.py case_size['test'])
    train_size: int = int(np.iinfo(np.uint32).max) - 2000  # crowd_sim/envs/crowd_sim.py configure, case_size

    def offset(self, phase: str) -> int:
        return {"val": self.val_offset, "test": self.test_offset, "train": self.train_offset}[_phase(phase)]

    def size(self, phase: str) -> int:
        return {"val": self.val_size, "test": self.test_size, "train": self.train_size}[_phase(phase)]


CROWDNAV = CrowdNavFacts()

_SCENARIOS = {"circle": "circle", "circle_crossing": "circle", "square": "square", "square_crossing": "square"}


def _phase(phase: str) -> str:
    if phase not in ("train", "val", "test"):
        raise ValueError(f"phase must be 'train', 'val' or 'test', got {phase!r}")
    return phase


def _scenario(scenario: str) -> str:
    try:
        return _SCENARIOS[scenario]
    except KeyError:
        raise ValueError(f"scenario must be one of {sorted(_SCENARIOS)}, got {scenario!r}") from None


def _too_close(x, y, others, radius: float, discomfort: float) -> bool:
    """True if (x, y) is closer than ``radius + r + discomfort`` to any (ox, oy, r) in ``others``."""
    for ox, oy, r in others:
        if np.linalg.norm((x - ox, y - oy)) < radius + r + discomfort:
            return True
    return False


def _debug_case(f: CrowdNavFacts) -> dict:
    starts = np.array([[0.0, -6.0], [-5.0, -5.0], [5.0, -5.0]])
    goals = np.array([[0.0, 5.0], [-5.0, 5.0], [5.0, 5.0]])
    return {
        "human_start": starts,
        "human_goal": goals,
        "human_radius": np.full(3, f.human_radius),
        "human_v_pref": np.full(3, f.human_v_pref),
    }


def crowdnav_case(
    case: int,
    scenario: str = "circle",
    n_humans: int = 5,
    phase: str = "test",
    *,
    randomize_attributes: bool = False,
) -> dict:
    """The initial state of CrowdNav's ``reset(phase, test_case=case)`` with ``n_humans`` humans.

    Placed by a compiled rejection sampler (:mod:`crowdbench.envs.case_kernel`, driven by :class:`_Run`)
    with the same draws in the same order and the same accept/reject decisions and values as
    :func:`reference_case` (one candidate at a time, as CrowdNav does); ``randomize_attributes`` takes
    that reference path.

    Returns float64 arrays ``robot_start [2]``, ``robot_goal [2]``, ``human_start [n, 2]``,
    ``human_goal [n, 2]``, ``human_radius [n]``, ``human_v_pref [n]``, the scalars ``robot_theta``,
    ``seed`` (the ``np.random.seed`` argument, ``None`` for the debug case -1), ``case``, ``phase``,
    ``scenario`` and ``n_draws`` (uniform draws consumed), and per scenario the accepted draws:
    circle ``human_angle [n]`` and ``human_noise [n, 2]`` (start = circle_radius * (cos, sin) + noise);
    square ``human_sign [n]`` (+1: start at x >= 0, goal at x <= 0; -1: the reverse).
    """
    if randomize_attributes:
        return reference_case(case, scenario, n_humans, phase, randomize_attributes=True)
    f = CROWDNAV
    phase = _phase(phase)
    scen = _scenario(scenario)
    case, n = int(case), int(n_humans)
    if n < 0 or case < 0:
        return reference_case(case, scenario, n_humans, phase)  # the errors and the fixed debug case
    seed = f.offset(phase) + case
    r, v = f.human_radius, f.human_v_pref
    run = _Run(_seeded(seed), scen, n, r, v)
    starts, goals = run.place()
    out = {"robot_start": run.robot_start, "robot_goal": run.robot_goal, "robot_theta": f.robot_theta,
           "case": case, "phase": phase, "scenario": scen, "human_start": starts, "human_goal": goals,
           "human_radius": np.full(n, r), "human_v_pref": np.full(n, v), "seed": seed, "n_draws": run.used}
    if scen == "circle":  # the accepted candidates' draws, with CrowdNav's operations (angle, nx, ny)
        out.update(human_angle=run.acc[:, 0] * np.pi * 2, human_noise=(run.acc[:, 1:] - 0.5) * v)
    else:
        out["human_sign"] = run.signs
    return out


# candidate position from its draws, with CrowdNav's scalar operations in CrowdNav's order
def _circle_xy(d, v_pref: float) -> tuple[float, float]:
    angle = d[0] * np.pi * 2
    return CROWDNAV.circle_radius * np.cos(angle) + (d[1] - 0.5) * v_pref, \
        CROWDNAV.circle_radius * np.sin(angle) + (d[2] - 0.5) * v_pref


def _square_xy(d, sign: int) -> tuple[float, float]:
    return d[0] * CROWDNAV.square_width * 0.5 * sign, (d[1] - 0.5) * CROWDNAV.square_width


_RNG = threading.local()


def _seeded(seed: int) -> np.random.RandomState:
    """This thread's RandomState after ``seed(seed)``, which is what CrowdNav's ``np.random.seed`` does to
    the global one; ~60x cheaper than a new ``RandomState(seed)``, which first seeds from OS entropy."""
    rng = getattr(_RNG, "rng", None)
    if rng is None:
        rng = _RNG.rng = np.random.RandomState()
    rng.seed(seed)
    return rng


DRAWS = 3 * 1024  # draws taken at a time: the kernel's buffer is the draws it has not consumed plus these
# CrowdNav's rejection loop never ends when a human cannot be placed (e.g. training case 766005165 of circle
# crossing with 20 humans); no case of the published lists needs more than ~1.8M draws (~0.02 s here)
MAX_DRAWS = 3 * 10 ** 7  # ~4 s of draws here


class UnplaceableCase(ValueError):
    """A case whose humans CrowdNav's rejection sampler does not place within :data:`MAX_DRAWS` draws."""
MARGIN = 1e-9  # m: decisions this close to the threshold are re-made with CrowdNav's own scalar test


class _Run:
    """One case's placement by the compiled sampler (:mod:`crowdbench.envs.case_kernel`): draws in a
    buffer that grows as the kernel asks, and CrowdNav's own test for the candidates it leaves undecided."""

    def __init__(self, rng: np.random.RandomState, scen: str, n: int, r: float, v: float, margin: float = MARGIN):
        f = CROWDNAV
        self.rng, self.scen, self.n, self.r, self.v, self.margin = rng, scen, n, r, v, margin
        self.robot_start, self.robot_goal = np.array([0.0, -f.circle_radius]), np.array([0.0, f.circle_radius])
        self.d = rng.random_sample(DRAWS)
        self.forced_at, self.forced_ok = np.empty(0, np.int64), np.empty(0, np.bool_)
        self.thr = r + r + f.discomfort_dist  # CrowdNav's radius + r + discomfort between two humans
        # others' x, y, (threshold -/+ margin)^2, radius: circle [5, 2n + 2] (the robot's start and goal,
        # then each human's start and goal); square [2 (starts, goals), 5, n + 1] (the robot's first)
        robot_thr = r + f.robot_radius + f.discomfort_dist
        rows = [(0.0, y, (robot_thr - margin) ** 2, (robot_thr + margin) ** 2, f.robot_radius)
                for y in (-f.circle_radius, f.circle_radius)]
        self.o = np.zeros((5, 2 * n + 2) if scen == "circle" else (2, 5, n + 1))
        self.o[..., 4, :] = r
        if scen == "circle":
            self.o[:, :2] = np.array(rows).T
        else:
            self.o[:, :, 0] = rows
        self.acc, self.signs = np.zeros((n, 3)), np.zeros(n)
        self.used = 0

    def place(self) -> tuple[np.ndarray, np.ndarray]:
        """Run the kernel to the end; the humans' starts and goals ``[n, 2]`` (draws consumed: ``used``)."""
        circle, square = kernels()
        i, p, base = 0, 0, 0  # human, draw in the buffer, draws consumed before the buffer
        while True:
            if self.scen == "circle":
                ang = self.d[0::3] * np.pi * 2  # each candidate's angle: draws 0, 3, 6, ... of the buffer
                st, i, p, cand, loop = circle(self.d, np.cos(ang), np.sin(ang), CROWDNAV.circle_radius, self.v,
                                             self.thr, *self.o[:4], self.n, i, p, self.margin, self.forced_at,
                                             self.forced_ok, self.acc)
            else:
                st, i, p, cand, loop = square(self.d, CROWDNAV.square_width, self.thr, self.o[0], self.o[1], self.n,
                                             i, p, self.margin, self.forced_at, self.forced_ok, self.signs)
            if st == DONE:
                break
            if st == MORE:  # keep the draws from the resume point on, add fresh ones
                self.d = np.concatenate((self.d[p:], self.rng.random_sample(DRAWS)))
                keep = self.forced_at >= p
                self.forced_at, self.forced_ok = self.forced_at[keep] - p, self.forced_ok[keep]
                base, p = base + p, 0
                if base > MAX_DRAWS:
                    raise UnplaceableCase(f"CrowdNav's {self.scen} crossing with {self.n} humans: human {i} not placed "
                                          f"within {MAX_DRAWS:,} draws")
            else:
                self._decide(i, p, cand, loop)
        self.used = base + p
        if self.scen == "circle":
            return self.o[:2, 2::2].T.copy(), self.o[:2, 3::2].T.copy()
        return self.o[0, :2, 1:].T.copy(), self.o[1, :2, 1:].T.copy()

    def _decide(self, i: int, begin: int, cand: int, loop: int) -> None:
        """CrowdNav's own test (:func:`_too_close`) for the candidate drawn at ``cand`` of human ``i``."""
        d = [float(x) for x in self.d[cand:cand + 3]]
        if loop == CIRCLE:
            px, py = _circle_xy(d, self.v)
            o = self.o[:, :2 * i + 2]
        else:
            sign = -1 if self.d[begin] > 0.5 else 1
            px, py = _square_xy(d, sign if loop == SQUARE_START else -sign)
            o = self.o[0 if loop == SQUARE_START else 1, :, :i + 1]
        free = not _too_close(px, py, [(x, y, rr) for x, y, _, _, rr in o.T], self.r, CROWDNAV.discomfort_dist)
        self.forced_at = np.append(self.forced_at, cand)
        self.forced_ok = np.append(self.forced_ok, free)


def reference_case(
    case: int,
    scenario: str = "circle",
    n_humans: int = 5,
    phase: str = "test",
    *,
    randomize_attributes: bool = False,
) -> dict:
    """:func:`crowdnav_case` one candidate at a time, CrowdNav's loop transcribed: the reference the
    batched path is tested against, and the path of ``randomize_attributes``."""
    f = CROWDNAV
    phase = _phase(phase)
    scen = _scenario(scenario)
    case = int(case)
    n = int(n_humans)
    if n < 0:
        raise ValueError(f"n_humans must be >= 0, got {n}")
    robot_start = (0, -f.circle_radius)  # CrowdNav sets px = int 0
    robot_goal = (0, f.circle_radius)
    out = {
        "robot_start": np.array(robot_start, dtype=np.float64),
        "robot_goal": np.array(robot_goal, dtype=np.float64),
        "robot_theta": f.robot_theta,
        "case": case,
        "phase": phase,
        "scenario": scen,
    }
    if case < 0:
        if case == -1 and phase == "test":
            out.update(_debug_case(f), seed=None, n_draws=0)
            return out
        raise ValueError(f"CrowdNav has no case {case} in phase {phase!r} (only test case -1 is defined)")

    seed = f.offset(phase) + case
    rng = np.random.RandomState(seed)
    draws = 0

    def u() -> float:
        nonlocal draws
        draws += 1
        return rng.random_sample()

    # (x, y, radius) of the agents placed so far: their starts and their goals
    placed_starts = [(robot_start[0], robot_start[1], f.robot_radius)]
    placed_goals = [(robot_goal[0], robot_goal[1], f.robot_radius)]
    starts = np.zeros((n, 2))
    goals = np.zeros((n, 2))
    radii = np.full(n, f.human_radius)
    v_prefs = np.full(n, f.human_v_pref)
    angles = np.zeros(n)
    noises = np.zeros((n, 2))
    signs = np.zeros(n)
    for i in range(n):
        radius, v_pref = f.human_radius, f.human_v_pref
        if randomize_attributes:
            v_pref = rng.uniform(0.5, 1.5)
            radius = rng.uniform(0.3, 0.5)
            draws += 2
        if scen == "circle":
            others = placed_starts + placed_goals
            while True:
                angle = u() * np.pi * 2
                nx = (u() - 0.5) * v_pref
                ny = (u() - 0.5) * v_pref
                px = f.circle_radius * np.cos(angle) + nx
                py = f.circle_radius * np.sin(angle) + ny
                if not _too_close(px, py, others, radius, f.discomfort_dist):
                    break
            gx, gy = -px, -py
            angles[i], noises[i] = angle, (nx, ny)
        else:
            sign = -1 if u() > 0.5 else 1
            while True:
                px = u() * f.square_width * 0.5 * sign
                py = (u() - 0.5) * f.square_width
                if not _too_close(px, py, placed_starts, radius, f.discomfort_dist):
                    break
            while True:
                gx = u() * f.square_width * 0.5 * -sign
                gy = (u() - 0.5) * f.square_width
                if not _too_close(gx, gy, placed_goals, radius, f.discomfort_dist):
                    break
            signs[i] = sign
        starts[i], goals[i], radii[i], v_prefs[i] = (px, py), (gx, gy), radius, v_pref
        placed_starts.append((px, py, radius))
        placed_goals.append((gx, gy, radius))

    out.update(
        human_start=starts, human_goal=goals, human_radius=radii, human_v_pref=v_prefs, seed=seed, n_draws=draws
    )
    if scen == "circle":
        out.update(human_angle=angles, human_noise=noises)
    else:
        out["human_sign"] = signs
    return out


def case_list(
    scenario: str,
    n_humans: int,
    n: int = 500,
    phase: str = "test",
    *,
    randomize_attributes: bool = False,
) -> dict:
    """The first ``n`` episodes of a CrowdNav run of ``phase`` from a fresh env, stacked ``[n, ...]``.

    Episode ``k`` is CrowdNav case ``k % case_size[phase]`` (the counter wraps, ``crowd_sim.py`` line 283),
    given in ``episode``; ``seed`` holds the ``np.random.seed`` arguments. The array entries of
    :func:`crowdnav_case` are stacked; ``scenario``, ``phase`` and ``n_humans`` are kept as scalars.
    """
    size = CROWDNAV.size(phase)
    episodes = np.arange(int(n), dtype=np.int64) % size
    cases = [crowdnav_case(int(c), scenario, n_humans, phase, randomize_attributes=randomize_attributes)
             for c in episodes]
    keys = [k for k, v in cases[0].items() if isinstance(v, np.ndarray)] if cases else []
    out = {k: np.stack([c[k] for c in cases]) for k in keys}
    out["episode"] = episodes
    out["seed"] = np.array([c["seed"] for c in cases], dtype=np.int64)
    out["n_draws"] = np.array([c["n_draws"] for c in cases], dtype=np.int64)
    out.update(scenario=_scenario(scenario), phase=_phase(phase), n_humans=int(n_humans))
    return out
