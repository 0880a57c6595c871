"""Treelet restructuring (Karras & Aila 2013): bit-exact against its serial twin, valid
trees, a lower SAH cost, the same hits."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from lbvh.layout import is_leaf
from conftest import random_soup, shared_mesh, shipped_mesh
from lbvh.metrics.quality import sah_cost
from lbvh.builders.refit import refit_numpy
from lbvh.builders.restructure import TREELET_MIN_LEAVES, restructure_python, round_min_leaves


def _huge():
    v, f = random_soup(400, seed=7)
    return v * np.float32(2.0 ** 120), f  # areas overflow float32 without the scaling


def _tiny():
    v, f = random_soup(400, seed=9)
    return v * np.float32(2.0 ** -120), f  # and underflow


def _flat():
    v, f = random_soup(400, seed=8)
    v[:, 2] = -1.5
    return v, f


def _mixed_sizes():
    """Big and small triangles interleaved: Morton splits ignore size, the SAH does not."""
    v, f = random_soup(1500, seed=3)
    big = np.arange(len(f)) % 10 == 0
    centre = v[f].mean(axis=1)
    v[f[big]] = centre[big][:, None, :] + (v[f[big]] - centre[big][:, None, :]) * 40
    return v, f


MESHES = {
    "teapot": lambda: shipped_mesh("teapot.obj"),
    "cornell": lambda: shipped_mesh("cornell_box_gkit.obj"),
    "soup": lambda: random_soup(2000, seed=2),
    "mixed": _mixed_sizes,
    "huge": _huge,
    "tiny": _tiny,
    "flat": _flat,
    "identical": lambda: (np.eye(3, dtype=np.float32), np.zeros((60, 3), np.uint32) + [0, 1, 2]),
    "point": lambda: (np.zeros((3, 3), np.float32), np.zeros((20, 3), np.uint32)),
    "single": lambda: (np.eye(3, dtype=np.float32), np.array([[0, 1, 2]])),
    "pair": lambda: (np.eye(3, dtype=np.float32), np.array([[0, 1, 2], [2, 1, 0]])),
}


@pytest.mark.parametrize("rounds", [1, 2])
@pytest.mark.parametrize("name", sorted(MESHES))
def test_device_restructure_matches_twin_bit_for_bit(name, rounds):
    v, f = MESHES[name]()
    plain = lbvh.build(v, f)
    better = lbvh.build(v, f, treelet_rounds=rounds)
    better.validate()
    nodes, parent = restructure_python(plain.nodes, plain.tree.read("parent"), plain.root, rounds)
    assert better.nodes.tobytes() == nodes.tobytes()
    assert np.array_equal(better.tree.read("parent"), parent)
    # Leaves, slots and the primitive order stay; the root stays node 0.
    assert better.root == plain.root == 0
    assert np.array_equal(better.prim_order, plain.prim_order)
    leaves = is_leaf(plain.nodes)
    assert np.array_equal(is_leaf(better.nodes), leaves)
    assert better.nodes[leaves].tobytes() == plain.nodes[leaves].tobytes()
    assert better.tree.builder == f"lbvh+treelets{rounds}"
    assert "restructure" in better.report().phase_seconds


@pytest.mark.parametrize("name", ["teapot", "soup", "mixed", "huge", "tiny", "flat"])
def test_restructure_never_raises_the_sah_cost(name):
    v, f = MESHES[name]()
    costs = [sah_cost(lbvh.build(v, f, treelet_rounds=r)) for r in (0, 1, 2)]
    # Each treelet gets its optimal topology, the old one among the candidates;
    # only the float32 rounding of the sums can make a round look a hair worse.
    assert costs[1] <= costs[0] * (1 + 1e-5)
    assert costs[2] <= costs[1] * (1 + 1e-5)


def test_restructure_lowers_the_sah_cost_where_morton_splits_are_poor():
    v, f = _mixed_sizes()
    before, after = (sah_cost(lbvh.build(v, f, treelet_rounds=r)) for r in (0, 1))
    assert after < 0.9 * before


def test_restructured_shared_scene_is_closer_to_the_sah_reference():
    v, f = shared_mesh("stanford-bunny.obj")
    reference = sah_cost(lbvh.build(v, f, builder="sah"))
    plain = sah_cost(lbvh.build(v, f))
    better = lbvh.build(v, f, treelet_rounds=2)
    better.validate()
    # Measured: 1.22x the reference's cost before, 1.09x after two rounds.
    assert sah_cost(better) / reference < 0.95 * plain / reference


def test_same_closest_hits_as_the_karras_tree():
    v, f = _mixed_sizes()
    plain = lbvh.build(v, f)
    better = lbvh.build(v, f, treelet_rounds=2)
    rng = np.random.default_rng(5)
    origins = rng.uniform(-0.2, 1.2, (4000, 3)).astype(np.float32)
    directions = rng.normal(size=(4000, 3)).astype(np.float32)
    a = plain.intersect(origins, directions)
    b = better.intersect(origins, directions)
    # Each triangle test gives the same t whatever the order of the visits, so
    # the closest t is the same float; the primitive may differ only on a tie.
    assert np.array_equal(a.t, b.t)
    assert (a.prim >= 0).sum() > 500
    same_prim = a.prim == b.prim
    assert same_prim.mean() > 0.99
    assert np.array_equal(plain.occluded(origins, directions), better.occluded(origins, directions))


def test_refit_of_a_restructured_tree_matches_numpy():
    v, f = random_soup(1200, seed=4)
    bvh = lbvh.build(v, f, treelet_rounds=1)
    moved = v + np.float32(0.25) * np.sin(v * 7).astype(np.float32)
    bvh.refit(moved)
    bvh.validate()
    lower, upper = refit_numpy(bvh.nodes, bvh.tree.read("parent"), bvh.root, bvh.prim_order, moved, f)
    assert np.array_equal(bvh.nodes["lower"], lower) and np.array_equal(bvh.nodes["upper"], upper)


def test_collapse_after_restructure_gives_a_valid_tree():
    v, f = random_soup(1500, seed=6)
    bvh = lbvh.build(v, f, treelet_rounds=1, collapse=True)
    bvh.validate()
    assert bvh.tree.builder == "lbvh+treelets1+collapse"


@pytest.mark.parametrize("bad", [-1, 1.5, "2", True, None])
def test_bad_round_counts_are_refused(bad):
    v, f = random_soup(10)
    with pytest.raises(ValueError, match="treelet_rounds"):
        lbvh.build(v, f, treelet_rounds=bad)


def test_restructure_is_for_the_device_builder_only():
    v, f = random_soup(10)
    with pytest.raises(ValueError, match="treelet_rounds: only for builder='lbvh'"):
        lbvh.build(v, f, builder="sah", treelet_rounds=1)


@pytest.mark.parametrize("leaves", [3, 5])
@pytest.mark.parametrize("name", ["teapot", "mixed", "huge", "identical", "pair"])
def test_smaller_treelets_match_the_twin_bit_for_bit(name, leaves):
    v, f = MESHES[name]()
    plain = lbvh.build(v, f)
    better = lbvh.build(v, f, treelet_rounds=2, treelet_leaves=leaves)
    better.validate()
    nodes, parent = restructure_python(plain.nodes, plain.tree.read("parent"), plain.root, 2, leaves=leaves)
    assert better.nodes.tobytes() == nodes.tobytes()
    assert np.array_equal(better.tree.read("parent"), parent)
    assert np.array_equal(better.prim_order, plain.prim_order)
    assert better.tree.builder == f"lbvh+treelets2-{leaves}"


def test_treelet_size_trades_cost_for_build_work():
    """Larger treelets search more topologies per round: on a mesh where Morton
    splits are poor, each size lowers the cost, 7 leaves at least as far as 5
    and 5 at least as far as 3 (up to float32 rounding)."""
    v, f = _mixed_sizes()
    plain = sah_cost(lbvh.build(v, f))
    costs = {k: sah_cost(lbvh.build(v, f, treelet_rounds=1, treelet_leaves=k)) for k in (3, 5, 7)}
    assert costs[3] < 0.97 * plain
    assert costs[5] <= costs[3] * (1 + 1e-5)
    assert costs[7] <= costs[5] * (1 + 1e-5)
    assert lbvh.LBVHOptions().treelet_leaves == 7   # the documented default


@pytest.mark.parametrize("bad", [2, 8, 0, 5.0, "5", True, None])
def test_bad_treelet_sizes_are_refused(bad):
    v, f = random_soup(10)
    with pytest.raises(ValueError, match="treelet_leaves"):
        lbvh.build(v, f, treelet_rounds=1, treelet_leaves=bad)


@pytest.mark.parametrize("min_leaves", [0, 3, 14, 1 << 30])
@pytest.mark.parametrize("name", ["teapot", "soup", "mixed", "huge", "identical"])
def test_later_rounds_over_large_subtrees_match_the_twin_bit_for_bit(name, min_leaves):
    v, f = MESHES[name]()
    plain = lbvh.build(v, f)
    better = lbvh.build(v, f, treelet_rounds=3, treelet_leaves=5, treelet_min_leaves=min_leaves)
    better.validate()
    nodes, parent = restructure_python(plain.nodes, plain.tree.read("parent"), plain.root, 3, leaves=5,
                                       min_leaves=min_leaves)
    assert better.nodes.tobytes() == nodes.tobytes()
    assert np.array_equal(better.tree.read("parent"), parent)


def test_round_min_leaves_doubles_after_the_first_round():
    assert [round_min_leaves(r, 14) for r in range(4)] == [0, 14, 28, 56]
    assert [round_min_leaves(r, 0) for r in range(3)] == [0, 0, 0]
    assert round_min_leaves(40, 14) == 1 << 30          # no overflow of the kernel's int
    assert lbvh.LBVHOptions().treelet_min_leaves == TREELET_MIN_LEAVES == 14


def test_a_later_round_over_no_subtree_changes_nothing():
    """With every subtree below the threshold, rounds after the first only recompute
    costs: the tree is the one-round tree, bit for bit."""
    v, f = _mixed_sizes()
    one = lbvh.build(v, f, treelet_rounds=1)
    three = lbvh.build(v, f, treelet_rounds=3, treelet_min_leaves=1 << 30)
    assert three.nodes.tobytes() == one.nodes.tobytes()
    assert np.array_equal(three.tree.read("parent"), one.tree.read("parent"))


def test_later_rounds_over_large_subtrees_keep_most_of_the_gain():
    """Skipping the small subtrees after the first round changes the cost little:
    the later rounds' gain is in the upper levels."""
    v, f = _mixed_sizes()
    one = sah_cost(lbvh.build(v, f, treelet_rounds=1))
    every = sah_cost(lbvh.build(v, f, treelet_rounds=3, treelet_min_leaves=0))
    large = sah_cost(lbvh.build(v, f, treelet_rounds=3))
    assert every < one and large < one
    assert large <= every + 0.25 * (one - every)


@pytest.mark.parametrize("bad", [-1, 1.5, True, "14", 1 << 31])
def test_bad_min_leaves_is_refused_by_name(bad):
    v, f = random_soup(10)
    with pytest.raises(ValueError, match="treelet_min_leaves"):
        lbvh.build(v, f, treelet_rounds=2, treelet_min_leaves=bad)
