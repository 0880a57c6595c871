"""bench/bench_walk.py: the conversion of an n-ary tree (Embree's rtcBuildBVH) to
ours, checked without Embree on a tree of known shape, and, where embreex is
installed, Embree's tree of a shipped mesh traced with our answers."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import load_bench, shipped_mesh
from lbvh.builders.bounds import triangle_boxes_numpy
from lbvh.bvh import BVH
from lbvh.layout import parents_of
from lbvh.tree import upload_tree

bench = load_bench("bench_walk")


def _traced_like_the_default(v, f, nodes, order):
    """The converted tree validates and gives the default tree's closest hits."""
    ref = lbvh.build(v, f)
    bvh = BVH(ref.mesh, upload_tree(ref.ctx, nodes, parents_of(nodes, 0), order, 0, "nary"))
    bvh.validate()
    rng = np.random.default_rng(5)
    lo, hi = v.min(axis=0), v.max(axis=0)
    o = (lo + (hi - lo) * rng.uniform(-0.5, 1.5, (3000, 3))).astype(np.float32)
    d = (v[rng.integers(0, len(v), 3000)] - o).astype(np.float32)
    got, want = bvh.intersect(o, d), ref.intersect(o, d)
    assert np.array_equal(got.t, want.t) and (want.prim >= 0).sum() > 1000
    return bvh


def test_an_nary_tree_becomes_balanced_binary_subtrees_with_slot_ranges():
    v, f = shipped_mesh("teapot.obj")
    lo, hi = triangle_boxes_numpy(v, f.astype(np.uint32))
    n = len(f)
    # a root of 5 children, each an inner node of 3 leaves of consecutive triangles
    # (the last leaf takes the rest): 15 leaves
    cuts = np.linspace(0, n, 16).astype(int)
    leaves = {100 + k: list(range(cuts[k], cuts[k + 1]))[::-1] for k in range(15)}
    children = {1: [10, 11, 12, 13, 14]}
    children.update({10 + j: [100 + 3 * j + i for i in range(3)] for j in range(5)})
    nodes, order = bench.nary_to_binary(1, children, leaves, lo, hi)
    # 15 leaves, and k - 1 binary nodes for each inner node of k children: 4 + 5 * 2
    assert len(nodes) == 15 + 4 + 10
    assert sorted(order.tolist()) == list(range(n))
    is_leaf = nodes["b"] < 0
    assert is_leaf.sum() == 15
    for leaf in np.flatnonzero(is_leaf):   # a leaf's slots hold its own triangles
        first, count = nodes["a"][leaf], -nodes["b"][leaf]
        prims = order[first:first + count]
        assert any(sorted(prims.tolist()) == sorted(p) for p in leaves.values())
        assert np.array_equal(nodes["lower"][leaf], lo[prims].min(axis=0))
    root = nodes[0]
    assert np.array_equal(root["lower"], lo.min(axis=0))
    assert np.array_equal(root["upper"], hi.max(axis=0))
    _traced_like_the_default(v, f, nodes, order)


def test_embree_tree_of_the_teapot_answers_as_ours():
    try:
        lib = bench.embree_library()
    except (ImportError, OSError) as exc:
        pytest.skip(f"embreex is not installed ({exc})")
    v, f = shipped_mesh("teapot.obj")
    lo, hi = triangle_boxes_numpy(v, f.astype(np.uint32))
    nodes, order = bench.embree_tree(lib, lo, hi, **bench.EMBREE_BUILD)
    assert sorted(order.tolist()) == list(range(len(f)))
    leaf_sizes = -nodes["b"][nodes["b"] < 0]
    assert leaf_sizes.max() <= bench.EMBREE_BUILD["max_leaf"]
    _traced_like_the_default(v, f, nodes, order)
