"""Watertightness: rays through shared edges and vertices of closed surfaces never leak.

The watertight test (Woop, Benthin, Wald 2013, the default) must hit on every
ray below; the Moller-Trumbore leak count is printed (run with -s), not
asserted: it is the price list of the faster test, not a property of it.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh

import lbvh
from lbvh.queries import traverse as tr
from lbvh.verification import meshes


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@functools.lru_cache(maxsize=None)
def icosphere():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v = np.asarray(mesh.vertices, np.float32)
    f = np.asarray(mesh.faces, np.uint32)
    return v, f, lbvh.build(v, f)


@functools.lru_cache(maxsize=None)
def height_field(n=48, seed=0):
    """A grid of n x n cells over integer (x, y), random heights, both diagonals used."""
    v, f = meshes.height_field(n, seed)
    return v, f, lbvh.build(v, f), n


def leaks(bvh, o, d, label):
    """Assert that the watertight test hits every ray; print Moller-Trumbore's misses."""
    tight = bvh.intersect(o, d)
    missed = np.flatnonzero(~tight.hit)
    assert len(missed) == 0, (f"{label}: {len(missed)} of {len(o)} rays leak through the "
                              f"watertight test, first o={o[missed[0]].tolist()} "
                              f"d={d[missed[0]].tolist()}")
    assert bvh.occluded(o, d).all()
    mt = bvh.intersect(o, d, triangle_test="moller")
    print(f"\n{label}: Moller-Trumbore leaks {int((~mt.hit).sum())} of {len(o)} rays "
          f"(watertight: 0)")
    # where Moller-Trumbore hits, it hits the same surface
    both = mt.hit
    assert np.allclose(mt.t[both], tight.t[both], rtol=1e-4, atol=1e-5)
    return tight


def test_rays_from_inside_a_closed_icosphere_never_leak():
    v, f, bvh = icosphere()
    rng = np.random.default_rng(1)
    edges = np.unique(np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    # from the centre: exactly through every vertex, through every edge's midpoint, and random
    d_centre = np.concatenate([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]]),
                               rng.normal(size=(8000, 3))]).astype(np.float32)
    o_centre = np.zeros_like(d_centre)
    hit = leaks(bvh, o_centre, d_centre, "icosphere, from the centre")
    # the hit is on the sphere: between the inscribed radius and 1
    r = np.linalg.norm(hit.t[:, None] * d_centre, axis=1)
    assert (r > 0.99).all() and (r < 1 + 1e-5).all()
    # from random inside points: at vertices, at points on edges, and random
    n = 6000
    o = (_unit(rng.normal(size=(n, 3))) * rng.random((n, 1)) * 0.8).astype(np.float32)
    at_vertex = v[rng.integers(0, len(v), n)]
    e = edges[rng.integers(0, len(edges), n)]
    a = rng.random((n, 1)).astype(np.float32)
    on_edge = (1 - a) * v[e[:, 0]] + a * v[e[:, 1]]
    targets = np.concatenate([at_vertex, on_edge])
    origins = np.concatenate([o, o])
    d = (targets - origins).astype(np.float32)
    hit = leaks(bvh, origins, d, "icosphere, from inside points at vertices and edges")
    # aimed rays land on their target (t ~ 1)
    assert np.allclose(hit.t, 1.0, atol=1e-4)
    leaks(bvh, o, rng.normal(size=(n, 3)).astype(np.float32), "icosphere, random inside rays")


