"""Validation of configs against crowdbench/config_schema.py: one-line errors naming the key.

:func:`validate` checks a composed config (``crowdbench run|eval`` and every run of a sweep, before
anything is written); :func:`validate_checkpoint` the config and weights of a checkpoint given to
``crowdbench eval policy=``. Both raise :class:`ConfigError`: ``<dotted key>: <problem> (got <value>)``.

Types are OmegaConf's: the config is merged into ``OmegaConf.structured`` of the schema and an
``omegaconf.errors.ValidationError`` becomes the one-line message; the bounds of the schema's field
metadata are then checked on the merged, resolved values. The config the command uses is not changed.
Keys the schema does not know (added with Hydra's ``+key=value``) are accepted, as Hydra accepts them.
"""

from __future__ import annotations

import re
import reprlib
import typing
from dataclasses import fields, is_dataclass
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from crowdbench.config_fields import field_problem, value_range
from crowdbench.config_schema import SELECTED, RootConfig

CHECKPOINT_SECTIONS = ("env", "algo", "encoder")
# what rebuilding a checkpoint's actor reads (crowdbench/algos/checkpoint.py policy_from_checkpoint)
CHECKPOINT_REQUIRED = ("env.frame", "env.v_max", "algo.name", "encoder.name")
MAX_ENTRIES = 10_000  # a checkpoint's config, counted as expanded (shared references count each time)
_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxdict, _REPR.maxlist, _REPR.maxtuple, _REPR.maxstring, _REPR.maxother = 3, 4, 6, 6, 50, 50


class ConfigError(ValueError):
    """A config value that does not fit its schema: one line naming the key."""


def short(value, limit: int = 60) -> str:
    """``repr(value)`` in at most ``limit`` characters, without building the whole repr first."""
    if isinstance(value, DictConfig | ListConfig):
        value = OmegaConf.to_container(value, resolve=False)
    text = _REPR.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --------------------------------------------------------------------------------------------- schema
def _selected(raw: dict, groups, prefix: str = "") -> dict[str, type]:
    """The schema class of each of ``groups`` (``env``, ``algo``, ``encoder``), chosen by its ``name``."""
    out = {}
    for group in groups:
        schemas, default = SELECTED[group]
        section = raw.get(group, {})
        if not isinstance(section, dict):
            raise ConfigError(f"{prefix}{group}: must be a mapping of {group} keys (got {short(section)})")
        name = section.get("name", default)
        if not isinstance(name, str) or name not in schemas:
            raise ConfigError(f"{prefix}{group}.name: must be one of {', '.join(schemas)} (got {short(name)})")
        out[group] = schemas[name]
    return out


def _open(node) -> None:
    """Let every mapping of ``node`` take keys its schema lacks (``+key=value``) and values (a frozen runtime
    dataclass, e.g. ``ReactiveParams``, is read-only in OmegaConf); types stay checked."""
    if isinstance(node, DictConfig) and not node._is_none():
        OmegaConf.set_struct(node, False)
        OmegaConf.set_readonly(node, False)
        for key in node:
            _open(node._get_node(key))


def _schema(selected: dict[str, type], sections) -> DictConfig:
    root = OmegaConf.structured(RootConfig)
    if sections is not None:  # a checkpoint: only the sections that rebuild its actor
        root = OmegaConf.create({})
    for group, cls in selected.items():
        root[group] = OmegaConf.structured(cls)
    _open(root)
    return root


def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _strip_optional(tp):
    args = typing.get_args(tp)
    if type(None) in args:
        return next(a for a in args if a is not type(None)), True
    return tp, False


def _tokens(key: str) -> list[str | int]:
    return [int(t[1:-1]) if t.startswith("[") else t for t in re.findall(r"\[\d+\]|[^.\[\]]+", key)]


def _expected(key: str, selected: dict[str, type]) -> tuple:
    """The annotation and the bounds of dotted ``key`` in the schema; ``(None, {})`` if it has none."""
    tp, meta = RootConfig, {}
    for i, tok in enumerate(_tokens(key)):
        tp, _ = _strip_optional(tp)
        if isinstance(tok, int):
            args = typing.get_args(tp)
            if not args:
                return None, {}
            tp = args[0]
        elif i == 0 and tok in selected:
            tp, meta = selected[tok], {}
        elif isinstance(tp, type) and is_dataclass(tp) and tok in _hints(tp):
            meta = next(f.metadata for f in fields(tp) if f.name == tok)
            tp = _hints(tp)[tok]
        else:
            return None, {}
    return tp, meta


def describe(tp) -> str:
    """``list[int] | None`` -> ``a list of integers or null``."""
    tp, optional = _strip_optional(tp)
    names = {int: "an integer", float: "a number", bool: "a boolean (true or false)", str: "a string"}
    if tp in names:
        text = names[tp]
    elif typing.get_origin(tp) is list:
        item = names.get(typing.get_args(tp)[0], "a value")
        text = "a list of " + {"an integer": "integers", "a number": "numbers", "a string": "strings"}.get(item, "values")
    elif isinstance(tp, type) and is_dataclass(tp):
        text = "a mapping of its keys"
    else:
        text = "a value"
    return text + (" or null" if optional else "")


def _lookup(raw, key: str):
    for tok in _tokens(key):
        try:
            raw = raw[tok]
        except (KeyError, IndexError, TypeError):
            return None
    return raw


