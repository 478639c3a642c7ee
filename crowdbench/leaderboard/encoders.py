"""Making a learned submission's encoder known: its ``encoder_import`` module (a file inside the
submission directory, loaded by location) or its entry point, registered into ``ENCODERS``.

This runs the submission's code: only its worker process calls it (crowdbench/leaderboard/worker.py),
never the harness.
"""

from __future__ import annotations

import hashlib
import importlib.util
import sys
from importlib import metadata
from pathlib import Path

from crowdbench.leaderboard.submission import IMPORT_RE, REPO_DIR, Submission, SubmissionError, encoder_files
from crowdbench.leaderboard.text import short


def register_encoder(sub: Submission) -> None:
    """Make ``sub``'s encoder known: an import path or an entry point registers it into ENCODERS."""
    from torch import nn

    from crowdbench.models import ENCODERS

    data, path, name = sub.data, sub.yaml_path, sub.data["encoder"]
    cls = None
    if "encoder_import" in data:
        spec = data["encoder_import"]
        mod_name, _, attr = spec.partition(":")
        if not IMPORT_RE.fullmatch(spec):
            raise SubmissionError(path, "encoder_import", f"{short(spec)} is not of the form module:Class")
        (file,) = encoder_files(sub)
        module = _load_module(path, file, mod_name, sub.dir)
        cls = getattr(module, attr, None)
        if cls is None:
            raise SubmissionError(path, "encoder_import", f"module {mod_name!r} has no attribute {attr!r}")
        if file not in sub.extra_files:
            sub.extra_files.append(file)
    elif "encoder_entry_points" in data:
        group = data["encoder_entry_points"]
        found = [ep for ep in metadata.entry_points(group=group) if ep.name == name]
        if not found:
            raise SubmissionError(path, "encoder_entry_points",
                                  f"no entry point {name!r} in group {group!r} (is the package installed?)")
        try:
            cls = found[0].load()
        except Exception as e:  # noqa: BLE001
            raise SubmissionError(path, "encoder_entry_points", f"cannot load {found[0].value!r}: {e}") from None
    if cls is not None:
        if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
            raise SubmissionError(path, "encoder_import" if "encoder_import" in data else "encoder_entry_points",
                                  f"{cls!r} is not a torch.nn.Module subclass")
        if ENCODERS.get(name, cls) is not cls:
            raise SubmissionError(path, "encoder", f"{name!r} is already registered to another class "
                                                   f"({ENCODERS[name].__module__}.{ENCODERS[name].__name__})")
        ENCODERS[name] = cls
    if name not in ENCODERS:
        raise SubmissionError(path, "encoder", f"unknown encoder {name!r}; registered: {', '.join(sorted(ENCODERS))} "
                                               "(an external encoder needs encoder_import or encoder_entry_points)")


def _load_module(path: Path, file: Path, mod_name: str, sub_dir: Path):
    """The module in ``file`` (a submission's encoder), loaded from that file under a name unique to its
    content (``submission_encoder_<sha256>``), never through ``sys.modules[mod_name]``: two submissions
    that both ship a different ``my_encoder.py`` each get their own, while the same code (loaded again by
    the job, or a copy of the leaderboard) gives the same module and class. While it runs, the submission
    directory, the repository root and the current directory are on ``sys.path`` (its own imports)."""
    key = hashlib.sha256(mod_name.encode() + b"\0" + file.read_bytes()).hexdigest()[:16]
    unique = f"submission_encoder_{key}"
    if unique in sys.modules:
        return sys.modules[unique]
    spec = importlib.util.spec_from_file_location(unique, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[unique] = module  # (dataclasses and pickling look a class's module up there)
    added = [p for p in (str(sub_dir), str(REPO_DIR), str(Path.cwd())) if p not in sys.path]
    sys.path[:0] = added
    try:
        spec.loader.exec_module(module)
    except Exception as e:  # noqa: BLE001 - any import failure is the submission's error
        del sys.modules[unique]
        raise SubmissionError(path, "encoder_import", f"cannot import {mod_name!r}: {type(e).__name__}: {e}") \
            from None
    finally:
        for p in added:
            sys.path.remove(p)
    return module
