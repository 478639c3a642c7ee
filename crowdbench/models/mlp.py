"""MLP encoder (the DNN-RL baseline, paper Sec. V-D; SPEC section 4).

Input: the robot state followed by the (up to) ``max_humans`` = 40 observed humans
nearest to the robot, each padded to 6 features ``[px, py, vx, vy, 0, 0]``, zero rows for
missing humans: a ``(1 + 40) x 6`` vector, flattened, fed to an MLP with ReLU. Sorting
by distance makes it invariant to the order of the observation's human slots.
``h_nodes`` is ``robot_h`` with a node axis of size 1; ``last_gates`` is ``None``.
"""

from __future__ import annotations

import itertools

import torch
from torch import nn

from crowdbench.models.encoder import SplitEncoder
from crowdbench.models.graph import _gather_rows, flatten_obs, unpack_obs


class MLPEncoder(SplitEncoder):
    def __init__(self, dim: int = 256, hidden: tuple | list = (256, 256), max_humans: int = 40):
        super().__init__()
        self.out_dim = dim
        self.max_humans = max_humans
        sizes = [(1 + max_humans) * 6, *hidden, dim]
        mods: list[nn.Module] = []
        for i, o in itertools.pairwise(sizes):
            mods += [nn.Linear(i, o), nn.ReLU()]
        self.net = nn.Sequential(*mods)
        self.last_gates = None

    def features(self, robot, humans=None, humans_mask=None) -> torch.Tensor:
        """The ``[B*, (1 + max_humans) * 6]`` input vectors and the leading shape."""
        robot, humans, humans_mask = unpack_obs(robot, humans, humans_mask)
        robot, humans, mask, lead = flatten_obs(robot, humans, humans_mask)
        _b, m = mask.shape
        d2 = (humans[..., 0:2] - robot[:, None, 0:2]).square().sum(-1)
        key = torch.where(mask, d2, float("inf"))
        kk = min(self.max_humans, m)
        val, idx = torch.topk(key, kk, dim=-1, largest=False, sorted=True)
        near = _gather_rows(humans, idx) * (val < float("inf")).unsqueeze(-1)  # [B, kk, 4]
        near = torch.nn.functional.pad(near, (0, 2, 0, self.max_humans - kk))  # [B, 40, 6]
        return torch.cat((robot, near.flatten(1)), -1), lead

    def forward(self, robot, humans=None, humans_mask=None):
        x, lead = self.features(robot, humans, humans_mask)
        h = self.net(x).reshape(*lead, -1)
        return h.unsqueeze(-2), h

    prep_fields = ("x",)

    @property
    def prep_key(self) -> str:
        return f"mlp_n{self.max_humans}"

    def prepare(self, robot, humans=None, humans_mask=None) -> dict[str, torch.Tensor]:
        x, lead = self.features(robot, humans, humans_mask)
        return {"x": x.reshape(*lead, -1)}

    def forward_prepared(self, prep):
        h = self.net(prep["x"])
        return h.unsqueeze(-2), h
