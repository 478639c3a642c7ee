"""A tiny external encoder: the worked example of docs/submitting.md.

It lives outside the ``crowdbench`` package; a leaderboard submission ships a copy next to its
``submission.yaml`` and names it with ``encoder_import: tiny_encoder:TinyEncoder`` (or through the
``crowdbench.encoders`` entry-point group of an installed package) and the harness registers it into
``crowdbench.models.ENCODERS`` before loading the checkpoint.

The encoder interface (crowdbench/models/encoder.py) needs only ``out_dim`` and
``forward(robot, humans, humans_mask) -> (h_nodes [*, N, D], robot_h [*, D])``.
This one is deliberately simple: the robot state, the mean of the observed humans' features
and their count, through one hidden layer.
"""

from __future__ import annotations

import torch
from torch import nn

from crowdbench.models.graph import unpack_obs


class TinyEncoder(nn.Module):
    def __init__(self, dim: int = 16):
        super().__init__()
        self.out_dim = dim
        self.net = nn.Sequential(nn.Linear(6 + 4 + 1, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.last_gates = None  # no attention to visualise

    def forward(self, robot, humans=None, humans_mask=None):
        robot, humans, humans_mask = unpack_obs(robot, humans, humans_mask)
        m = humans_mask.to(humans.dtype).unsqueeze(-1)  # [*, M, 1]
        count = m.sum(-2)  # [*, 1]
        mean = (humans * m).sum(-2) / count.clamp_min(1.0)  # [*, 4]
        h = self.net(torch.cat((robot, mean, count / 10.0), -1))
        return h.unsqueeze(-2), h
