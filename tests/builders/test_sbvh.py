"""Spatial splits (lbvh/builders/sbvh.py): the clipping against a dense sampling of the
triangle, the tree's invariants (a triangle in several leaves, each part in a leaf's box),
and every query answering each hit once, as the oracle and the other trees do."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from lbvh.layout import is_leaf, prim_range_of
from conftest import shipped_mesh
from lbvh.builders.sbvh import clip_to_slab
from lbvh.queries.closest import closest_points_numpy
from lbvh.verification.oracle import all_hits_brute, brute_force
from lbvh.metrics.quality import sah_cost
from lbvh.metrics.validate import BVHValidationError


def long_triangles(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A few long slanted triangles across a field of small ones: the case spatial splits
    are for (long triangles make object splits overlap)."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 10, (3000, 1, 3)) + rng.normal(0, 0.05, (3000, 3, 3))
    a = rng.uniform(0, 10, (40, 3))
    b = rng.uniform(0, 10, (40, 3))
    long = np.stack([a, b, a + rng.normal(0, 0.2, (40, 3))], axis=1)
    tri = np.concatenate([small, long]).astype(np.float32)
    return tri.reshape(-1, 3), np.arange(3 * len(tri), dtype=np.uint32).reshape(-1, 3)


def test_clipping_holds_every_point_of_the_part_and_little_more():
    rng = np.random.default_rng(1)
    tri = rng.normal(size=(400, 3, 3))
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    for axis in range(3):
        a = rng.uniform(lo[:, axis], hi[:, axis])
        b = np.minimum(a + rng.uniform(0, 1, 400), hi[:, axis])
        clo, chi, ok = clip_to_slab(tri, lo, hi, axis, a, b)
        w = rng.dirichlet([1, 1, 1], (400, 2000))                   # points on each triangle
        points = np.einsum("tsk,tkj->tsj", w, tri)
        inside = (points[:, :, axis] >= a[:, None]) & (points[:, :, axis] <= b[:, None])
        held = ((points >= clo[:, None]) & (points <= chi[:, None])).all(axis=2)
        assert (held | ~inside).all()                               # never loses a point
        # and is the part's box: the sampled part spans nearly all of it
        for t in np.flatnonzero(ok & (inside.sum(axis=1) > 200))[:50]:
            part = points[t, inside[t]]
            assert (part.min(axis=0) - clo[t] <= 0.2 * (chi[t] - clo[t]) + 1e-9).all()
            assert (chi[t] - part.max(axis=0) <= 0.2 * (chi[t] - clo[t]) + 1e-9).all()


def test_spatial_splits_lower_the_cost_and_keep_the_invariants():
    v, f = long_triangles()
    sbvh = lbvh.build(v, f, builder="sbvh")
    sah = lbvh.build(v, f, builder="sah")
    sbvh.validate()
    assert sbvh.tree.clipped_leaves and sbvh.mesh.num_prims == len(f)
    assert sbvh.tree.num_prims > len(f)                          # some triangles split
    assert np.array_equal(np.unique(sbvh.prim_order), np.arange(len(f)))
    assert sah_cost(sbvh) < sah_cost(sah)
    # without spatial splits (alpha 1: never tried) it is the SAH's tree in cost
    plain = lbvh.build(v, f, builder="sbvh", alpha=1.0)
    assert plain.tree.num_prims == len(f)
    assert sah_cost(plain) == pytest.approx(sah_cost(sah), rel=0.02)


def rays_at(v: np.ndarray, f: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    o = lo + (hi - lo) * rng.uniform(-0.2, 1.2, (n, 3))
    return o.astype(np.float32), (v[f[rng.integers(0, len(f), n)]].mean(1) - o).astype(np.float32)


@pytest.mark.parametrize("scene", ["long", "teapot"])
def test_every_query_answers_each_hit_once(scene):
    v, f = long_triangles() if scene == "long" else shipped_mesh("teapot.obj")
    sbvh, lb = lbvh.build(v, f, builder="sbvh"), lbvh.build(v, f)
    o, d = rays_at(v, f, 2000, 2)
    ref = brute_force(v, f, o, d)
    for order in ("ordered", "global"):
        got = sbvh.intersect(o, d, order=order)
        assert got.overflow_count == 0
        assert np.array_equal(got.t, lb.intersect(o, d).t)     # tree-independent answers
        assert np.array_equal(got.mask, ref.hit)
    assert np.array_equal(sbvh.occluded(o, d), ref.hit)
    # all hits and their counts: the twin's, each triangle once though it sits in two leaves
    twin = all_hits_brute(v, f, o, d, dtype=np.float32)
    every = sbvh.all_hits(o, d)
    assert np.array_equal(every.offsets, twin.offsets) and np.array_equal(every.prim, twin.prim)
    assert np.array_equal(every.t, twin.t)
    assert np.array_equal(sbvh.count_hits(o, d), twin.total)
    near = sbvh.all_hits(o, d, max_hits=1)
    assert np.array_equal(near.total, twin.total) and np.array_equal(near.counts,
                                                                      np.minimum(twin.total, 1))
    # closest points: a split triangle is still one triangle
    c = sbvh.closest_points(o[:300])
    assert np.allclose(c.distance, closest_points_numpy(v, f, o[:300])[0], rtol=1e-5, atol=1e-6)


def test_what_an_sbvh_refuses_and_how_it_travels(tmp_path):
    v, f = long_triangles(3)
    sbvh = lbvh.build(v, f, builder="sbvh")
    for call, name in ((lambda: sbvh.overlapping(v[:2], v[:2] + 1), "overlapping"),
                       (lambda: sbvh.contains(v[:2]), "winding_numbers"),
                       (lambda: sbvh.refit(v), "refit")):
        with pytest.raises(ValueError, match=f"{name}: this tree has spatial splits"):
            call()
    # saved and loaded (validated as a tree of spatial splits), the same answers
    sbvh.save(tmp_path / "t.npz")
    again = lbvh.load(tmp_path / "t.npz")
    o, d = rays_at(v, f, 500, 4)
    assert again.tree.clipped_leaves and np.array_equal(again.intersect(o, d).t, sbvh.intersect(o, d).t)
    # in a scene of instances too: the answers of the same scene over an LBVH of the mesh
    moves = np.stack([np.eye(3, 4), np.eye(3, 4) * 0.5])
    scene = lbvh.Scene([sbvh], [0, 0], moves)
    fv, ff, _ = scene.flattened()
    so, sd = rays_at(fv, ff, 500, 5)
    want = lbvh.Scene([lbvh.build(v, f)], [0, 0], moves).intersect(so, sd)
    got = scene.intersect(so, sd)
    assert np.array_equal(got.t, want.t) and np.array_equal(got.instance, want.instance)


def test_the_validator_finds_a_part_outside_its_leaves():
    v, f = long_triangles(4)
    sbvh = lbvh.build(v, f, builder="sbvh")
    nodes = sbvh.nodes.copy()
    split = np.bincount(sbvh.prim_order) > 1
    tri = int(np.flatnonzero(split)[0])
    # shrink every leaf holding that triangle to the point of its lower corner: the boxes
    # still nest, only the rules of clipped leaves can see it
    slot = np.flatnonzero(sbvh.prim_order == tri)
    first, count = prim_range_of(sbvh.nodes)[:, 0], prim_range_of(sbvh.nodes)[:, 1]
    leaves = [i for i in np.flatnonzero(is_leaf(sbvh.nodes))
              if ((slot >= first[i]) & (slot < first[i] + count[i])).any()]
    for i in leaves:
        nodes["upper"][i] = nodes["lower"][i]
    with pytest.raises(BVHValidationError, match="lie|point|meet"):
        lbvh.BVH.from_arrays(nodes, sbvh.prim_order, sbvh.root, v, f, builder="sbvh")
