"""Run and evaluation directories: one writer at a time, no silent overwrite, unwritable outputs found
before any work, logs and checkpoints that survive kills, resume with the saved replay buffer."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch

import crowdbench.algos.train as train_mod
from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint
from crowdbench.algos.offpolicy import make_buffer
from crowdbench.algos.resume import restore_buffer, save_buffer, truncate_log
from crowdbench.algos.train import train
from crowdbench.cli import compose, main
from crowdbench.outputs import LOCK_NAME

TINY = ["train.pretrain=null", "env.batch=8", "train.frames_per_batch=64", "algo.warmup=128", "algo.batch_size=16", "train.utd=0.125",
        "train.checkpoint_every=128", "algo=td3", "encoder=mlp", "encoder.dim=16", "encoder.hidden=[32]",
        "algo.buffer_size=4096"]
EVAL = ["eval.episodes=2", "eval.scenes=[hotel]"]
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def expected_updates(frames: int) -> int:
    """TINY: 8 updates per 64-frame batch once the buffer holds the 128 warm-up transitions."""
    return 8 * (frames // 64 - 1)


def one_line_error(capsys, *needles):
    err = capsys.readouterr().err
    line = err.rstrip("\n").split("\r")[-1].split("\n")[-1]  # after the progress bar
    assert line.startswith("crowdbench: error: ") and err.endswith(line + "\n") and "Traceback" not in err, err
    for n in needles:
        assert str(n) in err, err
    return err


def snapshot(d):
    return {p.relative_to(d): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_a_directory_in_use_is_refused(tmp_path, capsys):
    """Finding 6: a second run (or an evaluation) into a directory another process holds fails at once."""
    holder = subprocess.Popen([sys.executable, "-c", ("import time; from crowdbench.outputs import claim_dir\n"
                               f"with claim_dir({str(tmp_path)!r}):\n print('held', flush=True); time.sleep(120)")],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": ROOT})
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(tmp_path)
        assert main(["run", *TINY, "train.total_frames=128", f"out={tmp_path}"]) == 2
        one_line_error(capsys, f"{tmp_path} is in use by another run (pid {holder.pid})")
        assert main(["eval", "policy=straight", *EVAL, f"out={tmp_path}"]) == 2
        one_line_error(capsys, "is in use by another run")
        assert snapshot(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()
    assert main(["eval", "policy=straight", *EVAL, f"out={tmp_path}"]) == 0  # released when its holder dies
    assert not (tmp_path / LOCK_NAME).exists() and (tmp_path / "results.json").is_file()


def test_eval_never_silently_replaces_results(tmp_path, capsys):
    """Finding 12: eval into a directory that holds results.json refuses unless eval.overwrite=true."""
    assert main(["eval", "policy=straight", *EVAL, f"out={tmp_path}"]) == 0
    saved = (tmp_path / "results.json").read_bytes()
    capsys.readouterr()
    assert main(["eval", "policy=orca", *EVAL, f"out={tmp_path}"]) == 2
    one_line_error(capsys, tmp_path / "results.json", "eval.overwrite=true")
    assert (tmp_path / "results.json").read_bytes() == saved
    assert main(["eval", "policy=orca", *EVAL, f"out={tmp_path}", "eval.overwrite=true"]) == 0
    assert json.loads((tmp_path / "results.json").read_text())["policy"] == "orca"


def test_partial_and_garbled_log_rows_do_not_block_resume(tmp_path):
    """Finding 15: a kill mid-row leaves `4096` without a value; resume drops such rows, atomically."""
    train(compose([*TINY, "train.total_frames=256"]), tmp_path, progress=False)
    log = tmp_path / "logs" / "scalars" / "updates.csv"
    good = log.read_text()
    log.write_text(good + "4x6,1.0\n,\n300,abc\n4096")
    truncate_log(tmp_path / "logs", 256)
    assert log.read_text() == good
    log.write_text(good + "200")  # a step before the checkpoint's: the row cannot be dropped for its step
    stats = train(compose([*TINY, "train.total_frames=384"]), tmp_path, resume=True, progress=False)
    assert stats["frames"] == 384
    rows = [line.split(",") for line in log.read_text().splitlines()]
    assert all(len(r) == 2 for r in rows) and [int(r[0]) for r in rows] == list(range(64, 385, 64))
    assert not [p for p in log.parent.iterdir() if p.suffix != ".csv"]  # no temporary file left


@pytest.mark.parametrize("kind", ["file", "under_file", "read_only"])
def test_unwritable_eval_output_fails_before_evaluating(kind, tmp_path, capsys, monkeypatch):
    """Finding 17: found before the evaluation runs (root ignores permissions: read-only is simulated)."""
    import crowdbench.protocols.replay

    monkeypatch.setattr(crowdbench.protocols.replay, "evaluate", lambda *a, **k: pytest.fail("evaluated"))
    blocker = tmp_path / "a_file"
    blocker.write_text("keep")
    out = {"file": blocker, "under_file": blocker / "sub", "read_only": tmp_path / "ro" / "out"}[kind]
    if kind == "read_only":
        (tmp_path / "ro").mkdir()
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, m: False if str(p) == str(tmp_path / "ro") else real(p, m))
    assert main(["eval", "policy=straight", *EVAL, f"out={out}"]) == 2
    one_line_error(capsys, out)
    assert blocker.read_text() == "keep" and not (tmp_path / "ro" / "out").exists()


def test_unwritable_run_and_viz_outputs(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(train_mod, "train", lambda *a, **k: pytest.fail("trained"))
    blocker = tmp_path / "a_file"
    blocker.write_text("keep")
    assert main(["run", *TINY, f"out={blocker}"]) == 2
    one_line_error(capsys, f"out={blocker} is not a directory")
    assert main(["eval", "policy=straight", *EVAL, "eval.save_episodes=true", f"out={tmp_path / 'e'}"]) == 0
    assert main(["viz", str(tmp_path / "e"), "--out", str(blocker / "x.png")]) == 2
    one_line_error(capsys, blocker)
    assert main(["plot", str(tmp_path / "e"), "--out", str(tmp_path)]) == 2
    one_line_error(capsys, f"{tmp_path} is a directory")


def test_eval_results_write_failure_is_one_line(tmp_path, capsys, monkeypatch):
    import crowdbench.protocols.replay

    def refuse(out_dir, *a, **k):
        raise PermissionError(13, "Permission denied", str(out_dir / "results.json"))

    monkeypatch.setattr(crowdbench.protocols.replay, "write_results", refuse)
    assert main(["eval", "policy=straight", *EVAL, f"out={tmp_path}"]) == 2
    one_line_error(capsys, f"cannot write {tmp_path / 'results.json'}: Permission denied")


def test_a_checkpoint_that_cannot_be_written_keeps_the_previous_one(tmp_path, capsys, monkeypatch):
    """Finding 17: out dir read-only mid-run (simulated): one line, the last checkpoint and its buffer stay."""
    real, calls = train_mod.save_torch_atomic, []

    def read_only_later(path, state):
        calls.append(state["frames"])
        if len(calls) > 1:
            raise PermissionError(13, "Permission denied", str(path.parent / ".checkpoint.pt.x.tmp"))
        real(path, state)

    monkeypatch.setattr(train_mod, "save_torch_atomic", read_only_later)
    assert main(["run", *TINY, *EVAL, "train.total_frames=512", f"out={tmp_path}"]) == 2
    one_line_error(capsys, f"cannot write the checkpoint in {tmp_path}: Permission denied",
                   "the previous checkpoint is kept")
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["frames"] == calls[0] == 128
    assert (tmp_path / state["replay"]["dir"]).is_dir() and not (tmp_path / "results.json").exists()


def test_an_actor_only_checkpoint_cannot_be_resumed(tmp_path, capsys):
    """Finding 19: a submitted checkpoint (config, actor, frames, updates, wall_time_s) named as such."""
    shipped = os.path.join(ROOT, "leaderboard", "submissions", "mlp_td3_s0", "checkpoint.pt")
    shutil.copy(shipped, tmp_path / "checkpoint.pt")
    assert main(["run", "encoder=mlp", f"out={tmp_path}", "resume=true"]) == 2
    one_line_error(capsys, f"{tmp_path / 'checkpoint.pt'} is an actor-only (submitted) checkpoint; "
                           "it cannot be resumed")


@pytest.mark.parametrize("args, message", [
    (["train.total_frames=-5"], "train.total_frames: must be >= 1 (got -5)"),
    (["seed=abc"], "seed: must be an integer"),
    (["algo.exploration=pink"], "algo.exploration: must be one of gaussian, ou (got 'pink')"),
    (["resume=true"], "checkpoint not found"),
])
def test_a_run_that_fails_validation_leaves_no_directory(args, message, tmp_path, capsys):
    """Finding 20: no out dir is created (or left behind) by a run that never started."""
    out = tmp_path / "new" / "run"
    assert main(["run", *TINY, *args, f"out={out}"]) == 2
    one_line_error(capsys, message)
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("replay", ["uniform", "prioritized"])
def test_the_saved_buffer_samples_as_the_original(replay, tmp_path):
    """Transitions, PER priorities and the buffer's generator come back: the next samples are identical."""
    from tensordict import TensorDict

    cfg = compose([*TINY, f"algo.replay={replay}"])
    rb = make_buffer(cfg.algo, torch.Generator().manual_seed(0))
    rb.extend(TensorDict({"x": torch.arange(300.0)}, batch_size=[300]))
    for _ in range(5):
        s = rb.sample()
        if replay == "prioritized":
            s.set("td_error", s["x"] / 300)
            rb.update_tensordict_priority(s)
    ref = save_buffer(rb, tmp_path, frames=300, updates=5)
    assert sum(f.stat().st_size for f in (tmp_path / ref["dir"]).rglob("*.memmap")) < 300 * 64 + 2e5  # not 4096 rows
    back = make_buffer(cfg.algo, torch.Generator())
    state = {"replay": ref, "frames": 300, "updates": 5}
    assert restore_buffer(back, state, tmp_path / "checkpoint.pt", True, None)
    for _ in range(3):
        a, b = rb.sample(), back.sample()
        assert torch.equal(a["x"], b["x"]) and torch.equal(a["index"], b["index"])
    with pytest.raises(CheckpointError, match="written at 300 frames, the checkpoint .* at 428"):
        restore_buffer(back, {**state, "frames": 428}, tmp_path / "checkpoint.pt", True, None)


