"""The results cache: a fingerprint of everything a submission's numbers depend on.

``results.json`` stores it; a submission whose fingerprint is unchanged is not re-evaluated.
It covers the submission's files (yaml, checkpoint, an imported encoder module), the protocol's
episode lists, the evaluation options, a baseline's constructor arguments, and the source of
every crowdbench module an evaluation runs (:func:`code_files`). The harness itself (this
package) is versioned by ``HARNESS_VERSION`` instead.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import json
from pathlib import Path

from crowdbench.envs.protocol import PROTOCOL_VERSION
from crowdbench.leaderboard.submission import REPO_DIR, Submission, policy_params
from crowdbench.leaderboard.tracks import TRACKS, Track, track_config
from crowdbench.numerics import describe

HARNESS_VERSION = 1
# what evaluating a submission runs: the policy registry and the evaluation loop; every crowdbench
# module these import (at any depth) is hashed into the cache fingerprint (code_files)
EVAL_MODULES = ("crowdbench.protocols", "crowdbench.policies", "crowdbench.algos.checkpoint", "crowdbench.models",
                "crowdbench.baselines.oracle", "crowdbench.baselines.orca", "crowdbench.baselines.straight")
# the published lists' hashes can refuse an evaluation, never change a number: a new list's hash is no reason
# to re-evaluate every submission
UNHASHED = ("crowdbench.protocols.lists",)


def _sha(h, path: Path) -> None:
    h.update(str(path.name).encode())
    with path.open("rb") as f:  # in chunks: the same digest as the whole file at once, in bounded memory
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)


def _module_file(name: str) -> Path | None:
    """``crowdbench.a.b`` -> its source file; None for a name that is not a module (an imported attribute)."""
    base = REPO_DIR.joinpath(*name.split("."))
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    return base.with_suffix(".py") if base.with_suffix(".py").is_file() else None


@functools.cache  # one walk per process, not one per submission (~50 ms each)
def code_files(roots=EVAL_MODULES) -> tuple[Path, ...]:
    """Source files of ``roots`` and of every crowdbench module they import, directly or not, with
    the packages' ``__init__.py`` (read statically with ``ast``, including imports inside functions).

    Why not all of ``crowdbench/``: training code (algos/train.py, learner.py) never runs in an
    evaluation, and hashing it made every training change mark all cached results stale.
    tests/test_leaderboard.py checks that every module an evaluation loads is in this list."""
    seen: set[Path] = set()
    todo = list(roots)
    while todo:
        name = todo.pop()
        if any(name == u or name.startswith(f"{u}.") for u in UNHASHED):
            continue
        parts = name.split(".")
        for i in range(1, len(parts) + 1):  # importing a.b.c runs a and a.b first
            path = _module_file(".".join(parts[:i]))
            if path is None or path in seen:
                continue
            seen.add(path)
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("crowdbench"):
                    todo += [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
                elif isinstance(node, ast.Import):
                    todo += [a.name for a in node.names if a.name.startswith("crowdbench")]
    return tuple(sorted(seen))


def fingerprint(sub: Submission, scenes: list[str], episodes: int | None, track: Track = TRACKS["v1"]) -> str:
    # a baseline's arguments come from the config files (env dynamics, orca.* / oracle.*), not only its yaml
    args = None if sub.kind == "learned" else policy_params(sub.yaml_path, sub.data, track_config(track))
    h = hashlib.sha256()
    # the numerical path too: a result computed on other kernels (or another torch) is not this one
    h.update(json.dumps({"harness": HARNESS_VERSION, "protocol": PROTOCOL_VERSION, "scenes": scenes,
                         "episodes": episodes, "policy_args": args, "numerics": describe()}, sort_keys=True).encode())
    if track.name != "v1":
        h.update(json.dumps({"track": track.name}).encode())
    for p in [sub.yaml_path, *([sub.checkpoint] if sub.checkpoint else []), *sub.extra_files]:
        _sha(h, p)
    # the episode lists (CrowdNav's cases are made by code, hashed below)
    for f in track.evaluator.list_files(track, scenes):
        _sha(h, f)
    for f in code_files():
        _sha(h, f)
    return h.hexdigest()
