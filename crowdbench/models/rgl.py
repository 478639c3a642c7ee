"""RGL encoder: relational graph learning (the RGL baseline).

C. Chen, S. Hu, P. Nikdel, G. Mori, M. Savva, "Relational Graph Learning for Crowd Navigation",
IROS 2020 (arXiv:1909.13165); reference code: ``ChanganVR/RelationalGraphLearning``,
``crowd_nav/policy/graph_model.py`` (class ``RGL``) with ``configs/icra_benchmark/rgl.py``. One
fully connected graph over the robot and the observed humans::

    X     = [w_r(s); w_h(w_1); ...; w_h(w_M)]                node embeddings (MLPs, ReLU), width D
    A_ij  = softmax_j (W_theta x_i)^T (W_phi x_j)             embedded Gaussian similarity (the paper's)
    A_ij  = softmax_j c cos(W_theta x_i, W_phi x_j)           scaled cosine (the default here, c = scale)
    H_1   = ReLU(A X W_1) + X,   H_2 = ReLU(A H_1 W_2) + H_1  GCN layers with the code's skip connection

The adjacency is computed once from ``X`` and shared by the layers (the benchmark config:
``layerwise_graph = False``, ``skip_connection = True``, 2 layers, ``X_dim = 32``,
``wr_dims = wh_dims = [64, 32]``). The output is the robot node's state ``H_L[0]``.

Adapted to the continuous actor-critic: the paper feeds the robot's state to a value network and
a state predictor for model-predictive planning; here it is ``robot_h``, which the TD3 actor and
critic heads consume (no planning). Node inputs are this benchmark's observation: the robot's
``[px, py, vx, vy, gx, gy]``, each human's ``[px, py, vx, vy]`` in the configured frame. The
code's single bilinear matrix ``W_a`` is written as the paper's ``W_theta^T W_phi`` (two bias-free
``D x D`` maps), and all maps take PyTorch's default initialisation instead of the code's
``torch.randn`` (unit-variance weights, which saturate a D = 32 network). Masking: unobserved or
padded humans get zero adjacency weight as targets (their rows of ``A`` are zero) and as sources
(their columns are excluded from the softmax), so each observed row sums to 1 over the observed
nodes (the robot included: its self-similarity is part of the softmax, as in the code).

Why a bounded similarity is the default (``similarity: cosine``, ``scale: 5``): with the paper's
unbounded bilinear logits, TD3's critic drove them up until the softmax was one-hot (the critic's
``W_theta^T W_phi`` grew to spectral norm ~100 and its loss from 0.01 to 20; docs/baselines.md), and
the trained policy stood still. The cosine keeps every logit in ``[-c, c]``, so the weight ratio of
two neighbours is at most ``e^{2c}`` (e^10 at c = 5): sharp, never one-hot. ``embedded_gaussian``
is the paper's form, kept for the first leaderboard row and for comparison.

``h_nodes [*, M + 1, D]``: the robot (node 0) and the human slots, zero on unobserved slots.
``last_adjacency [*, M + 1]`` is the robot's row of ``A`` in the most recent plain call (robot
first); ``last_gates`` shows its human entries as :class:`~crowdbench.models.base.Gates` for the
recordings (slot 0 = goal slot, never valid; node ids ``1..M``). The robot's self-weight has no
edge to draw, so those values sum to ``1 - A_00``, not 1.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from crowdbench.models.base import Gates, is_plain
from crowdbench.models.graph import flatten_obs, unpack_obs
from crowdbench.models.sarl import human_gates, masked_softmax, relu_mlp

SIMILARITIES = ("cosine", "embedded_gaussian")


class RGLEncoder(nn.Module):
    def __init__(self, dim: int = 32, embed=(64,), layers: int = 2, skip: bool = True,
                 similarity: str = "cosine", scale: float = 5.0):
        super().__init__()
        if similarity not in SIMILARITIES:
            raise ValueError(f"encoder.similarity: {similarity!r} is not one of {', '.join(SIMILARITIES)}")
        self.out_dim = self.dim = dim
        self.skip = skip
        self.similarity, self.scale = similarity, float(scale)
        self.w_r = relu_mlp(6, dim, embed, last_relu=True)
        self.w_h = relu_mlp(4, dim, embed, last_relu=True)
        self.w_theta = nn.Linear(dim, dim, bias=False)
        self.w_phi = nn.Linear(dim, dim, bias=False)
        self.gcn = nn.ModuleList(nn.Linear(dim, dim, bias=False) for _ in range(layers))
        self._last = None

    def adjacency(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """``[B, N, N]`` row-normalised similarity over valid nodes (zero rows for invalid nodes)."""
        q, k = self.w_theta(x), self.w_phi(x)
        if self.similarity == "cosine":  # eps: no division by zero for an all-zero embedding
            q = self.scale * F.normalize(q, dim=-1, eps=1e-8)
            k = F.normalize(k, dim=-1, eps=1e-8)
        sim = q @ k.transpose(-1, -2)
        return masked_softmax(sim, valid.unsqueeze(-2)) * valid.unsqueeze(-1)

    def forward(self, robot, humans=None, humans_mask=None):
        robot, humans, mask, lead = flatten_obs(*unpack_obs(robot, humans, humans_mask))
        valid = torch.cat((mask.new_ones(mask.shape[0], 1), mask), -1)  # [B, N]: robot, then the human slots
        hum = torch.where(mask.unsqueeze(-1), humans, 0.0)
        h = torch.cat((self.w_r(robot).unsqueeze(1), self.w_h(hum)), 1)  # X [B, N, D]
        a = self.adjacency(h, valid)
        for w in self.gcn:
            nxt = torch.relu(w(a @ h))
            h = nxt + h if self.skip else nxt
        if is_plain(a):
            self._last = (a[:, 0].detach(), mask, lead)
        robot_h = h[:, 0]
        h_nodes = h * valid.unsqueeze(-1)
        return h_nodes.reshape(*lead, *h_nodes.shape[1:]), robot_h.reshape(*lead, -1)

    @property
    def last_adjacency(self) -> torch.Tensor | None:
        """The robot's row of ``A`` ``[*, M + 1]`` (robot first) in the most recent plain call."""
        if self._last is None:
            return None
        row, _, lead = self._last
        return row.reshape(*lead, -1)

    @property
    def last_gates(self) -> Gates | None:
        """The robot's adjacency weights on the human nodes as :class:`Gates` ``[*, M + 1]``."""
        if self._last is None:
            return None
        row, mask, lead = self._last
        return human_gates(row[:, 1:], mask, lead)
