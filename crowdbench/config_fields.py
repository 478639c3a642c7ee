"""Config fields that carry their bounds, and the one check of those bounds.

The runtime dataclasses (``SimConfig``, ``ReactiveParams``, the algorithms' configs, ...) declare their
fields with :func:`bounded`; crowdbench/config_schema.py registers those same classes as the schemas, and
crowdbench/config_check.py reads the same metadata when it validates a composed config. The env and
baseline settings classes also check themselves with :func:`check_fields` in ``__post_init__``, so a value
is refused in the same words whether it comes from the command line, a YAML or Python. Kept at the bottom layer so that an env or
an algorithm module can declare its schema without importing the schema registry (which imports them)."""

from __future__ import annotations

import math
import numbers
from dataclasses import field, fields
from typing import Any

SEED_BOUNDS = {"ge": 0, "lt": 2**63}  # every seed: the config's, an evaluation set's, a submission's, reset(seed=)


def bounded(default: Any = None, **bounds) -> Any:
    """A dataclass field of an immutable type with ``bounds`` in its metadata: ``gt``, ``ge``, ``lt``,
    ``le``, ``choices``, ``casefold`` (compare choices case-insensitively); a list field declares the
    same keys (checked on each item) and ``min_len`` with ``field(default_factory=..., metadata=...)``."""
    return field(default=default, metadata=bounds)


def rebound(cls: type, name: str, default: Any) -> Any:
    """Field ``name`` of ``cls`` with another default and the same bounds (a subclass's own default)."""
    return field(default=default, metadata=next(f.metadata for f in fields(cls) if f.name == name))


def _num(x) -> str:
    return "2**63" if x == 2**63 else repr(x)


def value_range(meta) -> str | None:
    """``meta``'s numeric bounds in words (``> 0``, ``in [0, 1]``), or None."""
    lo = ("(", meta["gt"]) if "gt" in meta else ("[", meta["ge"]) if "ge" in meta else None
    hi = (")", meta["lt"]) if "lt" in meta else ("]", meta["le"]) if "le" in meta else None
    if lo and hi:
        return f"in {lo[0]}{_num(lo[1])}, {_num(hi[1])}{hi[0]}"
    if lo:
        return f"{'>' if lo[0] == '(' else '>='} {_num(lo[1])}"
    if hi:
        return f"{'<' if hi[0] == ')' else '<='} {_num(hi[1])}"
    return None


def problem(v, meta) -> str | None:
    """What is wrong with one value ``v`` under the bounds ``meta`` (None: nothing)."""
    if isinstance(v, float) and not math.isfinite(v):
        return "must be a finite number"
    choices = meta.get("choices")
    if choices is not None and isinstance(v, str):
        fold = str.casefold if meta.get("casefold") else str
        if fold(v) not in {fold(c) for c in choices}:
            return f"must be one of {', '.join(choices)}"
    rng = value_range(meta)
    if rng is not None and isinstance(v, numbers.Real) and not isinstance(v, bool):
        ok = (("gt" not in meta or v > meta["gt"]) and ("ge" not in meta or v >= meta["ge"])
              and ("lt" not in meta or v < meta["lt"]) and ("le" not in meta or v <= meta["le"]))
        if not ok:
            return f"must be {rng}"
    return None


def field_problem(v, meta) -> str | None:
    """What is wrong with a field's value ``v`` under its bounds ``meta``: a list's length and each of its
    items, or the value itself (None: nothing, or no value). A float must be finite, bounded or not."""
    if v is None:
        return None
    if not isinstance(v, list | tuple):
        return problem(v, meta)
    if len(v) < meta.get("min_len", 0):
        return "must not be empty"
    return next((f"each item {bad}" for bad in (problem(item, meta) for item in v) if bad), None)


def check_fields(obj, prefix: str) -> None:
    """Every bounded field of the dataclass instance ``obj`` (``prefix`` names its config section, e.g.
    ``env.``): ``ValueError("<prefix><field>: <problem> (got <value>)")``. A numeric default asks for a
    number (not a string, not a bool), an integer default for an integer (``3``, not ``3.5``)."""
    for f in fields(obj):
        v = getattr(obj, f.name)
        number = isinstance(f.default, numbers.Real) and not isinstance(f.default, bool)
        integer = number and isinstance(f.default, numbers.Integral)
        if number and (isinstance(v, bool) or not isinstance(v, numbers.Integral if integer else numbers.Real)):
            rng = value_range(f.metadata)
            kind = "an integer" if integer else "a number"
            raise ValueError(f"{prefix}{f.name}: must be {kind}{' ' + rng if rng else ''} (got {v!r})")
        bad = field_problem(v, f.metadata)
        if bad:
            raise ValueError(f"{prefix}{f.name}: {bad} (got {v!r})")
