"""M15 (`submit` took the checkpoint of a run still training), L1 (a worker's exception text, which
can quote any file it reads, was published in the README) and L2 (a worker that died silently was
reported with runpy's start-up warning as its last words)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from crowdbench.app import UsageError
from crowdbench.cli_submit import submit_run
from crowdbench.leaderboard import run
from crowdbench.leaderboard.sandbox import Limits
from crowdbench.leaderboard.worker import WorkerError, WorkerPolicy
from tests.test_isolation import ENCODER, add_straight, make_learned

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


@pytest.mark.slow
def test_a_silent_exit_has_no_borrowed_last_words(tmp_path):
    make_learned(tmp_path, "quiet", ENCODER + "import os\nos._exit(7)\n")
    with pytest.raises(WorkerError) as e:
        WorkerPolicy(tmp_path / "submissions" / "quiet", "quiet", Limits(load_s=120.0, memory_gb=6.0))
    assert "exited with code 7 while loading" in str(e.value)
    assert "last words" not in str(e.value) and "runpy" not in str(e.value), str(e.value)


@pytest.mark.slow  # two worker processes; the quick suite keeps one worker test per concern
def test_the_readme_publishes_no_text_a_worker_wrote(tmp_path):
    add_straight(tmp_path)
    make_learned(tmp_path, "leak", ENCODER + "raise RuntimeError('LEAK ' + open('/etc/hostname').read()[:20])\n")
    make_learned(tmp_path, "talk", ENCODER + "import os, sys\nsys.stderr.write('LEAK words\\n')\nos._exit(3)\n")
    log: list[str] = []
    assert run(tmp_path, log=log.append, episodes=3, scenes=["hotel"], tracks=["v1"],
               limits=Limits(load_s=120.0, memory_gb=6.0)) == 1
    errors = [m for m in log if "error" in m]
    assert len(errors) == 2 and all("LEAK" in m for m in errors), errors  # the log keeps the detail
    rejected = (tmp_path / "README.md").read_text().split("## Rejected")[1]
    assert "LEAK" not in rejected
    assert "leak/submission.yaml: field 'encoder_import': refused by its worker while loading (details in the harness log)" \
        in " ".join(rejected.split())
    assert "exited with code 3 while loading; its last words are in the harness log" in rejected


def test_a_runs_recorded_overrides_keep_how_it_trained_only(tmp_path):
    """Seeds of one row must record the same training: where a run ran, what it evaluated after training and
    how it logged are not part of it (a seed run with ``eval.episodes=1`` was refused as another method)."""
    import json

    from crowdbench.cli_submit import command_overrides

    got = ["experiment=value_crowdnav", "algo.lookahead=cv", "seed=1", "cpus=2", "out=/x", "resume=true",
           "eval.episodes=1", "eval.scenes=[hotel]", "viz.record=true", "train.logger=tensorboard"]
    (tmp_path / "results.json").write_text(json.dumps({"meta": {"overrides": got}}))
    assert command_overrides(tmp_path) == ["experiment=value_crowdnav", "algo.lookahead=cv", "seed=1", "cpus=2"]
    assert command_overrides(tmp_path / "missing") is None
