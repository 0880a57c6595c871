"""bench/bench_ploc.py: the PLOC tree of the tree study is a valid tree that answers
as the default tree does, and each step merges exactly the mutual nearest pairs."""
from __future__ import annotations

import numpy as np

import lbvh
from conftest import load_bench, shipped_mesh
from lbvh.layout import children_of, is_leaf

bench = load_bench("bench_ploc")


def test_ploc_tree_is_valid_and_answers_as_the_default():
    v, f = shipped_mesh("suzanne.obj")
    for radius in (1, 4, 16):
        bvh, seconds = bench.ploc_bvh(v, f, radius)
        bvh.validate()
        assert seconds >= 0 and bvh.tree.num_nodes == 2 * len(f) - 1
        rng = np.random.default_rng(3)
        lo, hi = v.min(axis=0), v.max(axis=0)
        o = (lo + (hi - lo) * rng.uniform(-0.5, 1.5, (2000, 3))).astype(np.float32)
        d = (v[rng.integers(0, len(v), 2000)] - o).astype(np.float32)
        got, want = bvh.intersect(o, d), lbvh.build(v, f).intersect(o, d)
        assert np.array_equal(got.t.view(np.int32), want.t.view(np.int32))
        assert np.array_equal(got.prim, want.prim) and (want.prim >= 0).sum() > 500


def test_first_step_merges_the_mutual_nearest_pairs():
    """Four boxes on a line, 0 1 . . 2 3 (gaps): with radius 3 the nearest of 0 is 1
    and of 1 is 0, of 2 is 3 and of 3 is 2: two merges, then the root."""
    lo = np.float32([[0, 0, 0], [1, 0, 0], [10, 0, 0], [11, 0, 0]])
    hi = lo + np.float32(0.5)
    nodes, order, root = bench.ploc_tree(lo, hi, np.arange(4), radius=3)
    assert root == 6 and not is_leaf(nodes)[4:].any() and is_leaf(nodes)[:4].all()
    kids = children_of(nodes)
    assert sorted(map(tuple, kids[4:6].tolist())) == [(0, 1), (2, 3)]
    assert sorted(kids[6].tolist()) == [4, 5]
