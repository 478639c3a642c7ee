"""Layers import downward only (data -> envs -> models -> algos -> evaluation -> leaderboard -> command line)
and no module imports itself back through others: read statically from every module's imports (those
inside functions included), so a cycle a lazy import hides is found too."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "crowdbench"
# module (its first name under crowdbench) -> layer; a module may import its own layer and those below
LAYERS = {
    0: ("numerics", "outputs", "config_schema", "config_check", "schema_fields", "metric_table"),
    1: ("data",),
    2: ("envs",),
    3: ("models", "baselines"),
    4: ("algos",),
    5: ("protocols", "policies", "social_metrics", "viz"),
    6: ("leaderboard",),
    7: ("cli_eval", "compose", "cli_run", "cli_value", "cli_submit", "cli_usage", "sweep", "sweep_check", "api"),
    8: ("cli", "entry", "__main__"),
}
LAYER = {name: layer for layer, names in LAYERS.items() for name in names}
# known upward imports, each a configuration or registry concern still to be moved (docs/architecture.md)
KNOWN_UPWARD = {
    ("crowdbench.config_schema", "crowdbench.algos.registry"),  # the algorithms' schemas, by registry name
    ("crowdbench.config_check", "crowdbench.algos.checkpoint"),  # validate_checkpoint reads one
    ("crowdbench.algos.pretrain", "crowdbench.policies"),  # the ORCA expert's arguments (policies.params)
}


def modules() -> dict[str, Path]:
    out = {}
    for p in PACKAGE.rglob("*.py"):
        parts = p.relative_to(PACKAGE.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def imports(name: str, mods: dict[str, Path]) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(mods[name].read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("crowdbench"):
            out |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in mods else node.module for a in node.names}
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("crowdbench")}
    return {m for m in out if m in mods and m != name}


def layer(name: str) -> int:
    parts = name.split(".")
    assert len(parts) > 1, "the package root is imported by nothing inside it"
    assert parts[1] in LAYER, f"{name}: place it in a layer of tests/test_layers.py (and docs/architecture.md)"
    return LAYER[parts[1]]


def test_layers_import_downward_only():
    mods = modules()
    graph = {m: imports(m, mods) for m in mods if m != "crowdbench"}
    up = {(m, d) for m, ds in graph.items() for d in ds if d != "crowdbench" and layer(d) > layer(m)}
    assert up == KNOWN_UPWARD, sorted(up ^ KNOWN_UPWARD)
    assert not any("crowdbench" in ds for ds in graph.values()), "import crowdbench's modules, not the root"


def test_no_import_cycle():
    mods = modules()
    graph = {m: imports(m, mods) for m in mods}
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*path[path.index(d):], d]))
            if d not in state:
                visit(d, [*path, d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
