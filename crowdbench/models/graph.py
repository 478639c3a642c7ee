"""Observation tensors -> padded neighbour-list graph (SPEC sections 3, 4 and 9).

Node numbering (one graph per agent; ``B* = prod(leading dims)`` graphs)::

    0          the agent itself ("robot"), features [px, py, vx, vy, gx, gy]
    1 .. M     the M padded human slots of the observation, features [px, py, vx, vy]
    M + 1      the agent's goal node, features [0, 0, 0, 0, gx, gy], position g

Edges (directed, stored per *receiving* node ``i`` as a padded incoming list):

- between any two observed nodes (robot, observed humans) with squared distance
  ``<= radius2`` (default 5, i.e. sqrt(5) m; compared with a 1e-6 relative tolerance so
  that float rounding of an exact 5 does not drop the edge), both directions;
- one edge goal -> robot, always present, whatever the distance;
- the goal node receives nothing; unobserved human slots have no edges.

The attribute of edge ``j -> i`` is ``p_j - p_i`` (so the goal edge carries ``g - p``).

Documented layout (:meth:`Graph.slots`): ``nbr [B*, T, K+1]`` node ids, ``nbr_mask`` and
``edge_attr [B*, T, K+1, 2]`` (zero on padding) for ``T`` receiving nodes; slot 0 is the
goal slot (valid for the robot only), slots ``1..K`` hold up to ``K`` human/robot
neighbours, nearest first, valid first. ``K`` (default 8) caps the neighbours of every
node; the robot always keeps its goal on top of its ``K`` humans. :func:`cap_binding`
reports how often the cap binds (a node has more than ``K`` candidates in the radius).

Storage: the goal slot is only ever valid for the robot, so it is stored *on the side*
(``goal_in``, one per graph) and the main lists have width ``K`` (``nbr [B*, T, K]``):
for L = 2, K = 8 this is 72 instead of 90 edge slots per graph. The goal node itself has
no incoming edge, so its state is also carried on the side by the encoders.

Receptive field (SPEC section 9). With ``L`` message-passing layers the robot's output
depends only on its ``L``-hop neighbourhood. With ``receptive_field=True`` (default) and
``L <= 2`` the graph holds only the receiving nodes the robot needs:

- layer 1 updates ``T_1 = [robot, its <= K neighbours]`` (``K + 1`` rows, padded rows
  included), reading the initial states of their neighbours (any node: the 2-hop set);
- layer 2 updates the robot alone, reading the layer-1 states of rows ``1..K`` (a
  contiguous slice, no gather) and of the goal node.

Instead of ``M + 1`` receiving rows per layer (76 on STUDENTS001) the encoder updates 9
rows, then 1. Neighbour lists are identical in both layouts (same candidates, same
nearest-first cap), so the robot's output equals the full computation (tested). Deeper
encoders (``L >= 3``, whose 3-hop frontier is about as large as the graph) and
``receptive_field=False`` use the full layout, ``T = M + 1`` rows (all nodes but the goal).

Measured (``benchmarks/bench_models.py``, batch 100 STUDENTS001 observations, M = 75
slots, 24 observed humans on average, 2 CPU cores, quiet machine): graph construction
2.1 ms receptive vs 6.1 ms full; gatedgcn forward + backward (graph prepared) 10.8 ms vs
66 ms at D = 32 and 42 ms vs 1.66 s at D = 256 (the paper's preset). Smaller choices
measured while developing (not re-run by the benchmark): rows gathered with
``index_select`` (``torch.gather`` with an expanded index was ~4x slower on CPU); the goal
slot stored on the side (20% fewer edge slots); the distance test on far-moved
coordinates (one comparison implements validity, goal exclusion and radius).

The cap ``K = 8`` binds (a node has more than ``K`` candidates) for 19.9% of observed
nodes on STUDENTS001 (robot: 20.9%) and 10.8% on STUDENTS003 (robot: 7.6%), measured on
40 steps of 500 straight-to-goal episodes per scene; K = 12 would lower this to 4.6% /
2.3% at 1.5x the edge cost. Report it per scene with :func:`cap_binding`.

Everything here is batched, free of Python loops over graphs or nodes, has static shapes
(no ``.item()``), and works under ``torch.vmap`` (TorchRL's losses vmap the critic over
its parameter copies with batched inputs). Graph construction is parameter-free and
runs without gradients (observations never need them).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from crowdbench.envs.observation import OBS

RADIUS2 = 5.0  # squared edge radius (paper III-A.2)
DEFAULT_K = 8
_TOL = 1e-6  # relative tolerance on the squared radius
_INF = float("inf")

# Typed node input ``z [19]``: the raw features of the node's type in their own columns
# plus a one-hot type indicator, so that every type-specific affine embedding (robot 6 -> D,
# human 4 -> D, goal 6 -> D) is ONE linear map of ``z`` (biases on the indicator columns).
Z_ROBOT, Z_HUMAN, Z_GOAL, Z_TYPE = slice(0, 6), slice(6, 10), slice(10, 16), slice(16, 19)
Z_DIM = 19
EDGE_IN = Z_DIM + 2  # the sender's typed input followed by the edge attribute

GRAPH_FIELDS = ("nbr", "nbr_mask", "z_t", "edge_in", "goal_in", "valid")  # what an encoder reads


class Graph(NamedTuple):
    """Flattened padded-neighbour-list graph of ``B*`` agent graphs (module docstring).

    ``T`` receiving rows (robot first), ``K`` main incoming slots each, plus the robot's
    goal slot stored on the side. ``z_t``, ``edge_in`` and ``goal_in`` are the
    parameter-free inputs of the first layer, gathered once here.
    """

    nbr: torch.Tensor  # [B*, T, K] long sender node ids (padding: 0 in the full layout, else arbitrary)
    nbr_mask: torch.Tensor  # [B*, T, K] bool
    z_t: torch.Tensor  # [B*, T, 19] typed inputs of the receiving nodes
    edge_in: torch.Tensor  # [B*, T, K, 21] sender's typed input ++ p_j - p_i (all zero on padding)
    goal_in: torch.Tensor  # [B*, 21] goal node's typed input ++ g - p (robot's goal edge)
    valid: torch.Tensor  # [B*, N] bool, N = M + 2 (robot and goal always valid)
    targets: torch.Tensor | None  # [B*, T] long node ids of the receiving rows
    sizes: tuple  # receiving rows per layer (python ints), layer 1 first
    full: bool  # True: rows are the nodes 0..N-2 in id order (no receptive-field restriction)
    lead_shape: tuple  # leading batch dims of the observation (e.g. (B, A))

    @property
    def edge_attr(self) -> torch.Tensor:
        """``[B*, T, K, 2]`` attributes ``p_j - p_i`` of the main slots (zero on padding; ``[.., 3]`` with the
        distance after them when built with ``edge_dist``)."""
        return self.edge_in[..., Z_DIM:]

    @property
    def n_nodes(self) -> int:
        return self.valid.shape[-1]

    def slots(self):
        """The documented ``K + 1``-slot layout: ``(nbr, mask, edge_attr)`` with slot 0 = goal
        slot (valid, id ``N - 1`` and attribute ``g - p`` on row 0 only)."""
        b, t, _ = self.nbr.shape
        row0 = torch.zeros(b, t, 1, dtype=torch.bool, device=self.nbr.device)
        row0[:, 0] = True
        nbr = torch.cat((torch.full_like(self.nbr[..., :1], self.n_nodes - 1), self.nbr), -1)
        mask = torch.cat((row0, self.nbr_mask), -1)
        gattr = self.goal_in[:, None, None, Z_DIM:] * row0.unsqueeze(-1)
        return nbr, mask, torch.cat((gattr, self.edge_attr), 2)

    def tensors(self) -> dict[str, torch.Tensor]:
        """The encoder inputs with the observation's leading dims restored (for TensorDicts)."""
        lead = self.lead_shape
        return {f: getattr(self, f).reshape(*lead, *getattr(self, f).shape[1:]) for f in GRAPH_FIELDS}

    @classmethod
    def from_tensors(cls, t: dict, k: int, layers: int) -> Graph:
        """Inverse of :meth:`tensors` (the static layout is recovered from the shapes)."""
        lead = tuple(t["valid"].shape[:-1])
        flat = {f: t[f].reshape(-1, *t[f].shape[len(lead) :]) for f in GRAPH_FIELDS}
        n, n_t = flat["valid"].shape[-1], flat["nbr"].shape[-2]
        full = n_t == n - 1
        sizes = (n_t,) * layers if full else receptive_sizes(layers, k)
        return cls(targets=None, sizes=sizes, full=full, lead_shape=lead, **flat)


