"""Self-play environments over :class:`SelfPlaySim`: TorchRL ``EnvBase`` and PettingZoo ``ParallelEnv``.

TorchRL (:class:`SelfPlayEnv`): all ``A`` learning agents in the ``agents`` group, keys
``[B, A, ...]`` exactly as :class:`~crowdbench.envs.torchrl_env.CrowdEnv` (same observation
layout, so the same policies run unchanged), per-agent ``reward``, ``done``, ``terminated``,
``truncated`` ``[B, A, 1]``. A per-agent done is *sticky*: it stays set (with zero reward and
a frozen agent) until its environment resets, which happens when every agent of it is done
(root ``done`` ``[B, 1]``; root ``terminated`` if all agents terminated). ``info/outcome`` is
each agent's status (RUNNING until it finishes, then its final outcome).

PettingZoo (:class:`SelfPlayParallelEnv`): one environment, agents ``agent_0 .. agent_{A-1}``,
a finished agent leaves ``env.agents``.
"""

from __future__ import annotations

import secrets
from typing import ClassVar

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Unbounded
from torchrl.envs import EnvBase

from crowdbench.envs.core import COLLISION, OUTCOMES, RUNNING, SUCCESS
from crowdbench.envs.policy import GROUP
from crowdbench.envs.selfplay import EpisodeSampler, SelfPlayConfig, SelfPlaySim
from crowdbench.envs.specs import gym_spaces, torchrl_specs


class SelfPlayEnv(EnvBase):
    """``B`` self-play environments of ``cfg.n_agents`` agents (TorchRL, one agent group)."""

    batch_locked = True

    def __init__(self, batch: int = 1, cfg: SelfPlayConfig | None = None, seed: int = 0,
                 progress_reward: float = 0.0):
        cfg = cfg or SelfPlayConfig()
        super().__init__(batch_size=torch.Size([batch]), device="cpu")
        self.progress_reward = float(progress_reward)  # training-only shaping, as CrowdEnv's
        self.cfg = cfg
        self.sim = SelfPlaySim(batch, cfg)
        self.sampler = EpisodeSampler(self.sim, seed)
        self._last: TensorDict | None = None
        self._make_specs()

    @property
    def n_agents(self) -> int:
        return self.sim.A

    def _make_specs(self) -> None:
        B, A = self.batch_size[0], self.sim.A
        info = {"outcome": Categorical(4, (B, A), dtype=torch.long), "clearance": Unbounded((B, A)),
                "agent_clearance": Unbounded((B, A))}
        for name, spec in torchrl_specs(B, A, self.sim.M, self.cfg.v_max, info).items():
            setattr(self, name, spec)

    def _output(self, clearance: torch.Tensor, agent_clearance: torch.Tensor) -> TensorDict:
        B, A = self.batch_size[0], self.sim.A
        status = self.sim.outcome.clone()
        term = ((status == SUCCESS) | (status == COLLISION)).unsqueeze(-1)
        done = (status != RUNNING).unsqueeze(-1)
        agents = TensorDict({"observation": self.sim.observe(),
                             "info": {"outcome": status, "clearance": clearance, "agent_clearance": agent_clearance},
                             "done": done, "terminated": term, "truncated": done & ~term}, batch_size=(B, A))
        env_done, env_term = done.all(1), term.all(1)
        return TensorDict({GROUP: agents, "done": env_done, "terminated": env_term, "truncated": env_done & ~env_term},
                          batch_size=(B,))

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        B = self.batch_size[0]
        mask = torch.ones(B, dtype=torch.bool)
        if tensordict is not None and "_reset" in tensordict:
            mask = tensordict["_reset"].reshape(B, -1).any(-1)
        if not mask.any() and self._last is not None:
            # an agent-level "_reset" only (some agents done, no environment done): nothing to reset
            return self._last.clone()
        n = int(mask.sum())
        start, goal = self.sim.start.clone(), self.sim.goal.clone()
        t0 = self.sim.t.clone()
        start[mask], goal[mask], t0[mask] = self.sampler(n)
        self.sim.reset(mask, start, goal, t0)
        clear = self.sim.min_clearance()
        self._last = self._output(clear, self.sim.agent_clearance().amin(-1))
        return self._last.clone()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        before = (self.sim.goal - self.sim.pos).norm(dim=-1)
        info = self.sim.step(tensordict[GROUP, "action"])
        reward = info.reward
        if self.progress_reward:  # c per metre of progress to the goal; done agents do not move: zero
            reward = reward + self.progress_reward * (before - (self.sim.goal - self.sim.pos).norm(dim=-1))
        out = self._output(info.clearance, info.extra["agent_clearance"])
        out[GROUP].set("reward", reward.unsqueeze(-1))
        self._last = out.exclude((GROUP, "reward"))
        return out

    def _set_seed(self, seed: int | None) -> None:
        self.sampler = EpisodeSampler(self.sim, 0 if seed is None else seed)


