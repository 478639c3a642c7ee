"""MP-GatedGCN encoder (paper Section III-B, Eq. 3-7; SPEC section 4).

Per layer ``l``, for every receiving node ``i`` and incoming edge ``j -> i`` (the robot's
incoming edges include the one from its goal node, Eq. 4/5/7)::

    e_ij  <- e_ij + ReLU(A h_i + B h_j + C e_ij)                       (Eq. 6-7)
    eta_ij = sigmoid(e_ij) / (sum_j' sigmoid(e_ij') + eps)   per channel (Eq. 5)
    h_i   <- h_i + ReLU(U h_i + sum_j eta_ij * V h_j)                   (Eq. 3-4)

Both updates of a layer read that layer's input states; the gates use the *updated* edge
states (the paper's Eq. 5 uses ``e^l`` from Eq. 6). Sums run over valid incoming edges
only; padded slots get a gate of exactly zero. ``A, U`` (receiver) and ``B, V`` (sender)
are stored as two fused ``D -> 2D`` linear maps; ``U, V`` are shared by robot and human
nodes. Node inputs are embedded by three linear maps (robot 6 -> D, human 4 -> D, goal
6 -> D) and edge attributes ``p_j - p_i`` by one 2 -> D map. No normalisation layers
(none in the paper; BatchNorm would also break TorchRL's vmapped critics).

Gates are ``D``-channel vectors per edge; for visualisation ``last_gates.values`` is their
mean over the channels (still summing to ~1 over the robot's incoming edges).

Preset: ``crowdbench/conf/encoder/gatedgcn.yaml`` (D = 32, L = 2; the paper's D = 256 with
``experiment=paper`` or ``encoder.dim=256``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from crowdbench.models.base import GraphEncoder, indicator_row
from crowdbench.models.graph import DEFAULT_K, RADIUS2, Z_DIM


class GatedLayer(nn.Module):
    """One MP-GatedGCN layer; ``tgt = [A; U]`` and ``src = [B; V]`` are fused ``D -> 2D`` maps."""

    def __init__(self, dim: int, eps: float):
        super().__init__()
        self.dim, self.eps = dim, eps
        self.tgt = nn.Linear(dim, 2 * dim)  # [A; U] applied to the receiving node
        self.src = nn.Linear(dim, 2 * dim)  # [B; V] applied to the sending node
        self.C = nn.Linear(dim, dim)

    def step(self, h, a, u, bc, v, e, mask, bcg, vg, eg, zero_padding: bool = False):
        """Eq. 6-7, 5, 3-4. Rows: ``h, a = A h_i, u = U h_i [B,T,D]``; main slots:
        ``bc = B h_j + C e_ij``, ``v = V h_j``, ``e = e_ij [B,T,K,D]``; row 0's goal slot:
        ``bcg, vg, eg [B,D]``.

        ``sum_j eta_ij V h_j`` is computed as ``(sum_j s_ij V h_j) / (den_i + eps)`` with
        ``s = sigmoid(e)`` on valid slots and ``den_i = sum_j s_ij`` (one division per row,
        not per edge). ``zero_padding``: the caller guarantees ``bc = v = e = 0`` on padded
        slots (layer 1, whose padded inputs are zero); then every padded slot of row ``i``
        has ``s = sigmoid(ReLU(a_i))`` and ``V h_j = 0``, so instead of masking ``s`` (a
        full-size multiply forward and backward) ``den`` is corrected per row:
        ``den_i = sum_all s - n_pad_i * sigmoid(ReLU(a_i))``.
        """
        e = e + torch.relu(a.unsqueeze(2) + bc)
        if zero_padding:
            s = torch.sigmoid(e)
            n_pad = mask.shape[-1] - mask.sum(-1, keepdim=True)
            den = s.sum(2) - n_pad * torch.sigmoid(torch.relu(a))
        else:
            s = torch.sigmoid(e) * mask.unsqueeze(-1)
            den = s.sum(2)
        eg = eg + torch.relu(a[:, 0] + bcg)
        sg = torch.sigmoid(eg)
        num = (s * v).sum(2)
        if num.shape[1] == 1:  # robot row only (last layer of the receptive layout)
            num, den = num + (sg * vg).unsqueeze(1), den + sg.unsqueeze(1)
        else:
            num = torch.cat(((num[:, 0] + sg * vg).unsqueeze(1), num[:, 1:]), 1)
            den = torch.cat(((den[:, 0] + sg).unsqueeze(1), den[:, 1:]), 1)
        h = h + torch.relu(u + num / (den + self.eps))
        return h, e, eg, (s, den, sg, mask)

    def gates(self, aux, robot_only: bool = False):
        """``eta [B, T, K+1, D]`` (Eq. 5), slot 0 = goal slot (row 0 only), exactly zero on
        padded slots; ``[B, K+1, D]`` for row 0 if ``robot_only``."""
        s, den, sg, mask = aux
        if robot_only:
            s, den, mask = s[:, :1], den[:, :1], mask[:, :1]
        s = s * mask.unsqueeze(-1)
        side = torch.zeros_like(s[:, :, :1])
        side = torch.cat((sg[:, None, None], side[:, 1:]), 1)
        eta = torch.cat((side, s), 2) / (den.unsqueeze(2) + self.eps)
        return eta[:, 0] if robot_only else eta

    def forward(self, h, sz, e, mask, hg, eg, last: bool = False):
        d = self.dim
        tgt, src, c = self.tgt, self.src, self.C  # F.linear directly: no Module-call overhead
        a, u = F.linear(h, tgt.weight, tgt.bias).split(d, -1)
        bj, v = sz.split(d, -1)
        bg, vg = F.linear(hg, src.weight, src.bias).split(d, -1)
        bc, bcg = bj + F.linear(e, c.weight, c.bias), bg + F.linear(eg, c.weight, c.bias)
        h, e, eg, aux = self.step(h, a, u, bc, v, e, mask, bcg, vg, eg)
        if not last:  # the goal node has no incoming edge: h_g <- h_g + ReLU(U h_g)
            hg = hg + torch.relu(F.linear(hg, tgt.weight[d:], tgt.bias[d:]))
        return h, e, hg, eg, aux

    def fold(self, emb, edge_emb):
        """Layer-1 maps of the typed inputs (``h0 = E z``, ``e0 = W_e x + b_e``), transposed:
        ``z [19] -> [h0, A h0, U h0]`` and ``x [21] -> B h_j + C e0``, ``V h_j``, ``e0``
        (three maps, and the three stacked for the goal edge). Every bias sits on the
        indicator columns (``ind``), so all-zero (padded) inputs map to exactly zero."""
        d = self.dim
        ind = indicator_row(emb)  # [19]: ones on the type-indicator columns
        cw, ew, eb = self.C.weight, edge_emb.weight, edge_emb.bias
        bv = torch.addmm(torch.outer(self.src.bias, ind), self.src.weight, emb)  # [B E; V E] + biases
        w_t = torch.cat((emb, torch.addmm(torch.outer(self.tgt.bias, ind), self.tgt.weight, emb)))
        w_bc = torch.cat((bv[:d] + torch.outer(cw @ eb + self.C.bias, ind), cw @ ew), 1)
        w_v = F.pad(bv[d:], (0, ew.shape[1]))  # V h_j reads no edge attribute (2 columns, 3 with edge_dist)
        w_e = torch.cat((torch.outer(eb, ind), ew), 1)
        return w_t.T, w_bc.T, w_v.T, w_e.T, torch.cat((w_bc, w_v, w_e)).T

    def first(self, w, z_t, edge_in, goal_in, mask):
        """Layer 1 on typed inputs through :meth:`fold`'s weights ``w`` (no bias adds; three
        separate products: their gradients need no full-size concatenation)."""
        d = self.dim
        w_t, w_bc, w_v, w_e, w_g = w
        h, a, u = (z_t @ w_t).split(d, -1)
        hg, _, ug = (goal_in[:, :Z_DIM] @ w_t).split(d, -1)
        bc, v, e = edge_in @ w_bc, edge_in @ w_v, edge_in @ w_e
        bcg, vg, eg = (goal_in @ w_g).split(d, -1)
        h, e, eg, aux = self.step(h, a, u, bc, v, e, mask, bcg, vg, eg, zero_padding=True)
        return h, e, hg + torch.relu(ug), eg, aux


class GatedGCNEncoder(GraphEncoder):
    """MP-GatedGCN: residual gated message passing with edge features (Eq. 3-7)."""

    uses_edges = True
    edge_dist_ok = True
    layer_cls = GatedLayer

    def __init__(
        self,
        dim: int = 256,
        layers: int = 2,
        k: int = DEFAULT_K,
        radius2: float = RADIUS2,
        receptive_field: bool = True,
        eps: float = 1e-6,
        robot_radius2: float | None = None,
        edge_dist: bool = False,
    ):
        super().__init__(dim, layers, k, radius2, receptive_field, robot_radius2, edge_dist, eps=eps)
