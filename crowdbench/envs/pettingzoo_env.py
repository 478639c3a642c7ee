"""PettingZoo ``ParallelEnv`` view over the batched :class:`CrowdSim` core.

A thin single-instance view (``B = 1``): no physics of its own, every step is one
:meth:`CrowdSim.step` on a ``[1, A, 2]`` action tensor and every observation is one
:meth:`CrowdSim.observe` (same layout as :mod:`crowdbench.envs.policy`, minus the batch and
agent dimensions). Agent ``i`` of the core is named ``"robot_{i}"``.

Per agent:

- observation: ``Dict`` with ``robot`` ``Box(6,)`` ``[px, py, vx, vy, gx, gy]``, ``humans``
  ``Box(M, 4)`` ``[px, py, vx, vy]`` (zero where unobserved) and ``humans_mask`` ``Box(M,)``
  with values in ``{0, 1}`` (1 = present and within the sensing range); all ``float32``,
  in the config's frame (``rotate`` by default). ``M`` is the scene's maximum crowd size.
- action: ``Box(-v_max, v_max, (2,), float32)``, velocity ``[vx, vy]`` in the observation
  frame. Out-of-range actions are *not* rejected: the core clips each component to
  ``[-v_max, v_max]`` and then the speed to ``v_max``. A NaN action raises ``ValueError``.
- reward: python ``float`` (SPEC section 3); termination on success or collision,
  truncation on timeout (``cfg.time_limit`` steps). A finished agent leaves ``self.agents``.
- info: ``outcome`` (``running`` / ``success`` / ``collision`` / ``timeout``), ``clearance``
  (min clearance at the end of the step, 1e6 when no human is present) and
  ``swept_clearance`` (min clearance over the step's motion, the collision criterion).

Episodes: ``reset(seed=s)`` re-seeds a :class:`TrainSampler` (random start time and angle,
the training distribution), so two resets with the same seed give the same episode;
``reset()`` without a seed draws the next episode from the current sampler (seeded from OS
entropy if the env was never seeded, as in Gymnasium). ``options={"t0": int, "angle": float}``
picks the episode explicitly (either key alone overrides only that part of the draw);
other option keys are ignored.
"""

from __future__ import annotations

import secrets
from typing import ClassVar

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from crowdbench.data.scenes import load_scene
from crowdbench.envs.core import OUTCOMES, CrowdSim, SimConfig
from crowdbench.envs.protocol import TRAIN_SCENE, TrainSampler
from crowdbench.envs.specs import gym_spaces


class CrowdParallelEnv(ParallelEnv):
    """Robot(s) navigating among replayed ETH/UCY pedestrians; one environment, ``A`` agents."""

    metadata: ClassVar[dict] = {"name": "crowdbench_v0", "render_modes": []}

    def __init__(
        self, scene: str = TRAIN_SCENE, cfg: SimConfig | None = None, render_mode: str | None = None
    ):
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} not supported; valid: None")
        self.render_mode = render_mode
        self.cfg = cfg or SimConfig()
        self.scene = load_scene(scene, self.cfg.dt, self.cfg.time_base)  # ValueError on unknown scene
        self.sim = CrowdSim(self.scene, batch_size=1, cfg=self.cfg)
        self.possible_agents = [f"robot_{i}" for i in range(self.sim.A)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._sampler: TrainSampler | None = None
        self._mask = torch.ones(1, dtype=torch.bool)
        self.episode: dict = {}  # t0 and angle of the current episode

        self.observation_spaces, self.action_spaces = gym_spaces(self.possible_agents, self.sim.M, self.cfg.v_max)

    # ------------------------------------------------------------------ spaces
    # the dicts hold one space object per agent, so every call returns the same object
    # (the PettingZoo API test checks identity; action-space seeding relies on it)
    def observation_space(self, agent: str) -> spaces.Dict:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[agent]

    # ------------------------------------------------------------------ episodes
    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._sampler = TrainSampler(self.sim.last_start, seed, self.sim.start_is_free)
        elif self._sampler is None:
            self._sampler = TrainSampler(self.sim.last_start, secrets.randbits(63), self.sim.start_is_free)
        t0, angle = self._sampler(1)  # always drawn, so the sampler stream does not depend on options
        options = options or {}
        if "t0" in options:
            t0 = torch.tensor([int(options["t0"])], dtype=torch.long)
        if "angle" in options:
            angle = torch.tensor([float(options["angle"])], dtype=torch.float64)
        self.sim.reset(self._mask, t0, angle)  # ValueError if t0 is out of range
        self.agents = self.possible_agents[:]
        self.episode = {"t0": int(t0[0]), "angle": float(angle[0])}

        hpos, _, hvalid = self.sim.humans()
        clearance = self.sim.clearance(self.sim.pos, hpos, hvalid).amin(-1)[0].tolist()
        infos = {
            a: {"outcome": "running", "clearance": clearance[i], "swept_clearance": clearance[i]}
            | self.episode
            for a, i in self._index.items()
        }
        return self._observe(self.agents), infos

    def step(self, actions: dict):
        if not self.agents:
            raise RuntimeError("step() called with no live agents; call reset() first")
        unknown = set(actions) - set(self.possible_agents)
        if unknown:
            raise ValueError(f"actions for unknown agents {sorted(unknown)}; agents: {self.possible_agents}")
        act = torch.zeros(1, self.sim.A, 2)
        for agent in self.agents:  # actions given for finished agents are ignored (the core freezes them)
            if agent not in actions:
                raise ValueError(f"missing action for live agent {agent!r}")
            a = np.asarray(actions[agent], dtype=np.float32)
            if a.size != 2:
                raise ValueError(f"action for {agent!r} must have 2 elements [vx, vy], got shape {a.shape}")
            if np.isnan(a).any():
                raise ValueError(f"action for {agent!r} contains NaN: {a.reshape(2).tolist()}")
            act[0, self._index[agent]] = torch.from_numpy(a.reshape(2))

        info = self.sim.step(act)
        live = self.agents
        reward = info.reward[0].tolist()
        term = info.terminated[0].tolist()
        trunc = info.truncated[0].tolist()
        outcome = info.outcome[0].tolist()
        clear = info.clearance[0].tolist()
        swept = info.swept_clearance[0].tolist()

        obs = self._observe(live)
        rewards, terminations, truncations, infos = {}, {}, {}, {}
        for agent in live:
            i = self._index[agent]
            rewards[agent] = reward[i]
            terminations[agent] = term[i]
            truncations[agent] = trunc[i]
            infos[agent] = {
                "outcome": OUTCOMES.get(outcome[i], "running"),
                "clearance": clear[i],
                "swept_clearance": swept[i],
            }
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        return obs, rewards, terminations, truncations, infos

    def _observe(self, agents: list[str]) -> dict[str, dict[str, np.ndarray]]:
        o = self.sim.observe()
        robot = o["robot"][0].numpy()
        humans = o["humans"][0].numpy()
        mask = o["humans_mask"][0].to(torch.float32).numpy()
        return {
            a: {"robot": robot[i], "humans": humans[i], "humans_mask": mask[i]}
            for a, i in ((a, self._index[a]) for a in agents)
        }

    # ------------------------------------------------------------------ misc
    def render(self):
        gymnasium.logger.warn(
            "CrowdParallelEnv has no render modes yet (render_mode=None); render() does nothing"
        )

    def close(self):
        pass
