"""Bounds the harness keeps on itself: M7 (a worker that cannot load was retried on every track),
M8 (a failure while loading left the worker running), M10 (checkpoints read whole for the
fingerprint, no size bound), M11 and L4 (baseline and oracle overrides unbounded, NaN and booleans)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from crowdbench.leaderboard import run, wire
from crowdbench.leaderboard import worker as worker_mod
from crowdbench.leaderboard.sandbox import Limits
from crowdbench.leaderboard.submission import SubmissionError, read_submission
from crowdbench.leaderboard.worker import WorkerPolicy
from tests.test_isolation import ENCODER, add_straight, make_learned

LIMITS = Limits(step_s=20.0, load_s=120.0, memory_gb=6.0)
REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_a_submission_that_cannot_load_is_rejected_on_every_track_at_once(tmp_path, monkeypatch):
    root = tmp_path / "lb"
    make_learned(root, "broken", ENCODER + "raise ImportError('no such thing')\n")
    starts = []
    init = WorkerPolicy.__init__

    def counting(self, *a, **k):
        starts.append(1)
        return init(self, *a, **k)

    monkeypatch.setattr(WorkerPolicy, "__init__", counting)
    log: list[str] = []
    assert run(root, log=log.append, episodes=3, scenes=["hotel"], tracks=["v1", "v2-orca"], limits=LIMITS) == 1
    errors = [m for m in log if "error" in m]
    assert len(starts) == 1 and len(errors) == 2, (starts, errors)
    assert "(track v1)" in errors[0] and "(track v2-orca)" in errors[1] and "no such thing" in errors[1]


def test_a_failure_while_loading_leaves_no_worker_running(tmp_path, monkeypatch):
    root = tmp_path / "lb"
    make_learned(root, "a", ENCODER)
    procs: list[subprocess.Popen] = []
    popen = subprocess.Popen

    def recording(*a, **k):
        procs.append(popen(*a, **k))
        return procs[-1]

    def deep(*a, **k):  # what a 30,000-deep JSON header does to the harness's decoder
        raise RecursionError("maximum recursion depth exceeded")

    monkeypatch.setattr(worker_mod.subprocess, "Popen", recording)
    monkeypatch.setattr(wire, "recv", deep)
    with pytest.raises(RecursionError):
        WorkerPolicy(root / "submissions" / "a", "a", LIMITS)
    # bubblewrap's one-off usability probe may come first, depending on which test ran before in this process
    workers = [p for p in procs if "crowdbench.leaderboard.worker" in " ".join(map(str, p.args))]
    assert len(workers) == 1 and all(p.poll() is not None for p in procs), procs


def test_a_huge_checkpoint_is_refused_before_it_is_read(tmp_path):
    """M10: a 2 GB sparse checkpoint tripled the harness's memory and took 66 s for the fingerprint."""
    root = tmp_path / "lb"
    add_straight(root)
    make_learned(root, "sparse", ENCODER)
    with open(root / "submissions" / "sparse" / "checkpoint.pt", "r+b") as f:
        f.truncate(2 * 1024 ** 3)  # sparse: no disk used
    with pytest.raises(SubmissionError) as e:
        read_submission(root / "submissions" / "sparse")
    assert e.value.field == "checkpoint" and "2048 MB, more than 256 MB" in str(e.value)
    log: list[str] = []
    assert run(root, log=log.append, episodes=3, scenes=["hotel"], tracks=["v1"]) == 1
    assert [m for m in log if "error" in m and "sparse" in m] and (root / "results" / "straight").is_dir()


@pytest.mark.parametrize(("yaml", "key"), [
    ("kind: oracle\nprivileged: true\noverrides: {beam: 4096, headings: 1024, chunk: 5}\n", "overrides.beam"),
    ("kind: oracle\nprivileged: true\noverrides: {speeds: [1.0, .nan]}\n", "overrides.speeds"),
    ("kind: baseline\npolicy: orca\noverrides: {safety_margin: .nan}\n", "overrides.safety_margin"),
    ("kind: baseline\npolicy: orca\noverrides: {safety_margin: true}\n", "overrides.safety_margin"),
    ("kind: baseline\npolicy: orca\noverrides: {seed: -5}\n", "overrides.seed"),
    ("kind: baseline\npolicy: orca\noverrides: {max_neighbors: 1000000}\n", "overrides.max_neighbors"),
])
def test_baseline_and_oracle_overrides_are_bounded(tmp_path, yaml, key):
    """M11: `{beam: 4096, headings: 1024, chunk: 5}` took the harness to 7.7 GB; L4: NaN, a negative
    seed and `true` were accepted by the harness (and refused by `crowdbench eval`)."""
    d = tmp_path / "submissions" / "b"
    d.mkdir(parents=True)
    (d / "submission.yaml").write_text(f"name: b\n{yaml}authors: [x]\n")
    with pytest.raises(SubmissionError) as e:
        read_submission(d)
    assert e.value.field == key, str(e.value)


def test_the_published_baselines_fit_the_bounds():
    for name in ("orca", "straight", "oracle"):
        read_submission(REPO / "leaderboard" / "submissions" / name)


def test_the_subset_note_states_the_episodes_evaluated():
    """L5: `--episodes 1000000000` was announced as such; an episode list holds 250."""
    from crowdbench.leaderboard.render import _subset_note

    assert "250 episodes per scene" in _subset_note(["hotel"], 10 ** 9)[0]
    assert "5 episodes per scene" in _subset_note(["hotel"], 5)[0]
