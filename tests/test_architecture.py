"""The layers hold: no import cycle anywhere, and no service imports another.

import-linter (run by CI with the contracts in pyproject.toml) checks the layers; these
tests check the whole module graph for cycles, imports inside functions included.
"""

from __future__ import annotations

import ast
from pathlib import Path

import grimp

PACKAGES = ("dammrl_core", "schemas", "services", "dammrl")
SERVICES = ("sim", "intent", "policy", "controller", "recorder", "robot")
TOP_DOWN = {"dammrl": 3, "services": 2, "dammrl_core": 1, "schemas": 1}
"""The layers, by their top-level folders: a folder imports only folders below it (the
library and the contract are side by side at the bottom and import neither the other)."""


def _graph() -> grimp.ImportGraph:
    return grimp.build_graph(*PACKAGES, cache_dir=None)


def _cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append(
                        (child, iter(sorted(graph.find_modules_directly_imported_by(child))))
                    )
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    components.append(sorted(component))
    return components


def test_no_module_imports_itself_through_others() -> None:
    assert _cycles(_graph()) == []


def test_no_service_imports_another_service() -> None:
    graph = _graph()
    crossings = [
        (a, b)
        for a in SERVICES
        for b in SERVICES
        if a != b and graph.chain_exists(f"services.{a}", f"services.{b}", as_packages=True)
    ]
    assert crossings == []


def test_the_core_library_and_the_schemas_import_nothing_above_them() -> None:
    graph = _graph()
    above = [m for m in graph.modules if not m.startswith(("dammrl_core", "schemas"))]
    for leaf in ("dammrl_core", "schemas"):
        imported = graph.find_upstream_modules(leaf, as_package=True)
        assert sorted(imported & set(above)) == [], leaf
    assert not graph.chain_exists("schemas", "dammrl_core", as_packages=True)


def _children_graph(graph: grimp.ImportGraph, parent: str) -> grimp.ImportGraph:
    """The imports between the children of folder ``parent`` (its modules and its
    subfolders, each with everything under it)."""
    children = grimp.ImportGraph()
    depth = parent.count(".") + 1
    for module in graph.modules:
        if not module.startswith(parent + "."):
            continue
        here = ".".join(module.split(".")[: depth + 1])
        for imported in graph.find_modules_directly_imported_by(module):
            if imported.startswith(parent + "."):
                there = ".".join(imported.split(".")[: depth + 1])
                if here != there:
                    children.add_import(importer=here, imported=there)
    return children


def _folders(graph: grimp.ImportGraph) -> set[str]:
    return {m.rsplit(".", 1)[0] for m in graph.modules if "." in m} | set(PACKAGES)


def test_the_folders_import_one_way() -> None:
    """How the folders are checked, not only the modules: the top-level folders import
    only the ones below them; inside every folder, its files and subfolders import each
    other one way (no two of them import each other, however indirectly)."""
    graph = _graph()
    upward = [
        (a, b)
        for a in graph.modules
        for b in graph.find_modules_directly_imported_by(a)
        if TOP_DOWN[a.split(".")[0]] <= TOP_DOWN[b.split(".")[0]]
        and a.split(".")[0] != b.split(".")[0]
    ]
    assert upward == []
    cycles = {folder: _cycles(_children_graph(graph, folder)) for folder in _folders(graph)}
    assert {folder: c for folder, c in cycles.items() if c} == {}


def test_the_cycle_finder_finds_a_cycle_hidden_in_a_longer_chain() -> None:
    graph = grimp.ImportGraph()
    for importer, imported in [("p.a", "p.b"), ("p.b", "p.c"), ("p.c", "p.a"), ("p.c", "p.d")]:
        graph.add_import(importer=importer, imported=imported)
    assert _cycles(graph) == [["p.a", "p.b", "p.c"]]


MAX_METHODS, MAX_CLASS_LINES, MAX_FUNCTION_LINES = 12, 200, 60
LARGE = {  # above the bounds, each with its reason in docs/reference/architecture.md
    "dammrl/people/session_steps.py:SessionSteps",
    "dammrl/people/session.py:StackRun",
    "dammrl/people/display/screens.py:Screens",
    "dammrl/people/display/participant.py:ParticipantDisplay",
    "dammrl/stack/runner.py:Episode",
    "dammrl/stack/launch.py:Stack",
    "dammrl/devices/emulators/servo_chain.py:ServoChain",
    "dammrl/devices/emulators/emg.py:EmgStream",
    "dammrl/devices/emulators/pad.py:SensorEmulator",
    "dammrl/cli/coadapt.py:_add_compare",
    "dammrl/cli/coadapt.py:register_adapt",
}


def test_the_tools_classes_and_functions_stay_readable() -> None:
    """No class of ``dammrl/`` over 12 methods or 200 lines, no function over 60 lines, but
    the ones the architecture page names with their reason."""
    root = Path(__file__).resolve().parents[1]
    large = set()
    for path in sorted((root / "dammrl").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                methods = sum(isinstance(n, ast.FunctionDef) for n in node.body)
                too_large = methods > MAX_METHODS or _lines(node) > MAX_CLASS_LINES
            elif isinstance(node, ast.FunctionDef):
                too_large = _lines(node) > MAX_FUNCTION_LINES
            else:
                continue
            if too_large:
                large.add(f"{path.relative_to(root)}:{node.name}")
    assert large - LARGE == set(), "split these, or give the reason on the architecture page"
    assert LARGE - large == set(), "these are within the bounds now: take them off the list"


def _lines(node: ast.ClassDef | ast.FunctionDef) -> int:
    return (node.end_lineno or node.lineno) - node.lineno + 1
