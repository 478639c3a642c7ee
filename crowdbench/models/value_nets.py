"""CrowdNav's state-value networks V(s) (Chen et al. 2019, ``crowd_nav/policy/*.py``) on its rotated joint state.

The joint state of the robot with human ``i`` (CrowdNav's ``rotate``; 13 numbers, in the frame centred on
the robot with x towards its goal)::

    dg, v_pref, theta, radius, vx, vy,  px_i, py_i, vx_i, vy_i, radius_i, da_i, radius_sum

``theta`` is 0 (holonomic robot). Every network maps ``[N, M, 13]`` joint states (``mask [N, M]``: real
humans) to ``[N, 1]`` values:

- ``cadrl``: one MLP (150, 100, 100, 1) on the joint state with one human; with several humans the value
  is the minimum over them (CrowdNav's ``CADRL.predict`` takes ``min`` over the pairwise values);
- ``lstm_rl``: an LSTM (hidden 50) over the joint states sorted by decreasing distance (the closest
  human last), then an MLP (150, 100, 100, 1) on the robot's 6 numbers and the LSTM's last state;
- ``sarl``: pairwise MLP (150, 100) -> interaction MLP (100, 50); attention MLP (100, 100, 1) on each pair
  feature and their mean (the global state); value MLP (150, 100, 100, 1) on the robot's 6 numbers and the
  attention-weighted interaction features;
- ``encoder``: any registered encoder of :mod:`crowdbench.models` (``encoder=gatedgcn``, ...) with a value head
  (:class:`EncoderValue`);
- ``lm_sarl``: SARL whose pairwise input also holds each human's local map (4 x 4 cells of 1 m around the
  human, in the frame of its velocity: occupied, mean vx, mean vy of the other humans in the cell).

Hidden sizes are CrowdNav's ``policy.config``.
"""

from __future__ import annotations

import torch
from torch import nn

from crowdbench.kinematics import to_local
from crowdbench.models.sarl import masked_softmax, relu_mlp

SELF_DIM, JOINT_DIM = 6, 13
NETS = ("cadrl", "lstm_rl", "sarl", "lm_sarl", "encoder")


