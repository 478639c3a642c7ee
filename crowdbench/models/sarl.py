"""SARL encoder: socially attentive RL (the SARL baseline).

C. Chen, Y. Liu, S. Kreiss, A. Alahi, "Crowd-Robot Interaction: Crowd-aware Robot Navigation
with Attention-based Deep Reinforcement Learning", ICRA 2019 (arXiv:1809.08835); reference
code: CrowdNav, ``crowd_nav/policy/sarl.py``. Per observed human ``i``::

    e_i   = phi_e([s, w_i])                      pairwise feature (MLP, ReLU after every layer)
    h_i   = psi_h(e_i)                           interaction feature (MLP)
    e_m   = mean_k e_k                           the crowd's "global state"
    alpha = softmax_i psi_alpha([e_i, e_m])      attention score (MLP), softmax over observed humans
    c     = sum_i alpha_i h_i                    crowd feature
    out   = f_v([s, c])

Adapted to the continuous actor-critic: the paper's value network ``f_v`` ends in the state
value; here its last layer is ``D``-wide (ReLU) and its output is ``robot_h``, which the TD3 actor
and critic heads consume (the heads play the part of the value output). Inputs are this
benchmark's observation: ``s`` = the robot's ``[px, py, vx, vy, gx, gy]`` and ``w_i`` = the human's
``[px, py, vx, vy]`` in the configured frame, plus the robot-human distance ``d_i`` (CrowdNav's
joint state also carries it; radii and preferred speed are constants here and are left out); no
occupancy map (the SARL variant without "om"); the score layer has no bias (a softmax ignores it,
so it would never receive a gradient). Sums, means and the softmax run over observed
humans only: unobserved or padded slots get a weight of exactly 0 and never enter ``e_m`` (CrowdNav
has no padding; its masked softmax tests ``score != 0``). Without observed humans ``c = 0``.
Widths are CPU-sized (``crowdbench/conf/encoder/sarl.yaml``; CrowdNav's are in the comments there).

``h_nodes`` is ``robot_h`` with a node axis of size 1. ``last_gates`` holds the attention weights of
the most recent plain call as the robot's incoming edges from each human slot (the layout of
:class:`~crowdbench.models.base.Gates`: slot 0 is the goal slot, never valid here; slots ``1..M``
are the human slots ``0..M-1``, node ids ``1..M``), so the rerun recordings draw them like gates.
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import MLP

from crowdbench.models.base import Gates, is_plain, soft_cap
from crowdbench.models.graph import flatten_obs, unpack_obs


def relu_mlp(n_in: int, n_out: int, hidden, last_relu: bool, last_bias: bool = True) -> MLP:
    """``Linear`` layers ``n_in -> *hidden -> n_out`` with ReLU between them (and after the last)."""
    return MLP(in_features=n_in, out_features=n_out, num_cells=list(hidden), activation_class=nn.ReLU,
               activate_last_layer=last_relu, bias_last_layer=last_bias)


def masked_softmax(scores: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Softmax of ``scores`` over the last axis restricted to ``mask``: exactly 0 where ``mask`` is
    False, all zero for a row without a True entry; finite gradients everywhere (vmap-safe)."""
    if scores.shape[-1] == 0:  # no human slots at all
        return scores * mask
    top = torch.where(mask, scores, -torch.inf).amax(-1, keepdim=True)
    top = torch.where(torch.isfinite(top), top, 0.0).detach()  # a constant shift: the softmax is unchanged
    ex = torch.exp(torch.where(mask, scores - top, 0.0)) * mask
    return ex / ex.sum(-1, keepdim=True).clamp_min(1.0)  # the row's maximum contributes exp(0) = 1


def human_inputs(robot: torch.Tensor, humans: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``[B, M, 5]``: each human's ``[px, py, vx, vy, d]`` (zero on unobserved slots)."""
    d = (humans[..., 0:2] - robot[:, None, 0:2]).norm(dim=-1, keepdim=True)
    return torch.where(mask.unsqueeze(-1), torch.cat((humans, d), -1), 0.0)


def human_gates(weights: torch.Tensor, mask: torch.Tensor, lead: tuple) -> Gates:
    """``weights [B, M]`` over the human slots as :class:`Gates` ``[*, M + 1]`` (one channel): slot 0
    is the goal slot (never valid), slot ``s + 1`` human slot ``s`` (node id ``s + 1``)."""
    b, m = mask.shape
    values = torch.cat((weights.new_zeros(b, 1), weights), -1)
    nbr = torch.cat((torch.full((b, 1), m + 1), torch.arange(1, m + 1).expand(b, m)), -1).to(mask.device)
    valid = torch.cat((mask.new_zeros(b, 1), mask), -1)
    return Gates(values=values.reshape(*lead, m + 1), nbr=nbr.reshape(*lead, m + 1),
                 mask=valid.reshape(*lead, m + 1), full=values.reshape(*lead, m + 1, 1))


class SARLEncoder(nn.Module):
    def __init__(self, dim: int = 32, embed=(64, 32), interact=(32, 32), attention=(32,), hidden=(64,),
                 score_cap: float | None = None):
        super().__init__()
        self.out_dim = self.dim = dim
        self.score_cap = score_cap  # None: SARL's unbounded MLP score (models/base.py soft_cap)
        self.phi_e = relu_mlp(6 + 5, embed[-1], embed[:-1], last_relu=True)
        self.psi_h = relu_mlp(embed[-1], interact[-1], interact[:-1], last_relu=False)
        self.psi_a = relu_mlp(2 * embed[-1], 1, attention, last_relu=False, last_bias=False)  # a softmax ignores it
        self.f_v = relu_mlp(6 + interact[-1], dim, hidden, last_relu=True)
        self._last = None

    def attend(self, robot, humans, mask):
        """``(robot_h [B, D], alpha [B, M])`` of flattened observations."""
        b, m = mask.shape
        x = torch.cat((robot.unsqueeze(1).expand(b, m, 6), human_inputs(robot, humans, mask)), -1)
        e = self.phi_e(x)  # [B, M, E]
        mf = mask.unsqueeze(-1).to(e.dtype)
        e_m = (e * mf).sum(1, keepdim=True) / mf.sum(1, keepdim=True).clamp_min(1.0)
        scores = soft_cap(self.psi_a(torch.cat((e, e_m.expand_as(e)), -1)).squeeze(-1), self.score_cap)
        alpha = masked_softmax(scores, mask)
        c = (alpha.unsqueeze(-2) @ self.psi_h(e)).squeeze(-2)  # [B, H]
        return self.f_v(torch.cat((robot, c), -1)), alpha

    def forward(self, robot, humans=None, humans_mask=None):
        robot, humans, mask, lead = flatten_obs(*unpack_obs(robot, humans, humans_mask))
        h, alpha = self.attend(robot, humans, mask)
        if is_plain(alpha):
            self._last = (alpha.detach(), mask, lead)
        h = h.reshape(*lead, -1)
        return h.unsqueeze(-2), h

    @property
    def last_gates(self) -> Gates | None:
        """The attention weights of the most recent plain call as :class:`Gates` ``[*, M + 1]``."""
        if self._last is None:
            return None
        return human_gates(*self._last)
