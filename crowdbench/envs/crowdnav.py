"""The CrowdNav protocol (Chen et al., ICRA 2019, "Crowd-Robot Interaction"): one robot crossing a
crowd of ORCA (or social-force) humans, with CrowdNav's settings and its test cases.

- Geometry and settings (``crowd_nav/configs/env.config``): robot and humans of radius 0.3 m,
  ``v_pref`` 1 m/s, ``dt`` 0.25 s, 25 s limit, discomfort distance 0.2 m, reward 1 / -0.25 /
  ``(d - 0.2) * 0.5 * dt`` (:func:`~crowdbench.envs.rules.step_reward`, ``reward: crowdnav``), an invisible
  robot by default (humans ignore it), a robot that observes every human.
- Scenarios: ``circle`` (humans on a 4 m circle, each heading for the opposite point) and ``square``
  (humans crossing a 10 m square between its left and right halves); the robot always goes from
  (0, -4) to (0, 4). Episode ``i`` of the test list is CrowdNav's test case ``i`` with the same
  initial positions and goals (:mod:`crowdbench.envs.crowdnav_cases`, reproduced bit for bit).
- Training draws CrowdNav *training* cases (seeds ``2000 + k``) in a seeded random order.

What differs from CrowdNav's simulator, and why:

- collisions are tested on the actual motion of both bodies over the step; CrowdNav moves the human
  along its *previous* velocity in that test (``crowd_sim.py`` l.331-351), which misses a collision
  whenever the human's new velocity differs;
- a timeout is declared after 100 steps (25 s); CrowdNav's check ``global_time >= time_limit - 1``
  ends episodes from 24 s on and before success is tested (l.368);
- the humans' ORCA is solved for all humans at once; equivalent to CrowdNav's one RVO2 simulator
  per human, because an agent's new velocity depends only on the others' current positions and
  velocities, never on their preferred velocities.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass

import numpy as np
import torch

from crowdbench.config_fields import bounded, rebound
from crowdbench.envs.crowdnav_cases import CROWDNAV, UnplaceableCase, case_list, crowdnav_case
from crowdbench.envs.humans.reactive import CROWDS, ORCA_BACKENDS, SFM_BACKENDS, OrcaParams, reactive_crowd
from crowdbench.envs.rules import SimConfig, check_seed, int_option

SCENARIOS = ("circle", "square")
HUMAN_MODELS = tuple(CROWDS)


@dataclass
class CrowdNavConfig(SimConfig):
    """``env=crowdnav``'s settings (CrowdNav's defaults), with their bounds: also its schema."""

    robot_radius: float = rebound(SimConfig, "robot_radius", CROWDNAV.robot_radius)
    human_radius: float = rebound(SimConfig, "human_radius", CROWDNAV.human_radius)
    danger_dist: float = rebound(SimConfig, "danger_dist", CROWDNAV.discomfort_dist)
    sensing_range: float = rebound(SimConfig, "sensing_range", 100.0)  # m: CrowdNav's robot observes every human
    r_reach: float = rebound(SimConfig, "r_reach", CROWDNAV.success_reward)
    r_fail: float = rebound(SimConfig, "r_fail", CROWDNAV.collision_penalty)
    reward: str = rebound(SimConfig, "reward", "crowdnav")
    discomfort_factor: float = rebound(SimConfig, "discomfort_factor", CROWDNAV.discomfort_penalty_factor)
    scenario: str = bounded("circle", choices=SCENARIOS)
    n_humans: int = bounded(CROWDNAV.human_num, ge=1)
    humans: str = bounded("orca", choices=HUMAN_MODELS)
    robot_visible: bool = CROWDNAV.robot_visible
    human_v_pref: float = bounded(CROWDNAV.human_v_pref, gt=0)
    orca_neighbor_dist: float = bounded(OrcaParams.neighbor_dist, gt=0)
    orca_max_neighbors: int = bounded(OrcaParams.max_neighbors, ge=0)
    orca_time_horizon: float = bounded(OrcaParams.time_horizon, gt=0)
    orca_radius_margin: float = bounded(OrcaParams.radius_margin, ge=0)
    orca_backend: str = bounded(OrcaParams.backend, choices=tuple(ORCA_BACKENDS))  # the same numbers; numba is faster
    # torch (the reference) | numba: faster, within a few float32 ulps (not identical)
    sfm_backend: str = bounded("torch", choices=tuple(SFM_BACKENDS))

    def __post_init__(self):
        super().__post_init__()  # every field's bounds
        if abs(self.dt - CROWDNAV.dt) > 1e-12 or self.v_max != CROWDNAV.robot_v_pref:
            # the case geometry (noise scaled by v_pref, 0.8 m spacing) is CrowdNav's only at its settings
            raise ValueError(f"env=crowdnav fixes dt={CROWDNAV.dt} and v_max={CROWDNAV.robot_v_pref}")

    @property
    def orca(self) -> OrcaParams:
        return OrcaParams(self.orca_neighbor_dist, int(self.orca_max_neighbors), self.orca_time_horizon,
                          self.orca_radius_margin, self.orca_backend)


def crowdnav_crowd(cfg: CrowdNavConfig, batch: int):
    """The crowd model ``cfg.humans`` for ``batch`` environments of ``cfg.n_humans`` humans."""
    return reactive_crowd(cfg, batch, cfg.orca)


def _episodes(cases: dict) -> dict[str, torch.Tensor]:
    """Stacked CrowdNav cases (numpy, :func:`case_list` layout) as the world's episode tensors."""
    f32 = lambda k: torch.from_numpy(np.asarray(cases[k], dtype=np.float32))
    return {"start": f32("robot_start").unsqueeze(1), "goal": f32("robot_goal").unsqueeze(1),
            "human_start": f32("human_start"), "human_goal": f32("human_goal"),
            "case": torch.from_numpy(np.asarray(cases["episode"], dtype=np.int64))}


