"""M6 / issue 30 item 3: a submission that sleeps under the per-step timeout (no CPU used) held the
leaderboard for 257 s on 5 episodes; a wall-clock budget per submission and track, relative to
ORCA's time on the same track, makes it one rejection line while the others finish."""

from __future__ import annotations

import re

import pytest

from crowdbench.leaderboard import run
from crowdbench.leaderboard.sandbox import Limits, bubblewrap
from crowdbench.leaderboard.worker import WorkerPolicy
from tests.test_entries import add_orca
from tests.test_isolation import ENCODER, add_straight, make_learned

FAST = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}
SLEEPER = '''
import time
_f = Enc.forward
def _slow(self, robot, *a, **k):
    if robot.shape[0] > 2:  # (not the harness's load-time check on a 2-batch)
        time.sleep(1.0)
    return _f(self, robot, *a, **k)
Enc.forward = _slow
'''


def rows(readme: str) -> list[str]:
    return [ln for ln in readme.splitlines() if re.match(r"\| (\d+|—) \| (Straight to goal|ORCA) \|", ln)]


@pytest.mark.slow
def test_a_sleeping_submission_is_one_rejection_and_the_other_rows_stay(tmp_path, monkeypatch):
    # the straight and ORCA rows of a run without it, to compare byte for byte
    clean = tmp_path / "clean"
    add_straight(clean)
    add_orca(clean)
    make_learned(clean, "honest", ENCODER)
    lim = Limits(step_s=20.0, load_s=120.0, memory_gb=6.0, budget_factor=20.0, budget_floor_s=8.0)
    assert run(clean, log=lambda m: None, limits=lim, **FAST) == 0

    root = tmp_path / "lb"
    add_straight(root)
    add_orca(root)
    make_learned(root, "honest", ENCODER)
    make_learned(root, "sleeper", ENCODER + SLEEPER)
    steps: dict[str, int] = {}
    act = WorkerPolicy.act

    def counting(self, td):
        steps[self.name] = steps.get(self.name, 0) + 1
        return act(self, td)

    monkeypatch.setattr(WorkerPolicy, "act", counting)
    log: list[str] = []
    assert run(root, log=log.append, limits=lim, **FAST) == 1
    (line,) = [m for m in log if "error" in m]
    assert "submissions/sleeper/" in line and "wall-clock budget" in line and "ORCA's time on track v1" in line
    # bounded work: 100 steps of 1 s without a budget; at 8 s (20 x ORCA's time is less here) about 8
    assert steps["sleeper"] <= 20 < steps["honest"], steps
    budget = [m for m in log if m.startswith("track v1: wall-clock budget")]
    assert len(budget) == 1 and re.search(r"budget per learned submission \d+ s \(20 x ORCA's", budget[0])
    for name in ("straight", "orca", "honest"):
        assert (root / "results" / name / "results.json").read_bytes() == \
            (clean / "results" / name / "results.json").read_bytes(), name
    assert rows((root / "README.md").read_text()) == rows((clean / "README.md").read_text()) != []


def test_every_run_starts_by_saying_whether_submitted_code_is_confined(tmp_path):
    """Issue 30 item 3: said even when no learned submission is evaluated."""
    add_straight(tmp_path)
    log: list[str] = []
    assert run(tmp_path, log=log.append, **FAST) == 0
    want = "CONFINED by bubblewrap" if bubblewrap() else "NOT confined"
    assert log[0].startswith("submitted code runs in worker processes") and want in log[0], log[0]
