"""The graph-encoder skeleton (:class:`GraphEncoder`) and what encoders share (:class:`Gates`, soft caps).

The encoder interface itself is declared in :mod:`crowdbench.models.encoder`: every encoder has
``out_dim`` and ``forward(robot, humans=None, humans_mask=None) -> (h_nodes, robot_h)`` (and optionally
``last_gates``); one whose parameter-free preprocessing is split out subclasses
:class:`~crowdbench.models.encoder.SplitEncoder` (``prep_key``, ``prep_fields``, ``prepare``,
``forward_prepared``), as :class:`GraphEncoder` does. Heads only use ``robot_h`` and ``out_dim``, so they
work with any registered encoder.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from crowdbench.models.encoder import SplitEncoder
from crowdbench.models.graph import (
    DEFAULT_K,
    GRAPH_FIELDS,
    RADIUS2,
    Z_DIM,
    Z_TYPE,
    Graph,
    _gather_rows,
    build_graph,
    unpack_obs,
)


class Gates(NamedTuple):
    """The robot's gate values over its incoming edges in the last layer.

    ``values [*, K+1]`` is the mean over the ``D`` gate channels of ``eta_rj`` (each
    channel sums to ~1 over the neighbours, so the means do too), ``nbr [*, K+1]`` the
    neighbour node ids (0 robot, 1..M human slot + 1, M + 1 goal; slot 0 is the goal),
    ``mask [*, K+1]`` which slots are real edges. ``full [*, K+1, D]`` keeps every channel.
    """

    values: torch.Tensor
    nbr: torch.Tensor
    mask: torch.Tensor
    full: torch.Tensor


def soft_cap(scores: torch.Tensor, cap: float | None) -> torch.Tensor:
    """Attention logits squashed into ``(-cap, cap)`` by ``cap * tanh(scores / cap)`` (``None``: unchanged).

    Why (``encoder.score_cap``): an unbounded score lets TD3's critic sharpen a softmax over the
    humans until it is one-hot, after which its Q-function jumps whenever the argmax changes
    (docs/baselines.md); with the cap, two weights differ by at most a factor ``e^(2 cap)``. The
    tanh keeps the gradient everywhere (a clamp would zero it), as in Gemma 2's logit soft-capping."""
    return scores if cap is None else cap * torch.tanh(scores / cap)


def is_plain(t: torch.Tensor) -> bool:
    """False inside ``torch.vmap`` / ``torch.func`` transforms (do not store such tensors)."""
    return not torch._C._functorch.is_functorch_wrapped_tensor(t)


_IND: dict = {}


def indicator_row(like: torch.Tensor) -> torch.Tensor:
    """``[19]`` constant with ones on the type-indicator columns of the typed inputs: every
    real node has exactly one indicator set, so ``W z + outer(b, ind) z == W z + b`` and a
    folded map needs no bias add (and maps all-zero padding to exactly zero)."""
    key = (like.dtype, like.device)
    if key not in _IND:
        ind = torch.zeros(Z_DIM, dtype=like.dtype, device=like.device)
        ind[Z_TYPE] = 1.0
        _IND[key] = ind
    return _IND[key]


