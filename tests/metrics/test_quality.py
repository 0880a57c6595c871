"""Quality metrics: SAH cost by hand, tree figures, and the sampled EPO against an exact value."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import shipped_mesh
from lbvh.layout import is_leaf, make_nodes, node_depths
from lbvh.metrics.quality import epo_estimate, memory_bytes, sah_cost, tree_quality


def _hand_made():
    """Root [0,2]x[0,1]x[0,1] (area 10) over a leaf of two triangles with box [0,1]^3
    (area 6) and a leaf of one flat triangle with box [1,2]x[0,1]x[0,0] (area 2)."""
    v = np.array([[0, 0, 0], [1, 1, 0], [0, 1, 1],      # box [0,1]^3
                  [0, 0, 0], [1, 0, 1], [1, 1, 1],      # box [0,1]^3
                  [1, 0, 0], [2, 0, 0], [2, 1, 0]],     # box [1,2]x[0,1]x[0,0]
                 np.float32)
    f = np.arange(9).reshape(3, 3)
    nodes = make_nodes(lower=[[0, 0, 0], [0, 0, 0], [1, 0, 0]],
                       upper=[[2, 1, 1], [1, 1, 1], [2, 1, 0]],
                       children=[[1, 2], [-1, -1], [-1, -1]],
                       prim_range=[[0, 0], [0, 2], [2, 1]])
    return lbvh.BVH.from_arrays(nodes, np.arange(3), 0, v, f, builder="hand")


def test_sah_cost_of_a_hand_made_tree():
    bvh = _hand_made()
    bvh.validate()
    # (C_node * 10 + C_tri * 2 * 6 + C_tri * 1 * 2) / 10
    assert sah_cost(bvh) == pytest.approx((10 + 12 + 2) / 10, rel=1e-15)
    assert sah_cost(bvh, c_node=2.0, c_tri=0.5) == pytest.approx((20 + 6 + 1) / 10, rel=1e-15)
    # the node array alone gives the same figure
    assert sah_cost(bvh.nodes) == sah_cost(bvh)


def test_single_leaf_and_zero_area_trees():
    v, f = shipped_mesh("cornell_box_gkit.obj")
    lo, hi = v[f].min(axis=(0, 1)), v[f].max(axis=(0, 1))
    one_leaf = make_nodes([lo], [hi], [[-1, -1]], [[0, len(f)]])
    assert sah_cost(one_leaf, c_tri=2.0) == 2.0 * len(f)
    # every triangle at one point: no area anywhere, each ratio is taken as 1
    point = lbvh.build(np.zeros((3, 3), np.float32), np.zeros((5, 3), np.uint32), builder="sah",
                       max_leaf_size=2)
    internal = int((~is_leaf(point.nodes)).sum())
    assert sah_cost(point) == internal + 5


def test_tree_quality_figures():
    v, f = shipped_mesh("teapot.obj")
    bvh = lbvh.build(v, f, builder="sah")
    q = tree_quality(bvh, epo_samples=4096)
    assert q["sah_cost"] == sah_cost(bvh) and q["c_node"] == 1.0 and q["c_tri"] == 1.0
    assert q["num_nodes"] == bvh.tree.num_nodes == 2 * q["num_leaves"] - 1
    assert sum(k * c for k, c in q["leaf_size_histogram"].items()) == len(f)
    assert q["depth"] == int(node_depths(bvh.tree.read("parent"), bvh.root).max())
    assert q["memory_bytes"] == memory_bytes(bvh.tree.num_nodes, len(f)) == 36 * bvh.tree.num_nodes + 4 * len(f)
    assert q["epo"] > 0 and 0 < q["epo_stderr"] < 0.1 * q["epo"] and q["epo_samples"] == 4096
    assert "epo" not in tree_quality(bvh, epo=False)


def _two_overlapping_triangles():
    # t0 = (0,0) (1,0) (0,1) and t1 = (.5,0) (1.5,0) (.5,1) in the plane z = 0, one leaf each.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [.5, 0, 0], [1.5, 0, 0], [.5, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    nodes = make_nodes(lower=[[0, 0, 0], [0, 0, 0], [.5, 0, 0]], upper=[[1.5, 1, 0], [1, 1, 0], [1.5, 1, 0]],
                       children=[[1, 2], [-1, -1], [-1, -1]], prim_range=[[0, 0], [0, 1], [1, 1]])
    return lbvh.BVH.from_arrays(nodes, np.arange(2), 0, v, f, builder="hand")


def test_epo_estimate_matches_the_exact_overlap():
    bvh = _two_overlapping_triangles()
    bvh.validate()
    # exact: area(t1 in box t0) = int_.5^1 (1.5 - x) dx = 0.375, area(t0 in box t1) = 0.125,
    # each weighted by C_tri * 1, over the total area 1
    epo, err = epo_estimate(bvh)
    assert 0 < err < 0.01
    assert abs(epo - 0.5) < 5 * err
    epo3, err3 = epo_estimate(bvh, c_tri=3.0)
    assert epo3 == pytest.approx(3 * epo) and err3 == pytest.approx(3 * err)


def test_epo_of_disjoint_leaves_is_zero():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0]], np.float32)
    bvh = lbvh.build(v, np.array([[0, 1, 2], [3, 4, 5]]), builder="sah")
    assert bvh.tree.num_nodes == 3
    assert epo_estimate(bvh) == (0.0, 0.0)


def test_sah_cost_rejects_other_objects():
    with pytest.raises(ValueError, match="NODE_DTYPE"):
        sah_cost(np.zeros((3, 3)))
