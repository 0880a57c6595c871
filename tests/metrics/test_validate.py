"""The validator must catch each kind of broken tree (a checker that cannot fail checks nothing)."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import shipped_mesh
from lbvh.metrics.validate import BVHValidationError, validate_tree


@pytest.fixture(scope="module")
def tree():
    v, f = shipped_mesh("suzanne.obj")
    bvh = lbvh.build(v, f)
    return bvh.nodes.copy(), bvh.tree.read("parent").copy(), bvh.prim_order.copy(), v, f


def check(nodes, parent, order, v, f, root=0):
    validate_tree(nodes, parent, order, root, v, f)


def test_valid_tree_passes(tree):
    check(*tree)


def mutate(tree, fn):
    nodes, parent, order, v, f = (a.copy() for a in tree)
    fn(nodes, parent, order)
    return nodes, parent, order, v, f


def shrink_internal(n, p, o):
    n["upper"][0, 0] = n["lower"][0, 0]


def shrink_leaf(n, p, o):
    thick = np.flatnonzero((n["b"] < 0) & (n["upper"][:, 1] > n["lower"][:, 1]))[0]
    n["upper"][thick, 1] = np.nextafter(n["upper"][thick, 1], np.float32(-np.inf))


def nan_box(n, p, o):
    n["lower"][3, 2] = np.nan


def swap_prims(n, p, o):
    o[0] = o[1]


def wrong_parent(n, p, o):
    p[n["a"][0]] = 5


def self_loop(n, p, o):
    n["a"][1] = 1


def out_of_range_child(n, p, o):
    n["b"][2] = len(n) + 7


def leaf_range_overlap(n, p, o):
    n["a"][len(n) - 1] = 0


def leaf_without_prims(n, p, o):
    n["b"][len(n) - 1] = 0  # b = 0: becomes an "internal" node pointing at the root


@pytest.mark.parametrize("broken, message", [
    (shrink_internal, "does not contain its"),
    (shrink_leaf, "not the exact box of its triangles"),
    (nan_box, "non-finite box"),
    (swap_prims, r"appears [02] times in prim_order"),
    (wrong_parent, "has parent 5"),
    (self_loop, "child of 2 nodes|child of another|nobody's child|cycle|has parent"),
    (out_of_range_child, "outside"),
    (leaf_range_overlap, "tile"),
    (leaf_without_prims, "internal nodes for|child"),
])
def test_each_violation_is_named(tree, broken, message):
    with pytest.raises(BVHValidationError, match=message):
        check(*mutate(tree, broken))


def test_wrong_root_parent(tree):
    nodes, parent, order, v, f = mutate(tree, lambda n, p, o: p.__setitem__(0, 3))
    with pytest.raises(BVHValidationError, match="root 0 has parent 3"):
        check(nodes, parent, order, v, f)
