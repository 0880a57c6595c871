"""Device leaf collapse: exact agreement with its numpy twin, valid trees, never a worse SAH cost."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from lbvh.layout import is_leaf, prim_range_of
from conftest import random_soup, shared_mesh, shipped_mesh
from lbvh.api import collapse_leaves
from lbvh.builders.collapse import collapse_decisions, collapse_numpy
from lbvh.builders.options import CollapseOptions
from lbvh.metrics.quality import sah_cost
from lbvh.builders.refit import refit_numpy

# Costs are float32 on the device; with correctly rounded division (PoCL has it)
# the twin reproduces them bit for bit, so every decision is compared exactly.


def _check_against_twin(bvh: lbvh.BVH, **options) -> lbvh.BVH:
    collapsed = collapse_leaves(bvh, **options)
    collapsed.validate()
    twin = collapse_numpy(bvh.nodes, bvh.tree.read("parent"), bvh.root, **options)
    decided = collapse_decisions(bvh.tree, CollapseOptions(**options))
    for key in ("first", "end", "count"):
        assert np.array_equal(decided[key], getattr(twin, key)), key
    assert np.array_equal(decided["cost"].view(np.int32), twin.cost.view(np.int32))
    assert np.array_equal(decided["becomes_leaf"], twin.becomes_leaf)
    assert collapsed.nodes.tobytes() == twin.nodes.tobytes()
    assert np.array_equal(collapsed.tree.read("parent"), twin.parent)
    assert np.array_equal(collapsed.tree.leaf_nodes, twin.leaf_nodes)
    assert collapsed.root == twin.root == 0
    assert np.array_equal(collapsed.prim_order, bvh.prim_order)
    return collapsed


def _huge():
    v, f = random_soup(300, seed=7)
    return v * np.float32(2.0 ** 120), f  # areas overflow float32 without the scaling


def _flat():
    v, f = random_soup(300, seed=8)
    v[:, 1] = 3.0
    return v, f


@pytest.mark.parametrize("name,mesh", [
    ("teapot", lambda: shipped_mesh("teapot.obj")),
    ("suzanne", lambda: shipped_mesh("suzanne.obj")),
    ("cornell", lambda: shipped_mesh("cornell_box_gkit.obj")),
    ("soup", lambda: random_soup(3000, seed=2)),
    ("huge", _huge),
    ("flat", _flat),
    ("identical", lambda: (np.eye(3, dtype=np.float32), np.zeros((50, 3), np.uint32) + [0, 1, 2])),
    ("point", lambda: (np.zeros((3, 3), np.float32), np.zeros((20, 3), np.uint32))),
    ("single", lambda: (np.eye(3, dtype=np.float32), np.array([[0, 1, 2]]))),
])
def test_collapse_of_lbvh_matches_twin_and_never_costs_more(name, mesh):
    v, f = mesh()
    bvh = lbvh.build(v, f)
    before = bvh.nodes.copy()
    collapsed = _check_against_twin(bvh)
    assert bvh.nodes.tobytes() == before.tobytes()  # the input tree is left alone
    assert sah_cost(collapsed) <= sah_cost(bvh) * (1 + 1e-6)
    assert prim_range_of(collapsed.nodes)[is_leaf(collapsed.nodes), 1].max() <= 8
    rep = collapsed.report()
    assert rep.builder == "lbvh+collapse" and "collapse" in rep.phase_seconds
    assert rep.num_leaves == len(collapsed.tree.leaf_nodes)


def test_collapse_of_a_sah_tree_uses_its_leaf_list():
    v, f = shipped_mesh("teapot.obj")
    sah = lbvh.build(v, f, builder="sah", max_leaf_size=2, c_node=0.0)
    collapsed = _check_against_twin(sah, max_leaf_size=6)
    assert sah_cost(collapsed) <= sah_cost(sah) * (1 + 1e-6)


def test_constants_steer_the_collapse():
    v, f = shipped_mesh("cornell_box_gkit.obj")
    bvh = lbvh.build(v, f)
    # max_leaf_size 1: nothing can merge, the tree is unchanged
    same = _check_against_twin(bvh, max_leaf_size=1)
    assert same.nodes.tobytes() == bvh.nodes.tobytes()
    # node visits far dearer than triangle tests: the whole scene becomes one leaf
    one = _check_against_twin(bvh, c_node=100.0, max_leaf_size=len(f))
    assert one.tree.num_nodes == 1 and prim_range_of(one.nodes)[0].tolist() == [0, len(f)]
    # cheaper node visits make merging pay less often
    free = _check_against_twin(bvh, c_node=0.0)
    assert free.tree.num_nodes >= collapse_leaves(bvh).tree.num_nodes > one.tree.num_nodes


@pytest.mark.parametrize("scene", ["stanford-bunny.obj"])
def test_collapse_on_a_shared_scene(scene):
    v, f = shared_mesh(scene)
    bvh = lbvh.build(v, f)
    collapsed = _check_against_twin(bvh)
    assert sah_cost(collapsed) < sah_cost(bvh)
    assert len(collapsed.tree.leaf_nodes) < len(f)


def test_refit_of_a_collapsed_tree():
    v, f = shipped_mesh("suzanne.obj")
    collapsed = collapse_leaves(lbvh.build(v, f))
    rng = np.random.default_rng(4)
    moved = (v * np.float32(1.5) + rng.normal(0, 0.05, v.shape)).astype(np.float32)
    collapsed.refit(moved)
    collapsed.validate()
    lower, upper = refit_numpy(collapsed.nodes, collapsed.tree.read("parent"), collapsed.root,
                               collapsed.prim_order, moved, f)
    assert np.array_equal(collapsed.nodes["lower"], lower) and np.array_equal(collapsed.nodes["upper"], upper)


@pytest.mark.parametrize("options", [{"c_node": -1.0}, {"c_tri": 0.0}, {"max_leaf_size": 0},
                                     {"key_bits": 30}])
def test_bad_options_are_value_errors(options):
    bvh = lbvh.build(*random_soup(10))
    with pytest.raises(ValueError, match=next(iter(options))):
        collapse_leaves(bvh, **options)
