"""GAT encoder: graph attention on the MP-GatedGCN graph.

Veličković, Cucurull, Casanova, Romero, Liò, Bengio, "Graph Attention Networks", ICLR 2018.

Same graph, node embeddings and skeleton as :mod:`~crowdbench.models.gcn` (the robot's
incoming edges include the one from its goal node; :func:`~crowdbench.models.graph.build_graph`).
Per layer, for every receiving node ``i``, incoming edge ``j -> i`` and head ``k``::

    e_ij^k     = LeakyReLU(a_dst^k . W^k h_i + a_src^k . W^k h_j + a_edge^k . (p_j - p_i))
    alpha_ij^k = softmax over the real incoming edges j of i   (padded slots exactly 0)
    h_i       <- h_i + ELU(U h_i + ||_k sum_j alpha_ij^k W^k h_j)    (hidden layers: concatenation)
    h_i       <- h_i + ELU(U h_i + mean_k sum_j alpha_ij^k W^k h_j)  (last layer: average)

The score ``a^T [W h_i || W h_j]`` of the paper's Eq. 1 is split into its receiver and sender
halves (identical). Hidden layers have ``heads`` heads of ``D / heads`` channels, concatenated
to ``D`` (the paper's Eq. 5); the last layer has ``out_heads`` heads of ``D`` channels,
averaged (Eq. 6; ``out_heads: 1`` is the paper's one-head output layer). LeakyReLU slope 0.2
as in the paper. Glorot initialisation of ``W`` and ``a``. No dropout (an actor-critic's
targets do not want it).

What was adapted (TD3's heads consume ``robot_h``, the robot's final node state):

- **Edge features** (not in the paper): the edge attribute the graph carries, the relative
  position ``p_j - p_i`` (``g - p`` on the goal edge), enters the score through ``a_edge``
  (``edge_features: true``; the same as PyG's ``GATConv(edge_dim=2)`` with a linear edge
  map, which composed with ``a_edge`` is one 2-vector per head). Messages do not use it.
- **Self-loop**: the paper's neighbourhood includes ``i`` itself; here the receiver enters through
  a residual connection and a root map ``U h_i`` outside the softmax (as in gcn and
  gatedgcn), so the attention is a distribution over the real incoming edges (humans in
  the radius, the goal for the robot), which is what ``last_gates`` shows. A node without
  incoming edges aggregates zero; the goal node (no incoming edge) gets ``h + ELU(U h)``.
- ``W`` has no bias (the paper's linear transformation); ``U`` has one.

``last_gates`` (:class:`~crowdbench.models.base.Gates`): the robot's attention ``alpha`` over
its incoming edges (goal slot first) in the last layer; ``values`` is the mean over the
heads (each head sums to 1, so the mean does too), ``full [*, K+1, heads]`` keeps every
head. The visualisation (crowdbench/viz/record.py) draws it like MP-GatedGCN's gates.

The receptive-field layout (``receptive_field: true``) comes from the skeleton and gives the
full computation's robot output (tested); layer 1 runs on the raw typed inputs through
folded weights like the other graph encoders. Preset: ``crowdbench/conf/encoder/gat.yaml``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from crowdbench.models.base import GraphEncoder, indicator_row, soft_cap
from crowdbench.models.graph import DEFAULT_K, RADIUS2, Z_DIM


class _Map(NamedTuple):
    """A composed linear map with the ``weight`` / ``bias`` that the skeleton reads."""

    weight: torch.Tensor
    bias: torch.Tensor | None


class GATLayer(nn.Module):
    """One graph-attention layer: ``heads`` heads of ``out`` channels, concatenated or averaged."""

    def __init__(self, dim: int, heads: int, concat: bool, negative_slope: float = 0.2,
                 edge_features: bool = True, score_cap: float | None = None):
        super().__init__()
        self.score_cap = score_cap  # None: GAT's unbounded LeakyReLU score (models/base.py soft_cap)
        if concat and dim % heads:
            raise ValueError(f"gat: encoder.dim ({dim}) must be divisible by encoder.heads ({heads})")
        self.dim, self.heads, self.concat, self.slope = dim, heads, concat, negative_slope
        self.out = dim // heads if concat else dim  # channels per head
        self.W = nn.Linear(dim, heads * self.out, bias=False)
        self.U = nn.Linear(dim, dim)  # root map of the receiving node (replaces the self-loop)
        att = {"src": torch.empty(heads, self.out), "dst": torch.empty(heads, self.out)}
        if edge_features:
            att["edge"] = torch.empty(heads, 2)
        self.att = nn.ParameterDict({n: nn.Parameter(p) for n, p in att.items()})
        nn.init.xavier_uniform_(self.W.weight)
        for p in self.att.values():
            nn.init.xavier_uniform_(p)

    # ------------------------------------------------------------------ composed maps
    def _score_rows(self, w: torch.Tensor, side: str) -> torch.Tensor:
        """``[H, in]``: ``a_side^k . W^k x`` as one map of ``x`` (``w`` = ``W`` composed with
        whatever precedes it, ``[H * out, in]``)."""
        return torch.einsum("hc,hcd->hd", self.att[side], w.view(self.heads, self.out, -1))

    @property
    def src(self) -> _Map:
        """``h_j -> [W h_j, a_src . W h_j]`` (``[H * out + H, D]``, no bias): what the skeleton
        applies to the sending nodes before arranging them per incoming slot."""
        w = self.W.weight
        return _Map(torch.cat((w, self._score_rows(w, "src"))), None)

    def _tgt(self) -> _Map:
        """``h_i -> [U h_i, a_dst . W h_i]``."""
        w = self.W.weight
        bias = F.pad(self.U.bias, (0, self.heads))
        return _Map(torch.cat((self.U.weight, self._score_rows(w, "dst"))), bias)

    def _edge_score(self, attr):
        return attr @ self.att["edge"].T if "edge" in self.att else 0.0

    # ------------------------------------------------------------------ the layer
    def step(self, h, u, sd, msg, ss, mask, msg_g, ss_g):
        """Rows: ``h, u = U h_i [B,T,D]``, ``sd [B,T,H]`` receiver scores; main slots: messages
        ``msg = W h_j [B,T,K,H*out]``, sender + edge scores ``ss [B,T,K,H]``; row 0's goal slot:
        ``msg_g [B,H*out]``, ``ss_g [B,H]``. Softmax with the row maximum subtracted; padded
        slots get ``exp(-inf) = 0`` exactly. The largest score contributes ``exp(0) = 1``, so
        a row with an edge has ``den >= 1``: ``den.clamp_min(1)`` only changes empty rows."""
        b, t, k, _ = ss.shape
        n_h = self.heads
        logit = soft_cap(F.leaky_relu(sd.unsqueeze(2) + ss, self.slope), self.score_cap)
        logit = torch.where(mask.unsqueeze(-1) > 0, logit, float("-inf"))
        lg = soft_cap(F.leaky_relu(sd[:, 0] + ss_g, self.slope), self.score_cap)  # [B, H] the robot's goal edge
        mx = logit.amax(2)
        m0 = torch.maximum(mx[:, 0], lg)
        mx = (m0.unsqueeze(1) if t == 1 else torch.cat((m0.unsqueeze(1), mx[:, 1:]), 1))
        mx = mx.clamp_min(-1e30).detach()  # rows without edges: -inf -> finite
        s = torch.exp(logit - mx.unsqueeze(2))  # [B, T, K, H]
        sg = torch.exp(lg - mx[:, 0])  # [B, H]
        num = (s.unsqueeze(-1) * msg.view(b, t, k, n_h, self.out)).sum(2)  # [B, T, H, out]
        den = s.sum(2)
        num_g = (sg.unsqueeze(-1) * msg_g.view(b, n_h, self.out)).unsqueeze(1)
        den_g = sg.unsqueeze(1)
        if t == 1:
            num, den = num + num_g, den + den_g
        else:
            num = torch.cat((num[:, :1] + num_g, num[:, 1:]), 1)
            den = torch.cat((den[:, :1] + den_g, den[:, 1:]), 1)
        agg = num / den.clamp_min(1.0).unsqueeze(-1)
        agg = agg.flatten(-2) if self.concat else agg.mean(-2)
        return h + F.elu(u + agg), (s, den, sg, mask)

    def gates(self, aux, robot_only: bool = False):
        """``alpha [B, T, K+1, H]`` (slot 0 = goal slot, row 0 only), exactly zero on padded
        slots; ``[B, K+1, H]`` for row 0 if ``robot_only``."""
        s, den, sg, mask = aux
        if robot_only:
            s, den, mask = s[:, :1], den[:, :1], mask[:, :1]
        side = torch.zeros_like(s[:, :, :1])
        side = torch.cat((sg[:, None, None], side[:, 1:]), 1)
        alpha = torch.cat((side, s), 2) / den.clamp_min(1.0).unsqueeze(2)
        return alpha[:, 0] if robot_only else alpha

    def forward(self, h, sz, e, mask, hg, eg, last: bool = False):
        d, hw = self.dim, self.heads * self.out
        tgt, src = self._tgt(), self.src
        u, sd = F.linear(h, tgt.weight, tgt.bias).split((d, self.heads), -1)
        msg, ss = sz.split((hw, self.heads), -1)
        msg_g, ss_g = F.linear(hg, src.weight).split((hw, self.heads), -1)
        if e is not None:
            ss, ss_g = ss + self._edge_score(e), ss_g + self._edge_score(eg)
        h, aux = self.step(h, u, sd, msg, ss, mask, msg_g, ss_g)
        if not last:  # the goal node has no incoming edge: h_g <- h_g + ELU(U h_g)
            hg = hg + F.elu(self.U(hg))
        return h, e, hg, eg, aux

    def fold(self, emb, edge_emb=None):
        """Layer-1 maps of the typed inputs (``h0 = E z``), transposed: ``z [19] -> [h0, U h0,
        a_dst . W h0]`` and ``x [21] -> [W h0_j, a_src . W h0_j + a_edge . attr]``. Biases sit
        on the indicator columns, so all-zero (padded) inputs map to exactly zero."""
        ind = indicator_row(emb)
        we = self.W.weight @ emb  # [H*out, 19]
        ue = torch.addmm(torch.outer(self.U.bias, ind), self.U.weight, emb)
        w_t = torch.cat((emb, ue, self._score_rows(we, "dst")))
        edge = self.att["edge"] if "edge" in self.att else emb.new_zeros(self.heads, 2)
        w_s = torch.cat((F.pad(we, (0, 2)), torch.cat((self._score_rows(we, "src"), edge), 1)))
        return w_t.T, w_s.T

    def first(self, w, z_t, edge_in, goal_in, mask):
        d, hw, n_h = self.dim, self.heads * self.out, self.heads
        w_t, w_s = w
        h, u, sd = (z_t @ w_t).split((d, d, n_h), -1)
        hg, ug, _ = (goal_in[:, :Z_DIM] @ w_t).split((d, d, n_h), -1)
        msg, ss = (edge_in @ w_s).split((hw, n_h), -1)
        msg_g, ss_g = (goal_in @ w_s).split((hw, n_h), -1)
        h, aux = self.step(h, u, sd, msg, ss, mask, msg_g, ss_g)
        e, eg = (edge_in[..., Z_DIM:], goal_in[:, Z_DIM:]) if "edge" in self.att else (None, None)
        return h, e, hg + F.elu(ug), eg, aux


class GATEncoder(GraphEncoder):
    """GAT (Veličković et al. 2018) on the crowdbench graph: multi-head attention over incoming edges."""

    uses_edges = False  # no edge states; the edge attribute enters the scores (a_edge per layer)
    layer_cls = GATLayer

    def __init__(
        self,
        dim: int = 32,
        layers: int = 2,
        k: int = DEFAULT_K,
        radius2: float = RADIUS2,
        receptive_field: bool = True,
        heads: int = 4,
        out_heads: int = 1,
        negative_slope: float = 0.2,
        edge_features: bool = True,
        score_cap: float | None = None,
        robot_radius2: float | None = None,
    ):
        kw = {"negative_slope": negative_slope, "edge_features": edge_features, "score_cap": score_cap}
        super().__init__(dim, 0, k, radius2, receptive_field, robot_radius2, heads=heads, concat=True, **kw)
        self.n_layers = layers
        hidden = [GATLayer(dim, heads, concat=True, **kw) for _ in range(layers - 1)]
        self.layers = nn.ModuleList([*hidden, GATLayer(dim, out_heads, concat=False, **kw)])  # output: average
