"""The median and midpoint builders (lbvh/builders/topdown.py) against a plain recursive
Python twin (the same tree, node for node), and the shape each promises."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import random_soup
from lbvh.builders.bounds import triangle_boxes_numpy
from lbvh.builders.topdown import split_tree
from lbvh.layout import NODE_DTYPE, is_leaf, node_depths, prim_range_of


def recursive_twin(lo: np.ndarray, hi: np.ndarray, rule: str, leaf: int):
    """One node at a time, in Python: the documented rule, written plainly. Nodes are
    renumbered level by level afterwards to compare with the builder's numbering."""
    centre = lo * np.float32(0.5) + hi * np.float32(0.5)
    order = list(range(len(lo)))
    tree = {}          # key: node path, value: (first, count, children paths or None)

    def split(path, first, count):
        prims = order[first:first + count]
        if count <= leaf:
            tree[path] = (first, count, None)
            return
        c = centre[prims].astype(np.float64)
        if rule == "median":
            ext = hi[prims].max(0).astype(np.float64) - lo[prims].min(0).astype(np.float64)
        else:
            ext = c.max(0) - c.min(0)
        axis = int(np.argmax(ext))
        by_centre = sorted(prims, key=lambda p: (float(centre[p, axis]), p))
        k = count // 2
        if rule == "midpoint":
            middle = 0.5 * (c[:, axis].min() + c[:, axis].max())
            below = [p for p in by_centre if centre[p, axis] < middle]
            if 0 < len(below) < count:
                k = len(below)
                by_centre = below + [p for p in by_centre if not centre[p, axis] < middle]
        order[first:first + count] = by_centre
        tree[path] = (first, count, (path + (0,), path + (1,)))
        split(path + (0,), first, k)
        split(path + (1,), first + k, count - k)

    split((), 0, len(lo))
    paths = sorted(tree, key=lambda p: (len(p), p))   # level by level, left to right
    index = {p: i for i, p in enumerate(paths)}
    nodes = np.zeros(len(paths), NODE_DTYPE)
    for p, i in index.items():
        first, count, kids = tree[p]
        prims = order[first:first + count]
        nodes["lower"][i], nodes["upper"][i] = lo[prims].min(0), hi[prims].max(0)
        if kids is None:
            nodes["a"][i], nodes["b"][i] = first, -count
        else:
            nodes["a"][i], nodes["b"][i] = index[kids[0]], index[kids[1]]
    return nodes, np.array(order, np.int32)


@pytest.mark.parametrize("rule", ["median", "midpoint"])
@pytest.mark.parametrize("leaf", [1, 3])
def test_the_same_tree_as_the_recursive_twin(rule, leaf):
    v, f = random_soup(300, seed=2)
    lo, hi = triangle_boxes_numpy(v, f)
    got_nodes, got_order = split_tree(lo, hi, rule, leaf)
    want_nodes, want_order = recursive_twin(lo, hi, rule, leaf)
    assert np.array_equal(got_order, want_order)
    assert np.array_equal(got_nodes, want_nodes)


def test_identical_centres_fall_back_to_the_median():
    lo = np.zeros((100, 3), np.float32)
    hi = np.ones((100, 3), np.float32)
    nodes, order = split_tree(lo, hi, "midpoint", 1)
    assert len(nodes) == 199
    assert np.array_equal(nodes, recursive_twin(lo, hi, "midpoint", 1)[0])


@pytest.mark.parametrize("rule", ["median", "midpoint"])
def test_through_build(rule):
    v, f = random_soup(2000, seed=4)
    bvh = lbvh.build(v, f, builder=rule)
    bvh.validate()
    assert bvh.tree.builder == rule and bvh.tree.report.builder == rule
    depth = int(node_depths(bvh.tree.read("parent"), bvh.root).max())
    if rule == "median":
        assert depth == int(np.ceil(np.log2(len(f))))   # balanced
    leafy = lbvh.build(v, f, builder=rule, max_leaf_size=4)
    assert prim_range_of(leafy.nodes)[is_leaf(leafy.nodes), 1].max() <= 4
    assert lbvh.build(v, f, options=lbvh.SplitOptions(max_leaf_size=4), builder=rule).tree.num_nodes \
        == leafy.tree.num_nodes
    # the hits are the oracle's: the same ray answers as the LBVH's
    rng = np.random.default_rng(0)
    o = rng.uniform(-0.5, 1.5, (500, 3)).astype(np.float32)
    d = (v[rng.integers(0, len(v), 500)] - o).astype(np.float32)
    want = lbvh.build(v, f).intersect(o, d)
    got = bvh.intersect(o, d)
    assert np.array_equal(got.t, want.t) and np.array_equal(got.prim, want.prim)


@pytest.mark.parametrize("kwargs, fragment", [
    ({"collapse": True}, "collapse"), ({"treelet_rounds": 1}, "treelet_rounds"),
    ({"c_node": 2.0}, "c_node"), ({"max_leaf_size": 0}, "max_leaf_size: 0")])
def test_bad_options(kwargs, fragment):
    v, f = random_soup(50, seed=1)
    with pytest.raises(ValueError, match=fragment):
        lbvh.build(v, f, builder="median", **kwargs)
