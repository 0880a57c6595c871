"""The package's imports form layers: no cycle, nothing imported from a higher layer,
no import of the package's own modules hidden inside a function.

The layers are those of ``lbvh/__init__.py``'s docstring; :data:`LAYERS` lists
them from the bottom, by module name prefix (the longest prefix decides).
"""
from __future__ import annotations

import ast
from pathlib import Path

import lbvh

PACKAGE = Path(lbvh.__file__).resolve().parent

#: (module prefix, layer): a module may import only modules of its layer or lower.
LAYERS = [
    ("lbvh.version", 0), ("lbvh.layout", 0), ("lbvh.mesh", 0), ("lbvh.progress", 0),
    ("lbvh.report", 1), ("lbvh.data", 1),   # lbvh.data: the shipped files (numpy only)
    # readers of the caller's files and cameras: numpy (and trimesh) only
    ("lbvh.rendering.camera", 1), ("lbvh.rendering.scene", 1),
    ("lbvh.device", 2),
    ("lbvh.tree", 3),
    ("lbvh.builders", 4),
    # numpy checks that trees and answers are measured by: below the facade
    ("lbvh.verification.validate", 4), ("lbvh.verification.quality", 4),
    ("lbvh.verification.error_bound", 4),
    ("lbvh.verification.oracle", 5),   # answers the queries in float64 (their Hits)
    ("lbvh.verification.meshes", 4),
    ("lbvh.queries", 5),
    ("lbvh.bvh", 6), ("lbvh.scene", 6), ("lbvh.dask", 6),
    ("lbvh.api", 7),
    ("lbvh.verification", 8), ("lbvh.rendering", 8), ("lbvh.trimesh", 8),
    ("lbvh.cli", 9),
    ("lbvh", 10),
]


def layer_of(module: str) -> int:
    best = max((p for p, _ in LAYERS if module == p or module.startswith(p + ".")), key=len)
    return dict(LAYERS)[best]


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
    for name in modules():
        assert layer_of(name) >= 0, name


def test_no_module_imports_from_a_higher_layer():
    edges, _ = graph()
    upward = [f"{a} (layer {layer_of(a)}) imports {b} (layer {layer_of(b)})"
              for a, targets in edges.items() for b in targets
              if layer_of(b) > layer_of(a) and not a.startswith(b + ".")
              and not (b == "lbvh" and a.startswith("lbvh."))]
    assert not upward, "\n".join(sorted(upward))


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
    """The check itself can fail: a device module that imported the facade would be caught."""
    assert layer_of("lbvh.device.memory") < layer_of("lbvh.bvh")
    fake = tmp_path / "m.py"
    fake.write_text("from ..bvh import BVH\n\ndef f():\n    from .. import tree\n")
    top, inner = imports_of("lbvh.device.m", fake, set(modules()) | {"lbvh.device.m"})
    assert top == ["lbvh.bvh"] and inner == ["lbvh.tree"]
