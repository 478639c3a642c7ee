"""GCN encoder (the GCN-RL / U-GCNRL baseline, SPEC section 4).

Same graph and node embeddings as :mod:`~crowdbench.models.gatedgcn` (the robot's
neighbourhood includes its goal node), but uniform attention: every layer is

    h_i <- h_i + ReLU(U h_i + mean_{j -> i} V h_j)

with the mean over valid incoming edges (zero for nodes without neighbours). No gates
and no edge features (``last_gates`` stays ``None``); relative positions are still in the
node features, which are expressed in the robot frame.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from crowdbench.models.base import GraphEncoder, indicator_row
from crowdbench.models.graph import Z_DIM


class MeanLayer(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim
        self.tgt = nn.Linear(dim, dim)  # U
        self.src = nn.Linear(dim, dim)  # V

    @staticmethod
    def step(h, u, v, mask, vg):
        """Mean of ``V h_j`` over the valid main slots, plus the goal for row 0."""
        num = (mask.unsqueeze(-2) @ v).squeeze(-2)  # [B, T, D]
        cnt = mask.sum(-1, keepdim=True)
        if num.shape[1] == 1:
            num, cnt = num + vg.unsqueeze(1), cnt + 1.0
        else:
            num = torch.cat(((num[:, 0] + vg).unsqueeze(1), num[:, 1:]), 1)
            cnt = torch.cat((cnt[:, :1] + 1.0, cnt[:, 1:]), 1)
        return h + torch.relu(u + num / cnt.clamp_min(1.0))

    def forward(self, h, sz, e, mask, hg, eg, last: bool = False):
        h2 = self.step(h, self.tgt(h), sz, mask, self.src(hg))
        return h2, None, hg if last else hg + torch.relu(self.tgt(hg)), None, None

    def fold(self, emb, edge_emb):
        ind = indicator_row(emb)
        w_t = torch.cat((emb, torch.addmm(torch.outer(self.tgt.bias, ind), self.tgt.weight, emb)))  # h0, U h0
        w_v = F.pad(torch.addmm(torch.outer(self.src.bias, ind), self.src.weight, emb), (0, 2))  # V h_j
        return w_t.T, w_v.T

    def first(self, w, z_t, edge_in, goal_in, mask):
        d = self.dim
        w_t, w_v = w
        h, u = (z_t @ w_t).split(d, -1)
        hg, ug = (goal_in[:, :Z_DIM] @ w_t).split(d, -1)
        h = self.step(h, u, edge_in @ w_v, mask, goal_in @ w_v)
        return h, None, hg + torch.relu(ug), None, None


class GCNEncoder(GraphEncoder):
    """Residual GCN with uniform (mean) aggregation."""

    uses_edges = False
    layer_cls = MeanLayer
