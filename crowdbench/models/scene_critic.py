"""Centralised critics over the whole scene: a state value (``algo=mappo``; Yu et al. 2022's MAPPO) and an
action value (``algo=matd3``; Ackermann et al. 2019's MATD3).

Agent ``i``'s value reads every body of its environment, with no sensing range, and the other agents'
goals (:meth:`crowdbench.envs.world.World.scene_view`), which its policy never sees: the "global state"
of MAPPO, kept per agent and in the agent's own frame so that one shared-weight network serves every
agent and any number of them. The pooling is SARL's attention (Chen et al. 2019) over all bodies:

    h_e = MLP([own, x_e, |p_e|])                    per body e of the scene
    w_e = softmax_e MLP([h_e, mean_e' h_e'])        over the bodies present
    V   = MLP([own, sum_e w_e h_e])

``forward(robot [*, 6], scene [*, N, 7], scene_mask [*, N]) -> V [*, 1]``. An agent alone in its scene
(every slot masked) pools zero. :class:`SceneQ` is the same network with the agent's own action beside the
pooled scene: ``Q = MLP([own, sum_e w_e h_e, a])`` (each agent's own action: the others' are in the scene as
the velocities they move with).
"""

from __future__ import annotations

import torch
from torch import nn

from crowdbench.models.heads import mlp

OWN, BODY = 6, 7


class SceneCritic(nn.Module):
    extra = 0  # inputs beside the agent's own row and the pooled scene

    def __init__(self, dim: int = 64, hidden: tuple | list = (128, 128)):
        super().__init__()
        self.dim = int(dim)
        self.pair = mlp([OWN + BODY + 1, self.dim, self.dim])
        self.score = mlp([2 * self.dim, self.dim, 1])
        self.value = mlp([OWN + self.dim + self.extra, *hidden, 1])

    def forward(self, robot: torch.Tensor, scene: torch.Tensor, scene_mask: torch.Tensor) -> torch.Tensor:
        return self.value(torch.cat((robot, self.pool(robot, scene, scene_mask)), -1))

    def pool(self, robot: torch.Tensor, scene: torch.Tensor, scene_mask: torch.Tensor) -> torch.Tensor:
        """``sum_e w_e h_e`` ``[*, D]``."""
        own = robot.unsqueeze(-2).expand(*scene.shape[:-1], OWN)
        dist = scene[..., :2].norm(dim=-1, keepdim=True)
        h = torch.relu(self.pair(torch.cat((own, scene, dist), -1)))  # [*, N, D]
        m = scene_mask.unsqueeze(-1).to(h.dtype)
        mean = (h * m).sum(-2) / m.sum(-2).clamp_min(1.0)
        score = self.score(torch.cat((h, mean.unsqueeze(-2).expand_as(h)), -1)).squeeze(-1)
        # a finite floor, not -inf: an empty scene gives a uniform softmax that the mask then zeroes
        w = torch.softmax(score.masked_fill(~scene_mask, -1e9), -1).unsqueeze(-1) * m
        return (w * h).sum(-2)


class SceneQ(SceneCritic):
    """``Q(s, a) = MLP([own, pooled scene, a])`` ``[*, 1]`` for ``forward(robot, scene, scene_mask, action)``."""

    extra = 2

    def forward(self, robot, scene, scene_mask, action) -> torch.Tensor:
        pooled = self.pool(robot, scene, scene_mask)
        return self.value(torch.cat((robot, pooled, action.to(robot.dtype)), -1))
