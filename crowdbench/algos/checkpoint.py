"""Checkpoints: state dicts + config only, written atomically, loaded with ``weights_only=True``."""

from __future__ import annotations

import os
from pathlib import Path

import torch
from tensordict import TensorDict

from crowdbench.envs.policy import ACTION, Policy


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: the message names the file and the problem."""


REQUIRED = ("format", "config", "actor", "frames")
FORMAT = "crowdbench-checkpoint-v1"


def save_checkpoint(path: Path, state: dict) -> None:
    """Write to a temporary file, then rename: a kill mid-write never corrupts the last checkpoint."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save({"format": FORMAT, **state}, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for truncated zips, pickled code, garbage
        reason = " ".join(str(e).split())[:200]
        raise CheckpointError(f"corrupted or unsafe checkpoint {path}: {type(e).__name__}: {reason}") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"not a crowdbench checkpoint: {path} (missing format tag {FORMAT!r})")
    missing = [k for k in REQUIRED if k not in state]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks field(s): {', '.join(missing)}")
    return state


class LearnedPolicy(Policy):
    """A trained actor behind the evaluation :class:`Policy` interface (deterministic actions)."""

    def __init__(self, actor, name: str = "learned", frame: str = "rotate"):
        self.actor, self.name, self.frame = actor, name, frame

    @torch.no_grad()
    def act(self, td: TensorDict) -> torch.Tensor:
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.actor(td.clone(False))[ACTION]


def policy_from_checkpoint(path: Path) -> LearnedPolicy:
    """Rebuild the actor from a checkpoint's config and load its weights (shapes checked)."""
    from crowdbench.algos.builders import build_actor

    state = load_checkpoint(path)
    cfg = state["config"]
    try:
        actor = build_actor(cfg["algo"]["name"], dict(cfg["encoder"]), cfg["env"]["v_max"],
                            squash=cfg["algo"].get("actor_squash", "box"))
        actor.load_state_dict(state["actor"])
    except (KeyError, RuntimeError, ValueError, TypeError) as e:
        reason = " ".join(str(e).split())[:200]
        raise CheckpointError(f"checkpoint {path} does not fit its model: {reason}") from None
    actor.eval()
    name = f"{cfg['algo']['name']}-{cfg['encoder']['name']}"
    return LearnedPolicy(actor, name=name, frame=cfg["env"]["frame"])
