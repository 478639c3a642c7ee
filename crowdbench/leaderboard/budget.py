"""A wall-clock budget per learned submission and track (docs/submitting.md, "What the harness
protects"): ``--budget-factor`` times what the reference policy, ORCA, takes on the same track,
scenes and episodes in this run, and never less than ``Limits.budget_floor_s``.

Why on top of the per-step timeout and the CPU limit: a worker that sleeps just under the step
timeout uses no CPU, and at 60 s per step it would hold the leaderboard for days per track. Why
relative to ORCA: the budget then scales with the protocol's size and the machine's speed, so the
same factor holds for a 5-episode check and the full protocol, on a laptop or a loaded server.
The budget counts from the loaded worker's first step (starting and loading have ``load_s``).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

from crowdbench import policies
from crowdbench.leaderboard.sandbox import Limits
from crowdbench.leaderboard.submission import baseline_args
from crowdbench.leaderboard.tracks import TRACKS, evaluate_track, track_config

REFERENCE = "orca"


def reference_seconds(track: str, scenes: list[str], episodes: int | None) -> float:
    """Wall time of ORCA (built as its submission is, default parameters) on ``track``."""
    t_ = TRACKS[track]
    policy = policies.build(*baseline_args({"kind": "baseline", "policy": REFERENCE}, track_config(t_)))
    with tempfile.TemporaryDirectory(prefix="crowdbench-budget-") as tmp:
        t = time.monotonic()
        evaluate_track(t_, policy, scenes, episodes, Path(tmp), {"submission": REFERENCE})
        return time.monotonic() - t


def with_budgets(limits: Limits, tracks: list[str], scenes: list[str], episodes: int | None, log) -> Limits:
    """``limits`` with the budget of each of ``tracks`` (measured here, once per run)."""
    out = []
    for track in tracks:
        ref = reference_seconds(track, scenes, episodes)
        budget = max(limits.budget_floor_s, limits.budget_factor * ref)
        log(f"track {track}: wall-clock budget per learned submission {budget:.0f} s "
            f"({limits.budget_factor:g} x ORCA's {ref:.1f} s, at least {limits.budget_floor_s:g} s)")
        out.append((track, budget))
    return dataclasses.replace(limits, budgets=tuple(out))


def budget_of(limits: Limits, track: str) -> float | None:
    return dict(limits.budgets).get(track)
