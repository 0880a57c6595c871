"""The SAH reference with ray-sampled probabilities (``SAHOptions(rays=...)``,
lbvh/builders/ray_sampled.py) against a plain recursive Python twin (the same tree,
node for node), and through ``lbvh.build``: valid trees, the same hits."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import random_soup, shipped_mesh
from lbvh.builders.bounds import triangle_boxes_numpy
from lbvh.builders.ray_sampled import TMAX_SLACK, RaySample
from lbvh.builders.options import SAHOptions
from lbvh.builders.sah import sah_tree
from lbvh.camera import frame_bounds


def _enters(o, inv, tmax, lo, hi):
    """float32 slab test of rays ``(R, 3)`` against one box, written for the twin."""
    with np.errstate(invalid="ignore", over="ignore"):
        a = (lo[None, :] - o) * inv
        b = (hi[None, :] - o) * inv
    near = np.full(len(o), -np.inf, np.float32)
    far = np.full(len(o), np.inf, np.float32)
    for axis in range(3):   # nan (0 * inf) takes no part, as fmin / fmax do
        lo_t, hi_t = np.fmin(a[:, axis], b[:, axis]), np.fmax(a[:, axis], b[:, axis])
        near = np.fmax(near, lo_t)
        far = np.fmin(far, hi_t)
    return (near <= far) & (far >= 0) & (near <= tmax)


def _area(lo, hi):
    d = hi.astype(np.float64) - lo.astype(np.float64)
    return 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])


def twin(lo, hi, sample, prior, candidates, max_leaf, c_node=1.0, c_tri=1.0):
    """One node at a time: the module docstring's rule. Returns the set of every node's
    primitives (as frozensets) and the set of the leaves' (which fix a binary tree)."""
    o = sample.origins
    with np.errstate(divide="ignore", over="ignore"):
        inv = (np.float32(1) / sample.directions).astype(np.float32)
    tmax = (sample.tmax * np.float32(1 + TMAX_SLACK)).astype(np.float32)
    centre = lo * np.float32(0.5) + hi * np.float32(0.5)
    nodes, leaves = set(), set()

    def node(prims, rays):
        n = len(prims)
        box_lo, box_hi = lo[prims].min(axis=0), hi[prims].max(axis=0)
        nodes.add(frozenset(prims))
        if n == 1:
            leaves.add(frozenset(prims))
            return
        rays = rays[_enters(o[rays], inv[rays], tmax[rays], box_lo, box_hi)]
        r, a_n = len(rays), _area(box_lo, box_hi)
        step = max(1, -(-n // -(-candidates // 2)))
        best = None
        for axis in range(3):
            order = sorted(prims, key=lambda p: (float(centre[p, axis]), p))

            def area_cost(k):
                return (_area(lo[order[:k]].min(axis=0), hi[order[:k]].max(axis=0)) * k
                        + _area(lo[order[k:]].min(axis=0), hi[order[k:]].max(axis=0)) * (n - k))
            cheapest = sorted(range(1, n), key=lambda k: (area_cost(k), k))[:candidates // 2]
            for k in range(1, n):
                if r and k % step and k not in cheapest:
                    continue
                sides = []
                for part in (order[:k], order[k:]):
                    plo, phi = lo[part].min(axis=0), hi[part].max(axis=0)
                    area = _area(plo, phi)
                    if r:
                        h = int(_enters(o[rays], inv[rays], tmax[rays], plo, phi).sum())
                        ratio = area / a_n if a_n > 0 else 0.0
                        area = a_n * (h + prior * ratio) / (r + prior)
                    sides.append(area * len(part))
                key = (sides[0] + sides[1], abs(2 * k - n), axis, k)
                if best is None or key < best[0]:
                    best = (key, order[:k], order[k:])
        split_cost = c_node * a_n + c_tri * best[0][0]
        if n <= max_leaf and split_cost >= c_tri * n * a_n:
            leaves.add(frozenset(prims))
            return
        node(best[1], rays)
        node(best[2], rays)

    node(list(range(len(lo))), np.arange(len(o)))
    return nodes, leaves


def _sets(nodes, prim_order):
    """The builder's tree as the twin's two sets."""
    every, leaves = set(), set()

    def prims(i):
        if nodes["b"][i] < 0:
            first, count = nodes["a"][i], -nodes["b"][i]
            out = frozenset(prim_order[first:first + count].tolist())
            leaves.add(out)
        else:
            out = prims(nodes["a"][i]) | prims(nodes["b"][i])
        every.add(out)
        return out

    prims(0)
    return every, leaves


def _case(seed):
    """Random boxes (some on a coarse grid, so that ties happen) and rays aimed into
    them, some ending early (tmax), some axis-parallel (zero direction components)."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 70))
    if seed % 3 == 0:
        lo = rng.integers(0, 4, (n, 3)).astype(np.float32)
        hi = lo + rng.integers(0, 2, (n, 3)).astype(np.float32)
    else:
        lo = rng.random((n, 3), dtype=np.float32)
        hi = lo + rng.random((n, 3), dtype=np.float32) * np.float32(0.2)
    num_rays = int(rng.integers(1, 200))
    o = (rng.normal(size=(num_rays, 3)) * 3).astype(np.float32)
    d = (rng.random((num_rays, 3)) * (hi.max(0) - lo.min(0)) + lo.min(0) - o).astype(np.float32)
    d[rng.random(num_rays) < 0.2, int(rng.integers(0, 3))] = 0
    d[~(d != 0).any(axis=1)] = 1
    t = np.where(rng.random(num_rays) < 0.5, rng.random(num_rays) * 1.5, np.inf).astype(np.float32)
    return lo, hi, RaySample(o, d, t), rng


@pytest.mark.parametrize("seed", range(40))
def test_the_tree_is_the_twins_node_for_node(seed):
    lo, hi, sample, rng = _case(seed)
    prior = float(rng.choice([0.5, 4.0, 16.0]))
    candidates = int(rng.choice([2, 3, 8, 32]))
    max_leaf = int(rng.choice([1, 4, 8]))
    nodes, prim_order = sah_tree(lo, hi, SAHOptions(max_leaf_size=max_leaf, rays=sample,
                                                    ray_prior=prior, ray_candidates=candidates))
    assert _sets(nodes, prim_order) == twin(lo, hi, sample, prior, candidates, max_leaf)


def test_where_no_ray_enters_the_tree_is_the_sah_references():
    lo, hi, _, rng = _case(4)
    away = RaySample(np.full((20, 3), 50, np.float32), np.ones((20, 3), np.float32),
                     np.full(20, np.inf, np.float32))
    with_rays = sah_tree(lo, hi, SAHOptions(rays=away))
    plain = sah_tree(lo, hi)
    for a, b in zip(with_rays, plain):
        assert np.array_equal(a, b)


def test_the_rays_change_the_tree():
    # the twin test would pass if the rays were ignored where the SAH and they agree;
    # here they must not agree somewhere: a camera close to one corner of a soup
    v, f = random_soup(3000, seed=2)
    lo, hi = triangle_boxes_numpy(v, f)
    rng = np.random.default_rng(1)
    o = np.tile(lo.min(axis=0) - 0.1, (500, 1)).astype(np.float32)
    d = (rng.random((500, 3)) * 0.3 + 0.05).astype(np.float32)
    sample = RaySample(o, d, np.full(500, 0.5, np.float32))
    assert not np.array_equal(sah_tree(lo, hi, SAHOptions(rays=sample))[1], sah_tree(lo, hi)[1])


def _camera_rays(v, width, height):
    return frame_bounds(v.min(axis=0), v.max(axis=0), width, height).rays()


@pytest.mark.parametrize("scene", ["teapot.obj", "cornell_box_gkit.obj"])
def test_build_traces_the_sample_and_the_tree_gives_the_same_hits(scene):
    v, f = shipped_mesh(scene)
    so, sd = _camera_rays(v, 24, 16)
    bvh = lbvh.build(v, f, builder="sah", rays=(so, sd))
    bvh.validate()
    report = bvh.report()
    assert report.builder == "sah" and "trace ray sample" in report.phase_seconds
    assert report.wall_seconds >= report.phase_seconds["trace ray sample"]
    o, d = _camera_rays(v, 96, 64)
    reference = lbvh.build(v, f, builder="sah")
    got, want = bvh.intersect(o, d), reference.intersect(o, d)
    assert np.array_equal(got.t, want.t)     # the same triangle test, any tree: the same t
    assert np.array_equal(got.mask, want.mask)
    # a sample already traced is not traced again, and gives the same tree
    traced = RaySample(so, sd, lbvh.build(v, f).intersect(so, sd).t)
    again = lbvh.build(v, f, builder="sah", options=lbvh.SAHOptions(rays=traced))
    assert "trace ray sample" not in again.report().phase_seconds
    assert np.array_equal(again.nodes, bvh.nodes) and np.array_equal(again.prim_order,
                                                                     bvh.prim_order)


@pytest.mark.parametrize("rays, match", [
    ((np.zeros((0, 3)), np.zeros((0, 3))), "empty sample"),
    ((np.zeros((2, 3)), np.ones((3, 3))), "directions has 3 rows"),
    ((np.array([[0, 0, 0], [0, np.nan, 0]]), np.ones((2, 3))), r"origins\[1\]"),
    ((np.zeros((2, 3)), np.array([[1, 0, 0], [0, 0, 0]])), r"directions\[1\] is zero"),
    ((np.zeros((2, 3)), np.ones((2, 3)), np.array([1.0, -1.0])), r"tmax\[1\] = -1"),
    ((np.zeros((2, 3)), np.ones((2, 2))), "must be a numeric"),
    ("camera", "expected a RaySample"),
])
def test_bad_samples_are_value_errors(rays, match):
    v, f = random_soup(10)
    with pytest.raises(ValueError, match=match):
        lbvh.build(v, f, builder="sah", rays=rays)


@pytest.mark.parametrize("options, match", [({"ray_prior": 0}, "ray_prior: 0"),
                                            ({"ray_prior": float("inf")}, "ray_prior"),
                                            ({"ray_candidates": 1}, "ray_candidates: 1"),
                                            ({"ray_candidates": 2.5}, "ray_candidates")])
def test_bad_ray_options_are_value_errors(options, match):
    with pytest.raises(ValueError, match=match):
        lbvh.SAHOptions(**options)
