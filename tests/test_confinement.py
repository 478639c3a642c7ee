"""What a worker can reach: host Unix sockets and temporary directories (H1), its scratch space and
the number of its processes (H3, M9). Each hostile encoder module reports what it managed in the
exception it raises while loading, which the harness turns into the one-line rejection read here."""

from __future__ import annotations

import os
import re
import socket
import threading
from pathlib import Path

import pytest
from conftest import require_system

from crowdbench.leaderboard import run
from crowdbench.leaderboard.sandbox import Limits, bubblewrap
from crowdbench.leaderboard.worker import WorkerError, WorkerPolicy
from tests.test_isolation import ENCODER, add_straight, make_learned

FAST = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}
MODES = ["bubblewrap", "none"]


def limits(mode: str, **kw) -> Limits:
    if mode == "bubblewrap":
        require_system("bwrap", bubblewrap() is not None)
    return Limits(step_s=20.0, load_s=120.0, memory_gb=6.0, sandbox=mode, **kw)


def report(root: Path, name: str, code: str, lim: Limits) -> str:
    """The one-line rejection of a submission whose module runs ``code`` then raises ``REPORT``."""
    make_learned(root, name, ENCODER + code + "\nraise RuntimeError('REPORT ' + REPORT)\n")
    with pytest.raises(WorkerError) as e:
        WorkerPolicy(root / "submissions" / name, name, lim)
    assert "REPORT" in str(e.value), str(e.value)
    return str(e.value).split("REPORT ", 1)[1]


class Listener:
    """A Unix socket on the host that records whatever connects to it."""

    def __init__(self, path: Path):
        self.got: list[bytes] = []
        self.sock = socket.socket(socket.AF_UNIX)
        self.sock.bind(str(path))
        self.sock.listen(4)
        self.sock.settimeout(0.2)
        self.stop = False
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            conn.settimeout(2)
            try:
                self.got.append(conn.recv(100) or b"<connected>")
            except OSError:
                self.got.append(b"<connected>")
            conn.close()

    def close(self) -> None:
        self.stop = True
        self.thread.join()
        self.sock.close()


SOCKET = '''
import socket
REPORT = ""
for path in SOCKETS:
    try:
        s = socket.socket(socket.AF_UNIX)
        s.settimeout(2)
        s.connect(path)
        s.sendall(b"secret")
        REPORT += "connected;"
    except OSError as e:
        REPORT += f"refused {type(e).__name__};"
'''


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.slow
def test_a_worker_reaches_no_host_unix_socket(tmp_path, mode):
    """H1: a worker sent /etc/shadow's first bytes to a listener on a socket file under /tmp."""
    lim = limits(mode)
    listener = Listener(tmp_path / "s")
    # a short path outside /tmp too (sun_path holds 108 bytes): the filter, not only the mounts
    other = Path(os.path.realpath(Path(__file__).parent)) / f".sock-{os.getpid()}-{mode}"
    listener2 = Listener(other)
    try:
        said = report(tmp_path / "lb", "sock", f"SOCKETS = {[str(tmp_path / 's'), str(other)]!r}\n" + SOCKET, lim)
    finally:
        listener.close()
        listener2.close()
        other.unlink(missing_ok=True)
    assert listener.got == [] and listener2.got == [], (listener.got, listener2.got)
    assert said.count("refused") == 2, said


HOST_DIRS = '''
import os
REPORT = "saw:" + ",".join(p for p in PATHS if os.path.exists(p))
'''


@pytest.mark.slow
def test_a_confined_worker_sees_no_host_temp_or_home_directory(tmp_path):
    """H1: /tmp, /run and $HOME of the host are hidden; only what the worker needs is bound back."""
    lim = limits("bubblewrap")
    marker = tmp_path / "host-secret.txt"
    marker.write_text("x")
    run_dir = Path("/run") / f"crowdbench-test-{os.getpid()}"
    run_dir.mkdir(exist_ok=True)
    home = Path(os.environ.get("HOME", "/root"))
    home_marker = home / f".crowdbench-test-{os.getpid()}"
    home_marker.write_text("x")
    try:
        said = report(tmp_path / "lb", "peek", f"PATHS = {[str(marker), str(run_dir), str(home_marker)]!r}\n"
                      + HOST_DIRS, lim)
    finally:
        run_dir.rmdir()
        home_marker.unlink()
    assert said.strip() == "saw:", said