class SelfPlayParallelEnv(ParallelEnv):
    """PettingZoo view of one self-play environment (``B = 1``); agent ``i`` is ``"agent_{i}"``.

    Observation, action, reward and info per agent as :class:`~crowdbench.envs.pettingzoo_env.CrowdParallelEnv`
    (``humans`` has ``A + M`` rows: the other agents first, then background humans). ``reset(seed=s)``
    re-seeds the episode stream; ``options={"start": [[x, y]] * A, "goal": [[x, y]] * A}`` places
    the agents explicitly (world frame; ``t0`` for the background start index).
    """

    metadata: ClassVar[dict] = {"name": "crowdbench_selfplay_v0", "render_modes": []}

    def __init__(self, cfg: SelfPlayConfig | None = None, render_mode: str | None = None):
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} not supported; valid: None")
        self.render_mode = render_mode
        self.cfg = cfg or SelfPlayConfig()
        self.sim = SelfPlaySim(1, self.cfg)
        self.possible_agents = [f"agent_{i}" for i in range(self.sim.A)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._sampler: EpisodeSampler | None = None
        self.observation_spaces, self.action_spaces = gym_spaces(self.possible_agents, self.sim.M, self.cfg.v_max)

    def observation_space(self, agent: str) -> spaces.Dict:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._sampler = EpisodeSampler(self.sim, seed)
        elif self._sampler is None:
            self._sampler = EpisodeSampler(self.sim, secrets.randbits(63))
        start, goal, t0 = self._sampler(1)  # always drawn: the stream does not depend on options
        options = options or {}
        if "start" in options:
            start = torch.as_tensor(options["start"], dtype=torch.float32).view(1, self.sim.A, 2)
        if "goal" in options:
            goal = torch.as_tensor(options["goal"], dtype=torch.float32).view(1, self.sim.A, 2)
        if "t0" in options:
            t0 = torch.tensor([int(options["t0"])], dtype=torch.long)
        self.sim.reset(torch.ones(1, dtype=torch.bool), start, goal, t0)
        self.agents = self.possible_agents[:]
        clear = self.sim.min_clearance()[0].tolist()
        infos = {a: {"outcome": "running", "clearance": clear[i], "swept_clearance": clear[i]}
                 for a, i in self._index.items()}
        return self._observe(self.agents), infos

    def step(self, actions: dict):
        if not self.agents:
            raise RuntimeError("step() called with no live agents; call reset() first")
        unknown = set(actions) - set(self.possible_agents)
        if unknown:
            raise ValueError(f"actions for unknown agents {sorted(unknown)}; agents: {self.possible_agents}")
        act = torch.zeros(1, self.sim.A, 2)
        for agent in self.agents:  # actions for finished agents are ignored (the core freezes them)
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
        o = self.sim.observe()
        robot, humans = o["robot"][0].numpy(), o["humans"][0].numpy()
        mask = o["humans_mask"][0].to(torch.float32).numpy()
        return {a: {"robot": robot[i], "humans": humans[i], "humans_mask": mask[i]}
                for a, i in ((a, self._index[a]) for a in agents)}

    def render(self):
        gymnasium.logger.warn("SelfPlayParallelEnv has no render modes (render_mode=None); render() does nothing")

    def close(self):
        pass
