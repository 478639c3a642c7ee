"""Self-play: ``A`` learning agents per environment with their own goals, optional replayed background.

Every agent is a robot of the single-robot protocol (radius ``robot_radius``, holonomic,
``v_max``); all act at once from one ``[B, A, 2]`` action tensor. The world
(:mod:`crowdbench.envs.world`, ``interact=True``) makes the agents bodies for each other:
agent-agent collisions, the nearest-body danger penalty, done agents that vanish or stay as
obstacles (``done_agents``) and the ``A + M``-slot observation.

Scenarios (:func:`sample_episodes`; ``mixed``: each episode is one of the two, 50/50): ``circle`` (agents evenly spaced on a circle of
``circle_radius`` around the centre with a random rotation, goals at the antipodes, each
point jittered by up to ``jitter`` m per axis) and ``square`` (each agent starts on a random
side of a ``square_width`` square and heads for a random point of the opposite side; starts,
and goals, are at least ``min_spacing`` m apart). With ``background=<scene>`` the agents
are placed around that scene's centre and its pedestrians are replayed (they never react),
starting at a random time where no start point is within ``START_CLEARANCE`` of a human.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from crowdbench.config_fields import bounded
from crowdbench.data.scenes import Scene
from crowdbench.envs.humans.reactive import CROWDS
from crowdbench.envs.rules import START_CLEARANCE, SimConfig, check_seed, free_start, int_option
from crowdbench.envs.world import DONE_AGENTS

SCENARIOS = ("circle", "square", "mixed")


@dataclass
class SelfPlayConfig(SimConfig):
    """``env=selfplay``'s settings, with their bounds: also its schema."""

    n_agents: int = bounded(8, ge=1)
    scenario: str = bounded("circle", choices=SCENARIOS)  # mixed: each episode one of the two, 50/50
    circle_radius: float = bounded(4.0, gt=0)  # m
    square_width: float = bounded(8.0, gt=0)  # m, side of the square (start and goal sides are this far apart)
    jitter: float = bounded(0.1, ge=0)  # m, uniform noise per axis on every start and goal
    # m, square crossing: min distance between starts (and between goals), before jitter
    min_spacing: float = bounded(0.8, gt=0)
    background: str = ""  # scene name of replayed ETH/UCY background humans; "" = none
    done_agents: str = bounded("vanish", choices=DONE_AGENTS)
    n_humans: int = bounded(0, ge=0)  # reactive humans placed by the scenario like extra agents (not with a background)
    humans: str = bounded("orca", choices=tuple(CROWDS))  # their model
    robot_visible: bool = True  # whether they see (and avoid) the learning agents
    human_v_pref: float = bounded(1.0, gt=0)  # m/s
    # each agent observes its obs_slots nearest bodies (0 = every slot): the observation, and the graph an
    # encoder builds from it, stay linear in the number of agents (World.observe)
    obs_slots: int = bounded(0, ge=0)
    # square crossing of more agents than the sides hold (n * min_spacing > 2 * width): widen the square to
    # fit them and lengthen the time limit in proportion (the same time per metre of side), instead of failing
    scale_geometry: bool = False

    def __post_init__(self):
        super().__post_init__()  # every field's bounds
        if self.scale_geometry and self.scenario != "circle":
            need = (self.n_agents + self.n_humans) * self.min_spacing / 2
            if need > self.square_width:  # (idempotent: a scaled config is not scaled again by replace())
                self.time_limit = math.ceil(self.time_limit * need / self.square_width)
                self.square_width = need
        gap = 2 * self.circle_radius * math.sin(math.pi / self.n_agents) - 2 * math.sqrt(2) * self.jitter
        if self.scenario != "square" and self.n_agents > 1 and gap <= 2 * self.robot_radius:
            raise ValueError(f"{self.n_agents} agents do not fit on a circle of radius {self.circle_radius} m "
                             f"(neighbours {gap:.2f} m apart at worst, need > {2 * self.robot_radius}); "
                             "raise env.circle_radius")
        if self.scenario != "circle" and self.n_agents * self.min_spacing > 2 * self.square_width:
            # random sequential placement on the 4 sides jams well before they are full
            raise ValueError(f"{self.n_agents} agents {self.min_spacing} m apart do not fit on the sides of a "
                             f"{self.square_width} m square (need n * min_spacing <= 2 * width); "
                             "raise env.square_width or set env.scale_geometry=true")
        if self.min_spacing <= 2 * self.robot_radius:
            raise ValueError(f"min_spacing must exceed two robot radii ({2 * self.robot_radius} m)")
        if self.n_humans:
            if self.background:
                raise ValueError("env.n_humans (reactive humans) and env.background (replayed humans) exclude "
                                 "each other in self-play")
            replace(self, n_agents=self.n_agents + self.n_humans, n_humans=0)  # agents and humans must fit


