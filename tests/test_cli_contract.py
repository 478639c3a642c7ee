"""The command line's contract under careless input: one line naming the key, exit 2, nothing written,
nothing already saved lost; Ctrl-C without a traceback; a sweep rerun into its own directory."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from crowdbench.cli import compose, main

TINY = ["train.pretrain=null", "train.total_frames=256", "train.frames_per_batch=128", "algo.warmup=128", "encoder.dim=8",
        "train.probe_every=1000000", "train.checkpoint_every=1000000", "eval.episodes=2", "eval.scenes=[hotel]"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RL_WARNINGS": "False"}


def one_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("crowdbench: error: "), err
    return err


def snapshot(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_an_unquoted_non_ascii_path_says_how_to_quote_it(tmp_path, capsys):
    """L6: ``bad override: LexerNoViableAltException ...``; the suggested spelling must work."""
    out = tmp_path / "ünïcödé"
    assert main(["run", f"out={out}"]) == 2
    err = one_error(capsys)
    assert f"'out={out}'" in err and "quote" in err and not out.exists()
    suggested = err.rsplit("quote the value: ", 1)[1].strip().strip('"')
    assert compose([suggested]).out == str(out)


def test_a_sweep_over_a_missing_option_is_one_line_and_writes_nothing(tmp_path, capsys):
    """L7: Hydra's 17-line report, exit 1, and ``multirun.yaml`` left in the sweep directory."""
    assert main(["run", "-m", "experiment=nonexistent_xyz,leaderboard", f"out={tmp_path / 'sweep'}"]) == 2
    assert "unknown experiment 'nonexistent_xyz'" in one_error(capsys)
    assert not (tmp_path / "sweep").exists()


@pytest.mark.parametrize("subdir", ["seed_${seed}", "../../escaped"])
def test_a_custom_sweep_subdir_is_refused_before_any_run(tmp_path, capsys, monkeypatch, subdir):
    """M14: runs in ``seed_0/`` made an empty summary and exit 0; ``../..`` wrote outside the sweep."""
    monkeypatch.chdir(tmp_path)  # (a relative subdir that escapes lands here)
    assert main(["run", "-m", "seed=0,1", f"hydra.sweep.subdir={subdir}", *TINY, f"out={tmp_path / 's' / 'w'}"]) == 2
    assert "hydra.sweep.subdir" in one_error(capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("env", [[], ["env=selfplay"], ["env=crowdnav"]])
def test_an_absurd_env_batch_is_refused_before_allocating(tmp_path, capsys, env):
    """L9: ``env.batch=100000000`` ended in ``DefaultCPUAllocator: can't allocate memory``."""
    assert main(["run", *env, "env.batch=100000000", f"out={tmp_path / 'r'}"]) == 2
    assert "env.batch" in one_error(capsys) and not (tmp_path / "r").exists()


def fake_job(d: Path, overrides: list[str], status: str | None) -> None:
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (d / "checkpoint.pt").write_bytes(b"a checkpoint")
    if status:
        (d / "status.json").write_text(json.dumps({"job": int(d.name), "overrides": overrides, "status": status}))
        (d / "results.json").write_text("{}")


def test_a_rerun_into_an_interrupted_sweep_touches_no_run_of_it(tmp_path, capsys):
    """M13: rerunning into an interrupted sweep marked its finished runs failed (``already holds a
    training run``), so that submit skipped them and resume=true was refused."""
    sweep = tmp_path / "sweep"
    fake_job(sweep / "0", ["seed=0", *TINY], "ok")
    fake_job(sweep / "1", ["seed=1", *TINY], None)  # interrupted while training
    before = snapshot(sweep)
    assert main(["run", "-m", "seed=0,1,2", *TINY, f"out={sweep}"]) == 2  # another run than 1's would start
    assert "resume=true" in one_error(capsys)
    assert main(["run", "-m", "seed=5,6", *TINY, f"out={sweep}", "resume=true"]) == 2  # other jobs: another sweep
    assert "other overrides" in one_error(capsys)
    assert snapshot(sweep) == before


@pytest.mark.slow
def test_an_interrupted_sweep_continues_and_keeps_its_finished_runs(tmp_path):
    """M13 end to end: the finished runs are kept byte for byte, the summary counts every run."""
    run = [sys.executable, "-m", "crowdbench", "run", "-m"]
    p = subprocess.run([*run, "seed=0,1", *TINY, "out=sweep"], cwd=tmp_path, env=ENV, check=False,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    sweep = tmp_path / "sweep"
    (sweep / "sweep.json").unlink()  # as a sweep interrupted after its second run: no summary yet
    first = {k: v for k, v in snapshot(sweep / "0").items() if not k.startswith(".hydra")}
    p = subprocess.run([*run, "seed=0,1,2", *TINY, "out=sweep", "resume=true"], cwd=tmp_path, env=ENV,
                       check=False, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    assert {k: v for k, v in snapshot(sweep / "0").items() if not k.startswith(".hydra")} == first
    summary = json.loads((sweep / "sweep.json").read_text())
    assert [r["status"] for r in summary["runs"]] == ["ok"] * 3 and summary["table"][0]["finished"] == 3


CTRL_C_WHILE_IMPORTING = """
import os, signal, sys
class CtrlC:  # a Ctrl-C while the CLI module (torch, Hydra, ...) is being imported: seconds on a busy machine
    def find_spec(self, name, path=None, target=None):
        if name == "crowdbench.cli":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None
sys.meta_path.insert(0, CtrlC())
sys.argv = ["crowdbench", *sys.argv[1:]]
from crowdbench.entry import main
sys.exit(main())
"""


def test_ctrl_c_before_the_command_starts_is_one_line(tmp_path):
    """L8: Ctrl-C of a sweep printed a full KeyboardInterrupt traceback."""
    p = subprocess.run([sys.executable, "-c", CTRL_C_WHILE_IMPORTING, "run", "-m", "seed=0,1", "out=sweep"],
                       cwd=tmp_path, env=ENV, check=False, capture_output=True, text=True, timeout=300,
                       preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert p.returncode == 130 and p.stderr == "crowdbench: interrupted\n", p.stderr[-2000:]
    assert not (tmp_path / "sweep").exists()
