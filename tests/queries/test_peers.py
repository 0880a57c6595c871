"""The point and box queries against the peers that CI has: trimesh's proximity queries
(closest points, signed distance) and rtree's box index. The speed comparison with
Open3D and warp is the bench's (bench/bench_queries.py); here the answers."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import lbvh
from conftest import shared_mesh, shipped_mesh
from lbvh.builders.bounds import triangle_boxes_numpy
from lbvh.metrics.error_bound import closest_distance_bound

rtree = pytest.importorskip("rtree")   # trimesh's contains uses it too


def points_around(v: np.ndarray, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    return (lo + (hi - lo) * rng.uniform(-0.2, 1.2, (n, 3))).astype(np.float32)


def trimesh_nearest(v: np.ndarray, f: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """trimesh's own point-triangle closest points (``trimesh.triangles.closest_point``) over
    every triangle: the nearest point and its distance for each of ``p``."""
    tri = v.astype(np.float64)[f]
    best = np.full(len(p), np.inf)
    where = np.zeros((len(p), 3))
    per = max(1, (1 << 21) // len(tri))
    for s in range(0, len(p), per):
        q = p[s:s + per].astype(np.float64)
        near = trimesh.triangles.closest_point(np.tile(tri, (len(q), 1, 1)), np.repeat(q, len(tri), 0))
        dist = np.linalg.norm(near - np.repeat(q, len(tri), 0), axis=1).reshape(len(q), len(tri))
        k = dist.argmin(axis=1)
        best[s:s + per] = dist[np.arange(len(q)), k]
        where[s:s + per] = near.reshape(len(q), len(tri), 3)[np.arange(len(q)), k]
    return where, best


@pytest.mark.parametrize("name", ["teapot", "bunny"])
def test_closest_points_agree_with_trimesh(name):
    v, f = shipped_mesh("teapot.obj") if name == "teapot" else shared_mesh("stanford-bunny.obj")
    p = points_around(v, 60 if name == "bunny" else 300, 1)
    got = lbvh.build(v, f).closest_points(p)
    where, distance = trimesh_nearest(v, f, p)
    assert (np.abs(got.distance - distance) <= closest_distance_bound(v, p) + 1e-12).all()
    assert np.abs(got.points - where).max() <= 1e-4 * np.abs(v).max()


def test_signed_distance_against_trimesh_s_distance_and_contains():
    """trimesh's signed_distance needs scipy; its parts need only rtree: the distance
    (its point-triangle test) and the sign (its contains, by rays), positive inside there
    and negative here (Open3D's and warp's sign)."""
    ico = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.float32(ico.vertices), np.uint32(ico.faces)
    mesh = trimesh.Trimesh(v.astype(np.float64), f, process=False)
    p = points_around(v, 300, 2)
    got = lbvh.build(v, f).signed_distance(p)
    _, distance = trimesh_nearest(v, f, p)
    assert np.allclose(np.abs(got), distance, rtol=1e-5, atol=1e-6)
    clear = distance > 1e-4
    assert np.array_equal((got < 0)[clear], mesh.contains(p.astype(np.float64))[clear])


def test_box_queries_agree_with_rtree():
    v, f = shipped_mesh("teapot.obj")
    lo, hi = triangle_boxes_numpy(v, f)
    props = rtree.index.Property()
    props.dimension = 3
    index = rtree.index.Index(((i, (*lo[i], *hi[i]), None) for i in range(len(f))),
                              properties=props)
    rng = np.random.default_rng(3)
    centre = points_around(v, 200, 4)
    half = (rng.uniform(0, 0.3, (200, 3)) * np.ptp(v, axis=0)).astype(np.float32)
    qlo, qhi = centre - half, centre + half
    got = lbvh.build(v, f).overlapping(qlo, qhi)
    for i in range(len(qlo)):
        want = np.sort(np.fromiter(index.intersection((*qlo[i], *qhi[i])), np.int64))
        assert np.array_equal(got.of(i), want), i
    assert got.counts.sum() > 0
