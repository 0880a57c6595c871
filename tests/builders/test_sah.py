"""The serial SAH reference builder: its split choice against brute force, valid trees everywhere."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from lbvh.layout import is_leaf, prim_range_of
from conftest import random_soup, shipped_mesh
from lbvh.metrics.quality import sah_cost
from lbvh.builders.options import SAHOptions
from lbvh.builders.sah import best_split, sah_tree
from lbvh.builders.bounds import triangle_boxes_numpy as triangle_boxes


def _brute_force_split(lo: np.ndarray, hi: np.ndarray):
    """Try every partition along every axis's centre order; the builder's rule picks among equals.

    Returns ``(axis, num_left, cost_sum)`` minimising ``A(L)|L| + A(R)|R|``,
    ties to the most balanced split, then the lower axis, then the smaller left side.
    """
    n = len(lo)
    centres = lo * np.float32(0.5) + hi * np.float32(0.5)
    best = None
    for axis in range(3):
        order = np.argsort(centres[:, axis], kind="stable")
        for k in range(1, n):
            left, right = order[:k], order[k:]
            s = 0.0
            for part in (left, right):
                d = hi[part].max(axis=0).astype(np.float64) - lo[part].min(axis=0).astype(np.float64)
                s += 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]) * len(part)
            key = (s, abs(2 * k - n), axis, k)
            if best is None or key < best:
                best = key
    return best[2], best[3], best[0]


def _random_boxes(rng: np.random.Generator, n: int, grid: bool):
    if grid:  # coordinates on a coarse grid: equal centres and equal costs happen
        a = rng.integers(0, 3, (n, 3)).astype(np.float32)
        b = a + rng.integers(0, 2, (n, 3)).astype(np.float32)
    else:
        a = rng.random((n, 3), dtype=np.float32)
        b = a + rng.random((n, 3), dtype=np.float32) * np.float32(0.3)
    return a, b


def _subtree_prims(nodes: np.ndarray, prim_order: np.ndarray, node: int) -> set[int]:
    stack, prims = [node], set()
    while stack:
        i = stack.pop()
        if nodes["b"][i] < 0:
            first, count = nodes["a"][i], -nodes["b"][i]
            prims.update(prim_order[first:first + count].tolist())
        else:
            stack += [nodes["a"][i], nodes["b"][i]]
    return prims


@pytest.mark.parametrize("seed", range(48))
def test_root_split_is_the_brute_force_best(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 9))
    lo, hi = _random_boxes(rng, n, grid=seed % 3 == 0)
    axis, k, cost = _brute_force_split(lo, hi)
    decision = best_split(lo, hi)
    assert (decision.axis, decision.num_left, decision.cost_sum) == (axis, k, cost)
    # the builder's root makes the same split (max_leaf_size=1 forces a split)
    nodes, prim_order = sah_tree(lo, hi, SAHOptions(max_leaf_size=1))
    assert _subtree_prims(nodes, prim_order, nodes["a"][0]) == set(decision.left.tolist())


def test_split_costs_primitive_boxes_not_centres():
    # Costing the centres' bounds instead of the primitive boxes is a known SAH
    # bug. On these sets the two rules disagree; the builder must follow the boxes.
    disagree = 0
    for seed in range(100, 160):
        rng = np.random.default_rng(seed)
        lo, hi = _random_boxes(rng, int(rng.integers(3, 9)), grid=False)
        hi = hi + rng.random(hi.shape, dtype=np.float32) * np.float32(2.0)  # large, overlapping boxes
        centres = lo * np.float32(0.5) + hi * np.float32(0.5)
        by_boxes = _brute_force_split(lo, hi)
        if _brute_force_split(centres, centres)[:2] != by_boxes[:2]:
            disagree += 1
            d = best_split(lo, hi)
            assert (d.axis, d.num_left) == by_boxes[:2]
    assert disagree >= 10


@pytest.mark.parametrize("scene", ["teapot.obj", "suzanne.obj", "cornell_box_gkit.obj"])
def test_sah_trees_of_shipped_scenes_are_valid_and_better_than_lbvh(scene):
    v, f = shipped_mesh(scene)
    bvh = lbvh.build(v, f, builder="sah")
    bvh.validate()
    rep = bvh.report()
    assert rep.builder == "sah" and rep.num_triangles == len(f) and rep.wall_seconds > 0
    assert max(rep.leaf_size_histogram) <= 8
    assert sah_cost(bvh) < sah_cost(lbvh.build(v, f))


def _identical(n):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    return v, np.zeros((n, 3), np.uint32) + np.arange(3, dtype=np.uint32)


def _flat(n, seed=1):
    v, f = random_soup(n, seed)
    v[:, 2] = 0
    return v, f


def _on_a_line(n):
    # every triangle degenerate on the x axis: every box has zero area
    x = np.arange(3 * n, dtype=np.float32)
    v = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    return v, np.arange(3 * n, dtype=np.uint32).reshape(n, 3)


@pytest.mark.parametrize("case,mesh", [
    ("single", (np.eye(3, dtype=np.float32), np.array([[0, 1, 2]]))),
    ("two", (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]], np.float32),
             np.array([[0, 1, 2], [3, 4, 5]]))),
    ("identical", _identical(1000)),
    ("flat", _flat(500)),
    ("line", _on_a_line(300)),
    ("point", (np.zeros((3, 3), np.float32), np.zeros((40, 3), np.uint32))),
])
def test_degenerate_scenes_give_valid_shallow_trees(case, mesh):
    v, f = mesh
    bvh = lbvh.build(v, f, builder="sah")
    bvh.validate()
    rep = bvh.report()
    assert max(rep.leaf_size_histogram) <= 8
    if case in ("identical", "line", "point"):
        # equal costs go to balanced splits: no chain of one-primitive peels
        assert rep.depth <= int(np.ceil(np.log2(len(f))))
    assert np.isfinite(sah_cost(bvh))


def test_two_far_triangles_split_two_overlapping_ones_stay_a_leaf():
    far = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [50, 0, 0], [51, 0, 0], [50, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    assert lbvh.build(far, faces, builder="sah").tree.num_nodes == 3
    near = far.copy()
    near[3:] = far[:3] + np.float32(0.01)
    tree = lbvh.build(near, faces, builder="sah")
    assert tree.tree.num_nodes == 1 and prim_range_of(tree.nodes)[0].tolist() == [0, 2]


def test_costs_do_not_overflow_and_scale_exactly():
    # Scaling by a power of two scales every area by its square exactly (float64):
    # the tree must not change, even where float32 areas would overflow.
    v, f = random_soup(400, seed=3)
    small = sah_tree(*triangle_boxes(v, f))
    big_v = v * np.float32(2.0 ** 100)  # coordinates near 1e30: areas near 1e60
    big = sah_tree(*triangle_boxes(big_v, f))
    assert np.array_equal(small[1], big[1])
    assert np.array_equal(small[0]["a"], big[0]["a"]) and np.array_equal(small[0]["b"], big[0]["b"])
    lbvh.build(big_v, f, builder="sah").validate()


@pytest.mark.parametrize("max_leaf", [1, 2, 4, 16])
def test_max_leaf_size_and_constants_are_honoured(max_leaf):
    v, f = random_soup(2000, seed=5)
    tree = lbvh.build(v, f, builder="sah", max_leaf_size=max_leaf)
    tree.validate()
    assert prim_range_of(tree.nodes)[is_leaf(tree.nodes), 1].max() <= max_leaf
    # a free node visit splits everything down to single triangles where it can
    cheap = lbvh.build(v, f, builder="sah", c_node=0.0, max_leaf_size=max_leaf)
    assert cheap.tree.num_nodes >= tree.tree.num_nodes


@pytest.mark.parametrize("options", [{"c_node": -1}, {"c_tri": 0}, {"max_leaf_size": 0},
                                     {"max_leaf_size": 2.5}, {"c_node": float("nan")}, {"bins": 16}])
def test_bad_options_are_value_errors(options):
    v, f = random_soup(10)
    with pytest.raises(ValueError, match=next(iter(options))):
        lbvh.build(v, f, builder="sah", **options)


def test_best_split_needs_two_primitives():
    with pytest.raises(ValueError, match="at least 2"):
        best_split(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
