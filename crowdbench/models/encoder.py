"""The encoder interface, declared once: what the heads, the algorithms and the leaderboard may use.

Every encoder meets :class:`Encoder`: an ``nn.Module`` with ``out_dim`` and ``forward``. That is all an
external encoder needs (docs/submitting.md section 3, ``examples/tiny_encoder.py``); it subclasses nothing.

An encoder whose parameter-free preprocessing (graph building, sorting, compaction) can run apart from
its parameters subclasses :class:`SplitEncoder` and declares that split: a training batch is then
preprocessed once and shared by the actor, the critics and their targets
(:func:`~crowdbench.models.heads.prepare_batch`). The heads ask :func:`splits` (a subclass check),
never whether a method happens to exist, so a misspelt ``prepare`` is an error, not a silent slow path.
Every other encoder is read through the raw observation (:data:`RAW_FIELDS`); the numbers are the same
either way (``forward(obs) == forward_prepared(prepare(obs))``).
"""

from __future__ import annotations

from typing import Any, Protocol

import torch
from torch import nn

RAW_FIELDS = ("robot", "humans", "humans_mask")  # the observation, the prepared fields of a non-split encoder


class Encoder(Protocol):
    """What every encoder has (registered in :data:`crowdbench.models.ENCODERS` or external).

    ``forward(robot [*, 6], humans [*, M, 4], humans_mask [*, M]) -> (h_nodes [*, N, D], robot_h [*, D])``,
    or the observation TensorDict as the only argument (:func:`~crowdbench.models.graph.unpack_obs`);
    node 0 of ``h_nodes`` is the agent itself and ``robot_h`` what the heads consume. ``last_gates``
    (optional): :class:`~crowdbench.models.base.Gates` of the agent's incoming edges in the last layer of
    the most recent plain (non-vmapped) call, ``None`` for encoders without gates (crowdbench/viz/record.py)."""

    out_dim: int  # D, the size of the node states

    def __call__(self, robot: Any, humans: Any = None, humans_mask: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        ...


class SplitEncoder(nn.Module):
    """An :class:`Encoder` with its parameter-free preprocessing split out.

    ``prep_key`` names the preprocessing (encoders with equal keys share it in a batch), ``prep_fields``
    the tensors :meth:`prepare` returns (leading dims kept); ``forward(obs) == forward_prepared(prepare(obs))``.
    Subclasses keep their own ``forward`` (this class defines none, so a mixin such as
    :class:`~crowdbench.models.compact.CompactHumans` can put it in front of any encoder)."""

    out_dim: int
    prep_key: str
    prep_fields: tuple[str, ...]

    def prepare(self, robot, humans=None, humans_mask=None) -> dict[str, torch.Tensor]:
        raise NotImplementedError(f"{type(self).__name__}.prepare")

    def forward_prepared(self, prep: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError(f"{type(self).__name__}.forward_prepared")


def splits(encoder: nn.Module) -> bool:
    """Whether ``encoder`` declares its preprocessing split (:class:`SplitEncoder`)."""
    return isinstance(encoder, SplitEncoder)


def prep_fields(encoder: nn.Module) -> tuple[str, ...]:
    """The encoder's prepared fields; the raw observation for an encoder without the split."""
    return tuple(encoder.prep_fields) if splits(encoder) else RAW_FIELDS


def prepare(encoder: nn.Module, robot, humans, humans_mask) -> dict:
    if splits(encoder):
        return encoder.prepare(robot, humans, humans_mask)
    return dict(zip(RAW_FIELDS, (robot, humans, humans_mask), strict=True))


def forward_prepared(encoder: nn.Module, prep: dict):
    if splits(encoder):
        return encoder.forward_prepared(prep)
    return encoder(*(prep[f] for f in RAW_FIELDS))
