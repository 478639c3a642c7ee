"""LSTM-RL encoder: an LSTM over the observed humans, farthest first (the GA3C-CADRL / LSTM-RL baseline).

M. Everett, Y. F. Chen, J. P. How, "Motion Planning Among Dynamic, Decision-Making Agents with
Deep Reinforcement Learning", IROS 2018 (arXiv:1805.01956). The other agents' states are fed one
by one to an LSTM in order of **decreasing distance** to the robot, so that the closest agent is
the last input and has the most effect on the final hidden state ``h_n``; ``h_n`` is concatenated
with the robot's own state and passed through fully connected layers.

Adapted to the continuous actor-critic: the paper's network ends in a policy and a value head
(A3C); here the fully connected layers end in a ``D``-wide ReLU layer whose output is ``robot_h``,
which the TD3 actor and critic heads consume. Inputs are this benchmark's observation: the robot's
``[px, py, vx, vy, gx, gy]`` and, per human, ``[px - px_r, py - py_r, vx, vy, d]`` (position
relative to the robot, velocity in the configured frame, distance ``d``; the paper's radii are
constants here and are left out).

Padding: the observed humans are sorted to the front of the sequence (farthest first) and the
unobserved slots after them; the LSTM runs over the whole padded sequence (static shapes) and
``h_n`` is read at each row's last observed step. The LSTM is causal, so the later padded steps
cannot affect it; a row without observed humans gets the LSTM's initial state ``h_0 = 0``.
``torch.nn.LSTM`` has no ``torch.vmap`` batching rule, so under ``torch.func`` transforms (TorchRL's
vmapped critics) the same cell equations run as a Python loop on the module's own weights (tested
equal to ``nn.LSTM``), over the steps up to the batch's largest number of observed humans.
``h_nodes`` is ``robot_h`` with a node axis of size 1; ``last_gates`` is ``None``.
"""

from __future__ import annotations

import torch
from torch import nn

from crowdbench.models.base import is_plain
from crowdbench.models.encoder import SplitEncoder
from crowdbench.models.graph import _gather_rows, flatten_obs, unpack_obs
from crowdbench.models.sarl import relu_mlp
from crowdbench.models.vmap_once import batch_max

HUMAN_IN = 5  # [px - px_r, py - py_r, vx, vy, d]


def sorted_sequence(robot: torch.Tensor, humans: torch.Tensor, mask: torch.Tensor):
    """``seq [B, M, 5]`` (observed humans by decreasing distance, then zero padding) and the number
    of observed humans ``n [B]``. Sort indices carry no gradient; the features do."""
    rel = humans[..., 0:2] - robot[:, None, 0:2]
    d = rel.norm(dim=-1, keepdim=True)
    feat = torch.where(mask.unsqueeze(-1), torch.cat((rel, humans[..., 2:4], d), -1), 0.0)
    with torch.no_grad():
        key = torch.where(mask, -d.squeeze(-1), torch.inf)  # ascending: farthest observed first, padding last
        order = torch.argsort(key, dim=-1, stable=True)
    return _gather_rows(feat, order), mask.sum(-1)


class LSTMRLEncoder(SplitEncoder):
    def __init__(self, dim: int = 32, hidden_size: int = 32, hidden=(64,)):
        super().__init__()
        self.out_dim = self.dim = dim
        self.hidden_size = hidden_size
        self.lstm = nn.LSTM(HUMAN_IN, hidden_size, batch_first=True)
        self.fc = relu_mlp(6 + hidden_size, dim, hidden, last_relu=True)
        self.last_gates = None

    def run_lstm(self, seq: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """``[B, M, 5] -> [B, T, H]``: the LSTM's hidden state after each of the first ``T`` steps
        (``T = M`` plain; ``T >= max(n)`` under ``torch.func``, enough for ``h_n``)."""
        w = (self.lstm.weight_ih_l0, self.lstm.weight_hh_l0, self.lstm.bias_ih_l0, self.lstm.bias_hh_l0)
        if all(is_plain(t) for t in (seq, *w)):
            return self.lstm(seq)[0]
        w_ih, w_hh, b_ih, b_hh = w  # the cell equations of nn.LSTM (gates i, f, g, o), step by step
        # unbind, not x[:, t]: the backward of M selects allocates and adds M full-size zero gradients
        xs = (seq @ w_ih.T + (b_ih + b_hh)).unbind(1)
        h = c = seq.new_zeros(seq.shape[0], self.hidden_size)
        out = []
        # steps after every row's last observed human cannot reach h_n (the LSTM is causal)
        for t in range(batch_max(n)):
            i, f, g, o = (xs[t] + h @ w_hh.T).chunk(4, -1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
            out.append(h)
        return torch.stack(out, 1) if out else seq.new_zeros(seq.shape[0], 0, self.hidden_size)

    def encode(self, robot: torch.Tensor, seq: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """``robot [B, 6]``, ``seq [B, M, 5]``, ``n [B]`` -> ``robot_h [B, D]``."""
        out = self.run_lstm(seq, n) if seq.shape[1] else seq.new_zeros(seq.shape[0], 0, self.hidden_size)
        if out.shape[1] == 0:
            h_n = robot.new_zeros(robot.shape[0], self.hidden_size)
        else:
            last = _gather_rows(out, (n - 1).clamp_min(0).unsqueeze(-1)).squeeze(1)
            h_n = torch.where((n > 0).unsqueeze(-1), last, 0.0)
        return self.fc(torch.cat((robot, h_n), -1))

    def forward(self, robot, humans=None, humans_mask=None):
        robot, humans, mask, lead = flatten_obs(*unpack_obs(robot, humans, humans_mask))
        h = self.encode(robot, *sorted_sequence(robot, humans, mask)).reshape(*lead, -1)
        return h.unsqueeze(-2), h

    # the sort is parameter-free: a training batch sorts once for actor, critics and targets
    prep_fields = ("robot", "seq", "n")
    prep_key = "lstm_rl_sorted"

    def prepare(self, robot, humans=None, humans_mask=None) -> dict[str, torch.Tensor]:
        robot, humans, mask, lead = flatten_obs(*unpack_obs(robot, humans, humans_mask))
        seq, n = sorted_sequence(robot, humans, mask)
        return {"robot": robot.reshape(*lead, 6), "seq": seq.reshape(*lead, *seq.shape[1:]), "n": n.reshape(lead)}

    def forward_prepared(self, prep):
        lead = prep["n"].shape
        robot, seq = prep["robot"].reshape(-1, 6), prep["seq"]
        seq = seq.reshape(-1, *seq.shape[-2:])
        h = self.encode(robot, seq, prep["n"].reshape(-1)).reshape(*lead, -1)
        return h.unsqueeze(-2), h
