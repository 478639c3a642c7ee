"""PettingZoo ``ParallelEnv`` over the batched world: one adapter for every scenario and crowd model.

A thin single-instance view (``B = 1``): no physics of its own, every step is one
:meth:`World.step` on a ``[1, A, 2]`` action tensor and every observation is one
:meth:`World.observe` (the layout of :mod:`crowdbench.envs.observation` minus the batch and agent
dimensions). Agents are ``robot_0 ..`` in the robot protocols and ``agent_0 .. agent_{A-1}`` in
self-play.

Per agent:

- observation: ``Dict`` with ``robot`` ``Box(6,)`` ``[px, py, vx, vy, gx, gy]``, ``humans``
  ``Box(S, 4)`` ``[px, py, vx, vy]`` (zero where unobserved) and ``humans_mask`` ``Box(S,)``
  with values in ``{0, 1}`` (1 = present and within the sensing range); all ``float32``, in the
  config's frame (``rotate`` by default). ``S`` is the crowd's size (plus the agents in self-play).
- action: ``Box(-v_max, v_max, (2,), float32)``, velocity ``[vx, vy]`` in the observation
  frame. Out-of-range actions are *not* rejected: the world clips each component to
  ``[-v_max, v_max]`` and then the speed to ``v_max``. A NaN action raises ``ValueError``.
- reward: python ``float``; termination on success or collision, truncation on timeout
  (``cfg.time_limit`` steps). A finished agent leaves ``self.agents``.
- info: ``outcome`` (``running`` / ``success`` / ``collision`` / ``timeout``), ``clearance``
  (min clearance at the end of the step, 1e6 when nobody is near) and ``swept_clearance``
  (min clearance over the step's motion, the collision criterion); at reset also the episode's
  scalar keys (``t0`` and ``angle`` on a replayed scene, ``case`` in CrowdNav).

Episodes: ``reset(seed=s)`` re-seeds the scenario's training stream, so two resets with the same
seed give the same episode; ``reset()`` without a seed draws the next episode (seeded from OS
entropy if the env was never seeded, as in Gymnasium). ``options`` pick the episode explicitly:
any episode key of the scenario (replay: ``t0``, ``angle``; self-play: ``start``, ``goal``,
``t0``; CrowdNav: ``case``) overrides that part of the draw; other keys are ignored.
"""

from __future__ import annotations

import secrets
from typing import ClassVar

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from crowdbench.envs.rules import OUTCOMES, check_seed
from crowdbench.envs.specs import gym_spaces
from crowdbench.envs.world import World


class CrowdParallelEnv(ParallelEnv):
    """One environment of a :class:`World` (``B = 1``); build one with
    :func:`crowdbench.envs.factory.make_parallel_env`."""

    metadata: ClassVar[dict] = {"name": "crowdbench_v1", "render_modes": []}

    def __init__(self, world: World, scenario, render_mode: str | None = None):
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} not supported; valid: None")
        if world.B != 1:
            raise ValueError(f"the PettingZoo view holds one environment, got a world of {world.B}")
        self.render_mode = render_mode
        self.world, self.scenario, self.cfg = world, scenario, world.cfg
        prefix = "agent" if world.interact else "robot"
        self.possible_agents = [f"{prefix}_{i}" for i in range(world.A)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._sampler = None
        self._mask = torch.ones(1, dtype=torch.bool)
        self.episode: dict = {}  # scalar keys of the current episode
        self.observation_spaces, self.action_spaces = gym_spaces(self.possible_agents, world.M, self.cfg.v_max)

    # the dicts hold one space object per agent, so every call returns the same object
    # (the PettingZoo API test checks identity; action-space seeding relies on it)
    def observation_space(self, agent: str) -> spaces.Dict:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._sampler = self.scenario.sampler(check_seed(seed))
        elif self._sampler is None:
            self._sampler = self.scenario.sampler(secrets.randbits(63))
        episode = self._sampler(1)  # always drawn, so the stream does not depend on options
        if options:
            episode = self.scenario.with_options(episode, options)
        self.world.reset(self._mask, episode)  # ValueError if the episode is invalid (e.g. t0 out of range)
        self.agents = self.possible_agents[:]
        self.episode = {k: v.reshape(-1)[0].item() for k, v in episode.items() if v.numel() == 1}
        clear = self.world.min_clearance()[0].tolist()
        infos = {a: {"outcome": "running", "clearance": clear[i], "swept_clearance": clear[i]} | self.episode
                 for a, i in self._index.items()}
        return self._observe(self.agents), infos

    def step(self, actions: dict):
        if not self.agents:
            raise RuntimeError("step() called with no live agents; call reset() first")
        unknown = set(actions) - set(self.possible_agents)
        if unknown:
            raise ValueError(f"actions for unknown agents {sorted(unknown)}; agents: {self.possible_agents}")
        act = torch.zeros(1, self.world.A, 2)
        for agent in self.agents:  # actions given for finished agents are ignored (the world freezes them)
            if agent not in actions:
                raise ValueError(f"missing action for live agent {agent!r}")
            a = np.asarray(actions[agent], dtype=np.float32)
            if a.size != 2:
                raise ValueError(f"action for {agent!r} must have 2 elements [vx, vy], got shape {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"action for {agent!r} is not finite: {a.reshape(2).tolist()}")
            act[0, self._index[agent]] = torch.from_numpy(a.reshape(2))
        info = self.world.step(act)
        live = self.agents
        reward, term, trunc = info.reward[0].tolist(), info.terminated[0].tolist(), info.truncated[0].tolist()
        outcome, clear, swept = info.outcome[0].tolist(), info.clearance[0].tolist(), info.swept_clearance[0].tolist()
        obs = self._observe(live)
        rewards, terminations, truncations, infos = {}, {}, {}, {}
        for agent in live:
            i = self._index[agent]
            rewards[agent], terminations[agent], truncations[agent] = reward[i], term[i], trunc[i]
            infos[agent] = {"outcome": OUTCOMES.get(outcome[i], "running"), "clearance": clear[i],
                            "swept_clearance": swept[i]}
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        return obs, rewards, terminations, truncations, infos

    def _observe(self, agents: list[str]) -> dict[str, dict[str, np.ndarray]]:
        o = self.world.observe()
        robot, humans = o["robot"][0].numpy(), o["humans"][0].numpy()
        mask = o["humans_mask"][0].to(torch.float32).numpy()
        return {a: {"robot": robot[i], "humans": humans[i], "humans_mask": mask[i]}
                for a, i in ((a, self._index[a]) for a in agents)}

    def render(self):
        gymnasium.logger.warn("CrowdParallelEnv has no render modes (render_mode=None); render() does nothing")

    def close(self):
        pass