class GraphEncoder(SplitEncoder):
    """Skeleton of a message-passing encoder over :func:`build_graph` graphs.

    Subclasses define ``self.layers`` (an ``nn.ModuleList``) whose items have

    - ``src``: the ``nn.Linear`` applied to sending node states (before arranging them
      per incoming slot);
    - ``fold(E [D,19], edge_emb) -> weights``: the embeddings composed with the layer's
      maps (parameters only); ``first(weights, z_t, edge_in, goal_in, mask) ->
      (h, e, hg, eg, aux)``: layer 1 on the raw typed inputs through those weights;
    - ``forward(h [B,T,D], sz [B,T,K,*], e, mask [B,T,K] float, hg, eg) -> (h, e, hg, eg, aux)``
      for later layers, ``sz = src(h_sender)`` arranged per slot;
    - ``gates(aux, robot_only=False) -> eta [B,T,K+1,D]`` (slot 0 = goal slot) if the layer
      has gates (``[B,K+1,D]`` for row 0 with ``robot_only``).

    ``h`` are the receiving rows' states (row 0 = robot), ``e`` their main edge states,
    ``hg [B,D]`` the goal node's state and ``eg [B,D]`` the state of the robot's goal edge
    (row 0's side slot). ``e`` / ``eg`` / ``aux`` are ``None`` without edge states / gates.
    """

    uses_edges = True
    # whether the layers' folded maps take a 3-column edge attribute (``edge_dist``: the distance after p_j - p_i)
    edge_dist_ok = False
    layer_cls: type[nn.Module]  # one message-passing layer, built as layer_cls(dim, **layer_kwargs)

    def __init__(
        self,
        dim: int = 256,
        layers: int = 2,
        k: int = DEFAULT_K,
        radius2: float = RADIUS2,
        receptive_field: bool = True,
        robot_radius2: float | None = None,
        edge_dist: bool = False,
        **layer_kwargs,
    ):
        super().__init__()
        if edge_dist and not self.edge_dist_ok:
            raise ValueError(f"encoder.edge_dist: {type(self).__name__} has no edge attribute to carry it "
                             "(available with encoder=gatedgcn)")
        self.edge_dist = bool(edge_dist)
        self.out_dim = self.dim = dim
        self.n_layers = layers
        self.k = k
        self.radius2 = radius2
        self.robot_radius2 = robot_radius2
        self.receptive_field = receptive_field
        self.robot_emb = nn.Linear(6, dim)
        self.human_emb = nn.Linear(4, dim)
        self.goal_emb = nn.Linear(6, dim)
        self.edge_emb = nn.Linear(3 if edge_dist else 2, dim) if self.uses_edges else None
        self._last_aux = None
        self.layers = nn.ModuleList(self.layer_cls(dim, **layer_kwargs) for _ in range(layers))

    # ------------------------------------------------------------------ graph
    def build_graph(self, robot, humans=None, humans_mask=None) -> Graph:
        robot, humans, humans_mask = unpack_obs(robot, humans, humans_mask)
        return build_graph(
            robot, humans, humans_mask, self.k, self.radius2, self.n_layers, self.receptive_field,
            self.robot_radius2, self.edge_dist,
        )

    def forward(self, robot, humans=None, humans_mask=None):
        return self.encode(self.build_graph(robot, humans, humans_mask))

    prep_fields = GRAPH_FIELDS

    @property
    def prep_key(self) -> str:
        layout = "rf" if self.receptive_field else "full"
        r2 = f"{self.radius2:g}".replace(".", "p")
        if self.robot_radius2 is not None:
            r2 += "_rr" + f"{self.robot_radius2:g}".replace(".", "p")
        if self.edge_dist:
            r2 += "_dist"
        return f"graph_k{self.k}_l{self.n_layers}_{layout}_r{r2}"

    def prepare(self, robot, humans=None, humans_mask=None) -> dict[str, torch.Tensor]:
        """The graph tensors (:data:`~crowdbench.models.graph.GRAPH_FIELDS`, leading dims kept)."""
        return self.build_graph(robot, humans, humans_mask).tensors()

    def forward_prepared(self, prep):
        return self.encode(Graph.from_tensors(prep, self.k, self.n_layers))

    # ------------------------------------------------------------------ encode
    def embedding_matrix(self) -> torch.Tensor:
        """``[D, 19]``: the three node embeddings as one linear map of typed inputs ``z``
        (:func:`~crowdbench.models.graph.typed_inputs`; biases sit on the type columns)."""
        embs = (self.robot_emb, self.human_emb, self.goal_emb)
        bias = torch.stack([m.bias for m in embs], 1)
        return torch.cat([m.weight for m in embs] + [bias], 1)

    def folded(self):
        """Layer 1's folded weights (``self.layers[0].fold``). Cached only for a module in eval
        mode without gradients (an evaluated policy: ``policy_from_checkpoint`` sets eval mode),
        keyed on the parameters' identities and versions: about 20 small ops less per call, which
        matters at B = 1. Recomputed on every call otherwise: in training the parameters change
        in place under optimisers that do not bump tensor versions (fused Adam does not), so a
        version key would serve the first weights forever (the training actor would act with
        its initial layer 1). Never cached under ``torch.func``."""
        def compute():
            return self.layers[0].fold(self.embedding_matrix(), self.edge_emb)

        if self.training or torch.is_grad_enabled():
            return compute()
        mods = (self.robot_emb, self.human_emb, self.goal_emb, self.edge_emb, *self.layers[0].children())
        params = [p for m in mods if m is not None for p in m._parameters.values() if p is not None]  # bias=False: None
        if not all(is_plain(p) for p in params):
            return compute()
        key = tuple((id(p), p._version) for p in params)
        cache = self.__dict__.setdefault("_fold_cache", {})
        if key not in cache:
            if len(cache) >= 4:
                cache.pop(next(iter(cache)))
            cache[key] = compute()
        return cache[key]

    def encode(self, g: Graph, gates_out: list | None = None):
        """Run the layers on a graph; returns ``(h_nodes [*, N_out, D], robot_h [*, D])``.

        Layer 1 is applied to the raw typed inputs through folded weights (``layer.first``:
        embeddings and layer-1 maps composed, exact since both are affine), so it costs
        ``O(21 D)`` per edge instead of ``O(D^2)`` and no gradient flows through a gather.
        Later layers read the previous layer's states: by gather in the full layout, by a
        contiguous slice in the receptive-field layout. If ``gates_out`` is a list, the gates
        ``eta [B*, T_l, K+1, D]`` of every layer are appended to it (analysis and tests).
        """
        b = g.z_t.shape[0]
        mask = g.nbr_mask.to(g.z_t.dtype)
        h, e, hg, eg, aux = self.layers[0].first(self.folded(), g.z_t, g.edge_in, g.goal_in, mask)
        if gates_out is not None and aux is not None:
            gates_out.append(self.layers[0].gates(aux))
        for li in range(1, self.n_layers):
            layer = self.layers[li]
            if g.full:
                sz = _gather_rows(F.linear(h, layer.src.weight, layer.src.bias), g.nbr)
            else:
                n_t = g.sizes[li]
                sz = F.linear(h[:, n_t:], layer.src.weight, layer.src.bias).view(b, n_t, self.k, -1)
                h, mask = h[:, :n_t], mask[:, :n_t]
                e = e[:, :n_t] if e is not None else None
            last = li == self.n_layers - 1 and not g.full
            h, e, hg, eg, aux = layer.forward(h, sz, e, mask, hg, eg, last=last)
            if gates_out is not None and aux is not None:
                gates_out.append(layer.gates(aux))
        self._record_gates(g, aux)
        robot_h = h[:, 0]
        if g.full:
            h_nodes = torch.cat((h, hg.unsqueeze(1)), 1) * g.valid.unsqueeze(-1)
        else:
            h_nodes = h[:, :1]
        lead = g.lead_shape
        return h_nodes.reshape(*lead, h_nodes.shape[1], -1), robot_h.reshape(*lead, -1)

    def _record_gates(self, g: Graph, aux):
        """Keep what ``last_gates`` needs (robot row only); the Gates are built on access."""
        if aux is None or not is_plain(aux[0]):
            return
        s, den, sg, mask = aux
        s0 = s[:, :1].detach()
        if s.shape[1] > 1:  # full layout: do not keep the whole [B, T, K, D] tensor alive
            s0 = s0.clone()
        self._last_aux = (s0, den[:, :1].detach(), sg.detach(), mask[:, :1])
        self._last_graph = (g.nbr[:, 0], g.nbr_mask[:, 0], g.n_nodes, g.lead_shape)

    @property
    def last_gates(self) -> Gates | None:
        """:class:`Gates` of the robot's incoming edges in the last layer of the most recent
        plain call (``None`` before the first call and for layers without gates)."""
        if getattr(self, "_last_aux", None) is None:
            return None
        nbr0, mask0, n_nodes, lead = self._last_graph
        with torch.no_grad():
            full = self.layers[-1].gates(self._last_aux, robot_only=True)  # [B, K+1, D]
            nbr = torch.cat((torch.full_like(nbr0[:, :1], n_nodes - 1), nbr0), -1)
            mask = torch.cat((torch.ones_like(mask0[:, :1]), mask0), -1)
        return Gates(
            values=full.mean(-1).reshape(*lead, -1),
            nbr=nbr.reshape(*lead, -1),
            mask=mask.reshape(*lead, -1),
            full=full.reshape(*lead, *full.shape[1:]),
        )
