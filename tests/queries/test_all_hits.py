"""Every hit and the hit counts (kernels/all_hits.cl) against their numpy twin and the
float64 oracle (lbvh.verification.oracle.all_hits_brute): the same hits bit for bit, a
crossing through a shared edge or vertex counted once, the same answer from every tree."""
from __future__ import annotations

import dataclasses

import numpy as np
import pyopencl as cl
import pytest

import lbvh
from lbvh.verification import hard_cases, meshes
from lbvh.verification.oracle import all_hits_brute, brute_force, signed_counts_brute
from lbvh.queries.all_hits import FIRST_SLOTS
from lbvh.queries.winding import winding_numbers_numpy


def dense_soup(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random triangles large enough that a ray crosses several."""
    return meshes.soup(n, seed, 0.15, spread="normal")


def same(got, want) -> None:
    """Bit for bit: the same hits of every ray, in the same order."""
    assert np.array_equal(got.offsets, want.offsets)
    assert np.array_equal(got.total, want.total)
    assert np.array_equal(got.prim, want.prim)
    for name in ("t", "u", "v"):
        assert np.array_equal(getattr(got, name).view(np.uint32),
                              getattr(want, name).view(np.uint32)), name
    assert got.overflow_count == 0


def random_rays(v: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    o = lo + (hi - lo) * rng.uniform(-0.5, 1.5, (n, 3))
    target = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    return o.astype(np.float32), (target - o).astype(np.float32)


@pytest.mark.parametrize("kind", ["lbvh", "lbvh+collapse", "sah", "treelets"])
def test_every_tree_gives_the_twins_hits(kind):
    v, f = dense_soup(1500, 5)
    bvh = {"lbvh": lambda: lbvh.build(v, f), "lbvh+collapse": lambda: lbvh.build(v, f, collapse=True),
           "sah": lambda: lbvh.build(v, f, builder="sah"),
           "treelets": lambda: lbvh.build(v, f, treelet_rounds=2)}[kind]()
    o, d = random_rays(v, 600, 2)
    got = bvh.all_hits(o, d)
    same(got, all_hits_brute(v, f, o, d, dtype=np.float32))
    assert got.counts.max() >= 3 and (got.counts == 0).any()   # deep rays and misses
    assert np.array_equal(bvh.count_hits(o, d), got.total)
    assert np.array_equal(bvh.count_hits(o, d, signed=True), signed_counts_brute(v, f, o, d))
    # the float64 oracle finds the same triangles (no ray of these passes within
    # rounding of an edge)
    exact = all_hits_brute(v, f, o, d, dtype=np.float64)
    assert np.array_equal(got.offsets, exact.offsets) and np.array_equal(got.prim, exact.prim)


@pytest.mark.parametrize("name", ["closed_cube_vertices_edges", "closed_sphere_vertices_edges",
                                  "rays_on_surface", "rays_in_face_planes",
                                  "axis_rays_signed_zeros", "scaled_directions",
                                  "huge_coordinates", "tiny_coordinates", "slivers",
                                  "zero_area_mix", "identical_triangles",
                                  "1_triangle", "2_triangles"])
def test_hard_cases_match_the_twin(name):
    """(1_triangle: a tree whose root is a leaf, no wide records; 2_triangles: one
    record of two leaf lanes.)"""
    case = hard_cases.make(name)
    bvh = lbvh.build(case.vertices, case.faces)
    o, d, lo, hi = case.origins, case.directions, case.tmin, case.tmax
    if len(case.faces) <= 2:   # the walks' smallest trees: the aimed rays, and turned away
        o, d = np.concatenate([o, o]), np.concatenate([d, -d])
        lo, hi = (np.concatenate([x, x]) if np.ndim(x) else x for x in (lo, hi))
    got = bvh.all_hits(o, d, lo, hi)
    same(got, all_hits_brute(case.vertices, case.faces, o, d, lo, hi, dtype=np.float32))
    assert np.array_equal(bvh.count_hits(o, d, lo, hi), got.total)
    assert np.array_equal(bvh.count_hits(o, d, lo, hi, signed=True),
                          signed_counts_brute(case.vertices, case.faces, o, d, lo, hi))
    if len(case.faces) <= 2:
        assert bvh.query_data.wide_records().packed
        assert 0 < (got.total > 0).sum() < len(got.total)


@pytest.mark.parametrize("name", ["closed_cube_vertices_edges", "closed_sphere_vertices_edges"])
def test_rays_through_vertices_and_edges_cross_a_closed_mesh_once_each_way(name):
    """The cases aim rays exactly at the vertices and along-the-edge points of closed
    meshes, from outside (two crossings) and from the centre (one): without the edge
    rule such a ray would hit every triangle around the vertex."""
    case = hard_cases.make(name)
    bvh = lbvh.build(case.vertices, case.faces)
    counts = bvh.count_hits(case.origins, case.directions, case.tmin, case.tmax)
    assert set(np.unique(counts)) <= {1, 2}
    exact = all_hits_brute(case.vertices, case.faces, case.origins, case.directions,
                           case.tmin, case.tmax, dtype=np.float64)
    assert np.array_equal(counts, exact.total)


def test_a_crossing_at_a_grid_vertex_or_edge_counts_once():
    """A flat grid (6 triangles meet at a vertex): rays through every vertex and every
    edge's midpoint, straight and slanted, cross it once."""
    v, f = meshes.grid_mesh(12, 9)
    bvh = lbvh.build(v, f)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    points = np.concatenate([v, (v[edges[:, 0]] + v[edges[:, 1]]) * np.float32(0.5)])
    normal = np.cross(v[f[0, 1]] - v[f[0, 0]], v[f[0, 2]] - v[f[0, 0]])
    normal = (normal / np.linalg.norm(normal)).astype(np.float32)
    rng = np.random.default_rng(4)
    for tilt in (0.0, 0.3, 1.7):
        d = normal + np.float32(tilt) * rng.normal(size=(len(points), 3)).astype(np.float32)
        d = d.astype(np.float32)
        o = (points - 5 * d).astype(np.float32)
        lo, hi = v.min(0), v.max(0)
        inside = ((points > lo) & (points < hi)).sum(axis=1) >= 2   # not on the border
        counts = bvh.count_hits(o, d)
        assert (counts[inside] == 1).all(), (tilt, np.bincount(counts[inside]))
        same(bvh.all_hits(o, d), all_hits_brute(v, f, o, d, dtype=np.float32))


def test_signed_counts_are_the_winding_numbers_of_closed_meshes():
    """From a point to infinity, count_hits(signed=True) is the point's winding number
    on a closed surface, whatever the direction: rays aimed exactly at the vertices and
    edges of the closed hard cases (from outside and from the centre), and rays in
    random directions and aimed at vertices from points around a cube_sphere with a
    smaller copy inside it (2 there), turned inside out (-1 inside), and with its
    vertices split at every face (closed by coordinates only)."""
    for name in ("closed_cube_vertices_edges", "closed_sphere_vertices_edges"):
        case = hard_cases.make(name)
        bvh = lbvh.build(case.vertices, case.faces)
        o, d = case.origins, case.directions
        exact = np.round(winding_numbers_numpy(case.vertices, case.faces, o))
        assert set(np.unique(exact)) == {0.0, 1.0}, name
        assert np.array_equal(bvh.count_hits(o, d, signed=True), exact), name
    v, f = meshes.cube_sphere(10)
    nested = (np.concatenate([v, v * np.float32(0.5)]), np.concatenate([f, f + len(v)]))
    split = (v[f].reshape(-1, 3), np.arange(3 * len(f), dtype=np.uint32).reshape(-1, 3))
    rng = np.random.default_rng(8)
    for mesh, values in ((nested, {0, 1, 2}), ((v, f[:, ::-1].copy()), {0, -1}),
                         (split, {0, 1})):
        bvh = lbvh.build(*mesh)
        points = rng.uniform(-1.5, 1.5, (2000, 3)).astype(np.float32)
        r = np.linalg.norm(points.astype(np.float64), axis=1)
        points = points[(np.abs(r - 1) > 0.05) & (np.abs(r - 0.5) > 0.05)]
        exact = np.round(winding_numbers_numpy(*mesh, points))
        assert set(np.unique(exact)) == values
        aimed = mesh[0][rng.integers(0, len(mesh[0]), len(points))] - points
        for d in (rng.normal(size=points.shape), aimed):
            assert np.array_equal(bvh.count_hits(points, d.astype(np.float32), signed=True),
                                  exact)


def _closed_twin(v: np.ndarray, f: np.ndarray) -> bool:
    """lbvh.mesh.is_closed one edge at a time in plain Python: the count of each
    directed edge between positions (coordinates, -0.0 as 0.0) equals its reverse's."""
    count: dict[tuple, int] = {}
    for tri in f:
        corners = [tuple(float(x) + 0.0 for x in v[i]) for i in tri]
        for a, b in zip(corners, corners[1:] + corners[:1]):
            count[(a, b)] = count.get((a, b), 0) + 1
    return all(count.get((b, a), 0) == k for (a, b), k in count.items())


def _closed_cases() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    v, f = meshes.cube_sphere(4)
    split = (v[f].reshape(-1, 3), np.arange(3 * len(f), dtype=np.uint32).reshape(-1, 3))
    signed_zero = meshes.cube_mesh(2, half=1.0)   # a vertex at 0.0 on every axis
    sz_v = signed_zero[0][signed_zero[1]].reshape(-1, 3)
    zero = sz_v == 0
    sz_v[zero] = np.where(np.arange(zero.sum()) % 2 == 1, np.float32(-0.0), np.float32(0.0))
    assert np.signbit(sz_v[zero]).any() and not np.signbit(sz_v[zero]).all()
    collinear = (np.concatenate([v, [[0, 0, 2], [0, 0, 3], [0, 0, 4]]]).astype(np.float32),
                 np.concatenate([f, [[len(v), len(v) + 1, len(v) + 2]]]).astype(np.uint32))
    two = (np.concatenate([v, v + np.float32(2.0)]), np.concatenate([f, f + len(v)]))
    # three faces on one edge: two tetrahedra sharing edge (0, 1), both closed
    tets = (np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0], [0, 0, -1]]),
            np.uint32([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3],
                       [0, 1, 4], [0, 5, 1], [0, 4, 5], [1, 5, 4]]))
    return {"cube_sphere": (v, f), "blob": meshes.blob(2000, seed=1), "split_vertices": split,
            "signed_zero_seams": (sz_v, np.arange(len(sz_v), dtype=np.uint32).reshape(-1, 3)),
            "two_shells": two, "tetrahedra_on_one_edge": tets,
            "a_face_missing": (v, f[1:]),
            "a_face_flipped": (v, np.concatenate([f[:1, ::-1], f[1:]])),
            "a_collinear_face": collinear, "a_face_twice": (v, np.concatenate([f, f[:1]]))}


