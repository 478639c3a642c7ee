"""The algorithm registry, read by the CLI, the config schemas, the checkpoint loader and the leaderboard.

An algorithm is a component class (:class:`crowdbench.algos.base.Algorithm`) in one module, with a
typed config schema, and one YAML in ``crowdbench/conf/algo/``. The built-in ones are named here
by module path and actor kind: what an evaluation needs (the actor, ``crowdbench.algos.actors``)
is known without importing any training code, so an evaluation never loads a loss or an optimiser
and training code stays out of the leaderboard's cache fingerprint. A module is imported the first
time its component is asked for (training, config validation).

Adding an algorithm: one file defining the component (``ALGORITHM = MyAlgo``), one YAML, one line in
:data:`BUILTIN`; or, from outside the package, :func:`register_algorithm` (docs/algorithms.md).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

# what acting needs: a deterministic actor (TD3, DDPG) or a TanhNormal one acting by its mode (SAC, PPO);
# "value": no actor, a state-value network acting by one-step lookahead (algo=value, its own loop and policy)
ACTOR_KINDS = ("deterministic", "tanh_normal", "value")


@dataclass(frozen=True)
class AlgorithmEntry:
    name: str
    actor: str  # one of ACTOR_KINDS
    module: str | None = None  # imported on first use; None: ``component`` is already set
    component: type | None = None


BUILTIN = {
    "td3": AlgorithmEntry("td3", "deterministic", "crowdbench.algos.td3"),
    "ddpg": AlgorithmEntry("ddpg", "deterministic", "crowdbench.algos.ddpg"),
    "sac": AlgorithmEntry("sac", "tanh_normal", "crowdbench.algos.sac"),
    "ppo": AlgorithmEntry("ppo", "tanh_normal", "crowdbench.algos.ppo"),
    "matd3": AlgorithmEntry("matd3", "deterministic", "crowdbench.algos.matd3"),
    "ippo": AlgorithmEntry("ippo", "tanh_normal", "crowdbench.algos.ippo"),
    "mappo": AlgorithmEntry("mappo", "tanh_normal", "crowdbench.algos.mappo"),
    "value": AlgorithmEntry("value", "value", "crowdbench.algos.value"),
}
_ENTRIES: dict[str, AlgorithmEntry] = dict(BUILTIN)


def names() -> tuple[str, ...]:
    return tuple(_ENTRIES)


def entry(name) -> AlgorithmEntry:
    """The registered algorithm ``name``; an unknown one is a one-line error listing the valid names."""
    if not isinstance(name, str) or name not in _ENTRIES:
        raise ValueError(f"unknown algo {str(name)[:60]!r}; valid: {', '.join(_ENTRIES)}")
    return _ENTRIES[name]


def actor_kind(name) -> str:
    return entry(name).actor


def component(name) -> type:
    """The algorithm's class (imports its module the first time)."""
    e = entry(name)
    if e.component is None:
        cls = importlib.import_module(e.module).ALGORITHM
        if cls.name != name:
            raise ValueError(f"{e.module}.ALGORITHM is named {cls.name!r}, registered as {name!r}")
        e = _ENTRIES[name] = AlgorithmEntry(name, e.actor, e.module, cls)
    return e.component


def register_algorithm(cls: type) -> type:
    """Register a component class from outside the package (``name``, ``config``, ``actor_kind``).

    Its schema goes to Hydra's ConfigStore as ``algo/<name>`` (selectable as ``algo=<name>`` with no
    YAML; a YAML of the same name in a config path takes precedence) and ``schema/algo/<name>``."""
    if cls.actor_kind not in ACTOR_KINDS:
        raise ValueError(f"{cls.__name__}.actor_kind must be one of {', '.join(ACTOR_KINDS)}, got {cls.actor_kind!r}")
    _ENTRIES[cls.name] = AlgorithmEntry(cls.name, cls.actor_kind, None, cls)
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group="algo", name=cls.name, node=cls.config)
    ConfigStore.instance().store(group="schema/algo", name=cls.name, node=cls.config)
    return cls


def unregister_algorithm(name: str) -> None:
    """Undo :func:`register_algorithm` (tests), its ConfigStore entries included; a built-in one goes
    back to its module."""
    if name in BUILTIN:
        _ENTRIES[name] = BUILTIN[name]
        return
    if _ENTRIES.pop(name, None) is None:
        return
    from hydra.core.config_store import ConfigStore

    repo = ConfigStore.instance().repo
    for group in (repo.get("algo", {}), repo.get("schema", {}).get("algo", {})):
        group.pop(f"{name}.yaml", None)
