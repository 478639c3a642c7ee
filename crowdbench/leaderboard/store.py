"""Results on disk: written atomically, read back only if this harness wrote them.

Atomic: a temporary file in the same directory, flushed, then ``os.replace``, so a full disk or a
kill leaves the previous file whole, never a truncated one. Unreadable (truncated, not JSON, not a
mapping): treated as missing, so the submission is re-evaluated, never a crash.

Trusted: the fingerprint in ``results.json`` is a public hash of the inputs that anyone can
recompute, so a results file edited in a pull request would match it. The harness keeps a ledger,
outside the repository (``$CROWDBENCH_LEDGER``, default ``$XDG_CACHE_HOME/crowdbench/results-ledger``),
of the sha256 of every results file it wrote; a cached result is published as such only if its
bytes are in the ledger and it agrees with its inputs (fingerprint, name, kind, submission.yaml).
Why a ledger and not a MAC inside the file: a MAC field would differ per machine and change every
committed results file on each re-run; the ledger changes no file and needs no key to guard.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import tempfile
from pathlib import Path

from crowdbench.outputs import current_umask

MAX_RESULTS_BYTES = 64 * 1024 ** 2


def ledger_dir() -> Path:
    env = os.environ.get("CROWDBENCH_LEDGER")
    if env:
        return Path(env)
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(cache) / "crowdbench" / "results-ledger"


def write_atomic(path: Path, text: str) -> None:
    """``path`` holds ``text`` or its previous content, whatever happens (an OSError propagates)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_results(path: Path, res: dict) -> None:
    """Write ``res`` atomically and record it in the ledger (a ledger that cannot be written costs a
    re-evaluation next time, not this run)."""
    text = json.dumps(res, indent=1) + "\n"
    write_atomic(path, text)
    try:
        d = ledger_dir()
        d.mkdir(parents=True, exist_ok=True)
        (d / _digest(text.encode())).touch()
    except OSError:
        pass


def read_cached(path: Path, name: str, kind: str, data: dict, fp: str) -> tuple[dict | None, str | None]:
    """``(results, None)`` if ``path`` holds results this harness wrote for these inputs; ``(results, why)``
    if only the ledger does not know them; else ``(None, why)`` (why None: there is no file)."""
    if not path.is_file():
        return None, None
    try:
        if path.stat().st_size > MAX_RESULTS_BYTES:
            return None, f"larger than {MAX_RESULTS_BYTES >> 20} MB"
        raw = path.read_bytes()
        res = json.loads(raw)
    except (OSError, ValueError) as e:  # truncated, not UTF-8, not JSON
        return None, f"unreadable ({type(e).__name__})"
    if not isinstance(res, dict) or not isinstance(res.get("harness"), dict) or not isinstance(res.get("meta"), dict):
        return None, "not a results mapping"
    if res["harness"].get("fingerprint") != fp:
        return None, "out of date"
    if res["meta"].get("submission") != name or res["meta"].get("kind") != kind or res.get("submission") != data:
        return None, "does not match its submission"
    if not (ledger_dir() / _digest(raw)).is_file():
        return res, "not written by this harness"
    return res, None


class RootBusy(RuntimeError):
    """Another ``crowdbench leaderboard`` holds the root."""


@contextlib.contextmanager
def locked(root: Path):
    """Hold an exclusive ``flock`` on the root directory itself (no lock file to commit or clean up);
    released when the process ends, however it ends."""
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RootBusy(f"{root} is in use by another crowdbench leaderboard run; wait for it to finish") from None
        yield
    finally:
        os.close(fd)