def compact(state: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``state [N, M, D]``, ``mask [N, M]`` with each row's real humans first (in their order) and the slots past
    the most any row holds dropped: on a replayed scene the robot senses ~20 of 51-75 slots, and the graph
    encoders' cost grows with the square of the slots. A no-op when some row holds every slot (CrowdNav). The
    networks below read every human through ``mask`` (an absent one contributes nothing), so the values are
    the same up to the order of float sums (checked in tests/test_value_replay.py); the self-state of slot 0
    is every slot's."""
    M = mask.shape[-1]
    n = max(int(mask.sum(-1).max()), 1) if M else 0
    if n >= M:
        return state, mask
    order = torch.argsort((~mask).to(torch.int8), dim=-1, stable=True)[:, :n]
    return state.gather(1, order.unsqueeze(-1).expand(*order.shape, state.shape[-1])), mask.gather(1, order)


def _unit(v: torch.Tensor) -> torch.Tensor:
    """Unit vector of ``v`` ``[..., 2]``; the x axis where ``v`` is zero (CrowdNav's ``atan2(0, 0) = 0``)."""
    n = v.norm(dim=-1, keepdim=True)
    return torch.where(n > 1e-9, v / n.clamp_min(1e-9), torch.tensor([1.0, 0.0], dtype=v.dtype))


def joint_state(rpos, rvel, goal, hpos, hvel, robot_radius: float, human_radius: float, v_pref: float) -> torch.Tensor:
    """``[..., M, 13]`` rotated joint states of a robot at ``rpos`` with velocity ``rvel`` (``[..., 2]``),
    goal ``goal``, and humans at ``hpos`` with velocities ``hvel`` (``[..., M, 2]``), any common frame."""
    to_goal = goal - rpos
    dg = to_goal.norm(dim=-1, keepdim=True)
    u = _unit(to_goal)  # the joint state's x axis: towards the goal
    M = hpos.shape[-2]
    v = to_local(rvel.unsqueeze(-2), u).squeeze(-2)
    rel = hpos - rpos.unsqueeze(-2)
    hp, hv = to_local(rel, u), to_local(hvel, u)
    da = rel.norm(dim=-1, keepdim=True)
    const = lambda x, like: torch.full_like(like, float(x))
    robot = torch.cat((dg, const(v_pref, dg), torch.zeros_like(dg), const(robot_radius, dg), v), -1)
    robot = robot.unsqueeze(-2).expand(*robot.shape[:-1], M, SELF_DIM)
    human = torch.cat((hp, hv, const(human_radius, da), da, const(robot_radius + human_radius, da)), -1)
    return torch.cat((robot, human), -1)


def occupancy_maps(hpos, hvel, mask, cell_num: int = 4, cell_size: float = 1.0) -> torch.Tensor:
    """``[..., M, 3 cell_num^2]`` CrowdNav's 3-channel local maps: for human ``i``, the other humans in a
    ``cell_num`` x ``cell_num`` grid of ``cell_size`` cells centred on ``i`` in the frame of ``i``'s velocity;
    per cell (cell-major): 1 if occupied, the mean vx and vy of its humans in that frame (0 if empty)."""
    M = hpos.shape[-2]
    u = _unit(hvel)  # [..., M, 2]: human i's frame (to_local broadcasts it over j)
    rel = to_local(hpos.unsqueeze(-3) - hpos.unsqueeze(-2), u)  # [..., i, j, 2]: j seen from i
    vel = to_local(hvel.unsqueeze(-3).expand(*rel.shape), u)
    idx = torch.floor(rel / cell_size + cell_num / 2)
    inside = ((idx >= 0) & (idx < cell_num)).all(-1)
    other = ~torch.eye(M, dtype=torch.bool) & mask.unsqueeze(-2) & mask.unsqueeze(-1)
    keep = inside & other
    cell = (idx[..., 1] * cell_num + idx[..., 0]).long().clamp(0, cell_num**2 - 1)
    hot = torch.nn.functional.one_hot(cell, cell_num**2).to(hpos.dtype) * keep.unsqueeze(-1)  # [..., i, j, C]
    count = hot.sum(-2)  # [..., i, C]
    mean_v = (hot.unsqueeze(-1) * vel.unsqueeze(-2)).sum(-3) / count.clamp_min(1.0).unsqueeze(-1)  # [..., i, C, 2]
    return torch.cat(((count > 0).to(hpos.dtype).unsqueeze(-1), mean_v), -1).flatten(-2)


def mlp(n_in: int, dims) -> nn.Module:
    """CrowdNav's ``mlp``: Linear layers with ReLU between them, none after the last."""
    return relu_mlp(n_in, dims[-1], dims[:-1], last_relu=False)


class CADRLValue(nn.Module):
    def __init__(self, dims=(150, 100, 100, 1)):
        super().__init__()
        self.net = mlp(JOINT_DIM, dims)

    def forward(self, state, mask):
        state, mask = compact(state, mask)
        v = self.net(state).squeeze(-1)  # [N, M]: the value with each human alone
        # the most dangerous human decides; without humans the network sees a zero human
        lone = self.net(torch.cat((state[:, :1, :SELF_DIM], torch.zeros_like(state[:, :1, SELF_DIM:])), -1)).squeeze(-1)
        v = torch.where(mask, v, torch.inf).amin(-1, keepdim=True)
        return torch.where(mask.any(-1, keepdim=True), v, lone)


class LSTMRLValue(nn.Module):
    """(No :func:`compact`: the LSTM reads the absent slots as zero steps, so its value depends on their count.)"""

    def __init__(self, hidden: int = 50, dims=(150, 100, 100, 1)):
        super().__init__()
        self.lstm = nn.LSTM(JOINT_DIM, hidden, batch_first=True)
        self.net = mlp(SELF_DIM + hidden, dims)

    def forward(self, state, mask):
        # decreasing distance (da, column 11): the closest human is read last; absent humans first
        key = torch.where(mask, state[..., 11], torch.inf)
        order = torch.sort(key, dim=-1, descending=True, stable=True).indices
        seq = state.gather(1, order.unsqueeze(-1).expand_as(state)) * mask.gather(1, order).unsqueeze(-1)
        _, (h, _) = self.lstm(seq)
        return self.net(torch.cat((state[:, 0, :SELF_DIM], h[0]), -1))


class SARLValue(nn.Module):
    def __init__(self, in_dim: int = JOINT_DIM, mlp1=(150, 100), mlp2=(100, 50), attention=(100, 100, 1),
                 mlp3=(150, 100, 100, 1)):
        super().__init__()
        self.mlp1 = relu_mlp(in_dim, mlp1[-1], mlp1[:-1], last_relu=True)
        self.mlp2 = mlp(mlp1[-1], mlp2)
        self.attention = mlp(2 * mlp1[-1], attention)
        self.mlp3 = mlp(SELF_DIM + mlp2[-1], mlp3)
        self.weights = None  # the attention of the last call [N, M]

    def forward(self, state, mask):
        state, mask = compact(state, mask)
        e = self.mlp1(state)  # [N, M, E] pairwise features
        mf = mask.unsqueeze(-1).to(e.dtype)
        g = (e * mf).sum(1, keepdim=True) / mf.sum(1, keepdim=True).clamp_min(1.0)  # the crowd's global state
        scores = self.attention(torch.cat((e, g.expand_as(e)), -1)).squeeze(-1)
        w = masked_softmax(scores, mask)
        self.weights = w.detach()
        c = (w.unsqueeze(-1) * self.mlp2(e)).sum(1)
        return self.mlp3(torch.cat((state[:, 0, :SELF_DIM], c), -1))


class EncoderValue(nn.Module):
    """Any registered encoder (``crowdbench/models``: gatedgcn, gcn, rgl, gat, dsrnn, ...) as V: the joint state
    read back as the encoder's observation in the frame of the joint state (robot at the origin with velocity
    ``(vx, vy)``, goal at ``(dg, 0)``; the humans' positions and velocities), then SARL's value MLP
    (150, 100, 100, 1) on the robot's 6 self-state numbers and the encoder's ``robot_h``. The self-state goes to
    the MLP directly, as in SARL: the lookahead ranks candidates whose values differ by ~1%, mostly through
    ``dg`` and the velocity, which a 32-wide embedding alone carried too coarsely (measured in docs/value.md)."""

    def __init__(self, encoder_cfg: dict):
        super().__init__()
        from crowdbench.models import make_encoder

        cfg = dict(encoder_cfg)
        self.encoder = make_encoder(cfg.pop("name"), **cfg)
        self.head = mlp(SELF_DIM + self.encoder.out_dim, (150, 100, 100, 1))

    def forward(self, state, mask):
        state, mask = compact(state, mask)
        z = state.new_zeros(state.shape[0], 1)
        robot = torch.cat((z, z, state[:, 0, 4:6], state[:, 0, 0:1], z), -1)
        humans = state[..., 6:10] * mask.unsqueeze(-1)
        return self.head(torch.cat((state[:, 0, :SELF_DIM], self.encoder(robot, humans, mask)[1]), -1))


def build_value_net(name: str, encoder_cfg: dict | None = None) -> nn.Module:
    """Value network ``name`` (:data:`NETS`); ``encoder``: the run's encoder (``encoder_cfg``) with a value head."""
    if name == "encoder":
        if encoder_cfg is None:
            raise ValueError("algo.net=encoder needs the encoder config (the encoder group)")
        return EncoderValue(encoder_cfg)
    if name == "cadrl":
        return CADRLValue()
    if name == "lstm_rl":
        return LSTMRLValue()
    if name == "sarl":
        return SARLValue()
    if name == "lm_sarl":
        return SARLValue(in_dim=JOINT_DIM + 48)
    raise ValueError(f"unknown value network {name!r}; valid: {', '.join(NETS)}")


def net_input(name: str, rpos, rvel, goal, hpos, hvel, mask, radii: tuple[float, float], v_pref: float):
    """What value network ``name`` reads for these states: the joint states (plus the local maps for lm_sarl)."""
    s = joint_state(rpos, rvel, goal, hpos, hvel, radii[0], radii[1], v_pref)
    if name == "lm_sarl":  # the maps depend on the humans only: computed once, shared by every candidate
        om = occupancy_maps(hpos, hvel, mask)
        s = torch.cat((s, om.expand(*s.shape[:-1], om.shape[-1])), -1)
    return s
