"""How a submission's worker process is started: a fresh interpreter, resource limits, and, where the
machine has it, Debian's ``bubblewrap`` (docs/submitting.md, "What the harness protects").

Confined (``bwrap``): the whole file system read-only; the host's temporary and runtime directories
(``/tmp``, ``/var/tmp``, ``/run``, ``/dev/shm``, ``$HOME``) hidden under empty file systems, only what
the worker needs bound back read-only (its submission, this crowdbench, the interpreter); its
scratch (``TMPDIR``, ``/tmp`` inside) and ``/dev/shm`` its own size-bounded tmpfs, gone with it; no
network (a new network namespace), its own PID namespace (it cannot see or signal the harness or
other workers), every capability dropped, killed with the harness. Always: its own session (killed
as a process group), an address-space limit, a CPU-time limit, a limit on the size of files it
writes, no core dumps, a seccomp filter (crowdbench/leaderboard/seccomp.py: no Unix sockets, no new
processes); a minimal environment (no inherited secrets).
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

from crowdbench.leaderboard import seccomp
from crowdbench.numerics import PINNED

SANDBOXES = ("auto", "bubblewrap", "none")


class SandboxError(RuntimeError):
    """``--sandbox bubblewrap`` was asked for and this machine cannot provide it."""


@dataclass(frozen=True)
class Limits:
    """Bounds on one worker. ``step_s``: one reply (an action batch); ``load_s``: starting, importing
    the submission's code and loading its checkpoint; ``memory_gb``: address space (torch alone maps
    ~3 GB); ``cpu_s``: CPU time of the whole job; ``file_mb``: the largest file it may write;
    ``scratch_mb``: its scratch tmpfs and its ``/dev/shm`` (each; confined workers only); ``budget_*``: its
    wall-clock time per track (crowdbench/leaderboard/budget.py)."""

    step_s: float = 60.0
    load_s: float = 300.0
    memory_gb: float = 8.0
    cpu_s: int = 1800
    file_mb: int = 64
    scratch_mb: int = 256
    sandbox: str = "auto"
    budget_factor: float = 20.0  # x the reference policy's wall time on the track (crowdbench/leaderboard/budget.py)
    # a floor, not only the factor: ORCA ends most CrowdNav circle-5 episodes early (57% collide), 7.8 s for
    # the 500 cases, while a value-lookahead entry scores 81 candidates per step (~100-800 s by load)
    budget_floor_s: float = 900.0
    budgets: tuple = ()  # ((track, seconds), ...), measured by the harness at the start of a run


DEFAULT_LIMITS = Limits()


# hidden from a confined worker: where sockets (ssh-agent, X11, D-Bus, docker, Ray) and other users'
# temporary files live; the first is the worker's own scratch
PACKAGE_PARENT = Path(__file__).resolve().parents[2]  # the directory holding this crowdbench package
MASKED = ("/tmp", "/var/tmp", "/run")
SCRATCH = "/tmp"


@functools.cache
def bubblewrap() -> str | None:
    """The ``bwrap`` binary if it can run a confined process here (it needs user or mount namespaces)."""
    path = shutil.which("bwrap")
    if path is None:
        return None
    try:
        ok = subprocess.run([path, *_bwrap_args(DEFAULT_LIMITS, []), "true"], capture_output=True, timeout=20,
                            check=False).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    return path if ok else None


def _masked() -> list[str]:
    """Directories hidden from the worker: MASKED and ``$HOME``, those that exist (not as symlinks:
    ``/var/run`` is ``/run``)."""
    home = os.environ.get("HOME", "")
    out = []
    for p in (*MASKED, home):
        if p and os.path.isabs(p) and os.path.isdir(p) and not os.path.islink(p) and os.path.realpath(p) != "/":
            out.append(os.path.realpath(p))
    return list(dict.fromkeys(out))


def _kept(keep: list[str], masked: list[str]) -> list[str]:
    """Paths of ``keep`` (and where their symlinks lead) that lie under a masked directory, outermost first.
    Never a masked directory itself: a harness started from ``/tmp`` has it on ``sys.path``, and binding it
    would show the host's ``/tmp`` instead of the worker's scratch, read-only (no worker could start)."""
    paths = {q for p in keep if p and os.path.exists(p) for q in (os.path.abspath(p), os.path.realpath(p))}
    under = sorted(p for p in paths if any(p.startswith(m.rstrip("/") + "/") for m in masked))
    out: list[str] = []
    for p in under:  # sorted: an ancestor comes before what it contains
        if not any(p.startswith(q.rstrip("/") + "/") for q in out):
            out.append(p)
    return out


def needed_paths(sub_dir: Path | None, env: dict[str, str]) -> list[str]:
    """What a worker reads: its submission, the interpreter and its library paths, its PYTHONPATH."""
    exe = os.path.realpath(sys.executable)
    return [str(sub_dir) if sub_dir else "", *env.get("PYTHONPATH", "").split(os.pathsep), sys.prefix,
            sys.base_prefix, sys.exec_prefix, os.path.dirname(os.path.dirname(exe)), *sys.path]


def _bwrap_args(limits: Limits, keep: list[str]) -> list[str]:
    scratch = str(int(limits.scratch_mb) * 1024 ** 2)
    masked = _masked()
    args = ["--ro-bind", "/", "/", "--dev", "/dev", "--size", scratch, "--tmpfs", "/dev/shm",
            "--remount-ro", "/dev", "--proc", "/proc", "--size", scratch, "--tmpfs", SCRATCH]
    others = [m for m in masked if m != SCRATCH]
    for m in others:
        args += ["--tmpfs", m]
    for p in _kept(keep, masked):
        args += ["--ro-bind", p, p]
    for m in others:  # after the binds (their mount points are made in these): no unbounded writable tmpfs
        args += ["--remount-ro", m]
    return args + ["--chdir", SCRATCH, "--unshare-all", "--die-with-parent", "--new-session", "--cap-drop", "ALL"]


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


def confinement(sandbox: str, limits: Limits) -> str:
    """The line every leaderboard run starts with: how submitted code runs."""
    how = "CONFINED by bubblewrap" if sandbox == "bubblewrap" else \
        "NOT confined (no usable bwrap: apt-get install bubblewrap; or --sandbox none)"
    filt = "a seccomp filter" if seccomp.supported() else "no seccomp filter on this platform"
    return (f"submitted code runs in worker processes, {how}, with {filt}; {limits.memory_gb:g} GB, "
            f"{limits.cpu_s} s CPU, {limits.step_s:g} s per step, {limits.budget_factor:g} x ORCA's time per track")


def command(limits: Limits, keep: list[str] = ()) -> list[str]:
    """argv of a worker: ``python -m crowdbench.leaderboard.worker``, inside bwrap where available,
    with ``keep`` (:func:`needed_paths`) visible read-only."""
    # -s: no user site-packages; -P: the working directory is not on sys.path (a file planted in the
    # scratch dir cannot shadow a module); PYTHONPATH (env below) points at this crowdbench only
    # -W: runpy's warning that the worker module was imported before it ran (by its package) is on every
    # worker's stderr, so it was quoted as the "last words" of any worker that died silently
    py = [sys.executable, "-s", "-P", "-W", "ignore::RuntimeWarning:runpy", "-m", "crowdbench.leaderboard.worker"]
    if sandbox_name(limits) == "bubblewrap":
        return [bubblewrap(), *_bwrap_args(limits, list(keep)), "--", *py]
    return py


def environment(scratch: Path) -> dict[str, str]:
    """The worker's whole environment: this interpreter's crowdbench, evaluation's numerical path
    (crowdbench/numerics.py, as the harness runs it), one thread, nothing else inherited."""
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(scratch), "TMPDIR": str(scratch),
           "PYTHONPATH": str(PACKAGE_PARENT), "PYTHONHASHSEED": "0",
           "PYTHONDONTWRITEBYTECODE": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "RL_WARNINGS": "False", "LANG": "C.UTF-8"}
    env.update({k: os.environ[k] for k in PINNED if k in os.environ})
    return env


def apply_limits(memory_gb: float, cpu_s: int, file_mb: int) -> None:
    """Called by the worker on itself before it reads the submission (soft = hard: the submission's
    code cannot raise them again without CAP_SYS_RESOURCE, which bubblewrap drops). Not a
    ``preexec_fn``: that is unsafe in a harness with threads. Last, the seccomp filter (one process:
    the CPU limit then holds for the whole job; no Unix sockets)."""
    mem = int(memory_gb * 1024 ** 3)
    resource.setrlimit(resource.RLIMIT_AS, (mem, mem))
    resource.setrlimit(resource.RLIMIT_CPU, (int(cpu_s), int(cpu_s) + 5))
    size = int(file_mb) * 1024 ** 2
    resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if seccomp.supported():
        seccomp.install()
