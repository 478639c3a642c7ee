"""crowdbench's Python API (docs/api.md): policies, evaluation on any protocol with the numbers
``crowdbench eval`` and the leaderboard compute, and envs by name.

Import it before torch and numpy (``from crowdbench import api`` first): it pins the numerical path
then, as the ``crowdbench`` command does (crowdbench/numerics.py), because torch picks its kernels at
its first operation and numpy its CPU features at import. :func:`evaluate` refuses to give official
numbers on another path (:func:`check_numerics`; ``pinned=False``: this machine's kernels, faster, unofficial).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from crowdbench.numerics import PINNED, pin

if "torch" not in sys.modules and "numpy" not in sys.modules:
    pin()


def __getattr__(name: str):
    # PROTOCOLS: the registered tracks (crowdbench/protocols/), read when asked, not at import (before the pin)
    if name == "PROTOCOLS":
        from crowdbench.protocols import tracks

        return tuple(tracks())
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class NumericsError(RuntimeError):
    """The pinned numerical path could not be applied (torch or numpy started before it)."""


def check_numerics() -> dict:
    """What computes evaluations now (``crowdbench.numerics.describe``), after checking it is the pinned path."""
    from numpy._core._multiarray_umath import __cpu_features__ as numpy_features

    from crowdbench.numerics import describe

    now = describe()
    wrong = [k for k, v in PINNED.items() if os.environ.get(k) != v]
    if now["cpu_capability"] != "DEFAULT":
        wrong.append(f"torch kernels {now['cpu_capability']}")
    if any(numpy_features.get(f) for f in ("X86_V4", "AVX512_ICL", "AVX512_SPR")):
        wrong.append("numpy AVX-512 kernels")
    if wrong:
        raise NumericsError(f"not the pinned numerical path ({', '.join(wrong)}): import crowdbench.api before "
                            "torch and numpy, or pass pinned=False (unofficial numbers)")
    return now


def policy(name: str | Path, **overrides):
    """A policy: ``orca``, ``straight``, ``oracle`` (privileged), or a checkpoint path; ``overrides`` are
    the baseline's parameters (``safety_margin=0`` for ORCA, as ``orca.safety_margin=0`` on the command line)."""
    from crowdbench.policies import build

    return build(str(name), overrides=overrides or None)


def evaluate(policy, protocol: str = "v1", scenes: list[str] | None = None, episodes: int | None = None,
             out_dir: Path | str | None = None, pinned: bool = True) -> dict:
    """The results dict of ``policy`` on ``protocol`` (:data:`PROTOCOLS`), as ``crowdbench eval`` writes it.

    ``scenes``: replay protocols only (default: the four paper scenes, as ``crowdbench eval``);
    ``episodes``: N evenly strided episodes per scene or setting (unofficial); ``out_dir``: also write
    ``results.json`` and ``episodes.jsonl`` there."""
    from crowdbench.envs.protocol import PAPER_SCENES
    from crowdbench.leaderboard.tracks import TRACKS, track_config

    protocols = __getattr__("PROTOCOLS")
    if protocol not in protocols:
        raise ValueError(f"unknown protocol {protocol!r}; valid: {', '.join(protocols)}")
    if scenes and not TRACKS[protocol].replay:
        raise ValueError(f"scenes apply to the replay protocols; {protocol} has one setting, "
                         f"{TRACKS[protocol].setting}")
    if pinned:
        check_numerics()
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the leaderboard: the reductions, hence the last digits, do not depend on cores
    try:
        return _evaluate(policy, TRACKS[protocol], scenes or PAPER_SCENES, episodes, out_dir, track_config)
    finally:
        torch.set_num_threads(threads)


def _evaluate(policy, track, scenes: list[str], episodes: int | None, out_dir, track_config) -> dict:
    out = Path(out_dir) if out_dir is not None else None
    meta = {"api": True, "protocol": track.name}
    return track.evaluator.evaluate_track(track, policy, scenes, episodes, out, meta, env=track_config(track)["env"],
                                          save_episodes=out is not None)


def make_env(name: str, api: str = "torchrl", seed: int = 0, batch: int = 1, **env):
    """Env ``name`` (``replay``, ``reactive_replay``, ``crowdnav``, ``selfplay``) through ``api``
    (``torchrl``, ``pettingzoo``, ``gymnasium``); ``env``: keys of its config group
    (crowdbench/envs/registry.py). Importing this module also registers the Gymnasium ids."""
    from crowdbench.envs.registry import make

    return make(name, api=api, seed=seed, batch=batch, **env)


import crowdbench.envs.registry  # noqa: F401 - registers the Gymnasium ids (after the pin: it imports torch)
