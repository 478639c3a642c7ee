"""Batched self-play simulator: ``B`` environments, ``A`` learning agents each, optional replayed background.

Every agent is a robot of the single-robot protocol (radius ``robot_radius``, holonomic,
``v_max``) with its own goal; all agents act at once (one ``[B, A, 2]`` action tensor). The
geometry is core's (:mod:`crowdbench.envs.core`): surface clearance, swept collision test over
the step's linear motion of *both* bodies (:func:`segment_min_distance`), danger
``0 <= d < danger_dist``, success within ``robot_radius`` of the goal, reward of SPEC section 3.

Self-play additions:

- agent-agent clearance ``d = |p_i - p_j| - 2 robot_radius``; a swept ``d < 0`` during a step
  is a collision of *both* agents (``StepInfo.extra["pair_collision"]`` ``[B, A, A]``);
- the danger penalty uses the nearest body, agent or background human;
- an agent that succeeds, collides or times out is *done*: it no longer moves and gets zero
  reward, while the other agents go on; tensors keep their ``[B, A]`` shape (masked, not
  removed). ``done_agents="vanish"`` (default): a done agent leaves the scene (others
  neither sense it nor collide with it, like a pedestrian leaving through its goal);
  ``"obstacle"``: it stays where it stopped as a static body that is sensed and can be hit;
- observation of agent ``i`` is the single-robot layout (:mod:`crowdbench.envs.policy`):
  its own row ``robot [B, A, 6]`` and ``humans [B, A, S, 4]`` with ``S = A + M`` slots, the
  ``A`` agents first (its own slot and absent agents masked out), then the ``M`` background
  humans; so one shared-weight graph policy sees every other agent as a neighbour node.

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
from dataclasses import dataclass

import torch

from crowdbench.data.scenes import Scene, load_scene
from crowdbench.envs.core import (
    _FAR,
    RUNNING,
    START_CLEARANCE,
    TIMEOUT,
    SimConfig,
    StepInfo,
    clip_speed,
    free_start,
    heading_to,
    outcome_of,
    segment_min_distance,
    step_reward,
    to_local,
    to_world,
)

SCENARIOS = ("circle", "square", "mixed")
DONE_AGENTS = ("vanish", "obstacle")


@dataclass
class SelfPlayConfig(SimConfig):
    n_agents: int = 8
    scenario: str = "circle"  # circle | square | mixed (each episode one of the two, 50/50)
    circle_radius: float = 4.0  # m
    square_width: float = 8.0  # m, side of the square (start and goal sides are this far apart)
    jitter: float = 0.1  # m, uniform noise per axis on every start and goal
    min_spacing: float = 0.8  # m, square crossing: min distance between starts (and between goals), before jitter
    background: str = ""  # scene name of replayed ETH/UCY background humans; "" = none
    done_agents: str = "vanish"  # vanish | obstacle

    def __post_init__(self):
        super().__post_init__()
        if self.scenario not in SCENARIOS:
            raise ValueError(f"unknown self-play scenario {self.scenario!r}; valid: {', '.join(SCENARIOS)}")
        if self.done_agents not in DONE_AGENTS:
            raise ValueError(f"unknown done_agents {self.done_agents!r}; valid: {', '.join(DONE_AGENTS)}")
        if self.n_agents < 1:
            raise ValueError(f"n_agents must be >= 1, got {self.n_agents}")
        gap = 2 * self.circle_radius * math.sin(math.pi / self.n_agents) - 2 * math.sqrt(2) * self.jitter
        if self.scenario != "square" and self.n_agents > 1 and gap <= 2 * self.robot_radius:
            raise ValueError(f"{self.n_agents} agents do not fit on a circle of radius {self.circle_radius} m "
                             f"(neighbours {gap:.2f} m apart at worst, need > {2 * self.robot_radius}); "
                             "raise env.circle_radius")
        if self.scenario != "circle" and self.n_agents * self.min_spacing > 2 * self.square_width:
            # random sequential placement on the 4 sides jams well before they are full
            raise ValueError(f"{self.n_agents} agents {self.min_spacing} m apart do not fit on the sides of a "
                             f"{self.square_width} m square (need n * min_spacing <= 2 * width); "
                             "raise env.square_width")
        if self.min_spacing <= 2 * self.robot_radius:
            raise ValueError(f"min_spacing must exceed two robot radii ({2 * self.robot_radius} m)")


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


def _square(n: int, cfg: SelfPlayConfig, gen: torch.Generator, tries: int = 500) -> tuple[torch.Tensor, torch.Tensor]:
    """Random start/goal pairs on opposite sides of the square, ``min_spacing`` apart.

    Sequential rejection, vectorised over environments and agents (the loop is over attempts):
    every agent whose start or goal is too close to a lower-numbered agent's redraws both.
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
    for _ in range(tries):
        close = torch.zeros(n, A, A, dtype=torch.bool)
        for pts in (start, goal):
            close |= (pts.unsqueeze(1) - pts.unsqueeze(2)).norm(dim=-1) < cfg.min_spacing
        bad = (close & earlier).any(-1)  # [n, A]
        k = int(bad.sum())
        if k == 0:
            return start, goal
        start[bad], goal[bad] = draw(k)
    raise ValueError(f"could not place {A} agents {cfg.min_spacing} m apart in {tries} tries; "
                     "raise env.square_width or lower env.min_spacing")


