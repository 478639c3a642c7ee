"""A single-robot Gymnasium env over the PettingZoo view (``gymnasium.make("crowdbench/CrowdNav-v0")``).

Observations are the robot's dict (``robot`` [6], ``humans`` [M, 4], ``humans_mask`` [M]) in the
robot's frame, actions ``[vx, vy]``; the episode ends on success or collision (terminated) or at the
time limit (truncated). Ids and names, and building one by name: crowdbench/envs/registry.py (``gym_env``).
"""

from __future__ import annotations

from typing import ClassVar

import gymnasium


class CrowdGymEnv(gymnasium.Env):
    metadata: ClassVar[dict] = {"render_modes": []}

    def __init__(self, parallel):
        """``parallel``: a one-robot PettingZoo env (crowdbench/envs/pettingzoo_env.py)."""
        if len(parallel.possible_agents) != 1:
            raise ValueError("the Gymnasium env holds one robot; self-play (n agents): api='pettingzoo' or 'torchrl'")
        self.parallel = parallel
        (self.agent,) = self.parallel.possible_agents
        self.observation_space = self.parallel.observation_space(self.agent)
        self.action_space = self.parallel.action_space(self.agent)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, infos = self.parallel.reset(seed=seed, options=options)
        return obs[self.agent], infos[self.agent]

    def step(self, action):
        obs, rewards, terminated, truncated, infos = self.parallel.step({self.agent: action})
        a = self.agent
        return obs[a], float(rewards[a]), bool(terminated[a]), bool(truncated[a]), infos[a]
