"""A centralised state-value critic over the whole scene (``algo=mappo``; Yu et al. 2022's MAPPO).

Agent ``i``'s value reads every body of its environment, with no sensing range, and the other agents'
goals (:meth:`crowdbench.envs.world.World.scene_view`), which its policy never sees: the "global state"
of MAPPO, kept per agent and in the agent's own frame so that one shared-weight network serves every
agent and any number of them. The pooling is SARL's attention (Chen et al. 2019) over all bodies:

    h_e = MLP([own, x_e, |p_e|])                    per body e of the scene
    w_e = softmax_e MLP([h_e, mean_e' h_e'])        over the bodies present
    V   = MLP([own, sum_e w_e h_e])

``forward(robot [*, 6], scene [*, N, 7], scene_mask [*, N]) -> V [*, 1]``. An agent alone in its scene
(every slot masked) pools zero.
"""

from __future__ import annotations

import torch
from torch import nn

from crowdbench.models.heads import mlp

OWN, BODY = 6, 7


class SceneCritic(nn.Module):
    def __init__(self, dim: int = 64, hidden: tuple | list = (128, 128)):
        super().__init__()
        self.dim = int(dim)
        self.pair = mlp([OWN + BODY + 1, self.dim, self.dim])
        self.score = mlp([2 * self.dim, self.dim, 1])
        self.value = mlp([OWN + self.dim, *hidden, 1])

    def forward(self, robot: torch.Tensor, scene: torch.Tensor, scene_mask: torch.Tensor) -> torch.Tensor:
        own = robot.unsqueeze(-2).expand(*scene.shape[:-1], OWN)
        dist = scene[..., :2].norm(dim=-1, keepdim=True)
        h = torch.relu(self.pair(torch.cat((own, scene, dist), -1)))  # [*, N, D]
        m = scene_mask.unsqueeze(-1).to(h.dtype)
        mean = (h * m).sum(-2) / m.sum(-2).clamp_min(1.0)
        score = self.score(torch.cat((h, mean.unsqueeze(-2).expand_as(h)), -1)).squeeze(-1)
        # a finite floor, not -inf: an empty scene gives a uniform softmax that the mask then zeroes
        w = torch.softmax(score.masked_fill(~scene_mask, -1e9), -1).unsqueeze(-1) * m
        return self.value(torch.cat((robot, (w * h).sum(-2)), -1))
