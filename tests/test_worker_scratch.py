"""Unconfined workers' scratch directories (``--sandbox none``): a harness killed with SIGKILL cannot
remove its worker's; the next harness removes those whose harness is gone, and no other."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from crowdbench.leaderboard.sandbox import Limits

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "leaderboard" / "submissions" / "gatedgcn_td3_s0"
LIMITS = Limits(step_s=60.0, load_s=120.0, memory_gb=6.0, sandbox="none")

HARNESS = """
import sys, time
from crowdbench.leaderboard.sandbox import Limits
from crowdbench.leaderboard.worker import WorkerPolicy
p = WorkerPolicy(sys.argv[1], "g", Limits(step_s=60.0, load_s=120.0, memory_gb=6.0, sandbox="none"))
print("ready", flush=True)
time.sleep(600)
"""


def scratch_dirs(tmp: Path) -> set[str]:
    return {d.name for d in tmp.glob("crowdbench-worker-*")}


@pytest.mark.slow
def test_a_killed_harness_leaves_no_scratch_behind_the_next_one(tmp_path, monkeypatch):
    """L14: each SIGKILL of the harness left one /tmp/crowdbench-worker-* behind for good."""
    from crowdbench.leaderboard.worker import WorkerPolicy

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    sub = tmp_path / "lb" / "submissions" / SHIPPED.name  # (a submission is named as its directory)
    shutil.copytree(SHIPPED, sub)
    harness = subprocess.Popen([sys.executable, "-c", HARNESS, str(sub)], stdout=subprocess.PIPE, text=True,
                               env={**os.environ, "TMPDIR": str(tmp)})
    assert harness.stdout.readline().strip() == "ready"
    left = scratch_dirs(tmp)
    assert len(left) == 1
    harness.send_signal(signal.SIGKILL)
    harness.wait()
    time.sleep(0.5)
    assert scratch_dirs(tmp) == left  # a SIGKILL runs no cleanup: still there
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    with WorkerPolicy(sub, "g", LIMITS):
        mine = scratch_dirs(tmp)
        assert len(mine) == 1 and not mine & left  # the dead harness's removed, this one's made
    assert scratch_dirs(tmp) == set()


def test_only_scratch_of_harnesses_that_are_gone_is_removed(tmp_path):
    from crowdbench.leaderboard.worker import SCRATCH_PREFIX
    from crowdbench.outputs import reap_dead

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    for name in (f"{SCRATCH_PREFIX}-{gone.pid}-abc", f"{SCRATCH_PREFIX}-{os.getpid()}-def",
                 f"{SCRATCH_PREFIX}-xyz", "other-1-x"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "file").write_text("x")
    reap_dead(tmp_path, SCRATCH_PREFIX)
    assert {d.name for d in tmp_path.iterdir()} == {f"{SCRATCH_PREFIX}-{os.getpid()}-def", f"{SCRATCH_PREFIX}-xyz",
                                                    "other-1-x"}