def test_resume_into_another_replay_kind_keeps_the_transitions(tmp_path):
    train(compose([*TINY, "train.total_frames=256", "algo.replay=uniform"]), tmp_path, progress=False)
    train(compose([*TINY, "train.total_frames=384", "algo.replay=prioritized"]), tmp_path, resume=True,
          progress=False)
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["updates"] == expected_updates(384) and state["replay"]["transitions"] == 384
    assert state["config"]["algo"]["replay"] == "prioritized"


@pytest.mark.slow
def test_kill_and_resume_keeps_learning(tmp_path, monkeypatch):
    """Findings 21: three interruptions (frame budgets, and a kill between writing the buffer and the
    checkpoint) end with the frames, updates and buffer of an uninterrupted run."""
    total = 640
    train(compose([*TINY, f"train.total_frames={total}"]), tmp_path / "whole", progress=False)
    whole = load_checkpoint(tmp_path / "whole" / "checkpoint.pt")
    assert (whole["frames"], whole["updates"]) == (total, expected_updates(total))

    run = tmp_path / "killed"
    train(compose([*TINY, "train.total_frames=192"]), run, progress=False)
    train(compose([*TINY, "train.total_frames=320"]), run, resume=True, progress=False)
    assert load_checkpoint(run / "checkpoint.pt")["updates"] == expected_updates(320)  # no second warm-up
    real, calls = train_mod.save_torch_atomic, []

    def killed_after_the_buffer(path, state):  # the second checkpoint of this leg never lands
        calls.append(state["frames"])
        if len(calls) == 2:
            raise SystemExit("killed")
        real(path, state)

    monkeypatch.setattr(train_mod, "save_torch_atomic", killed_after_the_buffer)
    with pytest.raises(SystemExit):
        train(compose([*TINY, f"train.total_frames={total}"]), run, resume=True, progress=False)
    monkeypatch.setattr(train_mod, "save_torch_atomic", real)
    assert load_checkpoint(run / "checkpoint.pt")["frames"] == calls[0] == 448
    train(compose([*TINY, f"train.total_frames={total}"]), run, resume=True, progress=False)
    state = load_checkpoint(run / "checkpoint.pt")
    assert (state["frames"], state["updates"]) == (whole["frames"], whole["updates"])
    assert state["replay"]["transitions"] == whole["replay"]["transitions"] == total
    assert [p.name for p in run.iterdir() if "replay-" in p.name] == [state["replay"]["dir"]]  # stale ones removed
    log = [line.split(",")[0] for line in (run / "logs" / "scalars" / "updates.csv").read_text().splitlines()]
    assert log == [str(f) for f in range(64, total + 1, 64)]


@pytest.mark.slow
def test_sigkill_resume_continues_with_the_buffer(tmp_path, capsys):
    """A real `crowdbench run` SIGKILLed after a checkpoint: while it runs its directory is refused to a
    second run; resumed, it makes the updates of an uninterrupted run."""
    args = ["run", *TINY, *EVAL, f"out={tmp_path}"]
    proc = subprocess.Popen([sys.executable, "-m", "crowdbench.cli", *args, "train.total_frames=100000"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": ROOT})
    ckpt, deadline = tmp_path / "checkpoint.pt", time.time() + 240
    while time.time() < deadline and not (ckpt.exists() and load_checkpoint(ckpt)["frames"] >= 256):
        time.sleep(0.5)
    try:
        assert main([*args, "train.total_frames=100000", "resume=true"]) == 2
        one_line_error(capsys, f"is in use by another run (pid {proc.pid})")
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    saved = load_checkpoint(ckpt)["frames"]
    assert main([*args, f"train.total_frames={saved + 128}", "resume=true"]) == 0
    state = load_checkpoint(ckpt)
    assert (state["frames"], state["updates"]) == (saved + 128, expected_updates(saved + 128))
