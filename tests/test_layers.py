"""The package's layers, read from the source: which modules may import which.

Every ``import`` and ``from ... import`` of every module under ``evseg_torch/`` counts, at module level
or inside a function alike. ``from package import name`` imports ``package.name`` when that is a module,
``package`` otherwise.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "evseg_torch"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _imports(name: str, top_level_only: bool = False) -> set[str]:
    """Every module (of any package) that module ``name`` imports; with ``top_level_only``, only those
    imported when it is imported."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    found = set()
    for node in tree.body if top_level_only else ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module
            for alias in node.names:
                found.add(f"{source}.{alias.name}" if f"{source}.{alias.name}" in MODULES else source)
    return found


IMPORTS = {name: _imports(name) for name in MODULES}


def _importers(target: str) -> dict[str, set[str]]:
    """The modules that import ``target`` or a module inside it, with what they import."""
    hits = {}
    for name, imported in IMPORTS.items():
        matched = {m for m in imported if m == target or m.startswith(target + ".")}
        if matched:
            hits[name] = matched
    return hits


def _inside(name: str, *packages: str) -> bool:
    return any(name == package or name.startswith(package + ".") for package in packages)


def test_every_module_is_read():
    assert "evseg_torch.pipeline" in MODULES and "evseg_torch.app.cli.entry" in MODULES
    assert "evseg_torch.app.runs" in IMPORTS["evseg_torch.app.cli.segment"]  # function-level imports count


def test_only_the_application_layer_imports_it():
    outside = {
        name: hits
        for name, hits in _importers("evseg_torch.app").items()
        if not _inside(name, "evseg_torch.app") and name != "evseg_torch"
    }
    assert outside == {}


@pytest.mark.parametrize("library", ["torch", "kornia"])
def test_level_one_imports_neither_torch_nor_level_two(library):
    # corners.py scores corners with kornia, on torch; the package loads it (through features.py) on
    # first use only.
    torch_users = {"evseg_torch.level_one.corners"}
    level_one = [name for name in MODULES if _inside(name, "evseg_torch.level_one")]
    for name in level_one:
        assert not {m for m in IMPORTS[name] if _inside(m, "evseg_torch.level_two")}, name
        if name not in torch_users:
            assert not {m for m in IMPORTS[name] if _inside(m, library)}, name
    on_import = _imports("evseg_torch.level_one", top_level_only=True)
    assert not on_import & (torch_users | {"evseg_torch.level_one.features"})


def test_level_two_does_not_import_level_one():
    assert {
        name: hits
        for name, hits in _importers("evseg_torch.level_one").items()
        if _inside(name, "evseg_torch.level_two")
    } == {}


def test_only_evaluation_data_and_the_application_layer_import_the_pipeline():
    allowed = ("evseg_torch.evaluation", "evseg_torch.data", "evseg_torch.app")
    assert {
        name: hits
        for name, hits in _importers("evseg_torch.pipeline").items()
        if not _inside(name, *allowed) and name != "evseg_torch"
    } == {}


def test_viz_imports_neither_the_pipeline_nor_the_application_layer():
    for name in MODULES:
        if _inside(name, "evseg_torch.viz"):
            assert not {m for m in IMPORTS[name] if _inside(m, "evseg_torch.pipeline", "evseg_torch.app")}


def test_no_import_cycles():
    """No two modules import each other, directly or through others (Tarjan's strongly connected
    components of the import graph)."""
    graph = {name: {m for m in IMPORTS[name] if m in MODULES and m != name} for name in MODULES}
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in graph[node]:
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                cycles.append(sorted(component))

    for name in graph:
        if name not in index:
            visit(name)
    assert cycles == []
