"""Writing under faults: a full disk, a kill mid-write, a read-only root, shared file permissions.

A full disk is simulated with ``RLIMIT_FSIZE`` (a write past it fails with ``EFBIG``, as one past a full
disk fails with ``ENOSPC``): no privileges needed, and only this process is limited, for the block.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from crowdbench.cli import main

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "leaderboard" / "submissions" / "gatedgcn_td3_s0"


@contextlib.contextmanager
def disk_full(max_bytes: int):
    """Files written in the block cannot grow past ``max_bytes`` (the soft limit only: restorable)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (max_bytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)


def a_run(tmp_path: Path) -> Path:
    """A run directory: the shipped submission's checkpoint holds what submit reads (config, actor)."""
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(SHIPPED / "checkpoint.pt", run / "checkpoint.pt")
    return run


def test_checkpoints_and_submissions_get_the_mode_of_any_other_file(tmp_path):
    """L11: a checkpoint was 0600 (mkstemp's) while results and logs follow the umask."""
    from crowdbench.algos.checkpoint import save_checkpoint
    from crowdbench.leaderboard.submission import make_submission
    from crowdbench.outputs import save_torch_atomic

    old = os.umask(0o022)
    try:
        plain = tmp_path / "plain.txt"
        plain.write_text("x")
        (tmp_path / "plain_dir").mkdir()
        save_checkpoint(tmp_path / "checkpoint.pt", {"frames": 0})  # (a submission's)
        save_torch_atomic(tmp_path / "training.pt", {"frames": 0})  # (a training run's)
        sub = make_submission(a_run(tmp_path), "mine", "Mine", ["me"], ["seed=0"], root=tmp_path / "lb")
    finally:
        os.umask(old)
    mode = plain.stat().st_mode & 0o777
    assert (tmp_path / "checkpoint.pt").stat().st_mode & 0o777 == mode
    assert (tmp_path / "training.pt").stat().st_mode & 0o777 == mode
    assert (sub / "checkpoint.pt").stat().st_mode & 0o777 == mode
    assert sub.stat().st_mode & 0o777 == (tmp_path / "plain_dir").stat().st_mode & 0o777


def test_eval_on_a_full_disk_leaves_no_results_and_the_retry_works(tmp_path, capsys):
    """L17: a complete results.json with an empty episodes.jsonl made the retry refuse the directory."""
    args = ["eval", "policy=straight", "eval.scenes=[hotel]", "eval.episodes=20", "eval.save_episodes=true",
            f"out={tmp_path / 'e'}"]
    with disk_full(8 * 1024):  # results.json fits, the 20 episodes' paths do not
        assert main(args) == 2
    err = capsys.readouterr().err
    (line,) = [ln for ln in err.splitlines() if ln.strip() and "step/s" not in ln]  # (not the progress bar)
    assert line.startswith("crowdbench: error: cannot write") and "File too large" in line
    assert not (tmp_path / "e" / "results.json").exists()
    assert main(args) == 0
    rows = (tmp_path / "e" / "episodes.jsonl").read_text().splitlines()
    assert len(rows) == 20 and json.loads((tmp_path / "e" / "results.json").read_text())["policy"] == "straight"


def test_submit_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, capsys):
    """L17: torch's writer failed with ``RuntimeError: [enforce fail at inline_container.cc]``."""
    run, root = a_run(tmp_path), tmp_path / "lb"
    with disk_full(4 * 1024):  # the slim checkpoint is ~40 kB
        rc = main(["submit", str(run), "--name", "mine", "--entry", "Mine", "--root", str(root)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "File too large" in err, err
    assert not (root / "submissions" / "mine").exists()
    assert main(["submit", str(run), "--name", "mine", "--entry", "Mine", "--root", str(root)]) == 0
    assert {p.name for p in (root / "submissions" / "mine").iterdir()} == {"checkpoint.pt", "submission.yaml"}


KILL_AT_YAML = """
import os, signal, sys
import yaml
from crowdbench.cli import main
yaml.safe_dump = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)  # killed after the checkpoint is written
main(sys.argv[1:])
"""


@pytest.mark.slow
def test_a_submit_killed_midway_leaves_no_half_submission(tmp_path):
    """L16: a kill left submissions/NAME/ with only checkpoint.pt; submit then refused the name and the
    leaderboard rejected it (missing submission.yaml)."""
    run, root = a_run(tmp_path), tmp_path / "lb"
    args = ["submit", str(run), "--name", "mine", "--entry", "Mine", "--root", str(root)]
    p = subprocess.run([sys.executable, "-c", KILL_AT_YAML, *args], check=False, capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == -signal.SIGKILL
    assert not (root / "submissions" / "mine").exists()
    assert main(args) == 0
    assert {p.name for p in (root / "submissions" / "mine").iterdir()} == {"checkpoint.pt", "submission.yaml"}
    assert list((root / ".building").iterdir()) == []  # the killed process's partial copy is gone


@pytest.mark.slow
def test_a_run_that_cannot_write_does_not_claim_a_kept_checkpoint(tmp_path, capsys, monkeypatch):
    """L17: 'the last checkpoint (...) is kept' was printed when no checkpoint had been written."""
    from torchrl.record.loggers.csv import CSVLogger

    def full(self, name, value, step=None):  # the disk is full when the first scalars are logged
        raise OSError(28, "No space left on device", str(tmp_path / "r" / "logs"))

    monkeypatch.setattr(CSVLogger, "log_scalar", full)
    tiny = ["train.pretrain=null", "train.total_frames=256", "train.frames_per_batch=128", "algo.warmup=128", "encoder.dim=8",
            "train.probe_every=1000000", "train.checkpoint_every=1000000", "eval.episodes=2", "eval.scenes=[hotel]"]
    assert main(["run", *tiny, f"out={tmp_path / 'r'}"]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and not (tmp_path / "r" / "checkpoint.pt").exists()
    assert "is kept" not in err


def read_only(path: Path):
    """``path`` made read-only: a read-only bind mount as root (which ignores modes), else chmod."""
    if os.geteuid() != 0:
        path.chmod(0o555)
        return lambda: path.chmod(0o755)
    mount = shutil.which("mount")
    p = mount and subprocess.run([mount, "--bind", "-o", "ro", str(path), str(path)], check=False,
                                    capture_output=True)
    if not p or p.returncode:
        pytest.skip("cannot make a read-only directory here (root without mount)")
    return lambda: subprocess.run(["umount", str(path)], check=True)


def test_a_read_only_root_is_refused_before_any_evaluation(tmp_path, capsys):
    """L15: a read-only --root failed with a traceback, after evaluating with --force."""
    root = tmp_path / "lb"
    shutil.copytree(REPO / "leaderboard" / "submissions" / "straight", root / "submissions" / "straight")
    undo = read_only(root)
    try:
        rc = main(["leaderboard", "--root", str(root), "--episodes", "1", "--scenes", "hotel", "--tracks", "v1",
                   "--force"])
    finally:
        undo()
    out = capsys.readouterr()
    text = out.err + out.out
    assert rc != 0 and "is not writable" in text and "Traceback" not in text
    assert "evaluated" not in text and not (root / "results").exists()
