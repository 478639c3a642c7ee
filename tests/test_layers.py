"""Layers import downward only (data -> envs -> models -> algos -> evaluation -> leaderboard -> command line)
and no module or package imports itself back through others: read statically from every module's imports
(those inside functions included: a lazy import that goes upward is still an upward import), so a cycle a
lazy import hides is found too. The layer order is written here once; docs/architecture.md's table must
say the same (checked below). benchmarks/import_graph.py prints the same measures."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "crowdbench"
# module or package (its first name under crowdbench) -> layer; a module may import its own layer and those below
LAYERS = {
    0: ("numerics", "outputs", "config_fields", "metric_table", "kinematics"),
    1: ("data",),
    2: ("envs",),
    3: ("models", "baselines"),
    4: ("algos",),
    5: ("protocols", "policies", "social_metrics", "viz", "config_schema", "config_check"),
    6: ("leaderboard",),
    7: ("app", "compose", "cli_run", "cli_value", "cli_submit", "cli_usage", "sweep", "sweep_check", "api"),
    8: ("cli", "entry", "__main__"),
}
LAYER = {name: layer for layer, names in LAYERS.items() for name in names}


def modules() -> dict[str, Path]:
    out = {}
    for p in PACKAGE.rglob("*.py"):
        parts = p.relative_to(PACKAGE.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def imports(name: str, mods: dict[str, Path], by_name: bool = False) -> dict[str, bool]:
    """The crowdbench modules ``name`` imports -> whether every such import is inside a function (lazy).
    ``by_name``: a string that is exactly a module's name (``importlib.import_module``, ``python -m``) counts
    as a lazy import too. Only for the layers: a registry names the modules that import it, which is no
    cycle when the package loads."""
    out: dict[str, bool] = {}

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = lazy or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            targets = []
            if isinstance(child, ast.ImportFrom) and child.level == 0 and (child.module or "").startswith("crowdbench"):
                targets = [f"{child.module}.{a.name}" if f"{child.module}.{a.name}" in mods else child.module
                           for a in child.names]
            elif isinstance(child, ast.Import):
                targets = [a.name for a in child.names if a.name.startswith("crowdbench")]
            elif by_name and isinstance(child, ast.Constant) and isinstance(child.value, str) \
                    and child.value.startswith("crowdbench."):
                targets = [child.value]  # a module named for importlib or a subprocess: imported later, by name
                inner = True
            for t in targets:
                if t in mods and t != name:
                    out[t] = out.get(t, True) and inner
            visit(child, inner)

    visit(ast.parse(mods[name].read_text()), False)
    return out


def layer(name: str) -> int:
    parts = name.split(".")
    assert len(parts) > 1, "the package root is imported by nothing inside it"
    assert parts[1] in LAYER, f"{name}: place it in a layer of tests/test_layers.py (and docs/architecture.md)"
    return LAYER[parts[1]]


def graph(by_name: bool = False) -> dict[str, dict[str, bool]]:
    mods = modules()
    return {m: imports(m, mods, by_name) for m in mods}


def upward(g: dict[str, dict[str, bool]]) -> list[tuple[str, str, bool]]:
    """(importer, imported, lazy) for every import of a higher layer."""
    return sorted((m, d, lazy) for m, ds in g.items() if m != "crowdbench" for d, lazy in ds.items()
                  if d != "crowdbench" and layer(d) > layer(m))


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan): each holds at least one cycle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(g.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = stack[stack.index(v):]
            del stack[stack.index(v):]
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def package_graph(g: dict[str, dict[str, bool]]) -> dict[str, set[str]]:
    """``crowdbench.<first name>`` -> those it imports (a top-level module counts as its own package)."""
    def top(m: str) -> str:
        return ".".join(m.split(".")[:2])

    out: dict[str, set[str]] = {}
    for m, ds in g.items():
        out.setdefault(top(m), set()).update(top(d) for d in ds if top(d) != top(m))
    return out


def test_layers_import_downward_only():
    g = graph(by_name=True)
    assert upward(g) == [], "upward imports (importer, imported, lazy): " + repr(upward(g))
    assert not any("crowdbench" in ds for m, ds in g.items() if m != "crowdbench"), \
        "import crowdbench's modules, not the root"


def test_no_import_cycle():
    g = graph()
    assert cycles({m: set(ds) for m, ds in g.items()}) == []
    assert cycles(package_graph(g)) == []


def test_cycles_are_found():
    # the checker itself: a two-module loop and a three-package loop are reported, a chain is not
    assert cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]
    assert cycles({"x": {"y"}, "y": {"z"}, "z": {"x"}}) == [["x", "y", "z"]]
    assert cycles({"x": {"y"}, "y": {"z"}, "z": set()}) == []


def test_docs_state_the_same_layers():
    rows = re.findall(r"^\| (\d) \| (.+?) \| .+ \|$", (ROOT / "docs" / "architecture.md").read_text(), re.MULTILINE)
    documented = {int(n): {re.sub(r"(\.py|/)$", "", c) for c in re.findall(r"`([^`]+)`", cells)} for n, cells in rows}
    assert documented == {n: set(names) for n, names in LAYERS.items()}
    on_disk = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
               if (p.suffix == ".py" or (p / "__init__.py").is_file()) and p.name != "__init__.py"}
    assert on_disk == set(LAYER), "every top-level module or package of crowdbench/ has one layer"
    # the one-line summary names packages in layer order
    line = re.search(r"^In short: (.+)\.$", (ROOT / "docs" / "architecture.md").read_text(), re.MULTILINE)
    order = [LAYER[re.sub(r" \(.*\)", "", n)] for n in line.group(1).split(" -> ")]
    assert order == sorted(set(order)), line.group(1)
