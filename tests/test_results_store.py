"""The leaderboard root under faults and forgery: M1 (a forged results.json with a matching
fingerprint published as cached), M2/M3 (a truncated results.json crashed every later run; a full
disk truncated the previous result), M4 (two runs on one root), M5 (SIGTERM orphaned the pool)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from crowdbench.leaderboard import run, store
from tests.test_entries import add_orca
from tests.test_isolation import ENCODER, add_straight, make_learned

FAST = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}


@pytest.fixture
def ledger(tmp_path, monkeypatch):
    monkeypatch.setenv("CROWDBENCH_LEDGER", str(tmp_path / "ledger"))
    return tmp_path / "ledger"


def baselines(root: Path) -> None:
    add_straight(root)
    add_orca(root)
    log: list[str] = []
    assert run(root, log=log.append, **FAST) == 0, log


# one damage in the quick suite, the others in the full one (each evaluates the baselines again)
@pytest.mark.parametrize("damage", ["half", *(pytest.param(d, marks=pytest.mark.slow) for d in ("empty", "list", "binary"))])
def test_an_unreadable_results_file_is_re_evaluated_not_a_crash(tmp_path, ledger, damage):
    """M2: `JSONDecodeError` / `AttributeError: 'list' object has no attribute 'get'` on every run,
    `--force` and `--only OTHER` included, until the file was found and deleted."""
    root = tmp_path / "lb"
    baselines(root)
    path = root / "results" / "orca" / "results.json"
    good = path.read_bytes()
    path.write_bytes({"half": good[:len(good) // 2], "empty": b"", "list": b"[1, 2]", "binary": b"\xff\xfe\0"}[damage])
    log: list[str] = []
    assert run(root, only=["straight"], log=log.append, **FAST) == 0, log  # not selected: listed as missing
    assert "orca (v1): results missing or out of date" in (root / "README.md").read_text()
    log.clear()
    assert run(root, log=log.append, **FAST) == 0, log
    assert any(m.startswith("orca: evaluated") for m in log), log
    assert path.read_bytes() == good


def test_a_forged_results_file_is_not_published_as_cached(tmp_path, ledger):
    """M1: every success rate set to 1.0 and the outcomes to `S`, fingerprint kept: `unchanged, cached
    results`. The harness publishes as cached only results files it wrote (its ledger)."""
    root = tmp_path / "lb"
    baselines(root)
    path = root / "results" / "straight" / "results.json"
    good = path.read_bytes()
    res = json.loads(good)
    for scene in res["scenes"].values():
        scene["success_rate"]["mean"] = 1.0
    res["episode_outcomes"] = {s: "S" * len(o) for s, o in res["episode_outcomes"].items()}
    path.write_text(json.dumps(res, indent=1) + "\n")
    log: list[str] = []
    assert run(root, log=log.append, **FAST) == 0
    assert "straight: cached results not written by this harness: re-evaluated" in log
    assert not any(m.startswith("straight: unchanged") for m in log)
    assert path.read_bytes() == good
    log.clear()  # the harness's own file is then cached
    assert run(root, log=log.append, **FAST) == 0
    assert any(m.startswith("straight: unchanged, cached") for m in log), log


def test_a_full_disk_keeps_the_previous_result_and_the_rerun_recovers(tmp_path, ledger, monkeypatch):
    """M3: `No space left on device` left `results.json` cut at 4096 bytes; every rerun then failed."""
    root = tmp_path / "lb"
    baselines(root)
    path = root / "results" / "straight" / "results.json"
    good = path.read_bytes()
    fdopen = os.fdopen

    class Full:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, text):
            self.f.write(text[:4096])
            raise OSError(28, "No space left on device", self.f.name)

    monkeypatch.setattr(store.os, "fdopen", lambda fd, *a, **k: Full(fdopen(fd, *a, **k)))
    log: list[str] = []
    assert run(root, force=True, log=log.append, **FAST) == 1
    (line,) = [m for m in log if "error" in m]
    assert "No space left on device" in line and "previous file is kept" in line and "\n" not in line
    assert path.read_bytes() == good
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]
    monkeypatch.setattr(store.os, "fdopen", fdopen)
    log.clear()
    assert run(root, force=True, log=log.append, **FAST) == 0, log
    assert path.read_bytes() == good


def test_a_second_run_on_the_same_root_is_refused(tmp_path, ledger):
    """M4: two concurrent runs on one root left it inconsistent."""
    root = tmp_path / "lb"
    add_straight(root)
    log: list[str] = []
    with store.locked(root):
        assert run(root, log=log.append, **FAST) == 1
    (line,) = [m for m in log if "error" in m]
    assert "in use by another crowdbench leaderboard run" in line
    assert not (root / "results").exists()
    assert run(root, log=log.append, **FAST) == 0  # released
    assert run(root, check=True, log=log.append, **FAST) == 0  # --check writes nothing: no lock needed


SLOW = '''
import time
_f = Enc.forward
def _slow(self, robot, *a, **k):
    if robot.shape[0] > 2:
        time.sleep(0.5)
    return _f(self, robot, *a, **k)
Enc.forward = _slow
'''


def _descendants(pid: int) -> set[int]:
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(k) for k in (task / "children").read_text().split()]
            except OSError:
                continue
            out.update(kids)
            todo += kids
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads the process tree from /proc")
@pytest.mark.slow
@pytest.mark.parametrize("how", ["sigterm", "ctrl-c"])
def test_a_signal_stops_the_pool_and_every_worker(tmp_path, how):
    """M5: killing `leaderboard --jobs 2` orphaned its pool processes (and their workers). Ctrl-C is
    SIGINT to the terminal's whole process group: the main process and its pool processes at once."""
    root = tmp_path / "lb"
    for name in ("slow_a", "slow_b"):
        make_learned(root, name, ENCODER + SLOW)

    # a shell's background job (as CI runs pytest) inherits SIGINT ignored, and an ignored signal stays
    # ignored across exec; a handled one is reset to its default there, as a terminal's process has it
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        proc = subprocess.Popen([sys.executable, "-m", "crowdbench", "leaderboard", "--root", str(root), "--jobs",
                                 "2", "--episodes", "3", "--scenes", "hotel", "--tracks", "v1"],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, process_group=0)
    finally:
        signal.signal(signal.SIGINT, old)
    tree: set[int] = set()
    for _ in range(600):  # until both workers run (a pool process each, each with its worker)
        tree |= _descendants(proc.pid)
        workers = [p for p in tree if _cmdline(p).startswith(sys.executable) and "leaderboard.worker" in _cmdline(p)]
        if len(workers) >= 2 or proc.poll() is not None:
            break
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()[0]
    if how == "sigterm":
        proc.send_signal(signal.SIGTERM)
    else:
        os.killpg(proc.pid, signal.SIGINT)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 128 + (signal.SIGTERM if how == "sigterm" else signal.SIGINT), out
    assert "Traceback" not in out, out
    left = []
    for _ in range(100):
        left = [p for p in tree if _alive(p)]
        if not left:
            break
        time.sleep(0.1)
    assert not left, [(p, _cmdline(p)) for p in left]


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def test_only_keeps_the_other_rows_when_their_results_are_out_of_date(tmp_path, ledger):
    """After a change to the evaluation code every cached fingerprint is out of date: `--only straight`
    re-evaluated straight and dropped every other row from the tables (they are shown as on disk)."""
    root = tmp_path / "lb"
    baselines(root)
    table = (root / "README.md").read_text()
    path = root / "results" / "orca" / "results.json"
    res = json.loads(path.read_text())
    res["harness"]["fingerprint"] = "0" * 64  # as if computed by other evaluation code
    path.write_text(json.dumps(res, indent=1) + "\n")
    log: list[str] = []
    assert run(root, only=["straight"], force=True, log=log.append, **FAST) == 0, log
    assert (root / "README.md").read_text() == table  # the ORCA row as it was
    assert any(m.startswith("note: 1 cached result(s) not selected, out of date") for m in log), log
    assert json.loads(path.read_text())["harness"]["fingerprint"] == "0" * 64  # not re-evaluated, not rewritten


def test_check_only_lists_the_rows_without_results_as_the_run_did(tmp_path, ledger):
    """`--check --only straight` rendered the tables without the "Not evaluated" lines of the entries that
    have no results (the run that wrote the tables lists them): every such check failed on the README."""
    root = tmp_path / "lb"
    baselines(root)
    (root / "results" / "orca" / "results.json").unlink()
    log: list[str] = []
    assert run(root, only=["straight"], log=log.append, **FAST) == 0, log
    assert "orca (v1): results missing or out of date" in (root / "README.md").read_text()
    log.clear()
    assert run(root, only=["straight"], check=True, log=log.append, **FAST) == 0, log
