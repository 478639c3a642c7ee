"""A seccomp filter the worker installs on itself before it reads the submission (docs/submitting.md,
"What the harness protects"): no Unix-domain sockets, no new processes, no io_uring.

Why a filter and not only bubblewrap's mounts: a Unix socket file is reachable wherever it lies on
the (read-only) file system, and a new network namespace does not cover them; hiding /tmp, /run and
$HOME removes the usual ones, the filter removes the channel. Why no processes: the CPU-time limit
is per process and the kernel does not count processes of uid 0 against ``RLIMIT_NPROC``, so one
process (threads allowed) is what makes "30 CPU-minutes per job" hold. io_uring can open and connect
sockets without the ``socket`` system call.

A classic BPF program, written out here so that no libseccomp is needed; x86-64 and aarch64.
"""

from __future__ import annotations

import ctypes
import errno
import platform
import struct
import sys

# linux/audit.h, asm/unistd.h: (arch, {name: number}); a name missing on an arch is no system call there
ARCHES = {
    "x86_64": (0xC000003E, {"socket": 41, "fork": 57, "vfork": 58, "clone": 56, "clone3": 435,
                            "io_uring_setup": 425, "seccomp": 317}),
    "aarch64": (0xC00000B7, {"socket": 198, "clone": 220, "clone3": 435, "io_uring_setup": 425,
                             "seccomp": 277}),
}
AF_UNIX = 1
CLONE_THREAD = 0x00010000
X32_BIT = 0x40000000
RET_ALLOW = 0x7FFF0000
RET_ERRNO = 0x00050000
LD_ABS, JEQ, JGE, JSET, RET = 0x20, 0x15, 0x35, 0x45, 0x06
OFF_NR, OFF_ARCH, OFF_ARG0 = 0, 4, 16


class SeccompError(RuntimeError):
    """The filter could not be installed (then the worker refuses to run the submission)."""


def supported() -> bool:
    return sys.platform == "linux" and platform.machine() in ARCHES


def _ins(code: int, k: int, jt: int = 0, jf: int = 0) -> bytes:
    return struct.pack("HBBI", code, jt, jf, k)


def program(machine: str | None = None) -> bytes:
    """The filter for ``machine`` (default: this one), as an array of ``struct sock_filter``."""
    arch, nr = ARCHES[machine or platform.machine()]
    deny = lambda e: _ins(RET, RET_ERRNO | e)
    allow = _ins(RET, RET_ALLOW)
    checks = [(nr["socket"], "socket"), *((nr[n], "proc") for n in ("fork", "vfork") if n in nr),
              (nr["clone"], "clone"), (nr["clone3"], "nosys"), (nr["io_uring_setup"], "nosys")]
    # layout: header, one JEQ per checked call jumping to its handler, ALLOW, then the handlers
    handlers = {"socket": [_ins(LD_ABS, OFF_ARG0), _ins(JEQ, AF_UNIX, 0, 1), deny(errno.EACCES), allow],
                "clone": [_ins(LD_ABS, OFF_ARG0), _ins(JSET, CLONE_THREAD, 0, 1), allow, deny(errno.EAGAIN)],
                "proc": [deny(errno.EAGAIN)],
                # glibc falls back to clone() for threads when clone3 is missing: threads keep working
                "nosys": [deny(errno.ENOSYS)]}
    order = list(dict.fromkeys(kind for _, kind in checks))
    start, pos = {}, 0
    for kind in order:
        start[kind], pos = pos, pos + len(handlers[kind])
    head = [_ins(LD_ABS, OFF_ARCH), _ins(JEQ, arch, 1, 0), deny(errno.EPERM), _ins(LD_ABS, OFF_NR)]
    if machine in (None, "x86_64") and arch == ARCHES["x86_64"][0]:  # the x32 ABI: other numbers, refused
        head += [_ins(JGE, X32_BIT, 0, 1), deny(errno.EPERM)]
    jumps = []
    for i, (number, kind) in enumerate(checks):
        # from the instruction after this one: the rest of the jumps, ALLOW, then the handler
        jumps.append(_ins(JEQ, number, len(checks) - i - 1 + 1 + start[kind], 0))
    return b"".join(head + jumps + [allow] + [h for kind in order for h in handlers[kind]])


def install() -> None:
    """Apply :func:`program` to every thread of this process, for good (no new privileges; the
    filter is inherited and cannot be removed)."""
    if not supported():
        raise SeccompError(f"no seccomp filter for {sys.platform}/{platform.machine()}")
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(38, 1, 0, 0, 0) != 0:  # PR_SET_NO_NEW_PRIVS
        raise SeccompError(f"prctl(PR_SET_NO_NEW_PRIVS): errno {ctypes.get_errno()}")
    code = program()
    buf = ctypes.create_string_buffer(code, len(code))
    prog = struct.pack("HxxxxxxP", len(code) // 8, ctypes.addressof(buf))
    fprog = ctypes.create_string_buffer(prog, len(prog))
    number = ARCHES[platform.machine()][1]["seccomp"]
    # SECCOMP_SET_MODE_FILTER with SECCOMP_FILTER_FLAG_TSYNC: threads torch already started are covered too
    if libc.syscall(number, 1, 1, fprog) != 0:
        raise SeccompError(f"seccomp(SECCOMP_SET_MODE_FILTER): errno {ctypes.get_errno()}")
