"""How a submission's worker process is started: a fresh interpreter, resource limits, and, where the
machine has it, Debian's ``bubblewrap`` (docs/submitting.md, "What the harness protects").

Confined (``bwrap``): the whole file system read-only except the worker's scratch directory
(``TMPDIR``), no network (a new network namespace), its own PID namespace (it cannot see or
signal the harness or other workers), every capability dropped, killed with the harness. Always:
its own session (killed as a process group), an address-space limit, a CPU-time limit, a limit on
the size of files it writes, no core dumps; a minimal environment (no inherited secrets).
"""

from __future__ import annotations

import functools
import os
import resource
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import crowdbench
from crowdbench.numerics import PINNED

SANDBOXES = ("auto", "bubblewrap", "none")


class SandboxError(RuntimeError):
    """``--sandbox bubblewrap`` was asked for and this machine cannot provide it."""


@dataclass(frozen=True)
class Limits:
    """Bounds on one worker. ``step_s``: one reply (an action batch); ``load_s``: starting, importing
    the submission's code and loading its checkpoint; ``memory_gb``: address space (torch alone maps
    ~3 GB); ``cpu_s``: CPU time of the whole job; ``file_mb``: the largest file it may write."""

    step_s: float = 60.0
    load_s: float = 300.0
    memory_gb: float = 8.0
    cpu_s: int = 1800
    file_mb: int = 64
    sandbox: str = "auto"


DEFAULT_LIMITS = Limits()


@functools.cache
def bubblewrap() -> str | None:
    """The ``bwrap`` binary if it can run a confined process here (it needs user or mount namespaces)."""
    path = shutil.which("bwrap")
    if path is None:
        return None
    try:
        ok = subprocess.run([path, *_bwrap_args("/"), "true"], capture_output=True, timeout=20,
                            check=False).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    return path if ok else None


def _bwrap_args(scratch: str) -> list[str]:
    args = ["--ro-bind", "/", "/", "--dev", "/dev", "--proc", "/proc"]
    if scratch != "/":
        args += ["--bind", scratch, scratch, "--chdir", scratch]
    return args + ["--unshare-all", "--die-with-parent", "--new-session", "--cap-drop", "ALL"]


def sandbox_name(limits: Limits) -> str:
    """``bubblewrap`` or ``none``: what :func:`command` will use; :class:`SandboxError` if bubblewrap
    is required and unavailable."""
    if limits.sandbox not in SANDBOXES:
        raise SandboxError(f"unknown sandbox {limits.sandbox!r}; valid: {', '.join(SANDBOXES)}")
    if limits.sandbox == "none":
        return "none"
    if bubblewrap() is not None:
        return "bubblewrap"
    if limits.sandbox == "bubblewrap":
        raise SandboxError("--sandbox bubblewrap: bwrap is not installed or cannot create namespaces here "
                           "(Debian: apt install bubblewrap)")
    return "none"


def command(scratch: Path, limits: Limits) -> list[str]:
    """argv of a worker: ``python -m crowdbench.leaderboard.worker``, inside bwrap where available."""
    # -s: no user site-packages; -P: the working directory is not on sys.path (a file planted in the
    # scratch dir cannot shadow a module); PYTHONPATH (env below) points at this crowdbench only
    py = [sys.executable, "-s", "-P", "-m", "crowdbench.leaderboard.worker"]
    if sandbox_name(limits) == "bubblewrap":
        return [bubblewrap(), *_bwrap_args(str(scratch)), "--", *py]
    return py


def environment(scratch: Path) -> dict[str, str]:
    """The worker's whole environment: this interpreter's crowdbench, evaluation's numerical path
    (crowdbench/numerics.py, as the harness runs it), one thread, nothing else inherited."""
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(scratch), "TMPDIR": str(scratch),
           "PYTHONPATH": str(Path(crowdbench.__file__).resolve().parents[1]), "PYTHONHASHSEED": "0",
           "PYTHONDONTWRITEBYTECODE": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "RL_WARNINGS": "False", "LANG": "C.UTF-8"}
    env.update({k: os.environ[k] for k in PINNED if k in os.environ})
    return env


def apply_limits(memory_gb: float, cpu_s: int, file_mb: int) -> None:
    """Called by the worker on itself before it reads the submission (soft = hard: the submission's
    code cannot raise them again without CAP_SYS_RESOURCE, which bubblewrap drops). Not a
    ``preexec_fn``: that is unsafe in a harness with threads."""
    mem = int(memory_gb * 1024 ** 3)
    resource.setrlimit(resource.RLIMIT_AS, (mem, mem))
    resource.setrlimit(resource.RLIMIT_CPU, (int(cpu_s), int(cpu_s) + 5))
    size = int(file_mb) * 1024 ** 2
    resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
