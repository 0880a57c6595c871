"""The package's folders and top-level modules ("rooms") form layers: a room imports
only rooms of a lower layer (or itself), there is no cycle, and no import of the
package's own modules hides inside a function.

The layers are those of ``lbvh/__init__.py``'s docstring; :data:`LAYERS` lists the
rooms from the bottom. A folder is one room: every module in ``lbvh/queries/``
is checked as ``lbvh.queries``, so a folder cannot sit on both sides of another.
"""
from __future__ import annotations

import ast
from pathlib import Path

import lbvh

PACKAGE = Path(lbvh.__file__).resolve().parent

#: room -> layer: a room may import only rooms of a strictly lower layer.
LAYERS = {
    # foundations: the node record, mesh checks, the version, progress bars; the device
    "lbvh.version": 0, "lbvh.layout": 0, "lbvh.progress": 0, "lbvh.mesh": 0,
    "lbvh.device": 0,
    "lbvh.data": 1, "lbvh.report": 1,       # the shipped files; the build report
    # cameras; the tree's measures (validator, SAH cost model and quality, error
    # bounds), below the builders; the values builders take and return
    "lbvh.camera": 2, "lbvh.metrics": 2, "lbvh.tree": 2,
    "lbvh.files": 3,                        # reading mesh and scene files, beside mesh.py
    "lbvh.builders": 3,
    "lbvh.queries": 4,
    "lbvh.bvh": 5, "lbvh.scene": 6,
    "lbvh.api": 7, "lbvh.dask": 7,
    # on top: what runs builds to check them (lbvh check, the self-test, the oracle),
    # trimesh's interfaces, rendering, the command line, the package's namespace
    "lbvh.verification": 8, "lbvh.trimesh": 8,
    "lbvh.rendering": 9,
    "lbvh.cli": 10,
    "lbvh": 11,
}


def room_of(module: str) -> str:
    """``lbvh.queries.traverse`` -> ``lbvh.queries``; ``lbvh.api`` -> ``lbvh.api``."""
    return ".".join(module.split(".")[:2])


def layer_of(module: str) -> int:
    return LAYERS[room_of(module)]


def module_name(path: Path) -> str:
    parts = ("lbvh",) + path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in PACKAGE.rglob("*.py") if "kernels" not in p.parts}


def _resolve(importer: str, is_package: bool, level: int, target: str | None) -> str:
    if level == 0:
        return target or ""
    base = importer.split(".") if is_package else importer.split(".")[:-1]
    base = base[:len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def imports_of(name: str, path: Path, known: set[str]) -> tuple[list[str], list[str]]:
    """(package modules imported at module level, those imported inside functions).
    Imports under ``if TYPE_CHECKING:`` are annotations only and not counted."""
    tree = ast.parse(path.read_text())
    is_package = path.name == "__init__.py"
    top, inner = [], []

    def targets(node: ast.AST) -> list[str]:
        found = []
        if isinstance(node, ast.Import):
            found = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(name, is_package, node.level, node.module)
            for a in node.names:   # "from pkg import module" imports the module
                found.append(f"{base}.{a.name}" if f"{base}.{a.name}" in known else base)
        return [t for t in found if t == "lbvh" or t.startswith("lbvh.")]

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                (inner if in_function else top).extend(targets(child))
            visit(child, in_function or isinstance(child, (ast.FunctionDef,
                                                             ast.AsyncFunctionDef)))
    visit(tree, False)
    return top, inner


def graph() -> tuple[dict[str, set[str]], dict[str, list[str]]]:
    mods = modules()
    known = set(mods)
    edges, hidden = {}, {}
    for name, path in mods.items():
        top, inner = imports_of(name, path, known)
        edges[name] = {t for t in top if t in known and t != name}
        if inner:
            hidden[name] = inner
    return edges, hidden


def test_every_module_has_a_layer():
    missing = sorted({room_of(name) for name in modules()} - set(LAYERS))
    assert not missing, f"rooms without a layer in LAYERS: {missing}"
    assert not set(LAYERS) - {room_of(name) for name in modules()}, "a layer names no room"


def upward_imports(edges: dict[str, set[str]]) -> list[str]:
    """Imports from one room into another of the same or a higher layer."""
    return sorted(f"{a} ({room_of(a)}, layer {layer_of(a)}) imports {b} "
                  f"({room_of(b)}, layer {layer_of(b)})"
                  for a, targets in edges.items() for b in targets
                  if room_of(a) != room_of(b) and layer_of(b) >= layer_of(a))


def test_no_room_imports_from_its_layer_or_a_higher_one():
    edges, _ = graph()
    upward = upward_imports(edges)
    assert not upward, "\n".join(upward)


def test_the_imports_have_no_cycle():
    edges, _ = graph()
    # a package's __init__ importing its own modules is not a cycle with them
    edges = {a: {b for b in bs if not b.startswith(a + ".") and not a.startswith(b + ".")}
             for a, bs in edges.items()}
    state: dict[str, int] = {}
    path: list[str] = []

    def walk(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = walk(nxt)
                if found:
                    return found
        state[node] = 2
        path.pop()
        return None

    for node in sorted(edges):
        if node not in state:
            cycle = walk(node)
            assert cycle is None, " -> ".join(cycle)


def test_no_package_import_is_hidden_in_a_function():
    """Imports inside functions are for optional dependencies only (trimesh,
    OpenImageIO...), never for the package's own modules."""
    _, hidden = graph()
    assert not hidden, "\n".join(f"{m}: {', '.join(t)}" for m, t in sorted(hidden.items()))


def test_the_layer_check_finds_an_upward_import(tmp_path):
    """The check itself can fail: a device module that imported the facade, a metric
    that imported a builder, or a builder that imported a room of its own layer
    would be caught."""
    assert layer_of("lbvh.device.memory") < layer_of("lbvh.bvh")
    fake = tmp_path / "m.py"
    fake.write_text("from ..bvh import BVH\n\ndef f():\n    from .. import tree\n")
    top, inner = imports_of("lbvh.device.m", fake, set(modules()) | {"lbvh.device.m"})
    assert top == ["lbvh.bvh"] and inner == ["lbvh.tree"]
    assert upward_imports({"lbvh.device.m": {"lbvh.bvh"}})
    assert upward_imports({"lbvh.metrics.validate": {"lbvh.builders.bounds"}})
    assert upward_imports({"lbvh.builders.sah": {"lbvh.files"}})   # same layer
    assert not upward_imports({"lbvh.queries.traverse": {"lbvh.queries.rays"}})
    assert not upward_imports({"lbvh.rendering.render": {"lbvh.verification.oracle"}})
