"""Progress and interruption: the training estimate from training rates, the eval and leaderboard progress
bars, Ctrl-C during ``run`` (a checkpoint and the resume command), no third-party noise at start."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest
from test_leaderboard import FAST, add_straight

from crowdbench.algos import train as train_mod
from crowdbench.cli import main
from crowdbench.leaderboard import run

TINY = ["train.pretrain=null", "train.frames_per_batch=128", "algo.warmup=128", "encoder.dim=8", "train.utd=0.25",
        "train.probe_every=1000000", "train.checkpoint_every=1000000", "eval.episodes=2", "eval.scenes=[hotel]"]


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_the_estimate_uses_training_rates_not_the_warm_up(monkeypatch):
    clock = Clock()
    monkeypatch.setattr(train_mod.time, "perf_counter", clock)
    lines = []
    eta = train_mod.DurationEstimate(frames=10_000, updates=1_000, write=lines.append)
    for _ in range(10):  # warm-up: 1,000 random frames at 1,000 frames/s, no updates
        clock.t += 0.1
        eta.collected(100)
    assert eta.remaining_s() is None and eta.postfix() == "warm-up"
    for _ in range(2):  # training: 100 frames in 1 s, 10 updates in 1 s
        clock.t += 1.0
        eta.collected(100)
        clock.t += 1.0
        eta.updated(10)
    # 8,800 frames at 100 frames/s + 980 updates at 10 updates/s; the warm-up rate would say 12 s
    assert eta.remaining_s() == pytest.approx(88 + 98)
    assert eta.postfix() == "03:06" and "~3 min more" in lines[-1]


@pytest.mark.slow
def test_ctrl_c_checkpoints_and_prints_the_resume_command(tmp_path):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    env.pop("RL_WARNINGS", None)  # the console script's defaults, not the test suite's
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "crowdbench", "run", "train.total_frames=100000", *TINY,
                             f"out={out}"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    first = proc.stdout.readline()  # printed once Ctrl-C is handled: the loop stops at its next batch's end
    assert first.startswith("budget: 100,000 frames"), first + proc.stderr.read()
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130, stderr[-2000:]
    last = stderr.strip().splitlines()[-1].split("\r")[-1]
    assert last.startswith("crowdbench: interrupted at ") and f"checkpoint {out}/checkpoint.pt" in last
    assert "Traceback" not in stderr and "[torchrl]" not in first + stdout + stderr
    assert "Warning" not in stdout + stderr  # no third-party warnings either
    assert (out / "checkpoint.pt").is_file() and not (out / "results.json").exists()
    command = last.split("resume with: ", 1)[1].split()
    assert command[:2] == ["crowdbench", "run"] and command[-2:] == [f"out={out}", "resume=true"]
    # the printed command resumes (with a budget the checkpoint already reached: straight to the evaluation)
    args = ["train.total_frames=128" if a.startswith("train.total_frames=") else a.strip("'") for a in command[2:]]
    assert main(["run", *args]) == 0
    assert json.loads((out / "results.json").read_text())["scenes"]["hotel"]["success_rate"]["mean"] >= 0


def test_eval_shows_a_progress_bar_and_the_same_numbers(tmp_path, capsys):
    from crowdbench.policies import build
    from crowdbench.protocols.replay import evaluate

    assert main(["eval", "policy=straight", "eval.episodes=3", "eval.scenes=[hotel,eth]", f"out={tmp_path}/e"]) == 0
    err = capsys.readouterr().err
    assert "eval straight" in err and "100%" in err and "eth" in err
    cli = json.loads((tmp_path / "e" / "results.json").read_text())["scenes"]
    assert evaluate(build("straight"), ["hotel", "eth"], 3)["scenes"] == cli  # the bar changes no number


def test_leaderboard_shows_a_progress_bar_per_submission_and_track(tmp_path, capsys):
    add_straight(tmp_path)
    assert run(tmp_path, progress=True, **FAST) == 0
    err = capsys.readouterr().err
    assert "leaderboard" in err and "straight on v1" in err and "1/1" in err