@pytest.mark.parametrize("name", list(_closed_cases()))
def test_is_closed_is_its_twins(name):
    """lbvh.mesh.is_closed (sorted edge keys, positions merged by coordinates) against
    the edge-by-edge count, on closed meshes (split vertices, seams of -0.0 against
    0.0, separate shells, three faces on one edge) and on ones that are not. Where it
    says closed, the signed count of a ray from a point, in any direction and aimed at
    the corners, is the point's winding number (the exact sum, rounded)."""
    from lbvh.mesh import is_closed
    v, f = _closed_cases()[name]
    want = _closed_twin(v, f)
    assert want == (not name.startswith("a_"))
    assert is_closed(v, f) == want
    if want:
        rng = np.random.default_rng(9)
        lo, hi = v.min(axis=0), v.max(axis=0)
        p = (lo + (hi - lo) * rng.uniform(-0.3, 1.3, (1500, 3))).astype(np.float32)
        exact = winding_numbers_numpy(v, f, p)
        clear = np.abs(exact - np.round(exact)) < 1e-6   # off the surface
        p, exact = p[clear], np.round(exact[clear])
        assert len(p) > 1000 and len(np.unique(exact)) >= 2
        bvh = lbvh.build(v, f)
        for d in (rng.normal(size=p.shape), v[rng.integers(0, len(v), len(p))] - p):
            assert np.array_equal(bvh.count_hits(p, d.astype(np.float32), signed=True), exact)