def _stack(cases: list[dict]) -> dict:
    keys = ("robot_start", "robot_goal", "human_start", "human_goal")
    out = {k: np.stack([c[k] for c in cases]) for k in keys}
    out["episode"] = np.array([c["case"] for c in cases], dtype=np.int64)
    return out


def list_digest(episodes: dict[str, torch.Tensor]) -> str:
    """sha256 of an episode list's tensors: a fixed list is the same bytes on every machine."""
    h = hashlib.sha256()
    for k in sorted(episodes):
        h.update(k.encode())
        h.update(episodes[k].contiguous().numpy().tobytes())
    return h.hexdigest()


@functools.lru_cache(maxsize=16)  # the 500 cases of 20 humans take ~0.3 s (compiled sampler): once per process
def _test_list(scenario: str, n_humans: int, phase: str) -> dict[str, torch.Tensor]:
    return _episodes(case_list(scenario, n_humans, CROWDNAV.size(phase), phase))


class CrowdNavScenario:
    """CrowdNav circle or square crossing; episodes from CrowdNav's case seeding."""

    name = "crowdnav"

    def __init__(self, cfg: CrowdNavConfig):
        self.cfg, self.A = cfg, 1

    def test_list(self, phase: str = "test") -> dict[str, torch.Tensor]:
        """The fixed list of ``phase``: episode ``i`` is CrowdNav's case ``i`` (``case``); 500 test cases,
        100 validation cases (``phase="val"``, what training probes)."""
        return {k: v.clone() for k, v in _test_list(self.cfg.scenario, self.cfg.n_humans, phase).items()}

    def case(self, i: int, phase: str = "test") -> dict:
        """CrowdNav's case ``i`` of ``phase`` for this scenario (:func:`crowdnav_case`)."""
        return crowdnav_case(int(i), self.cfg.scenario, self.cfg.n_humans, phase)

    def cases(self, ids, phase: str = "test") -> dict[str, torch.Tensor]:
        return _episodes(_stack([self.case(i, phase) for i in ids]))

    def with_options(self, episode: dict, options: dict) -> dict[str, torch.Tensor]:
        """PettingZoo ``reset`` option ``case``: CrowdNav's test case of that number."""
        return self.cases([int_option(options, "case", 0, CROWDNAV.test_size)]) if "case" in options else episode

    def sampler(self, seed: int) -> CaseSampler:
        return CaseSampler(self, seed)


class CaseSampler:
    """The training stream: CrowdNav training cases (``phase="train"``) in a seeded random order."""

    def __init__(self, scenario: CrowdNavScenario, seed: int):
        self.scenario = scenario
        self.gen = torch.Generator().manual_seed(check_seed(seed))

    def __call__(self, n: int) -> dict[str, torch.Tensor]:
        ids = torch.randint(0, CROWDNAV.train_size, (n,), generator=self.gen).tolist()
        out = []
        for i in ids:
            while True:  # a case CrowdNav could never place is replaced by the stream's next draw
                try:
                    out.append(self.scenario.case(i, "train"))
                    break
                except UnplaceableCase:
                    i = int(torch.randint(0, CROWDNAV.train_size, (1,), generator=self.gen))
        return _episodes(_stack(out))

    def state_dict(self) -> dict:
        return {"rng": self.gen.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.gen.set_state(state["rng"])
