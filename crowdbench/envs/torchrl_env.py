"""TorchRL ``EnvBase`` over the batched world: the one env of every scenario and crowd model.

All ``B`` environments live in one env with ``batch_size=[B]``; agent keys sit under the
``agents`` group (``[B, A, ...]``: one robot in the robot protocols, ``A`` agents in self-play),
with per-agent ``reward``, ``done``, ``terminated``, ``truncated`` ``[B, A, 1]``. A per-agent done
is *sticky*: it stays set (with zero reward and a frozen agent) until its environment resets,
which happens when every agent of it is done (root ``done`` ``[B, 1]``; root ``terminated`` if all
agents terminated). ``info``: ``outcome`` (each agent's status: RUNNING until it finishes, then its
outcome), ``clearance`` (end-of-step gap to the nearest body), ``goal_dist`` (distance to the goal,
read by :class:`~crowdbench.envs.transforms.ProgressReward`) and, in self-play,
``agent_clearance``. Partial resets follow TorchRL's ``_reset`` mask; episodes come from the
scenario's seeded sampler (training) or, in order, from a fixed list (evaluation). Training-only
shaping and human dropout are transforms (:mod:`crowdbench.envs.transforms`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Unbounded
from torchrl.envs import EnvBase

from crowdbench.envs.observation import GROUP
from crowdbench.envs.rules import COLLISION, RUNNING, SUCCESS, StepInfo
from crowdbench.envs.specs import torchrl_specs
from crowdbench.envs.world import World


class CrowdEnv(EnvBase):
    """``B`` environments of one :class:`World`; build one with :func:`crowdbench.envs.factory.make_env`.

    Args:
        world: the batched world (its batch size is the env's).
        scenario: places episodes; ``scenario.sampler(seed)`` is the training stream.
        seed: seed of that stream.
        episodes: optional fixed list (a dict of ``[E, ...]`` episode tensors, as ``scenario.from_list``
            gives): episode ``i`` goes to the ``i``-th environment that resets; wraps around.
    """

    batch_locked = True

    def __init__(self, world: World, scenario, seed: int = 0, episodes: dict[str, torch.Tensor] | None = None):
        super().__init__(batch_size=torch.Size([world.B]), device="cpu")
        self.world, self.scenario = world, scenario
        self.cfg = world.cfg
        self.sampler = scenario.sampler(seed)
        self.episodes = episodes
        self._next_episode = 0
        self._last: TensorDict | None = None
        self.last_info: StepInfo | None = None  # the world's record of the last step (evaluation reads it)
        self._make_specs()

    @property
    def n_agents(self) -> int:
        return self.world.A

    def _make_specs(self) -> None:
        B, A = self.batch_size[0], self.world.A
        info = {"outcome": Categorical(4, (B, A), dtype=torch.long), "clearance": Unbounded((B, A)),
                "goal_dist": Unbounded((B, A))}
        if self.world.interact:
            info["agent_clearance"] = Unbounded((B, A))
        for name, spec in torchrl_specs(B, A, self.world.M, self.cfg.v_max, info).items():
            setattr(self, name, spec)

    # ------------------------------------------------------------------ episodes
    def _draw(self, n: int) -> dict[str, torch.Tensor]:
        if self.episodes is None:
            return self.sampler(n)
        E = len(self.episodes["start"])
        idx = (self._next_episode + torch.arange(n)) % E
        self._next_episode += n
        return {k: v[idx] for k, v in self.episodes.items()}

    def _output(self, clearance: torch.Tensor, agent_clearance: torch.Tensor | None,
                observation: dict | None = None) -> TensorDict:
        B, A, w = self.batch_size[0], self.world.A, self.world
        status = w.outcome.clone()
        term = ((status == SUCCESS) | (status == COLLISION)).unsqueeze(-1)
        done = (status != RUNNING).unsqueeze(-1)
        info = {"outcome": status, "clearance": clearance, "goal_dist": (w.goal - w.pos).norm(dim=-1)}
        if w.interact:
            info["agent_clearance"] = agent_clearance
        agents = TensorDict({"observation": w.observe() if observation is None else observation, "info": info,
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
        self.world.reset(mask, self._draw(int(mask.sum())))
        agent_clear = self.world.nearest_agent() if self.world.interact else None
        observation = None
        if self._last is not None and not mask.all():
            # only the reset environments' views change (the others' are those of the last step): new
            # tensors, since the last step's are the caller's
            rows = mask.nonzero().squeeze(-1)
            observation = self._last[GROUP, "observation"].clone()
            for key, value in self.world.observe(rows=rows).items():
                observation[key][rows] = value
        self._last = self._output(self.world.min_clearance(), agent_clear, observation)
        return self._last.clone()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict[GROUP, "action"]
        want = (*self.batch_size, self.world.A, 2)
        if tuple(action.shape) != want:  # a third component would be ignored, one too few an IndexError
            raise ValueError(f"action must have shape {list(want)} ([vx, vy] per agent), got {list(action.shape)}")
        if action.dtype != torch.float32:  # float64 would promote the world's state (and break the spec) for good
            action = action.to(torch.float32)
        info = self.world.step(action)
        self.last_info = info
        out = self._output(info.clearance, info.extra.get("agent_clearance"))
        out[GROUP].set("reward", info.reward.unsqueeze(-1))
        self._last = out.exclude((GROUP, "reward"))
        return out

    def _set_seed(self, seed: int | None) -> None:
        self.sampler = self.scenario.sampler(0 if seed is None else seed)
