"""Straight-to-goal: the no-avoidance lower bound."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from crowdbench.envs.observation import OBS, Policy


class StraightToGoal(Policy):
    """Head straight for the goal at ``v_max``, slowing down so as not to overshoot it."""

    name = "straight"

    def __init__(self, v_max: float = 1.0, dt: float = 0.25):
        self.v_max, self.dt = v_max, dt

    def act(self, td: TensorDict) -> torch.Tensor:
        robot = td[OBS + ("robot",)]
        to_goal = robot[..., 4:6] - robot[..., 0:2] if self.frame == "world" else robot[..., 4:6]
        dist = to_goal.norm(dim=-1, keepdim=True)
        speed = torch.minimum(dist / self.dt, torch.full_like(dist, self.v_max))
        return to_goal / dist.clamp_min(1e-9) * speed
