"""M15 (`submit` took the checkpoint of a run still training) and L2 (a worker that died silently was
reported with runpy's start-up warning as its last words)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from crowdbench.cli import UsageError, submit_run
from crowdbench.leaderboard.sandbox import Limits
from crowdbench.leaderboard.worker import WorkerError, WorkerPolicy
from tests.test_isolation import ENCODER, make_learned

HOLD = "import sys, time\nfrom pathlib import Path\nfrom crowdbench.outputs import claim_dir\n" \
       "with claim_dir(Path(sys.argv[1]), 'out'):\n    print('held', flush=True)\n    time.sleep(120)\n"


def test_submit_refuses_a_run_that_is_still_training(tmp_path):
    run = tmp_path / "live"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"a checkpoint being rewritten")
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UsageError) as e:
            submit_run(run, "livesub", "Live", ["a"], None, None, tmp_path / "lb", None)
    finally:
        holder.kill()
        holder.wait()
    assert f"{run} is in use by another run (pid {holder.pid})" in str(e.value)
    assert not (tmp_path / "lb").exists()


def test_a_silent_exit_has_no_borrowed_last_words(tmp_path):
    make_learned(tmp_path, "quiet", ENCODER + "import os\nos._exit(7)\n")
    with pytest.raises(WorkerError) as e:
        WorkerPolicy(tmp_path / "submissions" / "quiet", "quiet", Limits(load_s=120.0, memory_gb=6.0))
    assert "exited with code 7 while loading" in str(e.value)
    assert "last words" not in str(e.value) and "runpy" not in str(e.value), str(e.value)
