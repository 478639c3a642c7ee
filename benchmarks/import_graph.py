"""Import-graph measures of crowdbench/: cycles between modules and between packages, and upward imports
(module level and inside functions), against the layers of tests/test_layers.py (the one place they are
written). ``python benchmarks/import_graph.py [REPO]``; exit 1 if any."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path


def load_layers(repo: Path):
    spec = importlib.util.spec_from_file_location("test_layers", repo / "tests" / "test_layers.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv: list[str]) -> int:
    t = load_layers(Path(argv[0]) if argv else Path(__file__).resolve().parents[1])
    g = t.graph()
    mod_cycles = t.cycles({m: set(ds) for m, ds in g.items()})
    pkg_cycles = t.cycles(t.package_graph(g))
    up = t.upward(t.graph(by_name=True))  # modules named for importlib count as (lazy) imports here
    lazy = sum(lazy for *_, lazy in up)
    print(f"modules: {len(g)}, imports between them: {sum(len(ds) for ds in g.values())}")
    print(f"import cycles: {len(mod_cycles)} between modules, {len(pkg_cycles)} between packages")
    for c in mod_cycles + pkg_cycles:
        print("   ", " <-> ".join(c))
    print(f"upward imports: {len(up)} ({len(up) - lazy} at module level, {lazy} inside functions)")
    for m, d, is_lazy in up:
        print(f"    {m} -> {d}{' (inside a function)' if is_lazy else ''}")
    return 1 if mod_cycles or pkg_cycles or up else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
