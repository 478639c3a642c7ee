"""Output directories: one writer at a time (a lock held for a run's or an evaluation's lifetime),
unwritable paths found before any work, files replaced atomically through unique temporary files.

Errors are :class:`OutputError` (a ``ValueError``: the command line prints it as one line).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

LOCK_NAME = ".crowdbench.lock"
_held: dict[str, list] = {}  # resolved dir -> [fd, depth]: this process's locks (re-entrant)


class OutputError(ValueError):
    """An output path that cannot be used; the message names it."""


def nearest_existing(path: Path) -> Path:
    """``path`` or its closest existing ancestor."""
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_writable_dir(path: Path, what: str = "out") -> None:
    """Refuse a directory that cannot be created or written, before anything runs (nothing is created)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{what}={path} is not a directory (a file is in the way)")
    base = nearest_existing(path)
    if not base.is_dir():
        raise OutputError(f"{what}={path}: cannot create it, {base} is a file, not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputError(f"{what}={path}: {base} is not writable")


def check_writable_file(path: Path, what: str = "--out") -> None:
    """Refuse an output file that cannot be written (checked before any work; nothing is created)."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{what} {path} is a directory, not a file")
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputError(f"{what} {path} is not writable")
    check_writable_dir(path.parent, what=f"{what} {path}: directory")


def _holder(lock: Path) -> str:
    try:
        return lock.read_text().strip() or "?"
    except OSError:
        return "?"


def _created_dirs(path: Path) -> list[Path]:
    """The directories that ``mkdir(parents=True)`` of ``path`` would create, deepest first."""
    out, p = [], Path(os.path.abspath(path))
    while not p.exists() and p != p.parent:
        out.append(p)
        p = p.parent
    return out


@contextlib.contextmanager
def claim_dir(path: Path, what: str = "out") -> Iterator[Path]:
    """Create ``path`` if needed and hold an exclusive lock on it until the block ends.

    A second claim from another process fails at once with ``<dir> is in use by another run (pid N)``;
    claims from this process nest. The lock is ``fcntl.flock`` on ``<dir>/.crowdbench.lock``, which is
    removed again when released; if the block fails and ``path`` was created for it and holds nothing
    else, the directory is removed too (a run that fails before it starts leaves nothing behind).
    """
    check_writable_dir(path, what)
    key = os.path.realpath(path)
    if key in _held:
        _held[key][1] += 1
        try:
            yield Path(path)
        finally:
            _held[key][1] -= 1
        return
    created = _created_dirs(path)
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
        fd = _lock(Path(path) / LOCK_NAME)
    except OSError as e:
        _remove_empty(created)
        raise OutputError(f"{what}={path}: cannot write it ({e.strerror or e})") from None
    _held[key] = [fd, 1]
    failed = False
    try:
        yield Path(path)
    except BaseException:
        failed = True
        raise
    finally:
        del _held[key]
        with contextlib.suppress(OSError):
            os.unlink(Path(path) / LOCK_NAME)  # before unlocking: a waiting claim then sees a new inode
        os.close(fd)
        if failed:
            _remove_empty(created)


def _lock(lock: Path) -> int:
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise OutputError(f"{lock.parent} is in use by another run (pid {_holder(lock)})") from None
            raise
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:  # else its holder removed the file between our open and flock: take the new one
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)


def _remove_empty(dirs: list[Path]) -> None:
    for d in dirs:  # deepest first
        try:
            d.rmdir()
        except OSError:
            return


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A unique temporary file beside ``path``, moved onto it when the block ends without error
    (removed otherwise): readers see the old file or the new one, never a mix; two writers never share
    a temporary file."""
    path = Path(path)
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp", delete=False) as f:
        tmp = Path(f.name)
    try:
        yield tmp
        # NamedTemporaryFile makes it 0600: give it the mode any other file written here gets (the umask's),
        # so that a checkpoint is as readable as results.json for another user of a shared file system
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_text_atomic(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_torch_atomic(path: Path, state: dict) -> None:
    """``torch.save`` through a unique temporary file (the format :func:`load_checkpoint` reads).

    Serialised in memory first: torch's own writer reports a full disk as an opaque ``RuntimeError``
    (``enforce fail at inline_container.cc``), a plain write as ``OSError`` with its errno and path."""
    import io

    import torch

    buf = io.BytesIO()
    torch.save(state, buf)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(buf.getbuffer())
        f.flush()
        os.fsync(f.fileno())


def replace_dir(src: Path, dst: Path) -> None:
    """Move the finished directory ``src`` to the new name ``dst`` (removing a stale ``dst``)."""
    if dst.exists():
        shutil.rmtree(dst)
    os.replace(src, dst)


def pid_dir(parent: Path, what: str) -> Path:
    """A new directory ``parent/<what>-<pid>-*`` for this process's unfinished work; those left by processes
    that are gone (killed before they could clean up) are removed first."""
    parent.mkdir(parents=True, exist_ok=True)
    reap_dead(parent, what)
    d = Path(tempfile.mkdtemp(prefix=f"{what}-{os.getpid()}-", dir=parent))
    os.chmod(d, 0o777 & ~current_umask())  # (mkdtemp's is 0700) it may be renamed into place as it is
    return d


def reap_dead(parent: Path, what: str) -> None:
    """Remove ``parent/<what>-<pid>-*`` directories whose process no longer exists."""
    for d in Path(parent).glob(f"{what}-*-*"):
        pid = d.name[len(what) + 1:].split("-", 1)[0]
        if pid.isdigit() and not pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True