FLOOD = '''
import os, tempfile
REPORT = ""
for where in (tempfile.gettempdir(), "/dev/shm", "/run", "/var/tmp", os.path.expanduser("~")):
    n = 0
    try:
        while n < 200:  # bounded: without a quota this would write 200 MB to the host
            with open(os.path.join(where, f"fill{n}"), "wb") as f:
                f.write(b"x" * (1 << 20))
            n += 1
    except OSError as e:
        pass
    REPORT += f"{where}={n};"
'''


@pytest.mark.slow
def test_a_confined_worker_scratch_is_its_own_bounded_tmpfs(tmp_path):
    """H3: a worker filled the temp file system it shared with the harness (64 MB files, no count
    limit); every other submission was then rejected with `No space left on device`."""
    lim = limits("bubblewrap", scratch_mb=16)
    said = report(tmp_path / "lb", "flood", FLOOD, lim)
    written = {k: int(v) for k, v in re.findall(r"(\S+?)=(\d+);", said)}
    assert written["/tmp"] <= 16 and written["/dev/shm"] <= 16, said  # its own tmpfs, 16 MB
    assert all(v == 0 for k, v in written.items() if k not in ("/tmp", "/dev/shm")), said  # read-only
    # and the harness's own temporary files (episodes.jsonl) are unaffected: a run evaluates
    root = tmp_path / "lb2"
    add_straight(root)
    make_learned(root, "flood", ENCODER + FLOOD)
    make_learned(root, "honest", ENCODER)
    log: list[str] = []
    assert run(root, log=log.append, limits=lim, **FAST) == 0, log
    assert all((root / "results" / n / "results.json").is_file() for n in ("flood", "honest", "straight"))


FORK = '''
import os, time
REPORT, kids = "", []
for _ in range(40):
    try:
        pid = os.fork()
    except OSError as e:
        REPORT = f"fork refused {e.errno};"
        break
    if pid == 0:
        time.sleep(1)
        os._exit(0)
    kids.append(pid)
REPORT += f"forked {len(kids)}"
'''


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.slow
def test_a_worker_cannot_start_processes(tmp_path, mode):
    """M9: the CPU limit was per process with unlimited forks (6 busy children used 58 CPU-s against
    10 s; 300 sleeping children were forked). One process per worker: its CPU limit is the job's."""
    said = report(tmp_path / "lb", "forker", FORK, limits(mode))
    assert said.endswith("forked 0") and "fork refused" in said, said


def test_a_harness_started_from_tmp_still_gives_its_worker_a_private_scratch(tmp_path):
    """A harness run from /tmp (`python -m pytest` there puts /tmp on sys.path, which the worker's binds
    follow) bound the host's /tmp read-only over the worker's scratch: every worker died importing torch
    ("No usable temporary directory found"), and the host's /tmp was visible to it."""
    import subprocess

    from crowdbench.leaderboard.sandbox import _bwrap_args

    lim = limits("bubblewrap")
    host_file = Path("/tmp") / f"crowdbench-host-{os.getpid()}"
    host_file.write_text("x")
    sub = tmp_path / "sub"
    sub.mkdir()
    try:
        argv = [bubblewrap(), *_bwrap_args(lim, ["/tmp", str(sub)]), "--", "sh", "-c",
                f"touch /tmp/mine && ls /tmp && test ! -e {host_file} && test -d {sub}"]
        done = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    finally:
        host_file.unlink()
    assert done.returncode == 0, done.stderr + done.stdout
    assert "mine" in done.stdout.split()
