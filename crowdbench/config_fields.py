"""The field constructor of the typed config schemas (crowdbench/config_schema.py), kept apart so that
an algorithm module can declare its schema without importing the schema registry (which imports the
algorithms)."""

from dataclasses import field
from typing import Any


def bounded(default: Any = None, **bounds) -> Any:
    """A dataclass field of an immutable type with ``bounds`` in its metadata: ``gt``, ``ge``, ``lt``,
    ``le``, ``choices``, ``casefold`` (compare choices case-insensitively); a list field declares the
    same keys (checked on each item) and ``min_len`` with ``field(default_factory=..., metadata=...)``."""
    return field(default=default, metadata=bounds)
