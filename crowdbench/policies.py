"""The policy registry: the one place where baselines, the oracle and checkpoints are built.

``crowdbench eval policy=NAME`` (cli.py) and the leaderboard harness both call :func:`build`,
so a baseline gets the same arguments either way: the env config's dynamics (``v_max``, ``dt``,
radii), its section of ``conf/config.yaml`` (``orca.*``, ``oracle.*``), the seed, then the
caller's overrides (crowdbench/baselines/params.py). Layering: this module may import
envs/baselines/algos; cli.py and the leaderboard import it, never the reverse.
"""

from __future__ import annotations

from pathlib import Path

# the baselines' names and arguments live below the algorithms (the ORCA warm start reads them); re-exported
from crowdbench.baselines.params import (  # noqa: F401
    BASELINES,
    CONF_DIR,
    ENV_ARGS,
    NAMES,
    PRIVILEGED,
    SEEDED,
    PolicyError,
    default_config,
    params,
)


def _class(name: str):
    if name == "orca":
        from crowdbench.baselines.orca import ORCA

        return ORCA
    if name == "straight":
        from crowdbench.baselines.straight import StraightToGoal

        return StraightToGoal
    from crowdbench.baselines.oracle import Oracle

    return Oracle


def from_checkpoint(path: Path | str):
    """The deterministic policy of a training checkpoint (``weights_only=True``: never runs pickled code)."""
    from crowdbench.algos.checkpoint import CheckpointError, policy_from_checkpoint

    try:
        return policy_from_checkpoint(Path(path))
    except CheckpointError as e:
        raise PolicyError(str(e)) from None


def build(name: str, cfg=None, overrides: dict | None = None):
    """A :class:`~crowdbench.envs.observation.Policy`: one of :data:`NAMES` or a checkpoint path."""
    if name in NAMES:
        kwargs = params(name, cfg, overrides)
        try:
            return _class(name)(**kwargs)
        except (TypeError, ValueError) as e:
            raise PolicyError(f"{name}: {e}") from None
    if name.endswith(".pt") or Path(name).is_file():
        return from_checkpoint(name)
    raise PolicyError(f"unknown policy {name!r}; valid: {', '.join(NAMES)} or a checkpoint path")
