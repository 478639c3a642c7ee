"""A learned submission's policy in a worker process: the harness sends observation batches and
receives action batches (docs/submitting.md, "What the harness protects").

Harness side, :class:`WorkerPolicy`: a :class:`~crowdbench.envs.observation.Policy` whose ``act`` is a
round trip over a pipe (crowdbench/leaderboard/wire.py), every reply bounded in time and checked:
``[B, A, 2]`` float32, finite. The worker is a fresh interpreter per job (its own ``sys.modules``:
two submissions that ship a module of the same name never see each other's), started by
crowdbench/leaderboard/sandbox.py. Whatever it does, crash, exit with any code (``SystemExit(0)``
included), hang, flood its output, return NaN or the wrong shape, the harness gets a
:class:`WorkerError` with one line and the worker is killed.

Worker side, :func:`main` (``python -m crowdbench.leaderboard.worker``): reads the submission,
registers its encoder, loads its checkpoint (``weights_only``) and answers ``act`` / ``reset``.
"""

from __future__ import annotations

import collections
import os
import re
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch

from crowdbench.envs.lookahead import PRIVILEGED_MODELS, check_lookahead
from crowdbench.envs.observation import OBS, Policy, obs_tensordict
from crowdbench.leaderboard import wire
from crowdbench.leaderboard.sandbox import (
    DEFAULT_LIMITS,
    SCRATCH,
    Limits,
    apply_limits,
    command,
    environment,
    needed_paths,
    sandbox_name,
)
from crowdbench.outputs import reap_dead

FRAMES = ("rotate", "translate", "world")
MAX_LINE = 240
SCRATCH_PREFIX = "crowdbench-worker"


class WorkerError(RuntimeError):
    """The worker failed its submission: one line, for the leaderboard's rejection list."""

    def __init__(self, message: str, field: str | None = None, public: str | None = None):
        self.field = field
        # what may be published (the README): no text the worker wrote, which could quote any file it reads
        self.public = _line(public if public is not None else message)
        super().__init__(_line(message))


def _line(text: str, limit: int = MAX_LINE) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


class _Tail:
    """The last few kB the worker wrote to stderr (read by a thread so it can never block on a full pipe)."""

    def __init__(self, stream):
        self.buf: collections.deque[bytes] = collections.deque(maxlen=64)
        self.thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self.thread.start()

    def _read(self, stream) -> None:
        for chunk in iter(lambda: stream.read1(4096), b""):
            self.buf.append(chunk)

    def last_line(self) -> str:
        lines = [ln for ln in b"".join(self.buf)[-4096:].decode("utf-8", "replace").splitlines() if ln.strip()]
        return lines[-1] if lines else ""


def unconfined_scratch() -> tempfile.TemporaryDirectory:
    """An unconfined worker's scratch, ``$TMPDIR/crowdbench-worker-<harness pid>-*``: the pid lets a later
    harness remove those of a harness that was killed before it could (``outputs.reap_dead``)."""
    reap_dead(Path(tempfile.gettempdir()), SCRATCH_PREFIX)
    return tempfile.TemporaryDirectory(prefix=f"{SCRATCH_PREFIX}-{os.getpid()}-")