class SelfPlaySim:
    """``B`` self-play environments with ``A = cfg.n_agents`` agents and an optional background scene."""

    def __init__(self, batch_size: int, cfg: SelfPlayConfig | None = None, scene: Scene | None = None):
        self.cfg = cfg = cfg or SelfPlayConfig()
        if scene is None and cfg.background:
            scene = load_scene(cfg.background, cfg.dt, cfg.time_base)
        self.scene = scene
        if scene is not None:
            if abs(cfg.dt - scene.dt) > 1e-9:
                raise ValueError(f"scene resampled at dt={scene.dt}, simulator dt={cfg.dt}")
            if scene.n_steps <= cfg.time_limit + 1:
                raise ValueError(f"scene {scene.name} is shorter than the time limit ({cfg.time_limit} steps)")
        B, A = batch_size, cfg.n_agents
        self.B, self.A = B, A
        self.Mb = scene.max_humans if scene is not None else 0  # background humans
        self.M = A + self.Mb  # observed "human" slots per agent
        self.centre = scene.centre.clone() if scene is not None else torch.zeros(2)
        self.t = torch.zeros(B, dtype=torch.long)
        self.steps = torch.zeros(B, dtype=torch.long)
        self.pos = torch.zeros(B, A, 2)
        self.vel = torch.zeros(B, A, 2)
        self.goal = torch.zeros(B, A, 2)
        self.start = torch.zeros(B, A, 2)
        self.heading = torch.zeros(B, A, 2)
        self.heading[..., 0] = 1.0
        self.outcome = torch.full((B, A), TIMEOUT, dtype=torch.long)  # not started = finished
        self.eye = torch.eye(A, dtype=torch.bool)
        self.r_aa = 2 * cfg.robot_radius
        self.r_ah = cfg.robot_radius + cfg.human_radius

    # ------------------------------------------------------------------ episodes
    @property
    def last_start(self) -> int:
        return self.scene.last_start(self.cfg.time_limit) if self.scene is not None else 0

    def draw(self, n: int, gen: torch.Generator, tries: int = 50):
        """``n`` random episodes: start, goal ``[n, A, 2]`` (world frame) and background start index ``[n]``."""
        start, goal = sample_episodes(n, self.cfg, gen)
        start, goal = start + self.centre, goal + self.centre
        t0 = torch.zeros(n, dtype=torch.long)
        if self.scene is None or n == 0:
            return start, goal, t0
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
        return start, goal, t0  # after `tries` a few crowded starts may remain (a collision at step 1)

    def reset(self, mask: torch.Tensor, start: torch.Tensor, goal: torch.Tensor, t0: torch.Tensor | None = None):
        """Reset the environments where ``mask`` ([B] bool) is set; ``start``/``goal`` ``[B, A, 2]`` world frame."""
        t0 = torch.zeros(self.B, dtype=torch.long) if t0 is None else t0
        if self.scene is not None and ((t0[mask] < 0).any() or (t0[mask] > self.last_start).any()):
            raise ValueError(f"start index outside [0, {self.last_start}] for scene {self.scene.name}")
        m2 = mask.view(-1, 1, 1)
        self.t = torch.where(mask, t0, self.t)
        self.steps = torch.where(mask, 0, self.steps)
        self.start = torch.where(m2, start, self.start)
        self.pos = torch.where(m2, start, self.pos)
        self.goal = torch.where(m2, goal, self.goal)
        self.vel = torch.where(m2, 0.0, self.vel)
        self.outcome = torch.where(mask.view(-1, 1), RUNNING, self.outcome)
        self._update_heading()

    def _update_heading(self) -> None:
        self.heading = heading_to(self.goal, self.pos, self.heading)

    # ------------------------------------------------------------------ bodies
    def present(self) -> torch.Tensor:
        """``[B, A]``: agents that are bodies in the scene (running, or done and kept as obstacles)."""
        if self.cfg.done_agents == "obstacle":
            return torch.ones_like(self.outcome, dtype=torch.bool)
        return self.outcome == RUNNING

    def _pair_mask(self, present: torch.Tensor) -> torch.Tensor:
        """``[B, A, A]``: agent ``j`` is a body agent ``i`` can meet (not itself)."""
        return present.unsqueeze(1) & ~self.eye

    def humans(self, t: torch.Tensor | None = None):
        t = self.t if t is None else t
        if self.scene is None:
            z = torch.zeros(self.B, 0, 2)
            return z, z, torch.zeros(self.B, 0, dtype=torch.bool)
        return self.scene.pos[t], self.scene.vel[t], self.scene.valid[t]

    def agent_clearance(self, pos: torch.Tensor | None = None) -> torch.Tensor:
        """``[B, A, A]`` surface gaps between agents (``_FAR`` for itself and absent agents)."""
        pos = self.pos if pos is None else pos
        gap = (pos.unsqueeze(1) - pos.unsqueeze(2)).norm(dim=-1) - self.r_aa
        return gap.masked_fill(~self._pair_mask(self.present()), _FAR)

    def min_clearance(self) -> torch.Tensor:
        """Current clearance to the nearest body (agent or human), ``[B, A]``."""
        hpos, _, hvalid = self.humans()
        gap = ((hpos.unsqueeze(1) - self.pos.unsqueeze(2)).norm(dim=-1) - self.r_ah).masked_fill(
            ~hvalid.unsqueeze(1), _FAR)
        return torch.cat((self.agent_clearance(), gap), -1).amin(-1)

    def clip_action(self, action: torch.Tensor) -> torch.Tensor:
        return clip_speed(action, self.cfg.v_max)

    # ------------------------------------------------------------------ step
    def step(self, action: torch.Tensor, frame: str | None = None) -> StepInfo:
        """Advance every running agent by one step; ``action`` ``[B, A, 2]`` in the observation frame.

        ``extra``: ``pair_collision`` ``[B, A, A]`` (agent pairs that collided during the step),
        ``agent_clearance`` ``[B, A]`` (end-of-step gap to the nearest other agent, for the
        agent-agent danger metric) and ``human_clearance`` ``[B, A]``.
        """
        if torch.isnan(action).any():
            raise ValueError("action contains NaN")
        cfg = self.cfg
        frame = frame or cfg.frame
        act = to_world(action.unsqueeze(-2), self.heading).squeeze(-2) if frame == "rotate" else action
        active = self.outcome == RUNNING  # [B, A]
        vel = self.clip_action(act) * active.unsqueeze(-1)
        new_pos = self.pos + vel * cfg.dt
        env_active = active.any(-1)

        # agents: both bodies move linearly over the step (a done obstacle does not move)
        pair = self._pair_mask(self.present()) & active.unsqueeze(-1)  # [B, i, j]: i can hit j
        rel0 = self.pos.unsqueeze(1) - self.pos.unsqueeze(2)  # [B, i, j, 2] = p_j - p_i
        rel1 = new_pos.unsqueeze(1) - new_pos.unsqueeze(2)
        swept_aa = (segment_min_distance(rel0, rel1) - self.r_aa).masked_fill(~pair, _FAR)
        end_aa = (rel1.norm(dim=-1) - self.r_aa).masked_fill(~pair, _FAR)
        pair_hit = swept_aa < 0
        pair_hit = pair_hit | pair_hit.transpose(1, 2) & active.unsqueeze(-1)  # both agents of a running pair

        # background humans present at t1, moving from their previous position (as in core)
        if self.scene is not None:
            t1 = torch.where(env_active, self.t + 1, self.t)
            h1, hv1, h0 = self.scene.pos[t1], self.scene.valid[t1], self.scene.prev[t1]
            swept_h = (segment_min_distance(h0.unsqueeze(1) - self.pos.unsqueeze(2), h1.unsqueeze(1) - new_pos.unsqueeze(2))
                       - self.r_ah).masked_fill(~hv1.unsqueeze(1), _FAR).amin(-1)
            end_h = ((h1.unsqueeze(1) - new_pos.unsqueeze(2)).norm(dim=-1) - self.r_ah).masked_fill(
                ~hv1.unsqueeze(1), _FAR).amin(-1)
        else:
            t1 = self.t
            swept_h = end_h = torch.full((self.B, self.A), _FAR)
        agent_end = end_aa.amin(-1) if self.A > 1 else torch.full((self.B, self.A), _FAR)
        swept_a = swept_aa.amin(-1) if self.A > 1 else agent_end
        end = torch.minimum(agent_end, end_h)
        swept = torch.minimum(swept_a, swept_h)

        steps = self.steps + env_active.long()
        collision = active & (pair_hit.any(-1) | (swept_h < 0))
        success = active & ~collision & ((self.goal - new_pos).norm(dim=-1) < cfg.robot_radius)
        timeout = active & ~collision & ~success & (steps >= cfg.time_limit).unsqueeze(-1)

        reward = step_reward(cfg, end, success, collision | timeout, active)
        outcome = outcome_of(success, collision, timeout)
        self.outcome = torch.where(active, outcome, self.outcome)
        self.pos, self.vel, self.t, self.steps = new_pos, vel, t1, steps
        self._update_heading()
        return StepInfo(reward=reward, terminated=success | collision, truncated=timeout, outcome=outcome,
                        clearance=end, swept_clearance=swept, active=active,
                        extra={"pair_collision": pair_hit, "agent_clearance": agent_end, "human_clearance": end_h})

    # ------------------------------------------------------------------ observation
    def observe(self, frame: str | None = None) -> dict[str, torch.Tensor]:
        """Each agent's view in its own frame: ``robot [B, A, 6]``, ``humans [B, A, A+M, 4]``, ``humans_mask``.

        Slots ``0..A-1`` are the agents (agent ``i``'s own slot is always masked), then the
        background humans. Same layout and frames as :meth:`CrowdSim.observe`.
        """
        frame = frame or self.cfg.frame
        B, A, S = self.B, self.A, self.M
        hpos, hvel, hvalid = self.humans()
        opos = torch.cat((self.pos, hpos), 1)  # [B, S, 2] every body
        ovel = torch.cat((self.vel, hvel), 1)
        ovalid = torch.cat((self.present(), hvalid), 1)
        rel = opos.unsqueeze(1) - self.pos.unsqueeze(2)  # [B, A, S, 2]
        seen = ovalid.unsqueeze(1) & ((rel * rel).sum(-1) <= self.cfg.sensing_range**2)
        seen[:, :, :A] &= ~self.eye
        if frame == "world":
            rel = opos.unsqueeze(1).expand(B, A, S, 2)
        vel = ovel.unsqueeze(1).expand(B, A, S, 2)
        own = torch.stack((self.vel, self.goal - self.pos if frame != "world" else self.goal), -2)  # [B, A, 2, 2]
        if frame == "rotate":
            rel, vel, own = to_local(rel, self.heading), to_local(vel, self.heading), to_local(own, self.heading)
        humans = torch.cat((rel, vel), -1) * seen.unsqueeze(-1)
        pos = self.pos if frame == "world" else torch.zeros_like(self.pos)
        robot = torch.cat((pos, own.reshape(B, A, 4)), -1)
        return {"robot": robot, "humans": humans, "humans_mask": seen}


class EpisodeSampler:
    """Seeded stream of self-play episodes (a ``torch.Generator``), with ``state_dict`` for checkpoints."""

    def __init__(self, sim: SelfPlaySim, seed: int = 0):
        self.sim = sim
        self.gen = torch.Generator().manual_seed(int(seed))

    def __call__(self, n: int):
        return self.sim.draw(n, self.gen)

    def state_dict(self) -> dict:
        return {"rng": self.gen.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.gen.set_state(state["rng"])


def episode_set(cfg: SelfPlayConfig, n: int, seed: int, scene: Scene | None = None):
    """The fixed evaluation set: ``n`` episodes drawn from ``seed`` (same arguments, same episodes)."""
    sim = SelfPlaySim(1, cfg, scene)
    return sim.draw(n, torch.Generator().manual_seed(int(seed)))