def sample_episodes(n: int, cfg: SelfPlayConfig, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` episodes of ``cfg.scenario``: start and goal ``[n, A, 2]`` relative to the scene centre."""
    A = cfg.n_agents
    u = lambda *s: torch.rand(*s, generator=gen)
    if cfg.scenario != "square":
        ang = u(n, 1) * 2 * math.pi + torch.arange(A) * (2 * math.pi / A)
        ring = cfg.circle_radius * torch.stack((ang.cos(), ang.sin()), -1)
        start, goal = ring, -ring
    if cfg.scenario == "square":
        start, goal = _square(n, cfg, gen)
    elif cfg.scenario == "mixed":  # (the circle and square streams above stay those of the pure scenarios)
        sq_start, sq_goal = _square(n, cfg, gen)
        pick = u(n, 1, 1) < 0.5
        start, goal = torch.where(pick, sq_start, start), torch.where(pick, sq_goal, goal)
    start = start + cfg.jitter * (2 * u(n, A, 2) - 1)
    goal = goal + cfg.jitter * (2 * u(n, A, 2) - 1)
    return start, goal


def _square(n: int, cfg: SelfPlayConfig, gen: torch.Generator, tries: int = 500,
            restarts: int = 20) -> tuple[torch.Tensor, torch.Tensor]:
    """Random start/goal pairs on opposite sides of the square, ``min_spacing`` apart.

    Sequential rejection, vectorised over environments and agents (the loop is over attempts):
    every agent whose start or goal is too close to a lower-numbered agent's redraws both. Each attempt
    tests only the episodes that redrew an agent in the one before: the same draws as testing all.
    An episode still unplaced after ``tries`` attempts is jammed (its earlier agents leave no gap wide
    enough: it happens at 32 agents on the widened square, once in a training run's ~30,000 episodes)
    and is drawn again from scratch, up to ``restarts`` times; an episode placed within ``tries``
    draws what it always drew, so the published lists are unchanged.
    """
    A, half = cfg.n_agents, cfg.square_width / 2
    earlier = torch.ones(A, A, dtype=torch.bool).tril(-1)  # [i, j]: j < i

    def draw(k: int):
        side = torch.randint(0, 4, (k,), generator=gen)  # 0: x=-h, 1: x=+h, 2: y=-h, 3: y=+h
        along_s = (2 * torch.rand(k, generator=gen) - 1) * half
        along_g = (2 * torch.rand(k, generator=gen) - 1) * half
        sign = torch.where(side % 2 == 0, -half, half)
        vertical = (side < 2).unsqueeze(-1)  # start on a vertical side: x fixed
        s = torch.where(vertical, torch.stack((sign, along_s), -1), torch.stack((along_s, sign), -1))
        g = torch.where(vertical, torch.stack((-sign, along_g), -1), torch.stack((along_g, -sign), -1))
        return s, g

    start, goal = (x.view(n, A, 2) for x in draw(n * A))
    todo = torch.arange(n)  # the episodes that redrew an agent last time (the others cannot have a bad one)
    for restart in range(restarts + 1):
        if restart:  # the jammed episodes start again
            start[todo], goal[todo] = (x.view(len(todo), A, 2) for x in draw(len(todo) * A))
        for _ in range(tries):
            s, g = start[todo], goal[todo]
            close = torch.zeros(len(todo), A, A, dtype=torch.bool)
            for pts in (s, g):
                close |= (pts.unsqueeze(1) - pts.unsqueeze(2)).norm(dim=-1) < cfg.min_spacing
            bad = (close & earlier).any(-1)  # [len(todo), A], in the order of the full [n, A] mask
            k = int(bad.sum())
            if k == 0:
                return start, goal
            s[bad], g[bad] = draw(k)
            start[todo], goal[todo] = s, g
            todo = todo[bad.any(-1)]
    raise ValueError(f"could not place {A} agents {cfg.min_spacing} m apart in {tries} tries, {restarts} times "
                     "from scratch; raise env.square_width or lower env.min_spacing")


class SelfPlayScenario:
    """Self-play episodes: ``cfg.scenario`` placements around the background scene's centre (or the origin)."""

    name = "selfplay"

    def __init__(self, cfg: SelfPlayConfig, scene: Scene | None = None):
        self.cfg, self.scene, self.A = cfg, scene, cfg.n_agents
        self.centre = scene.centre.clone() if scene is not None else torch.zeros(2)
        self.last_start = scene.last_start(cfg.time_limit) if scene is not None else 0
        self.r_ah = cfg.robot_radius + cfg.human_radius

    def draw(self, n: int, gen: torch.Generator, tries: int = 50) -> dict[str, torch.Tensor]:
        """``n`` random episodes: ``start``, ``goal`` ``[n, A, 2]`` (world frame) and background start index ``t0``."""
        A, H = self.A, self.cfg.n_humans
        if H:  # the humans are placed as extra agents, at random places among them
            start, goal = sample_episodes(n, replace(self.cfg, n_agents=A + H, n_humans=0), gen)
            order = torch.rand(n, A + H, generator=gen).argsort(-1).unsqueeze(-1).expand(n, A + H, 2)
            start, goal = start.gather(1, order), goal.gather(1, order)
            return {"start": start[:, :A], "goal": goal[:, :A], "human_start": start[:, A:], "human_goal": goal[:, A:],
                    "t0": torch.zeros(n, dtype=torch.long)}
        start, goal = sample_episodes(n, self.cfg, gen)
        start, goal = start + self.centre, goal + self.centre
        t0 = torch.zeros(n, dtype=torch.long)
        if self.scene is not None and n > 0:
            todo = torch.ones(n, dtype=torch.bool)
            for _ in range(tries):  # a start time where no agent starts on top of a pedestrian
                idx = todo.nonzero().squeeze(-1)
                if len(idx) == 0:
                    break
                t = torch.randint(0, self.last_start + 1, (len(idx),), generator=gen)
                free = free_start(self.scene, t.repeat_interleave(self.A), start[idx].reshape(-1, 2), START_CLEARANCE,
                                  self.r_ah).view(len(idx), self.A).all(-1)
                t0[idx] = t
                todo[idx[free]] = False
            # after `tries` a few crowded starts may remain (a collision at step 1)
        return {"start": start, "goal": goal, "t0": t0}

    def with_options(self, episode: dict, options: dict) -> dict[str, torch.Tensor]:
        """One drawn episode with PettingZoo ``reset`` options ``start``/``goal`` (``[A, 2]``, world frame)
        and ``t0`` (background start index) applied."""
        episode = dict(episode)
        for key in ("start", "goal"):
            if key in options:
                try:
                    value = torch.as_tensor(options[key], dtype=torch.float32)
                except (TypeError, ValueError, RuntimeError):
                    value = None
                if value is None or value.shape != (self.A, 2):
                    raise ValueError(f"options[{key!r}] must be {self.A} points [x, y] (one per agent), "
                                     f"got {options[key]!r}")
                if not torch.isfinite(value).all():
                    raise ValueError(f"options[{key!r}] must be finite")
                episode[key] = value.view(1, self.A, 2)
        if "t0" in options:
            episode["t0"] = torch.tensor([int_option(options, "t0", 0, 2**63)], dtype=torch.long)
        return episode

    def sampler(self, seed: int) -> EpisodeSampler:
        return EpisodeSampler(self, seed)


class EpisodeSampler:
    """Seeded stream of self-play episodes (a ``torch.Generator``), with ``state_dict`` for checkpoints."""

    def __init__(self, scenario: SelfPlayScenario, seed: int = 0):
        self.scenario = scenario
        self.gen = torch.Generator().manual_seed(check_seed(seed))

    def __call__(self, n: int) -> dict[str, torch.Tensor]:
        return self.scenario.draw(n, self.gen)

    def state_dict(self) -> dict:
        return {"rng": self.gen.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.gen.set_state(state["rng"])


def background_scene(cfg: SelfPlayConfig) -> Scene | None:
    from crowdbench.envs.scenarios import replay_scene

    return replay_scene(cfg.background, cfg) if cfg.background else None


def episode_set(cfg: SelfPlayConfig, n: int, seed: int, scene: Scene | None = None) -> dict[str, torch.Tensor]:
    """The fixed evaluation set: ``n`` episodes drawn from ``seed`` (same arguments, same episodes)."""
    scene = background_scene(cfg) if scene is None else scene
    return SelfPlayScenario(cfg, scene).draw(n, torch.Generator().manual_seed(int(seed)))
