"""Box queries (kernels/overlap.cl) against the numpy brute force: exactly the same triangles."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import random_soup, shipped_mesh
from lbvh.queries.overlap import overlapping_numpy


def query_boxes(v: np.ndarray, n: int, seed: int, size: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    centre = lo + (hi - lo) * rng.uniform(-0.1, 1.1, (n, 3))
    half = (hi - lo) * size * rng.uniform(0, 1, (n, 3))
    return (centre - half).astype(np.float32), (centre + half).astype(np.float32)


def same(got, want) -> None:
    assert np.array_equal(got.offsets, want.offsets)
    assert np.array_equal(got.prims, want.prims)
    assert got.overflow_count == 0


@pytest.mark.parametrize("kind", ["lbvh", "lbvh+collapse", "sah", "treelets"])
def test_every_tree_gives_the_brute_force_answer(kind):
    v, f = random_soup(2000, seed=11)
    bvh = {"lbvh": lambda: lbvh.build(v, f), "lbvh+collapse": lambda: lbvh.build(v, f, collapse=True),
           "sah": lambda: lbvh.build(v, f, builder="sah"),
           "treelets": lambda: lbvh.build(v, f, treelet_rounds=2)}[kind]()
    lo, hi = query_boxes(v, 300, 1)
    got = bvh.overlapping(lo, hi)
    same(got, overlapping_numpy(v, f, lo, hi))
    assert got.counts.sum() > 0 and (got.counts == 0).any()   # some boxes hit, some do not
    for i in (0, 7, 299):
        assert np.array_equal(got.of(i), np.sort(got.of(i)))


def test_touching_boxes_and_points_count():
    """Closed boxes: a query box that only touches a triangle's box, or a point on it."""
    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]])
    f = np.uint32([[0, 1, 2], [3, 4, 5]])
    bvh = lbvh.build(v, f)
    lo = np.float32([[1, 0, 0], [1.5, 1.5, 1.5], [-1, -1, -1], [0.5, 0.5, 0]])
    hi = np.float32([[2, 1, 1], [2, 2, 2], [7, 7, 7], [0.5, 0.5, 0]])
    got = bvh.overlapping(lo, hi)
    assert [got.of(i).tolist() for i in range(4)] == [[0], [], [0, 1], [0]]


def test_the_teapot_and_large_boxes():
    v, f = shipped_mesh("teapot.obj")
    bvh = lbvh.build(v, f, collapse=True)
    lo, hi = query_boxes(v, 200, 2, size=0.6)
    same(bvh.overlapping(lo, hi), overlapping_numpy(v, f, lo, hi))


@pytest.mark.parametrize("lower, upper, message", [
    (np.float32([[0, 0, 0], [np.nan, 0, 0]]), np.ones((2, 3)), r"lower: box 1 has a NaN"),
    (np.zeros((2, 3)), np.float64([[1, 1, 1], [1e39, 1, 1]]), r"upper: box 1 .* beyond-float32"),
    (np.zeros((2, 3)), np.float32([[1, 1, 1], [1, -1, 1]]), r"box 1 has lower .* > upper"),
    (np.zeros((2, 2)), np.ones((2, 2)), r"lower: shape \(2, 2\), expected \(N, 3\)"),
    (np.zeros((3, 3)), np.ones((2, 3)), "upper: 2 boxes, but lower has 3"),
])
def test_bad_boxes_are_named(lower, upper, message):
    bvh = lbvh.build(*random_soup(50, seed=12))
    with pytest.raises(ValueError, match=message):
        bvh.overlapping(lower, upper)


def test_no_boxes_no_answers():
    bvh = lbvh.build(*random_soup(50, seed=12))
    got = bvh.overlapping(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(got) == 0 and got.offsets.tolist() == [0] and len(got.prims) == 0