def test_parity_tells_inside_from_outside_on_a_closed_mesh():
    v, f = meshes.cube_sphere(10)
    bvh = lbvh.build(v, f)
    rng = np.random.default_rng(7)
    points = rng.uniform(-1.5, 1.5, (3000, 3)).astype(np.float32)
    r = np.linalg.norm(points.astype(np.float64), axis=1)
    clear = np.abs(r - 1) > 0.05          # cube_sphere: the sphere of radius 1, faceted
    # through vertices too: rays from each point aimed at a mesh vertex
    target = v[rng.integers(0, len(v), len(points))]
    for d in (rng.normal(size=(len(points), 3)).astype(np.float32), target - points):
        counts = bvh.count_hits(points, d.astype(np.float32))
        assert np.array_equal(counts[clear] % 2 == 1, r[clear] < 1)


def test_a_hit_whose_t_overflows_float32_is_still_a_hit():
    """Directions of 1e-20 towards a triangle 1e20 away: t = 1e40, beyond float32.
    The kernels find it along d * 2^-texp (make_ray), where t is finite, and report
    t = inf, the float32 rounding of 1e40, as a hit: count_hits and all_hits count
    it and the closest hit names its triangle, as the float64 oracle does; the
    float32 twin agrees (a miss is its NaN, not its inf)."""
    big = np.float32(1e20)
    v = np.float32([[big, -big / 10, -big / 10], [big, big / 10, -big / 10], [big, 0, big / 10],
                    [-5, -5, -5], [-5, -4, -5], [-5, -5, -4]])
    f = np.uint32([[0, 1, 2], [3, 4, 5]])
    o = np.zeros((4, 3), np.float32)
    d = np.float32([[1e-20, 0, 0], [1e-20, 1e-22, 0], [1, 0, 0], [-1e-20, 0, 0]])
    bvh = lbvh.build(v, f)
    got = bvh.all_hits(o, d)
    assert got.total.tolist() == [1, 1, 1, 0] and np.isinf(got.t[:2]).all()
    same(got, all_hits_brute(v, f, o, d, dtype=np.float32))
    exact = all_hits_brute(v, f, o, d, dtype=np.float64)
    assert np.array_equal(got.offsets, exact.offsets) and np.array_equal(got.prim, exact.prim)
    assert np.array_equal(got.t, exact.t)
    assert np.array_equal(bvh.count_hits(o, d), got.total)
    assert np.array_equal(bvh.count_hits(o, d, signed=True), signed_counts_brute(v, f, o, d))
    hit = bvh.intersect(o, d)
    assert hit.prim.tolist() == [0, 0, 0, -1]
    for dtype in (np.float32, np.float64):
        want = brute_force(v, f, o, d, dtype=dtype)
        assert np.array_equal(hit.prim, want.prim) and np.array_equal(hit.t, want.t)
    # deep_sah_chain (triangles at +-2^127 .. 2^-150): rays from midpoints between two
    # corners towards a third, some with t beyond float32, through its deepest trees
    case = hard_cases.make("deep_sah_chain")
    v, f = case.vertices, case.faces
    pick = np.random.default_rng(0).integers(0, len(v), (400, 3))
    o = ((v[pick[:, 0]].astype(np.float64) + v[pick[:, 1]]) / 2).astype(np.float32)
    d = (v[pick[:, 2]].astype(np.float64) - o).astype(np.float32)
    o, d = o[np.abs(d).max(axis=1) > 0], d[np.abs(d).max(axis=1) > 0]
    want = all_hits_brute(v, f, o, d, dtype=np.float32)
    assert np.isinf(want.t).sum() > 10
    for builder in ("lbvh", "sah"):
        bvh = lbvh.build(v, f, builder=builder)
        same(bvh.all_hits(o, d), want)
        assert np.array_equal(bvh.count_hits(o, d), want.total)


