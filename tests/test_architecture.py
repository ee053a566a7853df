"""The package layout is the architecture: layers import only downwards, and no package imports in a cycle.

Every ``import`` statement of the library (module level *and* inside functions)
is read with :mod:`ast`; each module belongs to one layer, and a module may
import only from its own layer or the layers below it.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

LAYERS: list[tuple[str, ...]] = [
    ("aasoatt_env.errors", "aasoatt_env.validation", "aasoatt_env.cli_support", "aasoatt_env.compiled",
     "aasoatt_env.numba_jit"),
    ("aasoatt_env.model",),
    ("aasoatt_env.sim",),
    ("aasoatt_env.safety",),
    ("aasoatt_env.api", "aasoatt_env.tensor"),
    ("aasoatt_env.analysis",),
    ("agents",),
    ("train",),
    ("aasoatt_env.apps",),
]
"""Bottom to top.  ``aasoatt_env`` itself (the facade ``__init__``) is the public entry point
and may import any layer below ``agents``."""


def _layer(module: str) -> int | None:
    for rank, prefixes in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return rank
    return None


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in ("aasoatt_env", "agents", "train"):
        for path in (ROOT / pkg).rglob("*.py"):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _imports(module: str, path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.update(f"{node.module}.{a.name}" for a in node.names)  # resolved to the longest module
    return {m for m in found if m.split(".")[0] in ("aasoatt_env", "agents", "train")}


def _import_graph() -> dict[str, set[str]]:
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        deps = set()
        for imp in _imports(name, path):
            # resolve "pkg.module.symbol" to the longest module that exists
            parts = imp.split(".")
            while parts and ".".join(parts) not in mods:
                parts.pop()
            if parts:
                deps.add(".".join(parts))
        graph[name] = deps - {name}
    return graph


def test_every_library_module_belongs_to_a_layer():
    unassigned = [m for m in _modules() if m != "aasoatt_env" and _layer(m) is None]
    assert unassigned == []


def test_layers_import_only_downwards():
    upward = []
    for mod, deps in _import_graph().items():
        if mod == "aasoatt_env":
            assert all(_layer(d) is not None and _layer(d) < _layer("agents") for d in deps), deps
            continue
        for dep in deps:
            if dep == "aasoatt_env":
                upward.append((mod, dep))  # only the applications may use the facade ...
            elif _layer(dep) > _layer(mod):
                upward.append((mod, dep))
    upward = [(m, d) for m, d in upward if not (d == "aasoatt_env" and _layer(m) >= _layer("agents"))]
    assert upward == [], "\n".join(f"{m} imports {d}" for m, d in upward)


def unit_graph() -> dict[str, set[str]]:
    """Imports between the layer units (``aasoatt_env.model``, ..., ``agents``, ``train``, ``aasoatt_env.apps``)."""
    units: dict[str, set[str]] = {}
    for mod, deps in _import_graph().items():
        if mod == "aasoatt_env":
            continue
        src = LAYERS[_layer(mod)][0]
        units.setdefault(src, set())
        for d in deps:
            if d != "aasoatt_env" and LAYERS[_layer(d)][0] != src:
                units[src].add(LAYERS[_layer(d)][0])
    return units


def test_no_import_cycle_between_packages():
    graph = unit_graph()
    done: set[str] = set()

    def cycle_from(n: str, path: list[str]) -> list[str]:
        if n in path:
            return path[path.index(n):] + [n]
        if n in done:
            return []
        for d in sorted(graph.get(n, ())):
            found = cycle_from(d, path + [n])
            if found:
                return found
        done.add(n)
        return []

    cycles = [c for n in sorted(graph) if (c := cycle_from(n, []))]
    assert cycles == [], " -> ".join(cycles[0])


if __name__ == "__main__":  # print the unit graph (for the README / a review)
    for unit, deps in sorted(unit_graph().items(), key=lambda kv: _layer(kv[0])):
        print(f"{unit:28s} -> {', '.join(sorted(deps, key=_layer)) or '-'}")