def test_rays_at_shared_vertices_and_edges_of_a_grid_never_leak():
    v, f, bvh, n = height_field()
    rng = np.random.default_rng(2)
    grid = v.reshape(n + 1, n + 1, 3)
    inner = grid[1:-1, 1:-1].reshape(-1, 3)
    # edges of the interior: along x, along y and both diagonals, at random fractions
    edges = np.unique(np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    ends = v[edges]
    interior = ((ends[:, :, :2] > 0) & (ends[:, :, :2] < n)).all(axis=(1, 2))
    ends = ends[interior]
    a = rng.random((len(ends), 1)).astype(np.float32)
    on_edge = (1 - a) * ends[:, 0] + a * ends[:, 1]
    targets = np.concatenate([inner, on_edge]).astype(np.float32)
    # From above at slanted angles, the aim exact for vertices, rounded for edge points.
    # The rays descend faster than any face (slope <= 2 sqrt 2), so each crosses the
    # surface exactly once, at its target: a miss is a leak, not a graze of a ridge.
    up = rng.uniform(3, 10, (len(targets), 1))
    side = _unit(rng.normal(size=(len(targets), 2))) * rng.random((len(targets), 1)) * up / 4
    o = (targets + np.concatenate([side, up], axis=1)).astype(np.float32)
    d = (targets - o).astype(np.float32)
    hit = leaks(bvh, o, d, "height field, slanted rays at vertices and edges")
    assert np.allclose(hit.t, 1.0, atol=1e-4)
    # straight down through vertices and the middle of axis edges, with -0.0 and +0.0
    xy = np.concatenate([inner[:, :2], inner[:, :2] + [0.5, 0], inner[:, :2] + [0, 0.5],
                         inner[:, :2] + [0.5, 0.5]])
    o = np.concatenate([xy, np.full((len(xy), 1), 5.0)], axis=1).astype(np.float32)
    for zero in (0.0, -0.0):
        d = np.tile(np.float32([zero, zero, -1.0]), (len(o), 1))
        hit = leaks(bvh, o, d, f"height field, vertical rays (zero components {zero})")
        assert (hit.t > 2.9).all() and (hit.t < 5.0).all()


@pytest.mark.parametrize("triangle_test", ["watertight", "moller"])
def test_rays_along_a_shared_edge_plane_hit_one_side(triangle_test):
    """Two triangles sharing the diagonal of a unit square; rays through points of the
    diagonal from both sides and in the plane's normal direction."""
    v = np.float32([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    f = np.uint32([[0, 1, 2], [0, 2, 3]])
    bvh = lbvh.build(v, f)
    s = np.linspace(0.01, 0.99, 99, dtype=np.float32)
    o = np.stack([s, s, np.ones_like(s)], 1)
    for dz in (-1.0, 1.0):
        d = np.tile(np.float32([0.0, 0.0, dz]), (len(s), 1))
        oz = o.copy()
        oz[:, 2] = -dz
        got = bvh.intersect(oz, d, triangle_test=triangle_test)
        if triangle_test == "watertight":
            assert got.hit.all() and np.isin(got.prim, [0, 1]).all()
        assert (got.t[got.hit] == 1.0).all()


def test_watertight_without_the_double_fallback():
    """Devices without cl_khr_fp64 compile the kernel without the fallback; shared
    edges and vertices still never leak (the fallback only fixes signs of edge
    functions that round to zero)."""
    v, f, bvh = icosphere()
    edges = np.unique(np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    d = np.concatenate([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])]).astype(np.float32)
    rays = tr.check_rays(np.zeros_like(d), d)
    out = tr.trace_buffers(bvh.query_data, tr.upload_rays(bvh.ctx, rays), defines={"NO_FP64": 1})
    t, _, _, prim = tr.read_hits(bvh.ctx, out)
    assert (prim.view(np.int32) >= 0).all()
    with_fallback = bvh.intersect(np.zeros_like(d), d)
    assert np.allclose(t, with_fallback.t, rtol=1e-6)


@pytest.mark.parametrize("fp64", [True, False], ids=["fp64", "no-fp64"])
def test_rays_with_shears_below_float32s_range_never_leak(fp64):
    """Vertical rays tilted by components of 1e-45 .. 2^-126 (their shear d_x / d_z is
    below float32's normal range, and 1/d_x overflows): the kernel tests their
    triangles in double (or, without doubles, with the shear scaled only as far as
    is exact), the slab test bounds their near planes by FLT_MAX; through shared
    vertices and edge midpoints of the height field they still never leak."""
    v, f, bvh, n = height_field()
    grid = v.reshape(n + 1, n + 1, 3)
    inner = grid[1:-1, 1:-1].reshape(-1, 3)
    xy = np.concatenate([inner[:, :2], inner[:, :2] + [0.5, 0], inner[:, :2] + [0, 0.5],
                         inner[:, :2] + [0.5, 0.5]])
    o = np.concatenate([xy, np.full((len(xy), 1), 5.0)], axis=1).astype(np.float32)
    rng = np.random.default_rng(3)
    for tiny in (1e-45, 3e-44, 1e-40, 2.0 ** -126):
        for down in (-1.0, -1e7, -1e18):
            d = np.zeros((len(o), 3), np.float32)
            d[:, 0] = rng.choice([tiny, -tiny, 0.0], len(o))
            d[:, 1] = rng.choice([tiny, -tiny, 0.0], len(o))
            d[:, 2] = down
            if fp64:
                hit = leaks(bvh, o, d, f"height field, vertical rays tilted by {tiny:g}")
                t = hit.t * -down
            else:
                rays = tr.check_rays(o, d)
                out = tr.trace_buffers(bvh.query_data, tr.upload_rays(bvh.ctx, rays), defines={"NO_FP64": 1})
                t, _, _, prim = tr.read_hits(bvh.ctx, out)
                assert (prim.view(np.int32) >= 0).all(), (tiny, down)
                t = t * -down
            assert (t > 2.9).all() and (t < 5.0).all()
