"""Scenarios: where agents start, where they go, and where the crowd starts.

A scenario turns an episode description into the tensors :meth:`World.reset` takes (``start``,
``goal`` ``[n, A, 2]`` plus the crowd model's keys) and owns the seeded training stream
(a sampler with ``state_dict`` for checkpoints). Fixed evaluation lists are built by the same
scenario, so training and evaluation place episodes with one piece of code.

- :class:`ReplayScenario`: protocol v1 (SPEC section 3): one robot starts on a circle of
  ``start_radius`` around the scene centre and heads for the antipode, at a scene time ``t0``
  where no pedestrian is within ``START_CLEARANCE`` of the start point.
- self-play circle / square / mixed: :class:`crowdbench.envs.selfplay.SelfPlayScenario`.
- CrowdNav circle / square crossing: :class:`crowdbench.envs.crowdnav.CrowdNavScenario`.
"""

from __future__ import annotations

import math
import numbers

import torch

from crowdbench.data.scenes import Scene, load_scene, playback_scene
from crowdbench.envs.protocol import TrainSampler
from crowdbench.envs.rules import START_CLEARANCE, SimConfig, free_start, int_option

VAL_SEED = 2**31 - 1  # the validation stream's seed (training seeds are small integers)
VAL_EPISODES = 100  # as CrowdNav's validation set


def replay_scene(name: str, cfg: SimConfig) -> Scene:
    """Scene ``name`` resampled at ``cfg.dt``; an error if it is too short for one episode."""
    scene = load_scene(name, cfg.dt, cfg.time_base)  # ValueError on an unknown scene
    if scene.n_steps <= cfg.time_limit + 1:
        raise ValueError(f"scene {scene.name} is shorter than the time limit ({cfg.time_limit} steps)")
    return scene


def replay_scene_at(name: str, cfg: SimConfig, speeds: tuple[float, ...]) -> Scene:
    """Scene ``name`` replayed at each playback speed of ``speeds`` (``train.playback_speeds``; training only):
    :func:`~crowdbench.data.scenes.playback_scene`."""
    scene = playback_scene(name, cfg.dt, speeds, cfg.time_limit, cfg.time_base)
    if not bool(scene.starts.any()):
        raise ValueError(f"scene {scene.name} at playback speeds {list(speeds)} leaves no part longer than the time limit")
    return scene


class ReplayScenario:
    """Protocol v1 episodes ``(t0, angle)`` on a replayed scene; ``n_agents`` robots share start and goal."""

    name = "replay"

    def __init__(self, scene: Scene, cfg: SimConfig, n_agents: int = 1):
        self.scene, self.cfg, self.A = scene, cfg, n_agents
        self.last_start = scene.last_start(cfg.time_limit)
        self.radius_sum = cfg.robot_radius + cfg.human_radius

    def start_goal(self, angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Start and goal on the ``start_radius`` circle around the scene centre, diametrically opposed."""
        u = torch.stack((torch.cos(angle), torch.sin(angle)), -1)
        c = self.scene.centre
        return c + self.cfg.start_radius * u, c - self.cfg.start_radius * u

    def start_is_free(self, t0: torch.Tensor, angle: torch.Tensor, margin: float = START_CLEARANCE) -> torch.Tensor:
        return free_start(self.scene, t0, self.start_goal(angle.to(torch.float32))[0], margin, self.radius_sum)

    def episodes(self, t0: torch.Tensor, angle: torch.Tensor) -> dict[str, torch.Tensor]:
        """``[n]`` start indices and angles -> the world's episode tensors (float32 points, as the lists)."""
        start, goal = self.start_goal(angle.to(torch.float32))
        A = self.A
        return {"start": start.unsqueeze(1).expand(-1, A, 2), "goal": goal.unsqueeze(1).expand(-1, A, 2),
                "t0": t0.long(), "angle": angle}

    def from_list(self, rows: list[dict]) -> dict[str, torch.Tensor]:
        """A saved protocol list's rows (``t0``, ``angle``) as episode tensors."""
        return self.episodes(torch.tensor([e["t0"] for e in rows]),
                             torch.tensor([e["angle"] for e in rows], dtype=torch.float64))

    def with_options(self, episode: dict, options: dict) -> dict[str, torch.Tensor]:
        """One drawn episode with PettingZoo ``reset`` options ``t0`` (int) and ``angle`` (rad) applied."""
        t0, angle = episode["t0"], episode["angle"]
        if "t0" in options:  # (its range against the scene: World.reset)
            t0 = torch.tensor([int_option(options, "t0", 0, 2**63)], dtype=torch.long)
        if "angle" in options:
            a = options["angle"]
            if isinstance(a, bool) or not isinstance(a, numbers.Real) or not math.isfinite(float(a)):
                raise ValueError(f"options['angle'] must be a finite number, got {a!r}")
            angle = torch.tensor([float(options["angle"])], dtype=torch.float64)
        return self.episodes(t0, angle)

    def sampler(self, seed: int) -> ReplaySampler:
        return ReplaySampler(self, seed)

    def test_list(self, phase: str = "val") -> dict[str, torch.Tensor]:
        """``phase="val"``: :data:`VAL_EPISODES` episodes of the training scene drawn from a stream no training
        seed uses (``algo=value``'s network selection; never the evaluation scenes). The evaluation lists are
        the protocol's (crowdbench/protocols/lists.py)."""
        if phase != "val":
            raise ValueError(f"a replay scenario has only the 'val' list (the protocol's lists are the test), got {phase!r}")
        return self.sampler(VAL_SEED)(VAL_EPISODES)


class ReplaySampler:
    """The training distribution: random start time and angle (:class:`TrainSampler`), occupied starts redrawn."""

    def __init__(self, scenario: ReplayScenario, seed: int):
        self.scenario = scenario
        self.draws = TrainSampler(scenario.last_start, seed, scenario.start_is_free)

    def __call__(self, n: int) -> dict[str, torch.Tensor]:
        return self.scenario.episodes(*self.draws(n))

    def state_dict(self) -> dict:
        return self.draws.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.draws.load_state_dict(state)