def typed_inputs(robot: torch.Tensor, humans: torch.Tensor, humans_mask: torch.Tensor) -> torch.Tensor:
    """``[B*, N, 19]`` typed node inputs (robot, humans, goal; unobserved humans all zero)."""
    b, m = humans_mask.shape
    mf = humans_mask.to(robot.dtype)
    z = robot.new_zeros(b, m + 2, Z_DIM)
    z[:, 0, Z_ROBOT] = robot
    z[:, 0, 16] = 1.0
    z[:, 1:-1, Z_HUMAN] = humans * mf.unsqueeze(-1)
    z[:, 1:-1, 17] = mf
    z[:, -1, 14:16] = robot[:, 4:6]  # goal features [0, 0, 0, 0, gx, gy]
    z[:, -1, 18] = 1.0
    return z


def unpack_obs(robot, humans=None, humans_mask=None):
    """Accept a TensorDict (``("agents", "observation", ...)`` keys, or an observation-level
    TensorDict / dict with ``robot``, ``humans``, ``humans_mask``) or the three tensors."""
    if humans is None:
        src = robot
        keys = src.keys(include_nested=True) if hasattr(src, "batch_size") else src.keys()
        if (OBS + ("robot",)) in keys:
            src = src[OBS]
        return src["robot"], src["humans"], src["humans_mask"]
    return robot, humans, humans_mask


