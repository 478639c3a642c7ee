"""Crowd models: how the humans move. The interface they share is declared here.

A crowd model sees the agents (robots) it shares the scene with only as :class:`Agents`, their state at the
start of the step, never the world that steps it: what it may read is this list, and a model can be
stepped without a world (the oracle's future view, crowdbench/protocols/crowdnav.py, passes ``None``
for a crowd that does not see the robot).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import torch


class Agents(NamedTuple):
    """The agents as a crowd model sees them at the start of a step (``B`` environments, ``A`` agents)."""

    pos: torch.Tensor  # [B, A, 2]
    vel: torch.Tensor  # [B, A, 2]: the velocity of their last step
    present: torch.Tensor  # [B, A] bool: bodies in the scene (running, or done and kept as obstacles)


class Crowd(Protocol):
    """What the world (crowdbench/envs/world.py) and the value lookahead (crowdbench/envs/lookahead.py)
    call: ``M`` human slots, ``t`` the steps since each episode started."""

    name: str
    M: int
    t: torch.Tensor  # [B]

    def reset(self, mask: torch.Tensor, idx: torch.Tensor, episode: dict) -> None:
        """Start the episodes of environments ``idx`` (``mask`` their [B] bool mask) from ``episode``'s keys."""

    def observe(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The humans' ``pos`` ``[B, M, 2]``, ``vel`` ``[B, M, 2]`` and ``valid`` ``[B, M]`` now."""

    def advance(self, env_active: torch.Tensor, agents: Agents | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of the environments in ``env_active`` ``[B]``: the humans' positions before and after it
        (``[B, M, 2]`` each) and which slots are valid after it (``[B, M]``)."""
