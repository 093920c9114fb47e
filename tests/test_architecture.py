"""The package layout is the architecture: layers that follow the data flow, no import circles,
and a library that never imports the node entry points."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "gsfix_online"


def _import_graph() -> dict[str, set[str]]:
    grimp = pytest.importorskip("grimp")  # import-linter's graph builder (a dev dependency)
    graph = grimp.build_graph("gsfix_online", cache_dir=None)
    return {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in graph:
                    continue
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_cycle_finder_finds_a_circle_and_only_it() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles() -> None:
    """Module-level and function-level imports alike: a circle is a design knot, lazy or not."""
    assert _cycles(_import_graph()) == []


def test_import_linter_contracts_are_kept() -> None:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.fail("lint-imports is not installed: `make setup` installs the dev extras")
    done = subprocess.run([exe], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "0 broken" in done.stdout


def test_the_layers_contract_covers_every_package() -> None:

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    layers = next(c for c in cfg["contracts"] if c["type"] == "layers")
    assert layers["containers"] == ["gsfix_online"] and layers.get("exhaustive") is True
    named = {n.strip() for layer in layers["layers"] for n in layer.split("|")}
    children = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    children |= {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    assert children == named


def test_the_library_never_imports_the_nodes() -> None:
    """nodes/ installs as gsfix_online.nodes outside the package folder, where the contract does
    not look; the graphs reach the nodes through the registry (entry points) instead."""
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            if any(n == "gsfix_online.nodes" or n.startswith(("gsfix_online.nodes.", "nodes"))
                   for n in names):  # fmt: skip
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []


def test_every_node_kind_is_registered_and_loads() -> None:
    from gsfix_online.runtime.graph import node_kinds, node_module

    files = {p.stem for p in (ROOT / "nodes").glob("*.py") if not p.stem.startswith("_")}
    files -= {"__init__", "camera"}  # camera: the shared loop of the realsense and oak nodes
    kinds = node_kinds()
    assert set(kinds) == files
    for kind in kinds:
        module = node_module(kind)
        assert module.__name__ == f"gsfix_online.nodes.{kind}"
        assert callable(module.run) and hasattr(module, "Params")
