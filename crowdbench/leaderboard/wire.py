"""The harness <-> worker pipe format: a length-prefixed JSON header, then raw little-endian arrays.

Why not pickle or ``torch.save``: the harness reads what untrusted code wrote. A frame is
``>II`` (header bytes, payload bytes), a JSON header ``{"op": ..., "arrays": [[key, dtype, shape],
...], ...}`` and the arrays' bytes back to back. The reader checks both lengths against its bounds
before reading, the declared arrays against the payload, and the deadline on every read and write:
a peer that sends too much, too little, garbage or nothing costs the reader one :class:`WireError`.
"""

from __future__ import annotations

import json
import math
import os
import select
import struct
import time

import numpy as np

DTYPES = {"float32": np.dtype("<f4"), "bool": np.dtype("?"), "int64": np.dtype("<i8")}
PREFIX = struct.Struct(">II")
MAX_HEADER = 64 * 1024


class WireError(RuntimeError):
    """The peer broke the protocol, closed the pipe or missed the deadline."""


def _remaining(deadline: float | None) -> float | None:
    if deadline is None:
        return None
    left = deadline - time.monotonic()
    if left <= 0:
        raise TimeoutError
    return left


def _write_all(fd: int, data: bytes, deadline: float | None) -> None:
    view = memoryview(data)
    while view:
        _, ready, _ = select.select([], [fd], [], _remaining(deadline))
        if not ready:
            raise TimeoutError
        try:
            n = os.write(fd, view[:1 << 20])
        except BrokenPipeError:
            raise WireError("the pipe is closed") from None
        view = view[n:]


def _read_exact(fd: int, n: int, deadline: float | None) -> bytes:
    chunks, got = [], 0
    while got < n:
        ready, _, _ = select.select([fd], [], [], _remaining(deadline))
        if not ready:
            raise TimeoutError
        chunk = os.read(fd, min(n - got, 1 << 20))
        if not chunk:
            raise WireError("the pipe is closed")
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


def send(fd: int, header: dict, arrays: dict[str, np.ndarray] | None = None, deadline: float | None = None) -> None:
    arrays = arrays or {}
    parts, spec = [], []
    for key, a in arrays.items():
        name = a.dtype.name
        if name not in DTYPES:
            raise ValueError(f"array {key!r}: dtype {name} is not one of {', '.join(DTYPES)}")
        a = np.ascontiguousarray(a, dtype=DTYPES[name])
        spec.append([key, name, list(a.shape)])
        parts.append(a.tobytes())
    head = json.dumps({**header, "arrays": spec}, allow_nan=False).encode()
    payload = b"".join(parts)
    _write_all(fd, PREFIX.pack(len(head), len(payload)) + head + payload, deadline)


def recv(fd: int, deadline: float | None = None, max_payload: int = 1 << 30) -> tuple[dict, dict[str, np.ndarray]]:
    """One frame: ``(header, arrays)``; :class:`WireError` / ``TimeoutError`` on anything malformed or late."""
    n_head, n_payload = PREFIX.unpack(_read_exact(fd, PREFIX.size, deadline))
    if n_head > MAX_HEADER or n_payload > max_payload:
        raise WireError(f"a message of {n_head} + {n_payload} bytes exceeds the bound "
                        f"({MAX_HEADER} + {max_payload})")
    try:
        header = json.loads(_read_exact(fd, n_head, deadline))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise WireError(f"a malformed header: {type(e).__name__}") from None
    if not isinstance(header, dict) or not isinstance(header.get("op"), str):
        raise WireError("a header without an op")
    payload = _read_exact(fd, n_payload, deadline)
    specs = header.get("arrays") or []
    if not isinstance(specs, list):
        raise WireError("a header whose arrays are not a list")
    arrays, at = {}, 0
    for item in specs:
        try:
            key, name, shape = item
            dtype = DTYPES[name]
            shape = tuple(int(s) for s in shape)
            if any(s < 0 for s in shape):
                raise ValueError
        except (TypeError, ValueError, KeyError):
            raise WireError(f"a malformed array entry {str(item)[:60]!r}") from None
        size = math.prod(shape) * dtype.itemsize
        if at + size > len(payload):
            raise WireError(f"array {str(key)[:40]!r} declares more bytes than were sent")
        arrays[str(key)] = np.frombuffer(payload, dtype=dtype, count=math.prod(shape), offset=at).reshape(shape)
        at += size
    if at != len(payload):
        raise WireError(f"{len(payload) - at} bytes of payload that no array declares")
    return header, arrays
