"""TorchRL ``EnvBase`` over the batched core: the fast path used for training and evaluation.

All ``B`` environments live in one env with ``batch_size=[B]``; agent keys sit under the
``agents`` group (``[B, A, ...]``) so multi-agent self-play extends the same layout.
Partial resets follow TorchRL's ``_reset`` mask; episodes are drawn by the training
sampler, or taken in order from a fixed episode list (evaluation).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Unbounded
from torchrl.envs import EnvBase

from crowdbench.data.scenes import load_scene
from crowdbench.envs.core import CrowdSim, SimConfig
from crowdbench.envs.policy import GROUP
from crowdbench.envs.protocol import TrainSampler
from crowdbench.envs.specs import torchrl_specs


class CrowdEnv(EnvBase):
    """``B`` robots navigating one replayed scene.

    Args:
        scene: scene name (``crowdbench.data.SCENES``).
        batch: number of parallel environments ``B``.
        cfg: simulator configuration.
        seed: seed of the training sampler (random start time and angle).
        episodes: optional ``(t0 [E], angle [E])``: a fixed list replayed in order
            (episode ``i`` goes to the ``i``-th environment that resets); wraps around.
        progress_reward: training-only shaping ``c * (d_before - d_after)`` per step, ``d`` the
            distance to the goal (0 = the paper's reward, Eq. 1-2). It pays ``c`` per metre of
            progress, so stalling earns nothing (see docs/training.md for why it is needed at
            CPU budgets); evaluation never uses it.
        human_dropout: training-only density randomisation ``p``: each episode draws
            ``u ~ U(0, p)`` and drops each human with probability ``u`` for the whole episode,
            so that a policy trained on the dense students001 also sees sparse crowds (the
            evaluation scenes hotel and eth are sparse). 0 (default) = the paper's training.
    """

    batch_locked = True

    def __init__(self, scene: str = "students001", batch: int = 1, cfg: SimConfig | None = None,
                 seed: int = 0, episodes: tuple[torch.Tensor, torch.Tensor] | None = None,
                 progress_reward: float = 0.0, human_dropout: float = 0.0):
        cfg = cfg or SimConfig()
        super().__init__(batch_size=torch.Size([batch]), device="cpu")
        self.progress_reward = float(progress_reward)
        if not 0.0 <= human_dropout <= 1.0:
            raise ValueError(f"human_dropout must be in [0, 1], got {human_dropout}")
        self.human_dropout = float(human_dropout)
        self._dropout_rng = torch.Generator().manual_seed(seed + 7919)
        self.cfg = cfg
        self.sim = CrowdSim(load_scene(scene, cfg.dt, cfg.time_base), batch, cfg)
        self.sampler = TrainSampler(self.sim.last_start, seed, self.sim.start_is_free)
        self.episodes = episodes
        self._next_episode = 0
        self._make_specs()

    @property
    def n_agents(self) -> int:
        return self.sim.A

    def _make_specs(self) -> None:
        info = {"outcome": Categorical(4, (self.batch_size[0], self.sim.A), dtype=torch.long),
                "clearance": Unbounded((self.batch_size[0], self.sim.A))}
        for name, spec in torchrl_specs(self.batch_size[0], self.sim.A, self.sim.M, self.cfg.v_max, info).items():
            setattr(self, name, spec)

    # ------------------------------------------------------------------ episodes
    def _draw(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self.episodes is None:
            return self.sampler(n)
        t0, angle = self.episodes
        idx = (self._next_episode + torch.arange(n)) % len(t0)
        self._next_episode += n
        return t0[idx], angle[idx]

    def _observation(self, outcome: torch.Tensor, clearance: torch.Tensor) -> TensorDict:
        B, A = self.batch_size[0], self.sim.A
        agents = TensorDict({"observation": self.sim.observe(), "info": {"outcome": outcome, "clearance": clearance}},
                            batch_size=(B, A))
        return TensorDict({GROUP: agents}, batch_size=(B,))

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        B = self.batch_size[0]
        mask = torch.ones(B, dtype=torch.bool)
        if tensordict is not None and "_reset" in tensordict:
            mask = tensordict["_reset"].reshape(B, -1).any(-1)
        t0 = torch.zeros(B, dtype=torch.long)
        angle = torch.zeros(B)
        n = int(mask.sum())
        t0[mask], angle[mask] = self._draw(n)
        keep = None
        if self.human_dropout > 0:  # density randomisation: drop each human with a per-episode u ~ U(0, p)
            u = torch.rand(B, 1, generator=self._dropout_rng) * self.human_dropout
            keep = torch.rand(B, self.sim.M, generator=self._dropout_rng) >= u
        self.sim.reset(mask, t0, angle, keep)
        A = self.sim.A
        out = self._observation(self.sim.outcome.clone(), self.sim.min_clearance())
        false = torch.zeros(B, 1, dtype=torch.bool)
        out.update({"done": false, "terminated": false.clone(), "truncated": false.clone()})
        out[GROUP].update({k: torch.zeros(B, A, 1, dtype=torch.bool) for k in ("done", "terminated", "truncated")})
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        before = (self.sim.goal - self.sim.pos).norm(dim=-1)
        info = self.sim.step(tensordict[GROUP, "action"])
        reward = info.reward
        if self.progress_reward:
            # frozen (finished) agents do not move: their progress is exactly zero
            reward = reward + self.progress_reward * (before - (self.sim.goal - self.sim.pos).norm(dim=-1))
        out = self._observation(info.outcome, info.clearance)
        term, trunc = info.terminated.unsqueeze(-1), info.truncated.unsqueeze(-1)
        out[GROUP].update({"reward": reward.unsqueeze(-1), "terminated": term, "truncated": trunc,
                           "done": term | trunc})
        # an environment is done when all its agents are; truncated if not all terminated
        done, terminated = (term | trunc).all(1), term.all(1)
        out.update({"terminated": terminated, "truncated": done & ~terminated, "done": done})
        return out

    def _set_seed(self, seed: int | None) -> None:
        self.sampler = TrainSampler(self.sim.last_start, 0 if seed is None else seed, self.sim.start_is_free)
