"""Training-side compaction of the human slots for the set encoders (SARL, RGL, DS-RNN), opt-in.

The observation pads the humans to the scene's ``M`` slots (75 on students001) while about 20 are
observed (at most ~33 in a batch of 100): SARL's and DS-RNN's per-human MLPs and RGL's ``N x N``
attention spend most of an update on unobserved slots, whose weights are exactly zero. These
encoders are invariant to the slot order, so the *prepared* path (:func:`~crowdbench.models.heads.
prepare_batch` for the training actor, the critics' preprocessing) can move the observed humans to
the front and keep only as many slots as the batch's fullest observation needs.

Why opt-in (``make_encoder(name, compact=True)``): the sums over humans then run in another order
and length, which changes the low-order bits of every training update (not the result up to
rounding: tested), so a run would no longer reproduce one trained without it. The raw
``forward`` (acting, evaluation, the leaderboard) never compacts. Measured in
``benchmarks/profile_update.py --compact``.
"""

from __future__ import annotations

import torch

from crowdbench.models.encoder import SplitEncoder
from crowdbench.models.graph import _gather_rows, flatten_obs, unpack_obs
from crowdbench.models.vmap_once import batch_max

COMPACTABLE = ("sarl", "rgl", "dsrnn")


def compact_humans(humans: torch.Tensor, mask: torch.Tensor):
    """``humans [B, M, F]``, ``mask [B, M]`` -> the observed humans first (slot order kept) and
    ``W = max observed`` slots: ``[B, W, F]``, ``[B, W]``."""
    width = batch_max(mask.sum(-1))
    with torch.no_grad():
        order = torch.argsort((~mask).to(torch.uint8), dim=-1, stable=True)[:, :width]
    return _gather_rows(humans, order), torch.gather(mask, -1, order)


class CompactHumans(SplitEncoder):
    """Mixin (in front of the encoder class, :func:`compacted`) giving a set encoder the preprocessing API with compacted human slots. Its prepared
    ``h_nodes`` follow the compacted slots; gates are only recorded by the raw ``forward``."""

    prep_fields = ("robot", "humans", "humans_mask")
    prep_key = "humans_compact"

    def prepare(self, robot, humans=None, humans_mask=None) -> dict[str, torch.Tensor]:
        robot, humans, mask, lead = flatten_obs(*unpack_obs(robot, humans, humans_mask))
        humans, mask = compact_humans(humans, mask)
        return {"robot": robot.reshape(*lead, -1), "humans": humans.reshape(*lead, *humans.shape[1:]),
                "humans_mask": mask.reshape(*lead, -1)}

    def forward_prepared(self, prep):
        last = self._last
        out = self.forward(prep["robot"], prep["humans"], prep["humans_mask"])
        self._last = last  # compacted slots would name the wrong humans in last_gates
        return out


_CLASSES: dict[type, type] = {}


def compacted(cls: type) -> type:
    """``cls`` with :class:`CompactHumans` (same modules and state_dict keys)."""
    if cls not in _CLASSES:
        _CLASSES[cls] = type(f"Compact{cls.__name__}", (CompactHumans, cls), {"__doc__": cls.__doc__})
    return _CLASSES[cls]