def test_max_hits_keeps_the_nearest():
    v, f = dense_soup(1500, 6)
    bvh = lbvh.build(v, f)
    o, d = random_rays(v, 500, 3)
    full = bvh.all_hits(o, d)
    for k in (0, 1, 2, 5):
        got = bvh.all_hits(o, d, max_hits=k)
        assert np.array_equal(got.total, full.total)
        assert np.array_equal(got.counts, np.minimum(full.counts, k))
        assert np.array_equal(got.truncated, full.counts > k)
        for i in range(len(o)):
            keep = full.of(i)
            keep = slice(keep.start, keep.start + min(k, keep.stop - keep.start))
            assert np.array_equal(got.prim[got.of(i)], full.prim[keep])
            assert np.array_equal(got.t[got.of(i)], full.t[keep])
    # the nearest hit is the closest hit query's
    near = bvh.all_hits(o, d, max_hits=1)
    hits = bvh.intersect(o, d)
    assert np.array_equal(near.t, hits.t[hits.mask])
    assert np.array_equal(near.ray, np.flatnonzero(hits.mask))


def test_a_ray_through_many_layers_gets_them_in_order_ties_by_triangle():
    # 300 parallel squares (600 triangles, shuffled), every third one doubled: a ray
    # through them has 400 hits, pairs of them at the same t; the kernel sorts each ray's
    # hits itself (sort_kept), by t, then triangle index
    layers = np.concatenate([np.arange(300), np.arange(0, 300, 3)])
    quad = np.float32([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    v = np.concatenate([quad + np.float32([0, 0, z]) for z in layers]).astype(np.float32)
    f = np.concatenate([np.uint32([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(len(layers))])
    perm = np.random.default_rng(5).permutation(len(f))
    f = f[perm]
    o, d = np.float32([[0.3, 0.2, -5], [0.1, -0.4, 500]]), np.float32([[0, 0, 1], [0, 0, -1]])
    for builder in ("lbvh", "sah"):
        got = lbvh.build(v, f, builder=builder).all_hits(o, d)
        want = all_hits_brute(v, f, o, d)
        assert np.array_equal(got.counts, [400, 400]) and np.array_equal(got.counts, want.counts)
        assert np.allclose(got.t, want.t, rtol=1e-6)          # float32 against float64
        for i in range(2):
            assert set(got.prim[got.of(i)].tolist()) == set(want.prim[want.of(i)].tolist())
            t, prim = got.t[got.of(i)], got.prim[got.of(i)]
            tie = np.diff(t) == 0
            assert (np.diff(t) >= 0).all() and tie.sum() == 100 and (prim[1:][tie] > prim[:-1][tie]).all()
        capped = lbvh.build(v, f, builder=builder).all_hits(o, d, max_hits=7)
        assert np.array_equal(capped.t[capped.of(0)], got.t[got.of(0)][:7])


def test_intervals_batches_and_bad_rays():
    v, f = dense_soup(800, 8)
    bvh = lbvh.build(v, f)
    o, d = random_rays(v, 300, 4)
    rng = np.random.default_rng(5)
    tmin = rng.uniform(0, 0.5, len(o)).astype(np.float32)
    tmax = (tmin + rng.uniform(0, 1, len(o))).astype(np.float32)
    got = bvh.all_hits(o, d, tmin, tmax, batch_size=37)
    same(got, all_hits_brute(v, f, o, d, tmin, tmax, dtype=np.float32))
    assert ((got.t >= tmin[got.ray]) & (got.t <= tmax[got.ray])).all()
    assert np.array_equal(bvh.count_hits(o, d, tmin, tmax, batch_size=64), got.total)
    # locations lie on the hit triangles
    points = got.locations(o.astype(np.float64), d)
    p = v[f[got.prim]].astype(np.float64)
    bary = (1 - got.u - got.v)[:, None] * p[:, 0] + got.u[:, None] * p[:, 1] + got.v[:, None] * p[:, 2]
    assert np.abs(points - bary).max() < 1e-4 * np.abs(v).max()
    # a bad ray is refused, or counted as no hits with invalid_rays="miss"
    bad = d.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="ray 3"):
        bvh.count_hits(o, bad)
    counts = bvh.count_hits(o, bad, invalid_rays="miss")
    assert counts[3] == 0 and np.array_equal(np.delete(counts, 3),
                                             np.delete(bvh.count_hits(o, d), 3))
    miss = bvh.all_hits(o, bad, invalid_rays="miss")
    assert miss.invalid[3] and miss.counts[3] == 0
    with pytest.raises(ValueError, match="max_hits"):
        bvh.all_hits(o, d, max_hits=-1)
    assert len(bvh.all_hits(o[:0], d[:0])) == 0 and len(bvh.count_hits(o[:0], d[:0])) == 0


@pytest.mark.parametrize("max_hits", [None, 0, 1, FIRST_SLOTS - 1, FIRST_SLOTS, FIRST_SLOTS + 1, 30])
def test_rays_with_more_hits_than_the_first_slots_are_collected_again(max_hits):
    """all_hits keeps each ray's nearest FIRST_SLOTS hits in one pass and traces the
    rays with more again: stacked squares of shrinking size give rays of every count
    around FIRST_SLOTS in one batch (and across batches), each equal to the twin's."""
    quad = np.float32([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    layers = 2 * FIRST_SLOTS + 4
    v = np.concatenate([quad * np.float32([layers - k, layers - k, 1]) + np.float32([0, 0, k])
                        for k in range(layers)]).astype(np.float32)
    f = np.concatenate([np.uint32([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(layers)])
    f = f[np.random.default_rng(8).permutation(len(f))]
    x = np.arange(layers, dtype=np.float32) + np.float32(0.37)
    o = np.stack([x, np.full_like(x, 0.21), np.full_like(x, -3)], axis=1)
    o = np.concatenate([o, o[::-1]]).astype(np.float32)
    d = np.tile(np.float32([0, 0, 1]), (len(o), 1))
    want = all_hits_brute(v, f, o, d, dtype=np.float32)
    assert set(want.counts.tolist()) >= {FIRST_SLOTS - 1, FIRST_SLOTS, FIRST_SLOTS + 1,
                                         layers}
    bvh = lbvh.build(v, f)
    for batch in (len(o), 7):
        got = bvh.all_hits(o, d, max_hits=max_hits, batch_size=batch)
        assert np.array_equal(got.total, want.counts)
        k = want.counts if max_hits is None else np.minimum(want.counts, max_hits)
        assert np.array_equal(got.counts, k)
        for i in range(len(o)):
            w = want.of(i)
            nearest = slice(w.start, w.start + k[i])
            assert np.array_equal(got.t[got.of(i)], want.t[nearest]), (i, max_hits, batch)
            assert np.array_equal(got.prim[got.of(i)], want.prim[nearest])
            assert np.array_equal(got.u[got.of(i)], want.u[nearest])
    assert np.array_equal(bvh.count_hits(o, d), want.counts)


def test_a_large_batch_samples_its_slots_and_answers_as_the_twin():
    """A batch of at least 64 SAMPLE_EVERY rays sizes its slots from a counting pass
    over a sample (first_slots); every hit, all or capped, is still the twin's."""
    from lbvh.queries.all_hits import SAMPLE_EVERY, SLOT_RANGE
    v, f = dense_soup(600, 9)
    bvh = lbvh.build(v, f)
    n = 64 * SAMPLE_EVERY + 123
    o, d = random_rays(v, n, 10)
    want = all_hits_brute(v, f, o, d, dtype=np.float32)
    assert want.counts.max() > SLOT_RANGE[0]    # some rays are traced again
    same(bvh.all_hits(o, d), want)
    capped = bvh.all_hits(o, d, max_hits=2)
    assert np.array_equal(capped.counts, np.minimum(want.counts, 2))
    assert np.array_equal(capped.total, want.counts)
    firsts = want.offsets[:-1][want.counts > 0]
    assert np.array_equal(capped.t[capped.offsets[:-1][want.counts > 0]], want.t[firsts])


def test_slots_stay_within_the_largest_buffer_and_the_rest_is_traced_again(monkeypatch):
    """first_slots never gives a batch more slots than the device's largest buffer holds
    for all the columns together (read from the device, here made small); the rays past
    their slots are traced again, and every hit is still the twin's."""
    from lbvh.queries import all_hits as ah
    v, f = dense_soup(600, 11)
    bvh = lbvh.build(v, f)
    n = 64 * ah.SAMPLE_EVERY + 5
    o, d = random_rays(v, n, 12)
    want = all_hits_brute(v, f, o, d, dtype=np.float32)
    rays = ah._rays(o, d, 0.0, np.inf, "raise")
    pass_ = ah._Pass(bvh.ctx, ah.KERNEL_FILE, "all_hits", ah.wide_head(bvh), {}, (0,) * 4)
    free = ah.first_slots(pass_, rays, -1)
    assert free > 2
    monkeypatch.setattr(bvh.ctx.memory, "max_alloc", 4 * 4 * n * 2 + 15)
    assert ah.first_slots(pass_, rays, -1) == 2
    assert (want.counts > 2).sum() > n // 4      # many rays traced again
    same(bvh.all_hits(o, d), want)


def test_move_runs_equals_its_twin():
    """all_hits.cl move_runs, the kept hits gathered from their slots on the device:
    the numpy twin's words bit for bit, empty runs included, every column."""
    from lbvh.queries.all_hits import move_runs, move_runs_numpy
    ctx = lbvh.build(*dense_soup(20, 1)).ctx
    rng = np.random.default_rng(5)
    count = rng.integers(0, 9, 5000).astype(np.int32)
    count[::7] = 0
    src_first = np.arange(5000, dtype=np.int64) * 9
    dst_first = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
    order = rng.permutation(5000)      # runs in any order, to any place
    src_first, dst_first, count = src_first[order], dst_first[order], count[order]
    columns = [rng.integers(0, 2**32, 5000 * 9, dtype=np.uint32) for _ in range(3)]
    columns.append(rng.normal(size=5000 * 9).astype(np.float32).view(np.uint32))
    total = int(count.sum())
    src = [ctx.memory.upload(c) for c in columns]
    dst = [ctx.memory.alloc(4 * total) for _ in columns]
    try:
        move_runs(ctx, src, dst, src_first, dst_first, count)
        for c, buf in zip(columns, dst):
            want = np.zeros(total, np.uint32)
            move_runs_numpy(c, want, src_first, dst_first, count)
            got = np.empty(total, np.uint32)
            cl.enqueue_copy(ctx.queue, got, buf, is_blocking=True)
            assert np.array_equal(got, want)
    finally:
        ctx.memory.free(*src, *dst)


@pytest.mark.parametrize("clang", [0, 1], ids=["portable", "clang-builtins"])
def test_the_wide_walk_with_and_without_clang_builtins_and_with_a_full_stack(clang):
    """The every-hit walk through wide records (kernels/every_hit.h wide_tree_hits)
    gives the twin's counts and hits with clang's builtins (the lanes' bit mask, their
    lowest bit, the prefetch of the records pushed: set where the compiler is clang)
    and without them. With a stack of one entry a ray whose walk needs more is
    flagged, never silently short: the unflagged rays' counts are the twin's, the
    flagged rays' at most theirs."""
    from lbvh.queries import all_hits as ah
    from lbvh.queries.traverse import FLAG_OVERFLOW
    v, f = dense_soup(1500, 5)
    bvh = lbvh.build(v, f)
    if clang and not bvh.ctx.compiler_is_clang:
        pytest.skip(f"clang's builtins need clang; {bvh.ctx.name} compiles with another")
    o, d = random_rays(v, 600, 2)
    want = all_hits_brute(v, f, o, d, dtype=np.float32)
    wide = bvh.query_data.wide_records()
    assert wide.packed and wide.count > 1
    head = ah.wide_head(bvh)
    rays = ah._rays(o, d, 0.0, np.inf, "raise")
    defines = {**ah.wide_defines(bvh.ctx, wide.width), "CLANG_MOVMSK": clang,
               "CLANG_CTZ": clang, "CLANG_PREFETCH": clang}
    walk = ah.HitWalk(ah.KERNEL_FILE, "all_hits", head, ah.stack_need(bvh.query_data),
                      defines=defines)
    total, flags, _ = ah.run_passes(bvh.ctx, walk, rays, 1 << 18, None)
    assert np.array_equal(total, want.total) and not flags.any()
    total, flags, kept = ah.run_passes(bvh.ctx, walk, rays, 1 << 18, -1)
    assert np.array_equal(total, want.total) and not flags.any()
    for got, name in zip(kept, ("t", "prim", "u", "v")):
        assert np.array_equal(got.view(np.uint32), getattr(want, name).view(np.uint32)), name
    total, flags, _ = ah.run_passes(
        bvh.ctx, dataclasses.replace(walk, defines={**defines, "STACK_SIZE": 1}), rays, 1 << 18,
        None)
    full = (flags & FLAG_OVERFLOW) != 0
    assert 0 < full.sum() < len(full)
    assert np.array_equal(total[~full], want.total[~full])
    assert (total[full] <= want.total[full]).all() and (total[full] < want.total[full]).any()
    assert ah.wide_defines(bvh.ctx, wide.width)["CLANG_PREFETCH"] == int(bvh.ctx.compiler_is_clang)


def test_refit_renews_the_triangles_in_slot_order():
    """The every-hit walk reads each slot's triangle from a copy of its corners
    (bvh.slot_triangles): after a refit moves the vertices, the counts and hits are
    those of the moved mesh, as the twin gives them, not the copy's."""
    v, f = dense_soup(600, 7)
    bvh = lbvh.build(v, f)
    o, d = random_rays(v, 300, 8)
    before = bvh.query_data.slot_triangles()
    same(bvh.all_hits(o, d), all_hits_brute(v, f, o, d, dtype=np.float32))
    moved = (v * np.float32(1.5) + np.float32(0.25)).astype(np.float32)
    bvh.refit(moved)
    o2, d2 = random_rays(moved, 300, 9)
    want = all_hits_brute(moved, f, o2, d2, dtype=np.float32)
    assert np.array_equal(bvh.count_hits(o2, d2), want.total)
    same(bvh.all_hits(o2, d2), want)
    assert bvh.query_data.slot_triangles() is not before


# -- both passes as streams (kernels/hit_streams.h, all_hits.stream_plan) -----------------
def _per_ray(monkeypatch, query, *args, **kwargs):
    """A query by the per-ray walk, as on a GPU (no streams)."""
    from lbvh.queries import all_hits as ah
    with monkeypatch.context() as m:
        m.setattr(ah, "stream_records", lambda ctx, records: 0)
        return query(*args, **kwargs)


def _stream_cases():
    """(name, build options, vertices, faces, origins, directions, tmin, tmax)."""
    v, f = dense_soup(1500, 5)
    o, d = random_rays(v, 600, 2)
    yield "soup", {}, v, f, o, d, 0.0, np.inf
    # leaves of several triangles: the first of each by the lanes' vector test, the
    # rest one by one (hit_streams.h LANE_TRIANGLES)
    yield "soup-collapsed", {"collapse": True}, v, f, o, d, 0.0, np.inf
    # minor direction components of 1e-45 .. 1e-30: shears below float32's normal range
    # (make_ray's `hard` rays, which the vector test leaves to hit_triangle's double)
    rng = np.random.default_rng(7)
    lo, hi = v.min(axis=0), v.max(axis=0)
    o = (lo + rng.random((600, 3)) * (hi - lo)).astype(np.float32)
    d = (rng.choice([1e-45, -1e-45, 3e-42, -1e-40, 1e-38, 1e-30, 0.0], (600, 3))
         * rng.choice([1.0, 0.5], (600, 3)))
    d[np.arange(600), rng.integers(0, 3, 600)] = rng.choice([1.0, -1.0, 1e7, -3e20], 600)
    yield "soup-tiny-components", {}, v, f, o, d.astype(np.float32), 0.0, np.inf
    tv, tf = meshes.terrain(20000, 3)
    o, d = random_rays(tv, 3000, 4)
    yield "terrain", {}, tv, tf, o, d, 0.0, np.inf
    # huge and tiny coordinates: triangles whose edge functions leave the vector test for
    # the double fallback
    for name in ("closed_cube_vertices_edges", "rays_in_face_planes", "axis_rays_signed_zeros",
                 "scaled_directions", "huge_coordinates", "tiny_coordinates", "zero_area_mix",
                 "1_triangle"):
        case = hard_cases.make(name)
        yield (name, {}, case.vertices, case.faces, case.origins, case.directions, case.tmin,
               case.tmax)


# (per_chunk, items, scratch words a ray): the host's plan; chunks of 5 rays over 3
# work-items; room for the root's list alone (every ray goes on by the per-ray walk
# from the root); room for the root and its lanes (deeper records with long lists
# go on ray by ray)
_PLANS = [None, (5, 3, 32), (64, 2, 1), (64, 2, 12)]


@pytest.mark.parametrize("plan", _PLANS, ids=["host", "chunks-of-5", "no-room", "two-levels"])
def test_streams_give_the_per_ray_walks_and_the_twins_hits(monkeypatch, plan):
    """count_hits and all_hits on a CPU walk their rays as streams: the counts and the
    hits equal the per-ray walk's and the twin's on every case, bit for bit, with and
    without max_hits, whatever the chunks and however soon the room for the lists
    runs out (its rays then go on one by one)."""
    from lbvh.queries import all_hits as ah
    if plan is not None:
        per_chunk, items, words = plan
        monkeypatch.setattr(ah, "stream_plan", lambda ctx, rays, records: ah.StreamPlan(
            per_chunk, items, words * per_chunk))
    seen = []
    real = ah.stream_records
    monkeypatch.setattr(ah, "stream_records",
                        lambda ctx, records: seen.append(real(ctx, records)) or seen[-1])
    cpu = lbvh.device.context.get_context().is_cpu
    for name, options, v, f, o, d, lo, hi in _stream_cases():
        bvh = lbvh.build(v, f, **options)
        seen.clear()
        got = bvh.count_hits(o, d, lo, hi)
        # a CPU counts by streams, but in a tree of one leaf (no records)
        assert bool(seen[0]) == (cpu and name != "1_triangle"), name
        want = all_hits_brute(v, f, o, d, lo, hi, dtype=np.float32)
        assert np.array_equal(got, want.total), name
        assert np.array_equal(got, _per_ray(monkeypatch, bvh.count_hits, o, d, lo, hi)), name
        signed = bvh.count_hits(o, d, lo, hi, signed=True)
        assert np.array_equal(signed, signed_counts_brute(v, f, o, d, lo, hi)), name
        assert np.array_equal(signed, _per_ray(monkeypatch, bvh.count_hits, o, d, lo, hi,
                                               signed=True)), name
        same(bvh.all_hits(o, d, lo, hi), want)
        same(bvh.all_hits(o, d, lo, hi, max_hits=2),
             _per_ray(monkeypatch, bvh.all_hits, o, d, lo, hi, max_hits=2))


def test_the_leaf_lanes_vector_test_gives_the_one_by_one_hits(monkeypatch):
    """The streams test a ray's leaf lanes' first triangles in one vector computation
    (hit_streams.h lane_triangle_hits): the counts and the hits, t, u and v bit for
    bit, are those of the same streams testing every triangle one by one
    (LANE_TRIANGLES=0), on every stream case, the collapsed tree's included."""
    from lbvh.queries import all_hits as ah
    if not lbvh.device.context.get_context().is_cpu:
        pytest.skip("the streams walk a CPU's rays only")
    real = ah.wide_defines
    one_by_one = {"LANE_TRIANGLES": 0}
    monkeypatch.setattr(ah, "stream_records", lambda ctx, records: records)
    for name, options, v, f, o, d, lo, hi in _stream_cases():
        bvh = lbvh.build(v, f, **options)
        got = (bvh.count_hits(o, d, lo, hi), bvh.all_hits(o, d, lo, hi),
               bvh.all_hits(o, d, lo, hi, max_hits=2), bvh.count_hits(o, d, lo, hi, signed=True))
        with monkeypatch.context() as m:
            m.setattr(ah, "wide_defines", lambda ctx, width: {**real(ctx, width), **one_by_one})
            want = (bvh.count_hits(o, d, lo, hi), bvh.all_hits(o, d, lo, hi),
                    bvh.all_hits(o, d, lo, hi, max_hits=2),
                    bvh.count_hits(o, d, lo, hi, signed=True))
        assert np.array_equal(got[0], want[0]), name
        assert np.array_equal(got[3], want[3]), name
        same(got[1], want[1])
        same(got[2], want[2])
        if name in ("soup", "terrain"):
            assert got[0].sum() > len(o), name   # rays that cross several triangles


def test_streams_with_few_frames_go_on_ray_by_ray(monkeypatch):
    """A work-item whose frames (STREAM_FRAMES) run out sends that record's rays on by
    the per-ray walk: the same counts."""
    from lbvh.queries import all_hits as ah
    real = ah.wide_defines
    monkeypatch.setattr(ah, "wide_defines",
                        lambda ctx, width: {**real(ctx, width), "STREAM_FRAMES": 12})
    monkeypatch.setattr(ah, "stream_records", lambda ctx, records: records)
    tv, tf = meshes.terrain(20000, 3)
    o, d = random_rays(tv, 3000, 4)
    bvh = lbvh.build(tv, tf)
    want = all_hits_brute(tv, tf, o, d, dtype=np.float32).total
    assert np.array_equal(bvh.count_hits(o, d), want)


def test_stream_plan_fits_the_device_and_every_core():
    """The plan's chunks cover the rays with work for every compute unit, its buffers
    stay within the device's largest allocation (read from the device object), and a
    GPU does not take streams."""
    from types import SimpleNamespace
    from lbvh.queries import all_hits as ah
    for units, largest, memory, rays, records in [(2, 1 << 30, 1 << 34, 262144, 21791),
                                                  (2, 1 << 30, 1 << 34, 262144, 303914),
                                                  (16, 1 << 30, 1 << 34, 1000, 303914),
                                                  (64, 1 << 22, 1 << 34, 1 << 20, 80000),
                                                  (64, 1 << 30, 1 << 30, 1 << 22, 80000),
                                                  (1, 1 << 12, 1 << 15, 10, 3)]:
        ctx = SimpleNamespace(compute_units=units, memory=SimpleNamespace(max_alloc=largest),
                              device=SimpleNamespace(global_mem_size=memory))
        plan = ah.stream_plan(ctx, rays, records)
        sizes = plan.buffers()
        assert plan.per_chunk >= 1 and plan.items >= 1
        assert plan.scratch_words >= plan.per_chunk   # the root's list fits
        assert plan.items <= 2 * units
        chunks = -(-rays // plan.per_chunk)
        assert chunks >= min(2 * units, rays) or plan.per_chunk == 1
        if plan.per_chunk > 1:   # it shrank as far as it had to
            assert max(sizes.values()) <= largest and sum(sizes.values()) <= memory // 8
    assert ah.stream_records(SimpleNamespace(is_cpu=False), 100) == 0
    assert ah.stream_records(SimpleNamespace(is_cpu=True), 100) == 100