class WorkerPolicy(Policy):
    """A submission's policy behind a worker process; use as a context manager (the worker is killed on exit)."""

    def __init__(self, sub_dir: Path, name: str, limits: Limits = DEFAULT_LIMITS):
        self.name, self.limits, self.steps = name, limits, 0
        self.budget: tuple[float, str] | None = None  # (time.monotonic() deadline, what it is), set per track
        # confined: the scratch is a tmpfs inside the worker's own mount namespace, never a host directory
        confined = sandbox_name(limits) == "bubblewrap"
        self._scratch = None if confined else unconfined_scratch()
        scratch = Path(SCRATCH if confined else self._scratch.name)
        env = environment(scratch)
        self.proc = subprocess.Popen(command(limits, needed_paths(Path(sub_dir).resolve(), env)),
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                                     cwd="/" if confined else scratch, start_new_session=True)
        self._tail = _Tail(self.proc.stderr)
        load = {"op": "load", "dir": str(Path(sub_dir).resolve()), "memory_gb": limits.memory_gb,
                "cpu_s": limits.cpu_s, "file_mb": limits.file_mb}
        try:
            header, _ = self._call(load, {}, limits.load_s, "loading")
            if header.get("frame") not in FRAMES:
                raise self._fail(f"the policy's frame {str(header.get('frame'))[:40]!r} is not one of "
                                 f"{', '.join(FRAMES)}", public=f"the policy's frame is not one of {', '.join(FRAMES)}")
        except BaseException:  # any failure (a RecursionError on a reply, Ctrl-C): no worker left running
            self.close()
            raise
        self.frame = header["frame"]
        if "lookahead" in header:  # the candidates the evaluation loop hands over with each observation
            try:
                self.lookahead = check_lookahead(header["lookahead"], header.get("actions"))
            except (ValueError, TypeError, RuntimeError) as e:
                raise self._fail(f"the policy's lookahead: {e}") from None
            self.privileged_lookahead = self.lookahead[0] in PRIVILEGED_MODELS

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _fail(self, what: str, field: str | None = None, public: str | None = None) -> WorkerError:
        self.close()
        return WorkerError(what, field, public)

    def start_budget(self, seconds: float, what: str) -> None:
        self.budget = (time.monotonic() + seconds, what)

    def _call(self, header: dict, arrays: dict, timeout: float, what: str) -> tuple[dict, dict]:
        deadline = time.monotonic() + timeout
        budget = self.budget is not None and self.budget[0] < deadline
        if budget:
            deadline = self.budget[0]
        try:
            wire.send(self.proc.stdin.fileno(), header, arrays, deadline)
            reply, out = wire.recv(self.proc.stdout.fileno(), deadline, max_payload=self._max_reply(arrays))
        except TimeoutError:
            if budget:
                raise self._fail(f"the worker exceeded its wall-clock budget ({self.budget[1]})") from None
            raise self._fail(f"the worker did not answer within {timeout:g} s ({what})") from None
        except (wire.WireError, OSError) as e:
            raise self._died(what, e) from None
        if reply["op"] == "error":  # the worker's own report: a rejected field, or its exception
            field = reply.get("field")
            message = str(reply.get("message", ""))
            kind = message.partition(":")[0] if re.fullmatch(r"[A-Za-z_]\w{0,40}(Error|Exception|Exit)", message.partition(":")[0]) \
                else "an error"
            public = f"refused by its worker while {what}" if field else f"evaluation failed: {kind} ({what})"
            raise self._fail(message if field else f"evaluation failed: {message} ({what})", field,
                             public + " (details in the harness log)")
        return reply, out

    @staticmethod
    def _max_reply(arrays: dict) -> int:
        robot = arrays.get("robot")
        return 1 << 16 if robot is None else robot.shape[0] * robot.shape[1] * 2 * 4

    def _died(self, what: str, e: Exception) -> WorkerError:
        try:
            code = self.proc.wait(timeout=2)
        except subprocess.TimeoutExpired:
            code = None
        self._tail.thread.join(timeout=1)
        last = self._tail.last_line()
        if code is None:
            how = f"broke the protocol ({e})"
        elif code < 0:
            how = f"was killed by {signal.Signals(-code).name}" + \
                  (" (its CPU-time limit)" if -code == signal.SIGXCPU else "")
        else:
            how = f"exited with code {code}"
        return self._fail(f"the worker {how} while {what}" + (f"; its last words: {last}" if last else ""),
                          public=f"the worker {how} while {what}" + ("; its last words are in the harness log"
                                                                     if last else ""))

    def reset(self, mask: torch.Tensor) -> None:
        self._call({"op": "reset"}, {"mask": mask.numpy()}, self.limits.step_s, f"resetting at step {self.steps}")

    def act(self, td) -> torch.Tensor:
        obs = td.get(OBS)
        arrays = {k: obs.get(k).numpy() for k in obs.keys()}  # noqa: SIM118 - a TensorDict
        b, a = arrays["robot"].shape[:2]
        _, out = self._call({"op": "act"}, arrays, self.limits.step_s, f"acting at step {self.steps}")
        action = out.get("action")
        if action is None or action.dtype != np.float32 or action.shape != (b, a, 2):
            got = "no action" if action is None else f"{action.dtype} {list(action.shape)}"
            raise self._fail(f"returned {got} at step {self.steps}, expected float32 [{b}, {a}, 2]")
        if not np.isfinite(action).all():
            bad = np.argwhere(~np.isfinite(action))[0]
            raise self._fail(f"returned a non-finite action at step {self.steps} (environment {bad[0]}, agent {bad[1]})")
        self.steps += 1
        return torch.from_numpy(action.copy())

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                self.proc.kill()
        self.proc.wait()
        self._tail.thread.join(timeout=1)  # stderr's EOF (a process that escaped the group may hold it open)
        for f in (self.proc.stdin, self.proc.stdout, *([] if self._tail.thread.is_alive() else [self.proc.stderr])):
            try:
                f.close()
            except OSError:
                pass
        if self._scratch is not None:
            self._scratch.cleanup()
            self._scratch = None


# ---------------------------------------------------------------------------------- worker side
def _serve(read_fd: int, write_fd: int) -> None:
    from crowdbench.leaderboard.loading import learned_policy
    from crowdbench.leaderboard.submission import SubmissionError, read_submission

    header, _ = wire.recv(read_fd)
    apply_limits(header["memory_gb"], header["cpu_s"], header["file_mb"])
    try:
        sub = read_submission(Path(header["dir"]))
        policy = learned_policy(sub)
    except SubmissionError as e:
        wire.send(write_fd, {"op": "error", "field": e.field, "message": e.message})
        return
    ready = {"op": "ready", "frame": policy.frame}
    look = getattr(policy, "lookahead", None)
    if look is not None:  # a value-lookahead policy: the harness computes its candidates (envs/lookahead.py)
        ready["lookahead"], ready["actions"] = look[0], look[1].tolist()
    wire.send(write_fd, ready)
    while True:
        header, arrays = wire.recv(read_fd)
        if header["op"] == "act":
            b = arrays["robot"].shape[0]
            action = policy.act(obs_tensordict({k: torch.from_numpy(v.copy()) for k, v in arrays.items()}, b))
            wire.send(write_fd, {"op": "action"}, {"action": action.detach().to(torch.float32).numpy()})
        elif header["op"] == "reset":
            policy.reset(torch.from_numpy(arrays["mask"].copy()))
            wire.send(write_fd, {"op": "ok"})
        else:
            return


def main() -> None:
    # the protocol gets private copies of the pipes; fd 1 becomes stderr, so what the submission's
    # code prints cannot corrupt a reply
    read_fd, write_fd = os.dup(0), os.dup(1)
    os.dup2(2, 1)
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    torch.set_num_threads(1)  # as the in-process evaluation: the same reductions, the same numbers
    try:
        _serve(read_fd, write_fd)
    except Exception as e:  # noqa: BLE001 - the harness reports it as the submission's rejection
        try:
            wire.send(write_fd, {"op": "error", "message": _line(f"{type(e).__name__}: {e}")})
        except (wire.WireError, OSError):
            pass


if __name__ == "__main__":
    main()
