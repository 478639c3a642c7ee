"""Crowd models that do not react: recorded ETH/UCY tracks replayed, and an empty crowd.

A crowd model owns the humans' state. The world asks it for the humans now (:meth:`observe`)
and to advance one step (:meth:`advance`: positions at the start and at the end of the step,
and who is present at the end), after it has decided the agents' motion.
"""

from __future__ import annotations

import torch

from crowdbench.data.scenes import Scene


class ReplayCrowd:
    """Humans replayed from a :class:`Scene` (they never see the robot). Episode key: ``t0`` ``[n]``,
    the scene grid index at which the episode starts."""

    name = "replay"

    def __init__(self, scene: Scene, batch: int, time_limit: int):
        self.scene, self.M = scene, scene.max_humans
        self.last_start = scene.last_start(time_limit)
        self.t = torch.zeros(batch, dtype=torch.long)
        # [B, M] or None: training-only thinning (algo=value's algo.thin): a slot that is False is absent
        # from the episode (not seen, not hit); evaluation never sets it
        self.keep: torch.Tensor | None = None

    def reset(self, mask: torch.Tensor, idx: torch.Tensor, episode: dict) -> None:
        t0 = episode["t0"].long()
        if (t0 < 0).any() or (t0 > self.last_start).any():
            raise ValueError(f"start index outside [0, {self.last_start}] for scene {self.scene.name}")
        self.t[idx] = t0

    def observe(self):
        return self.scene.pos[self.t], self.scene.vel[self.t], self._valid(self.t)

    def advance(self, env_active: torch.Tensor, agents=None):
        # humans present at t1, moving from their previous position (their spawn point if they just appeared)
        t1 = torch.where(env_active, self.t + 1, self.t)
        self.t = t1
        return self.scene.prev[t1], self.scene.pos[t1], self._valid(t1)

    def _valid(self, t: torch.Tensor) -> torch.Tensor:
        valid = self.scene.valid[t]
        return valid if self.keep is None else valid & self.keep


class NoCrowd:
    """No humans (self-play among the agents only)."""

    name = "none"
    M = 0

    def __init__(self, batch: int):
        self.t = torch.zeros(batch, dtype=torch.long)
        self._empty = torch.zeros(batch, 0, 2), torch.zeros(batch, 0, 2), torch.zeros(batch, 0, dtype=torch.bool)

    def reset(self, mask: torch.Tensor, idx: torch.Tensor, episode: dict) -> None:
        pass

    def observe(self):
        return self._empty

    def advance(self, env_active: torch.Tensor, agents=None):
        z, _, v = self._empty
        return z, z, v
