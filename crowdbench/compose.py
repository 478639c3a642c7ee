"""Composing a run's config: Hydra over ``crowdbench/conf`` (and a project's ``configs/``), with its
multi-line errors turned into one line naming the key and the valid choices."""

from __future__ import annotations

import re
from pathlib import Path

from crowdbench.app import UsageError

CONFIG_DIR = Path(__file__).resolve().parent / "conf"


def normalise(overrides: list[str]) -> list[str]:
    """``+experiment=X`` / ``+method=X`` mean ``experiment=X`` / ``method=X``: both groups are in the
    defaults list (as null), where Hydra's append syntax would be an error."""
    return [o[1:] if o.startswith(("+experiment=", "+method=")) else o for o in overrides]


def compose(overrides: list[str]):
    """Compose ``conf/config.yaml`` with Hydra overrides; struct mode rejects unknown keys."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    if not CONFIG_DIR.is_dir():
        raise UsageError(f"config directory not found: {CONFIG_DIR} (install with pip install -e .)")
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
            cfg = hydra_compose(config_name="config", overrides=normalise(overrides))
    except HydraException as e:
        raise UsageError(hydra_message(e, overrides)) from None
    OmegaConf.set_struct(cfg, True)
    return cfg


def hydra_message(err: Exception, overrides: list[str]) -> str:
    """Turn Hydra's multi-line errors into one line naming the key and the valid choices."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    text = " ".join(str(err).split())
    missing = re.search(r"Could not find '([^/']+)/([^']+)'", text)
    if missing:
        group, choice = missing.groups()
        opts = sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))
        return f"unknown {group} {choice!r}; valid choices: {', '.join(opts)}"
    bad = re.search(r"Could not override '([^']+)'", text) or re.search(r"Key '([^']+)' is not in struct", text)
    if not bad:
        unparsed = _ungrammatical(overrides)
        if unparsed:  # e.g. a non-ASCII path: Hydra's grammar takes it quoted
            key, _, value = unparsed.partition("=")
            quoted = value.replace("\\", "\\\\").replace("'", "\\'")
            return (f"bad override {unparsed!r}: not valid in Hydra's override grammar; quote the value: "
                    f"\"{key}='{quoted}'\"")
        return f"bad override: {text}"
    key = bad.group(1)
    parent = key.rsplit(".", 1)[0] if "." in key else ""
    # list the keys of the config the user composed (group choices kept, the bad key dropped)
    groups = [o for o in overrides if "=" in o and "." not in o.split("=")[0] and o.split("=")[0] != key]
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
            node = OmegaConf.select(hydra_compose(config_name="config", overrides=groups), parent or "")
        valid = ", ".join(sorted(node.keys()))
    except (HydraException, AttributeError):
        valid = "?"
    return f"unknown config key {key!r}; valid keys{' under ' + repr(parent) if parent else ''}: {valid}"


def _ungrammatical(overrides: list[str]) -> str | None:
    """The first override Hydra's grammar cannot parse, if any."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    for o in normalise(overrides):
        try:
            parser.parse_overrides([o])
        except HydraException:
            return o
    return None
