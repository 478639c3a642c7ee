"""Encoders (observation -> node states) and actor / critic heads.

Register a new encoder with ONE line in :data:`ENCODERS`; the heads and algorithms use
only the common interface described in :mod:`crowdbench.models.base`.
"""

from __future__ import annotations

from torch import nn

from crowdbench.models.compact import COMPACTABLE, compacted
from crowdbench.models.dsrnn import DSRNNEncoder
from crowdbench.models.gat import GATEncoder
from crowdbench.models.gatedgcn import GatedGCNEncoder
from crowdbench.models.gcn import GCNEncoder
from crowdbench.models.lstm_rl import LSTMRLEncoder
from crowdbench.models.mlp import MLPEncoder
from crowdbench.models.rgl import RGLEncoder
from crowdbench.models.sarl import SARLEncoder

ENCODERS: dict[str, type[nn.Module]] = {
    "gatedgcn": GatedGCNEncoder,
    "gcn": GCNEncoder,
    "mlp": MLPEncoder,
    "sarl": SARLEncoder,
    "lstm_rl": LSTMRLEncoder,
    "rgl": RGLEncoder,
    "gat": GATEncoder,
    "dsrnn": DSRNNEncoder,
}


def make_encoder(name: str, compact: bool = False, **cfg) -> nn.Module:
    """Instantiate the encoder registered as ``name`` with the config ``cfg``
    (e.g. ``make_encoder(**yaml.safe_load(open("crowdbench/conf/encoder/gatedgcn.yaml")))``).
    ``compact=True``: training-side compaction of the human slots (models/compact.py; sarl, rgl, dsrnn)."""
    if name not in ENCODERS:
        raise ValueError(f"unknown encoder {name!r}; valid encoders: {', '.join(sorted(ENCODERS))}")
    if not compact:
        return ENCODERS[name](**cfg)
    if name not in COMPACTABLE:
        raise ValueError(f"encoder {name!r} has no compacted training path; compactable: {', '.join(COMPACTABLE)}")
    return compacted(ENCODERS[name])(**cfg)


__all__ = ["ENCODERS", "DSRNNEncoder", "GATEncoder", "GCNEncoder", "GatedGCNEncoder", "LSTMRLEncoder", "MLPEncoder",
           "RGLEncoder", "SARLEncoder", "make_encoder"]
