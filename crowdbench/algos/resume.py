"""What a training run needs beyond ``checkpoint.pt`` to resume as if it had never stopped: the
replay buffer (TorchRL's ``dumps`` / ``loads``: transitions, sampler state with PER priorities, the
buffer's generator), the CSV logs cut back to the checkpoint, and checks that name what is missing.

The buffer is a directory ``replay-<frames>-<id>/`` next to the checkpoint, written under a temporary
name and renamed when complete; the checkpoint names it (``state["replay"]``) and both record the
frames and updates they were written at. It is written *before* the checkpoint that references it and
the previous one is removed only after that checkpoint is in place, so a kill at any point leaves a
checkpoint whose buffer is on disk; :func:`restore_buffer` refuses a buffer whose counters differ.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import tempfile
from pathlib import Path

import torch

from crowdbench.algos.checkpoint import CheckpointError
from crowdbench.outputs import write_text_atomic

BUFFER_PREFIX = "replay-"
BUFFER_META = "crowdbench.json"
# what the loop reads to resume beyond the algorithm's own fields; a submitted (actor-only) checkpoint has none
LOOP_FIELDS = ("sampler", "torch_rng", "updates")


def check_resumable(state: dict, path: Path, fields: tuple[str, ...] = ("loss",)) -> None:
    """``fields``: what the algorithm reads back (crowdbench/algos/base.py ``resume_fields``)."""
    missing = [k for k in (*fields, *LOOP_FIELDS) if k not in state]
    if "loss" in missing:
        raise CheckpointError(f"{path} is an actor-only (submitted) checkpoint; it cannot be resumed "
                              "(resume needs the run's own checkpoint.pt)")
    if missing:
        raise CheckpointError(f"{path} cannot be resumed: it lacks training field(s) {', '.join(missing)}")


def compact_storage(rb) -> None:
    """Save only the filled part of the storage (TorchRL dumps the whole capacity otherwise: ~262 MB for
    an empty default buffer); pad it back to the capacity on load. Checkpointer hooks of TorchRL."""
    storage = rb.storage

    def trim(td, path=None):
        return td[: len(storage)]

    def pad(td, out=None):
        n, cap = td.shape[0], storage.max_size
        if n == cap:
            return td
        full = td[:1].clone().expand(cap).clone()
        full[:n] = td
        return full

    storage.register_save_hook(trim)
    storage.register_load_hook(pad)


def save_buffer(rb, out_dir: Path, frames: int, updates: int) -> dict | None:
    """Dump ``rb`` into a new ``replay-*`` directory of ``out_dir``; the reference the checkpoint stores."""
    if len(rb) == 0:
        return None
    tmp = Path(tempfile.mkdtemp(dir=out_dir, prefix=f".{BUFFER_PREFIX}", suffix=".tmp"))
    try:
        rb.dumps(tmp / "buffer")
        (tmp / "buffer" / "prefetch.pkl").unlink(missing_ok=True)  # no prefetching: nothing is pickled
        ref = {"dir": f"{BUFFER_PREFIX}{frames:09d}-{tmp.name[len(BUFFER_PREFIX) + 1:-4]}", "frames": frames,
               "updates": updates, "transitions": len(rb)}
        (tmp / BUFFER_META).write_text(json.dumps(ref) + "\n")
        tmp.rename(out_dir / ref["dir"])
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ref


def remove_stale_buffers(out_dir: Path, keep: str | None) -> None:
    """Remove every buffer directory but ``keep`` (the one the checkpoint on disk references)."""
    for d in out_dir.iterdir():
        stale = d.name.startswith((BUFFER_PREFIX, f".{BUFFER_PREFIX}")) and d.name != keep
        if stale and d.is_dir():
            shutil.rmtree(d, ignore_errors=True)


def restore_buffer(rb, state: dict, ckpt: Path, same_kind: bool, make_like_saved) -> bool:
    """Load the buffer ``state`` references into ``rb``; False if it saved none. ``same_kind``: the
    buffer's replay settings are the checkpoint's, so the sampler state (PER priorities) is restored;
    otherwise the transitions are moved into ``rb``, oldest first, through a buffer ``make_like_saved()``."""
    ref = state.get("replay")
    if ref is None:
        return False
    d = ckpt.parent / str(ref.get("dir", ""))
    hint = "pass train.save_buffer=false to resume with an empty buffer"
    try:
        meta = json.loads((d / BUFFER_META).read_text())
    except (OSError, ValueError):
        raise CheckpointError(f"resume: the replay buffer {d} that {ckpt} references is missing or "
                              f"unreadable; {hint}") from None
    if (meta.get("frames"), meta.get("updates")) != (state["frames"], state["updates"]):
        raise CheckpointError(f"resume: the replay buffer {d} was written at {meta.get('frames')} frames, the "
                              f"checkpoint {ckpt} at {state['frames']}; {hint}")
    if (d / "buffer" / "prefetch.pkl").exists():
        raise CheckpointError(f"resume: {d} holds a pickle (prefetch.pkl), which crowdbench never writes; {hint}")
    target = rb if same_kind else make_like_saved()
    try:
        target.loads(d / "buffer")
    except Exception as e:  # noqa: BLE001 - torchrl / tensordict raise many types for damaged files
        reason = " ".join(str(e).split())[:200]
        raise CheckpointError(f"resume: corrupted replay buffer {d}: {type(e).__name__}: {reason}; {hint}") from None
    if len(target) != meta.get("transitions"):
        raise CheckpointError(f"resume: the replay buffer {d} holds {len(target)} transitions, "
                              f"{meta.get('transitions')} were saved; {hint}")
    if not same_kind:
        n, cap = len(target), target.storage.max_size
        start = target.write_count % cap if n == cap else 0
        rb.extend(target.storage.get((torch.arange(n) + start) % n))
    return True


def _rows(text: str) -> list[tuple[int, str, str]]:
    """The complete ``step,value`` rows of a CSV log: a partial or garbled row (a kill mid-write) is dropped."""
    complete = text if text.endswith("\n") else text[: text.rfind("\n") + 1]
    rows = []
    for r in csv.reader(io.StringIO(complete)):
        if len(r) != 2:
            continue
        try:
            step = int(float(r[0]))
            float(r[1])
        except ValueError:
            continue
        rows.append((step, r[0], r[1]))
    return rows


def truncate_log(log_dir: Path, frames: int) -> None:
    """After a resume, keep the complete rows logged up to the checkpoint (the later ones are logged
    again); each file is replaced atomically."""
    for f in sorted((log_dir / "scalars").glob("*.csv")):
        text = f.read_text(errors="replace")
        kept = "".join(f"{s},{v}\n" for step, s, v in _rows(text) if step <= frames)
        if kept != text:
            write_text_atomic(f, kept)