def _type_error(err: OmegaConfBaseException, raw: dict, selected: dict[str, type], prefix: str) -> ConfigError:
    key = str(getattr(err, "full_key", "") or "?")
    value, (expected, meta) = _lookup(raw, key), _expected(key, selected)
    if expected is None:
        what = " ".join(str(getattr(err, "msg", err)).split("\n")[0].split())
    else:
        base, optional = _strip_optional(expected)
        rng = value_range(meta) if not typing.get_origin(base) else None
        what = ("must not be null; " if value is None else "") + "must be " + describe(base)
        what += (f" {rng}" if rng else "") + (" or null" if optional else "")
    return ConfigError(f"{prefix}{key}: {what} (got {short(value)})")


# --------------------------------------------------------------------------------------------- bounds
def _check_bounds(cls, values: dict, raw, selected: dict[str, type], prefix: str) -> None:
    """The bounds of ``cls``'s fields on the merged ``values``; the message shows the ``raw`` value."""
    hints = _hints(cls)
    for f in fields(cls):
        if f.name not in values:
            continue
        key, value = f"{prefix}{f.name}", values[f.name]
        tp = selected.get(f.name) or _strip_optional(hints[f.name])[0]
        if isinstance(tp, type) and is_dataclass(tp):
            if isinstance(value, dict):
                _check_bounds(tp, value, _lookup(raw, f.name), {}, key + ".")
            continue
        given = _lookup(raw, f.name)
        if given is None or (isinstance(given, str) and "${" in given):  # a default, an interpolation
            given = value
        bad = field_problem(value, f.metadata)
        if bad:
            raise ConfigError(f"{key}: {bad} (got {short(given)})")


# ---------------------------------------------------------------------------------------------- entry
def _check(raw: dict, sections=None, prefix: str = "") -> None:
    selected = _selected(raw, sections or tuple(SELECTED), prefix)
    if sections is not None:
        raw = {k: raw[k] for k in sections if k in raw}
    try:
        merged = OmegaConf.merge(_schema(selected, sections), raw)
        values = OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as e:
        raise _type_error(e, raw, selected, prefix) from None
    if "algo" in selected and isinstance(raw.get("algo"), dict):
        # an algorithm's config holds its own keys only: another algorithm's (an experiment written for
        # TD3 run with SAC) would be silently unused
        known = set(_hints(selected["algo"]))
        extra = [k for k in raw["algo"] if k not in known]
        if extra:
            raise ConfigError(f"{prefix}algo.{extra[0]}: algo={short(raw['algo'].get('name'))} has no such key "
                              f"(its keys: {', '.join(sorted(known))})")
    if sections is None:
        _check_bounds(RootConfig, values, raw, selected, "")
    else:
        for group in sections:
            if isinstance(values.get(group), dict):
                _check_bounds(selected[group], values[group], raw.get(group, {}), {}, f"{prefix}{group}.")


def validate(cfg) -> None:
    """Check a composed config (a DictConfig or a dict) against the schemas; :class:`ConfigError` if not."""
    raw = OmegaConf.to_container(cfg, resolve=False) if isinstance(cfg, DictConfig) else dict(cfg)
    raw.pop("hydra", None)
    _check(raw)


def unknown_keys(cfg) -> list[str]:
    """Dotted keys of a composed config that no schema declares (keys added with ``+key=value``; for a
    shipped YAML, a schema field is missing)."""
    raw = OmegaConf.to_container(cfg, resolve=False) if isinstance(cfg, DictConfig) else dict(cfg)
    raw.pop("hydra", None)
    selected, out = _selected(raw, tuple(SELECTED)), []

    def walk(cls, values: dict, prefix: str) -> None:
        hints = _hints(cls)
        for key, value in values.items():
            tp = selected.get(key) if cls is RootConfig and key in selected else hints.get(key)
            if tp is None:
                out.append(prefix + key)
            elif isinstance(tp, type) and is_dataclass(tp) and isinstance(value, dict):
                walk(tp, value, f"{prefix}{key}.")

    walk(RootConfig, raw, "")
    return out


def _entries(obj, budget: int) -> int:
    """How many values ``obj`` expands to, counting no further than ``budget``."""
    todo, n = [obj], 0
    while todo and n <= budget:
        x = todo.pop()
        n += 1
        if isinstance(x, dict):
            todo += list(x.values())
        elif isinstance(x, list | tuple):
            todo += list(x)
    return n


def validate_checkpoint(path: str | Path) -> dict:
    """Load a checkpoint (``weights_only``), check the ``env``/``algo``/``encoder`` parts of its config
    against the schemas and that its actor's weights are finite; its fields, or :class:`ConfigError`
    (a :class:`~crowdbench.algos.checkpoint.CheckpointError` for a file that is no checkpoint)."""
    import torch

    from crowdbench.algos.checkpoint import load_checkpoint

    state = load_checkpoint(Path(path))
    cfg, where = state["config"], f"checkpoint {path}: "
    if _entries(cfg, MAX_ENTRIES) > MAX_ENTRIES:
        raise ConfigError(f"{where}config: has more than {MAX_ENTRIES} entries, expanded (not a crowdbench run's)")
    for key in CHECKPOINT_REQUIRED:
        if _lookup(cfg, key) is None:
            raise ConfigError(f"{where}{key}: missing from its config (rebuilding the policy needs it)")
    _check(cfg, CHECKPOINT_SECTIONS, prefix=where)
    actor = state["actor"]
    for name, tensor in (actor.items() if isinstance(actor, dict) else ()):
        if torch.is_tensor(tensor) and tensor.is_floating_point() and not torch.isfinite(tensor).all():
            bad = int((~torch.isfinite(tensor)).sum())
            raise ConfigError(f"{where}actor.{name}: must be finite (got {bad} of {tensor.numel()} values NaN or inf)")
    return state