def flatten_obs(robot: torch.Tensor, humans: torch.Tensor, humans_mask: torch.Tensor):
    """``[*, 6], [*, M, 4], [*, M]`` -> ``[B*, 6], [B*, M, 4], [B*, M] bool`` and the leading shape."""
    lead = tuple(robot.shape[:-1])
    b, m = robot.numel() // 6, humans.shape[-2]
    return robot.reshape(b, 6), humans.reshape(b, m, 4), humans_mask.reshape(b, m).bool(), lead


def node_positions(robot: torch.Tensor, humans: torch.Tensor, humans_mask: torch.Tensor):
    """Positions ``[B*, N, 2]`` (robot, humans, goal) and validity ``[B*, N]``."""
    pos = torch.cat((robot[:, None, 0:2], humans[..., 0:2], robot[:, None, 4:6]), 1)
    ones = humans_mask.new_ones(humans_mask.shape[0], 1)
    valid = torch.cat((ones, humans_mask, ones), 1)
    return pos, valid


_OFFS: dict = {}


def _gather_rows(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``x [B, N, *F]`` gathered at ``idx [B, *I]`` -> ``[B, *I, *F]``.

    One ``index_select`` on the flattened rows (several times faster than ``torch.gather``
    with an expanded index on CPU; its backward is an ``index_add``)."""
    b, n = x.shape[:2]
    feat = x.shape[2:]
    key = (b, n, idx.dim(), idx.device)
    offs = _OFFS.get(key)
    if offs is None:  # row offsets of each graph, cached (constants)
        if len(_OFFS) > 256:
            _OFFS.clear()
        offs = _OFFS[key] = torch.arange(b, device=idx.device).view(b, *([1] * (idx.dim() - 1))) * n
    out = x.reshape(b * n, math.prod(feat)).index_select(0, (idx + offs).reshape(-1))
    return out.view(*idx.shape, *feat)


_FAR: dict = {}


def sender_coords(pos: torch.Tensor, valid: torch.Tensor):
    """Coordinates ``x, y [B*, N]`` for the edge test: nodes that take no part in
    human/robot edges (unobserved slots, the goal node) are moved to distinct far-away
    points (1e4 m apart), so that one squared-distance test implements the edge rule."""
    n = pos.shape[1]
    key = (n, pos.dtype, pos.device)
    if key not in _FAR:  # constants, cached
        far = 1e4 * torch.arange(1, n + 1, dtype=pos.dtype, device=pos.device)
        _FAR[key] = (far, torch.arange(n, device=pos.device) < n - 1)
    far, not_goal = _FAR[key]
    send = valid & not_goal
    return torch.where(send, pos[..., 0], far), torch.where(send, pos[..., 1], 0.0)


def _nearest(x, y, targets, k: int, radius2):
    """Up to ``k`` nearest candidates within the radius for each target ``[B, T]``:
    ``val, idx [B, T, k]`` (``val = inf`` on padding, padding last; ids on padding arbitrary).
    ``radius2``: one squared radius, or one per target row (a ``[T, 1]`` tensor)."""
    n = x.shape[1]
    tx, ty = torch.gather(x, 1, targets), torch.gather(y, 1, targets)
    dx = x.unsqueeze(1) - tx.unsqueeze(2)
    dy = y.unsqueeze(1) - ty.unsqueeze(2)
    d2 = dx * dx + dy * dy  # [B, T, N]
    key = d2.masked_fill(d2 > radius2 * (1.0 + _TOL), _INF)
    key = key.scatter(-1, targets.unsqueeze(-1), _INF)  # no self loop
    kk = min(k, n - 2)  # at most robot + humans minus self
    val, idx = torch.topk(key, kk, dim=-1, largest=False, sorted=True)
    if kk < k:  # fewer nodes than the cap: pad to a static width k
        val = torch.nn.functional.pad(val, (0, k - kk), value=_INF)
        idx = torch.nn.functional.pad(idx, (0, k - kk))
    return val, idx


def neighbour_lists(pos, valid, targets, k: int = DEFAULT_K, radius2: float = RADIUS2):
    """Main incoming lists of the nodes ``targets [B, T]`` (node ids, goal slot excluded):
    ``nbr [B, T, k]`` (nearest first, valid first; ids on padding arbitrary), ``mask`` and
    ``edge_attr = p_nbr - p_target`` (zero on padding)."""
    val, nbr = _nearest(*sender_coords(pos, valid), targets, k, radius2)
    mask = val < _INF
    attr = (_gather_rows(pos, nbr) - _gather_rows(pos, targets).unsqueeze(2)) * mask.unsqueeze(-1)
    return nbr, mask, attr


def receptive_sizes(layers: int, k: int) -> tuple:
    """Receiving rows per layer (layer 1 first) of the receptive-field layout (``L <= 2``)."""
    return ((k + 1, 1) if layers == 2 else (1,))[:layers]


def uses_receptive_layout(layers: int, k: int, n_nodes: int, receptive_field: bool = True) -> bool:
    return receptive_field and layers <= 2 and (k + 1) ** (layers - 1) < n_nodes - 1


def build_graph(
    robot: torch.Tensor,
    humans: torch.Tensor,
    humans_mask: torch.Tensor,
    k: int = DEFAULT_K,
    radius2: float = RADIUS2,
    layers: int = 2,
    receptive_field: bool = True,
    robot_radius2: float | None = None,
    edge_dist: bool = False,
) -> Graph:
    """Build the graph of ``[*, 6], [*, M, 4], [*, M]`` observations for ``layers`` layers.

    ``receptive_field=True`` uses the robot's receptive-field layout when ``layers <= 2``
    (module docstring); otherwise every node but the goal is a receiving row.
    ``robot_radius2`` (default ``radius2``): the squared radius of the robot's own incoming
    edges; the edges between humans, and from the robot to a human, keep ``radius2``.
    ``edge_dist``: every edge attribute (the goal edge's too) carries the distance ``|p_j - p_i|``
    after ``p_j - p_i`` (3 columns instead of 2).

    The topology (who is whose neighbour) is not differentiable; the node and edge features
    are, with respect to the observation, when it requires grad (the lookahead critic's
    ``dQ/da``, models/heads.py); otherwise nothing is recorded.
    """
    robot, humans, humans_mask, lead = flatten_obs(robot, humans, humans_mask)
    b, m = humans_mask.shape
    n = m + 2
    pos, valid = node_positions(robot, humans, humans_mask)
    with torch.no_grad():
        targets, idx, val, sizes, full = _topology(
            pos, valid, b, n, k, radius2, layers, receptive_field, robot_radius2
        )
    mask = val < _INF
    z = typed_inputs(robot, humans, humans_mask)
    z_t = z[:, :-1] if full else _gather_rows(z, targets)
    # one row selection of [z, p], then p_j -> p_j - p_i; padded slots all zero
    edge_in = _gather_rows(torch.cat((z, pos), -1), idx)
    rel = edge_in[..., Z_DIM:] - (pos[:, :-1] if full else _gather_rows(pos, targets)).unsqueeze(2)
    goal_rel = pos[:, -1] - pos[:, 0]
    if edge_dist:
        rel, goal_rel = with_distance(rel), with_distance(goal_rel)
    edge_in = torch.cat((edge_in[..., :Z_DIM], rel), -1) * mask.unsqueeze(-1)
    goal_in = torch.cat((z[:, -1], goal_rel), -1)
    return Graph(idx, mask, z_t, edge_in, goal_in, valid, targets, sizes, full, lead)


def with_distance(rel: torch.Tensor) -> torch.Tensor:
    """``[..., 2]`` offsets -> ``[..., 3]`` offsets and their length. The squared length is clamped at
    1e-12 m^2 before the root: a zero offset (the goal edge of a robot on its goal, a padded slot) keeps a
    finite gradient under the lookahead critic's ``dQ/da``, where ``|x|``'s gradient at 0 is 0 / 0."""
    return torch.cat((rel, rel.square().sum(-1, keepdim=True).clamp_min(1e-12).sqrt()), -1)


def _topology(pos, valid, b, n, k, radius2, layers, receptive_field, robot_radius2=None):
    """Receiving rows ``targets``, their neighbour ids ``idx`` and distances ``val`` (inf on padding)."""
    x, y = sender_coords(pos, valid)
    robot_r2 = radius2 if robot_radius2 is None else robot_radius2
    if uses_receptive_layout(layers, k, n, receptive_field):
        targets = torch.zeros(b, 1, dtype=torch.long, device=pos.device)
        val, idx = _nearest(x, y, targets, k, robot_r2)
        if layers == 2:  # T_1 = [robot, its K neighbour slots]
            v2, i2 = _nearest(x, y, idx[:, 0], k, radius2)
            targets = torch.cat((targets, idx[:, 0]), 1)
            val, idx = torch.cat((val, v2), 1), torch.cat((idx, i2), 1)
        sizes, full = receptive_sizes(layers, k), False
    else:
        targets = torch.arange(n - 1, device=pos.device).unsqueeze(0).expand(b, -1)
        r2 = radius2
        if robot_r2 != radius2:  # row 0 (the robot) has its own radius
            r2 = torch.full((n - 1, 1), radius2, dtype=pos.dtype, device=pos.device)
            r2[0] = robot_r2
        val, idx = _nearest(x, y, targets, k, r2)
        idx = idx.masked_fill(val == _INF, 0)  # padding -> node 0, a valid row for later gathers
        sizes, full = (n - 1,) * layers, True
    return targets, idx, val, sizes, full


@torch.no_grad()
def degrees(robot: torch.Tensor, humans: torch.Tensor, humans_mask: torch.Tensor, radius2: float = RADIUS2):
    """Number of candidate neighbours within the radius (before the cap) of every node,
    ``[B*, N]`` (goal not counted for the robot; -1 for the goal and unobserved slots)."""
    robot, humans, humans_mask, _ = flatten_obs(robot, humans, humans_mask)
    pos, valid = node_positions(robot, humans, humans_mask)
    b, n = valid.shape
    targets = torch.arange(n, device=pos.device).unsqueeze(0).expand(b, -1)
    val, _ = _nearest(*sender_coords(pos, valid), targets, n - 2, radius2)
    deg = (val < _INF).sum(-1)
    node = torch.cat((valid[:, :-1], torch.zeros_like(valid[:, -1:])), 1)
    return torch.where(node, deg, -1)


@torch.no_grad()
def cap_binding(
    robot, humans=None, humans_mask=None, k: int = DEFAULT_K, radius2: float = RADIUS2
) -> dict[str, float]:
    """How often the neighbour cap ``k`` binds on a batch of observations.

    Returns ``nodes`` (fraction of observed nodes, robot and humans, with more than ``k``
    candidate neighbours), ``robot`` (same for the robot nodes only, goal not counted),
    ``mean_degree``, ``max_degree`` and ``n_nodes`` (nodes counted). Accepts a TensorDict
    or the three observation tensors.
    """
    robot, humans, humans_mask = unpack_obs(robot, humans, humans_mask)
    deg = degrees(robot, humans, humans_mask, radius2)
    node = deg >= 0
    d = deg[node].float()
    return {
        "nodes": (d > k).float().mean().item(),
        "robot": (deg[:, 0] > k).float().mean().item(),
        "mean_degree": d.mean().item(),
        "max_degree": d.max().item(),
        "n_nodes": int(node.sum().item()),
    }
