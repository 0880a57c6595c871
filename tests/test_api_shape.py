"""The shape of the public API, counted from the code: a facade of few members, short
signatures, each option in one home.

- :class:`lbvh.BVH` has at most :data:`MAX_BVH_MEMBERS` public members (properties,
  methods, instance attributes).
- No public function or method of the package takes more than :data:`MAX_PARAMETERS`
  named parameters (positional and keyword-only, ``self`` aside); options beyond
  them travel as data (``QueryOptions``, ``LBVHOptions``...), or as their documented
  fields through ``**fields``.
- The query options are named in one signature, :class:`lbvh.QueryOptions`'s.
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
from pathlib import Path

import numpy as np
import pytest

import lbvh

PACKAGE = Path(lbvh.__file__).resolve().parent
MAX_BVH_MEMBERS = 25
MAX_PARAMETERS = 8


def public_functions() -> list[tuple[str, ast.FunctionDef]]:
    """``(where, node)`` of every public function and method of public classes."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())

        def walk(node: ast.AST, owner: str | None) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.ClassDef) and not child.name.startswith("_"):
                    walk(child, child.name)
                elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                        (not child.name.startswith("_") or child.name == "__init__"):
                    where = f"{path.relative_to(PACKAGE.parent)}:{owner + '.' if owner else ''}"
                    found.append((where + child.name, child))
        walk(tree, None)
    return found


def named_parameters(node: ast.FunctionDef) -> list[str]:
    args = node.args
    names = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs]
    return names[1:] if names and names[0] in ("self", "cls") else names


def test_the_bvh_has_few_public_members():
    bvh = lbvh.build(*lbvh.data.teapot())
    members = sorted({m for m in dir(bvh) if not m.startswith("_")})
    assert len(members) <= MAX_BVH_MEMBERS, f"{len(members)} public members: {members}"
    # the instance holds no public attribute beside the class's members
    assert not [k for k in vars(bvh) if not k.startswith("_")]


def test_no_public_function_takes_more_than_eight_parameters():
    found = public_functions()
    assert len(found) > 300   # the walk reads the package
    long = [f"{where}: {len(named_parameters(node))}" for where, node in found
            if len(named_parameters(node)) > MAX_PARAMETERS]
    assert not long, "\n".join(long)


def test_keyword_fields_are_documented_options():
    """A public function that takes ``**fields`` says what they are: an options class's
    fields (its docstring names the class or the fields)."""
    silent = []
    for where, node in public_functions():
        if node.args.kwarg is None:
            continue
        doc = ast.get_docstring(node) or ""
        if not any(word in doc for word in ("Options", "fields", "options")):
            silent.append(where)
    # the query methods take their docstrings from lbvh.queries.traverse.query_doc
    documented_elsewhere = {"lbvh/bvh.py:BVH.intersect", "lbvh/bvh.py:BVH.occluded",
                            "lbvh/bvh.py:BVH.intersect_async", "lbvh/bvh.py:BVH.occluded_async",
                            "lbvh/queries/traverse.py:intersect", "lbvh/queries/traverse.py:occluded",
                            "lbvh/queries/traverse.py:intersect_async",
                            "lbvh/queries/traverse.py:occluded_async"}
    assert set(silent) <= documented_elsewhere, sorted(set(silent) - documented_elsewhere)
    for name in ("intersect", "occluded", "intersect_async", "occluded_async"):
        assert "QueryOptions" in getattr(lbvh.BVH, name).__doc__ or "Arguments as" in \
            getattr(lbvh.BVH, name).__doc__


def test_the_query_options_have_one_home():
    fields = {f.name for f in dataclasses.fields(lbvh.QueryOptions)}
    assert {"invalid_rays", "triangle_test", "counters", "batch_size", "stack_size",
            "order"} == fields
    # the rays' checks take the option's value: lbvh/queries/rays.py applies it
    repeated = [where for where, node in public_functions()
                if "invalid_rays" in named_parameters(node)
                and not where.startswith("lbvh/queries/rays.py:")]
    assert not repeated, repeated


def test_query_options_as_data_or_keywords_give_the_same_answers():
    bvh = lbvh.build(*lbvh.data.teapot())
    rng = np.random.default_rng(1)
    o = rng.normal(size=(300, 3)).astype(np.float32) * 3
    d = -o + rng.normal(size=(300, 3)).astype(np.float32) * 0.3
    o[5] = np.nan
    opts = lbvh.QueryOptions(invalid_rays="miss", triangle_test="moller", counters=True,
                             batch_size=64)
    a = bvh.intersect(o, d, options=opts)
    b = bvh.intersect(o, d, invalid_rays="miss", triangle_test="moller", counters=True,
                      batch_size=64)
    for name in ("t", "prim", "u", "v", "nodes_visited", "tris_tested", "invalid"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.invalid_count == 1
    # a keyword beside the options replaces that field
    c = bvh.intersect(o, d, options=opts, counters=False)
    assert c.nodes_visited is None and np.array_equal(c.t, a.t)
    assert np.array_equal(bvh.count_hits(o, d, options=lbvh.QueryOptions(invalid_rays="miss")),
                          bvh.count_hits(o, d, invalid_rays="miss"))


@pytest.mark.parametrize("call, message", [
    (lambda b, o, d: b.count_hits(o, d, triangle_test="moller"), "does not apply"),
    (lambda b, o, d: b.occluded(o, d, order="global"), "does not apply"),
    (lambda b, o, d: b.intersect(o, d, bogus=1), "unexpected keyword argument 'bogus'"),
    (lambda b, o, d: b.intersect(o, d, options={"counters": True}), "expected lbvh.QueryOptions"),
])
def test_an_option_a_query_does_not_read_is_refused_by_name(call, message):
    bvh = lbvh.build(*lbvh.data.teapot())
    o, d = np.zeros((2, 3), np.float32), np.tile(np.float32([0, 0, 1]), (2, 1))
    with pytest.raises(TypeError, match=message):
        call(bvh, o, d)


@pytest.mark.parametrize("fields, message", [
    ({"invalid_rays": "skip"}, "invalid_rays"), ({"triangle_test": "fast"}, "triangle_test"),
    ({"order": "sideways"}, "order"), ({"batch_size": 0}, "batch_size"),
    ({"batch_size": True}, "batch_size"), ({"stack_size": -1}, "stack_size"),
    ({"counters": "yes"}, "counters")])
def test_bad_query_options_name_the_field(fields, message):
    with pytest.raises(ValueError, match=message):
        lbvh.QueryOptions(**fields)


def test_the_signatures_read_the_same_as_the_code():
    """inspect agrees with the ast count on the facade's query methods."""
    for name in ("intersect", "occluded", "count_hits", "all_hits"):
        sig = inspect.signature(getattr(lbvh.BVH, name))
        named = [p for p in sig.parameters.values()
                 if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL) and p.name != "self"]
        assert len(named) <= MAX_PARAMETERS and "options" in sig.parameters, name


def main() -> None:
    """``python tests/test_api_shape.py``: the counts the tests bound, printed."""
    members = sorted(m for m in dir(lbvh.BVH) if not m.startswith("_"))
    found = public_functions()
    long = [(len(named_parameters(n)), w) for w, n in found if len(named_parameters(n)) > 8]
    naming = [w for w, n in found if "invalid_rays" in named_parameters(n)]
    print(f"BVH public members: {len(members)}")
    print(f"public functions: {len(found)}, with more than {MAX_PARAMETERS} named parameters: "
          f"{len(long)} {sorted(long, reverse=True)}")
    print(f"signatures naming invalid_rays: {len(naming)} {naming}")


if __name__ == "__main__":
    main()
