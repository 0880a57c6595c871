"""Answers that depend on the triangles as sets of points only.

The ray/triangle decision of the default watertight test is exact
(kernels/ray_triangle.h, twin lbvh.queries.exact): a ray hits a triangle or not
whatever the order and winding of its corners and whatever power of two the
scene is scaled by; t scales bit for bit; exactly collinear triangles are
never hit and every other triangle can be; a ray whose origin lies on a
triangle hits it at t = 0 exactly (``tmin = 0`` counts it, ``tmin > 0`` leaves
it out). Named cases, properties against an exact rational oracle (hypothesis),
and the rewritings of lbvh.verification.invariance on real meshes, every query,
every builder, scenes of instances.
"""
from __future__ import annotations

import functools
import itertools
import numpy as np
import pyopencl as cl
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import lbvh
from lbvh.queries import exact, winding
from lbvh.verification import invariance
from lbvh.verification.oracle import all_hits_brute, brute_force, exact_pair

ORDERS = list(itertools.permutations(range(3)))
#: every builder and builder option whose tree the ray walks can read
BUILDS = [dict(builder="lbvh"), dict(builder="lbvh", collapse=True), dict(builder="sah"),
          dict(builder="median"), dict(builder="midpoint"), dict(builder="sbvh")]


def one(v, order, **build):
    return lbvh.build(np.asarray(v, np.float32), np.uint32([order]), **build)


# -- named cases ------------------------------------------------------------------------

def test_a_sliver_is_hit_in_every_corner_order():
    """1 long, 1e-7 high: a real triangle, hit straight through its interior at t = 1
    whichever corner comes first and whichever the winding (the old degenerate test
    at the first corner missed it for one order)."""
    v = [[0, 0, 0], [1, 0, 0], [1, 1e-7, 0]]
    o, d = np.float32([[0.9, 0.5e-7, 1]]), np.float32([[0, 0, -1]])
    for order in ORDERS:
        hit = one(v, order).intersect(o, d)
        assert hit.prim.tolist() == [0] and hit.t.tolist() == [1.0], order


def test_a_ray_leaving_a_surface_hits_it_at_t_zero():
    """An origin on the triangle: t = 0 exactly, at any angle, in every corner order;
    tmin = 0 counts the hit, tmin > 0 leaves it out (the library's convention)."""
    v = [[0, 0, 0], [0, 1, 0], [0, 0, 1]]
    d = np.float32([[1e-7, 1, .5], [1e-3, 1, .5], [1e-9, 1, .5], [-1e-7, 1, .5], [1, 0, 0]])
    o = np.float32([[0, .25, .25]] * len(d))
    for order in ORDERS:
        bvh = one(v, order)
        hit = bvh.intersect(o, d)
        assert hit.hit.all() and (hit.t == 0).all() and not np.signbit(hit.t).any(), order
        assert bvh.occluded(o, d).all()
        assert bvh.count_hits(o, d).tolist() == [1] * len(d)
        assert not bvh.intersect(o, d, tmin=np.float32(1e-30)).hit.any()
        assert not bvh.occluded(o, d, tmin=np.float32(1e-30)).any()
        assert bvh.count_hits(o, d, tmin=np.float32(1e-30)).tolist() == [0] * len(d)


def test_an_origin_a_hair_behind_or_ahead_of_the_plane():
    """Origins 2^-60 off the plane x = 0 on either side, rays along +x at a grazing
    angle: the one behind hits at a t > 0, the one ahead does not (t < 0), in
    every order, however small t is."""
    v = [[0, 0, 0], [0, 1, 0], [0, 0, 1]]
    o = np.float32([[-2.0 ** -60, .25, .25], [2.0 ** -60, .25, .25]])
    d = np.float32([[1e-7, 1, .5]] * 2)
    for order in ORDERS:
        hit = one(v, order).intersect(o, d)
        assert hit.hit.tolist() == [True, False] and hit.t[0] > 0, order


@pytest.mark.parametrize("corners", [
    [[0, 0, 0], [1, 1, 1], [3, 3, 3]],                  # collinear
    [[0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.5, 0.5, 0.5]],  # a repeated corner
    [[1, 2, 3], [1, 2, 3], [1, 2, 3]],                  # one point
    [[0.5, 0.25, 0], [0.75, 0.375, 0], [0.125, 0.0625, 0]],  # collinear, not axis-aligned
])
def test_collinear_triangles_are_never_hit(corners):
    """Exactly collinear corners: no ray hits, whatever it aims at, in every order."""
    v = np.float32(corners)
    rng = np.random.default_rng(0)
    target = v[rng.integers(0, 3, 64)] + (v[rng.integers(0, 3, 64)] - v[rng.integers(0, 3, 64)]) * \
        rng.random((64, 1)).astype(np.float32)
    o = (target + rng.normal(size=(64, 3))).astype(np.float32)
    d = (target - o).astype(np.float32)
    assert exact.collinear(v, np.int64([[0, 1, 2]])).all()
    for order in ORDERS:
        bvh = one(v, order)
        assert not bvh.intersect(o, d).hit.any()
        assert not bvh.occluded(o, d).any()
        assert (bvh.count_hits(o, d) == 0).all()


def test_the_degenerate_test_is_exact_and_symmetric():
    """kernels' degenerate() (through order_triangles) against the exact twin: a sliver
    1e-7 (or 2^-100) of its length is not degenerate in any order, exactly collinear
    corners are."""
    from lbvh.queries.traverse import order_triangles_numpy
    v = np.float32([[0, 0, 0], [1, 0, 0], [1, 1e-7, 0], [2, 2, 2], [4, 4, 4], [1, 2.0 ** -100, 0]])
    f = np.uint32([p for p in ORDERS] + [[0, 1, 3], [0, 3, 4], [0, 1, 5]])
    want = np.array([False] * 6 + [False, True, False])
    assert np.array_equal(exact.collinear(v, f), want)
    bvh = lbvh.build(v, f)
    got = np.empty((bvh.tree.num_prims, 3, 3), np.float32)
    cl.enqueue_copy(bvh.ctx.queue, got, bvh.query_data.slot_triangles(), is_blocking=True)
    assert np.array_equal(got.view(np.uint32),
                          order_triangles_numpy(v, f, bvh.prim_order).view(np.uint32))
    is_point = (got == got[:, :1]).all(axis=(1, 2))
    assert np.array_equal(is_point, want[bvh.prim_order])


# -- properties against an exact rational oracle ------------------------------------------

def _exact_hit(a, b, c, o, d):
    """Exact arithmetic on the float32 inputs: whether the ray hits (t >= 0) and t."""
    inside, t, _ = exact_pair(np.float32([a, b, c]), o, d)
    return inside and t >= 0, t


coordinate = st.floats(-1, 1, width=32, allow_subnormal=False)
height = st.floats(-7, -1).map(lambda x: 10.0 ** x)


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(a=st.tuples(coordinate, coordinate, coordinate),
       b=st.tuples(coordinate, coordinate, coordinate),
       h=height, s=st.floats(0, 1), seed=st.integers(0, 2 ** 31 - 1),
       k=st.sampled_from([0, -60, -40, -20, 20, 40, 60]))
def test_hits_are_the_exact_ones_in_every_order_and_scale(a, b, h, s, seed, k):
    """A random sliver (height 1e-7 .. 0.1 of its length) and rays aimed at its
    interior, edges and corners, and from points on its plane: hit or miss is the
    exact one, in every corner order, with the scene scaled by 2^k; t is the same
    bits in every order and times 2^k exactly."""
    a, b = np.float64(a), np.float64(b)
    if np.linalg.norm(b - a) < 1e-3:
        b = a + 0.5
    rng = np.random.default_rng(seed)
    side = np.cross(b - a, rng.normal(size=3))
    side *= h * np.linalg.norm(b - a) / np.linalg.norm(side)
    c = a + s * (b - a) + side
    v = np.float32([a, b, c])
    n = 48
    w = rng.random((n, 3))
    w[: n // 4, rng.integers(0, 3)] = 0          # on an edge line
    w /= w.sum(axis=1, keepdims=True)
    target = w @ v.astype(np.float64)
    o = target + rng.normal(size=(n, 3))
    o[: n // 8] = target[: n // 8]                # from the surface, any direction
    d = np.where(np.arange(n)[:, None] < n // 8, rng.normal(size=(n, 3)), target - o)
    o, d = o.astype(np.float32), d.astype(np.float32)
    want = np.array([_exact_hit(*v, o[i], d[i])[0] for i in range(n)])
    base = None
    for order in ORDERS:
        hit = one(v, order).intersect(o, d)
        assert np.array_equal(hit.hit, want), (order, np.flatnonzero(hit.hit != want))
        if base is None:
            base = hit.t
        assert np.array_equal(hit.t, base)
    if k and invariance.representable(v, k) and invariance.representable(o, k):
        scaled = one(np.ldexp(v, k), (0, 1, 2)).intersect(np.ldexp(o, k).astype(np.float32), d)
        assert np.array_equal(scaled.hit, want)
        normal = np.isfinite(base) & (np.abs(np.ldexp(base.astype(np.float64), k))
                                      >= np.finfo(np.float32).tiny)
        assert np.array_equal(scaled.t[normal], np.ldexp(base[normal], k).astype(np.float32))


# -- rewritings of real meshes ---------------------------------------------------------

@functools.lru_cache(maxsize=None)
def teapot():
    from lbvh.files import load_mesh
    from conftest import REPO
    return load_mesh(REPO / "scenes" / "teapot.obj")


@functools.lru_cache(maxsize=None)
def slivers():
    return invariance.sliver_soup(1500, 3)


def _check(v, f, build, rewrite_names=None, rays=600):
    base = lbvh.build(v, f, **build)
    sets = invariance.ray_sets(v, f, rays, 0, trace=base.intersect)
    order = np.random.default_rng(1).permutation(len(f))
    all_o = np.concatenate([o for o, _ in sets.values()])
    for rewrite in invariance.rewrites(v, all_o):
        if rewrite_names is not None and rewrite.name not in rewrite_names:
            continue
        other = lbvh.build(rewrite.points(v), rewrite.faces(f, order), **build)
        for name, (o, d) in sets.items():
            o2 = rewrite.points(o)
            diff = invariance.differences(base.intersect(o, d), other.intersect(o2, d), rewrite,
                                          order)
            assert diff == {"hit": 0, "prim": 0, "t": 0}, (rewrite.name, name, diff)
            assert np.array_equal(base.occluded(o, d), other.occluded(o2, d))
            assert np.array_equal(base.count_hits(o, d), other.count_hits(o2, d))
            if not base.tree.clipped_leaves:   # spatial splits: no signed counts
                sign = -1 if rewrite.corners == (0, 2, 1) else 1
                assert np.array_equal(base.count_hits(o, d, signed=True),
                                      sign * other.count_hits(o2, d, signed=True))
            if not rewrite.permute:
                x, y = base.all_hits(o, d), other.all_hits(o2, d)
                assert np.array_equal(x.offsets, y.offsets) and np.array_equal(x.prim, y.prim)
                assert np.array_equal(np.ldexp(x.t.astype(np.float64), rewrite.scale)
                                      .astype(np.float32), y.t), (rewrite.name, name)


@pytest.mark.parametrize("mesh", ["teapot", "slivers"])
def test_every_rewriting_on_the_default_build(mesh):
    v, f = {"teapot": teapot, "slivers": slivers}[mesh]()
    _check(v, f, {})


@pytest.mark.parametrize("build", BUILDS[1:], ids=lambda b: "-".join(map(str, b.values())))
def test_rewritings_on_every_builder(build):
    v, f = slivers()
    _check(v, f, build, {"rotate", "flip", "permute", "scale -60", "scale 60"}, rays=300)


def test_rewritings_through_a_scene_of_instances():
    """Two placed copies of the sliver soup: rotating every corner order, or scaling
    meshes, placements and origins by 2^-40, changes no hit, triangle or t."""
    v, f = slivers()
    place = np.zeros((2, 3, 4))
    place[:, :, :3] = np.eye(3)
    place[1, :, 3] = [1.5, 0, 0]

    def scene(vv, ff, k):
        p = place.copy()
        p[:, :, 3] *= 2.0 ** k
        return lbvh.Scene([lbvh.build(vv, ff)], [0, 0], p)
    sets = invariance.ray_sets(v, f, 600, 0)
    base = scene(v, f, 0)
    for corners, k in (((1, 2, 0), 0), ((0, 2, 1), 0), ((0, 1, 2), -40)):
        other = scene(np.ldexp(v, k).astype(np.float32), np.ascontiguousarray(f[:, corners]), k)
        for o, d in sets.values():
            x, y = base.intersect(o, d), other.intersect(np.ldexp(o, k).astype(np.float32), d)
            assert np.array_equal(x.hit, y.hit) and np.array_equal(x.prim, y.prim)
            assert np.array_equal(np.ldexp(x.t.astype(np.float64), k).astype(np.float32)[x.hit],
                                  y.t[x.hit])
            assert np.array_equal(base.count_hits(o, d),
                                  other.count_hits(np.ldexp(o, k).astype(np.float32), d))
        # closest points through the scene: the same, times 2^k
        p = sets["aimed"][0][:500]
        x, y = base.closest_points(p), other.closest_points(np.ldexp(p, k).astype(np.float32))
        assert np.array_equal(x.instance, y.instance) and np.array_equal(x.prim, y.prim)
        assert np.array_equal(np.ldexp(x.distance.astype(np.float64), k).astype(np.float32),
                              y.distance)
        assert np.array_equal(np.ldexp(x.points.astype(np.float64), k).astype(np.float32),
                              y.points)


# -- against the float64 oracle ------------------------------------------------------------

def test_slivers_and_surface_rays_agree_with_the_float64_oracle():
    """Zero wrong against the float64 watertight oracle on slivers (aimed rays) and on
    rays that start on axis-aligned triangles (t = 0 exactly)."""
    v, f = slivers()
    bvh = lbvh.build(v, f)
    o, d = invariance.ray_sets(v, f, 2000, 5)["aimed"]
    got, want = bvh.intersect(o, d), brute_force(v, f, o, d, dtype=np.float64)
    assert np.array_equal(got.hit, want.hit) and np.array_equal(got.prim, want.prim)
    # origins on the faces of a unit cube grid (exact), leaving at every angle
    rng = np.random.default_rng(2)
    gv = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    gf = np.uint32([[0, 1, 2], [1, 3, 2]])
    o = np.float32(np.c_[rng.integers(1, 64, (500, 2)) / 128.0, np.zeros(500)])
    d = rng.normal(size=(500, 3)).astype(np.float32)
    d[:, 2] *= 10.0 ** rng.uniform(-9, 0, 500)
    g = lbvh.build(gv, gf)
    got, want = g.intersect(o, d), brute_force(gv, gf, o, d, dtype=np.float64)
    assert got.hit.all() and (got.t == 0).all()
    assert np.array_equal(got.hit, want.hit) and np.array_equal(got.t, want.t)
    counts = all_hits_brute(gv, gf, o, d, dtype=np.float64)
    assert np.array_equal(g.count_hits(o, d), counts.total)


# -- closest points --------------------------------------------------------------------

@pytest.mark.parametrize("mesh", ["teapot", "slivers"])
def test_closest_points_do_not_depend_on_how_the_mesh_is_written(mesh):
    """Corners rotated or flipped: the same triangle, distance and point, bit for bit,
    and the barycentrics of the same point; faces permuted: the same distance and
    point; the scene scaled by 2^k: distance and point times 2^k exactly."""
    v, f = {"teapot": teapot, "slivers": slivers}[mesh]()
    rng = np.random.default_rng(4)
    lo, hi = v.min(axis=0), v.max(axis=0)
    p = (lo + (hi - lo) * rng.uniform(-0.2, 1.2, (3000, 3))).astype(np.float32)
    on = v[f[rng.integers(0, len(f), 1000)]]
    p = np.concatenate([p, on[:, 0], on.mean(axis=1, dtype=np.float64).astype(np.float32)])
    order = np.random.default_rng(1).permutation(len(f))
    for build in BUILDS[:3]:
        base = lbvh.build(v, f, **build).closest_points(p)
        for rewrite in invariance.rewrites(v, p):
            other = lbvh.build(rewrite.points(v), rewrite.faces(f, order), **build) \
                .closest_points(rewrite.points(p))
            k = rewrite.scale
            scale = (lambda x: np.ldexp(x.astype(np.float64), k).astype(np.float32))
            assert np.array_equal(scale(base.distance), other.distance), rewrite.name
            assert np.array_equal(scale(base.points), other.points), rewrite.name
            if not rewrite.permute:
                assert np.array_equal(base.prim, other.prim), rewrite.name
            if rewrite.corners != (0, 1, 2):
                # the barycentrics are of the rewritten corners, and name the same point
                tri = v[f[base.prim]][:, list(rewrite.corners)].astype(np.float64)
                w = np.c_[1 - other.u.astype(np.float64) - other.v, other.u, other.v]
                got = np.einsum("ij,ijk->ik", w, tri)
                assert np.allclose(got, base.points, atol=1e-5 * float(np.abs(v).max()))


# -- winding numbers and inside tests -------------------------------------------------------

@pytest.mark.parametrize("mesh", ["teapot", "slivers"])
@pytest.mark.parametrize("build", BUILDS[:5], ids=lambda b: "-".join(map(str, b.values())))
def test_winding_numbers_do_not_depend_on_how_the_mesh_is_written(mesh, build):
    """Every corner rotated: the same winding numbers, bit for bit; every face
    flipped: negated exactly; the scene scaled by 2^k: the same bits. Both walks (a
    point a work-item and 16, the CPU's default), every builder a winding walk reads
    (spatial splits have none); the inside test follows. The faces in another order
    make another tree, which expands other nodes: the two then agree within twice the
    walk's bound, and their inside tests wherever the exact winding number is farther
    than the bound from 1/2."""
    from lbvh.metrics.error_bound import WINDING_BOUND
    from lbvh.queries.winding import winding_numbers_numpy
    v, f = {"teapot": teapot, "slivers": slivers}[mesh]()
    p = invariance.winding_points(v, f, 1200, 6)
    order = np.random.default_rng(1).permutation(len(f))
    base = lbvh.build(v, f, **build)
    walks = {packets: winding.winding_numbers(base.query_data, p, packets=packets)
             for packets in (False, True)}
    inside = base.contains(p)
    for rewrite in invariance.rewrites(v, p):
        other = lbvh.build(rewrite.points(v), rewrite.faces(f, order), **build)
        q = rewrite.points(p)
        for packets, w in walks.items():
            got = winding.winding_numbers(other.query_data, q, packets=packets)
            if rewrite.permute:
                assert np.abs(got - w).max() <= 2 * WINDING_BOUND, rewrite.name
                continue
            want = -w if rewrite.corners == (0, 2, 1) else w
            assert np.array_equal(got.view(np.uint32), want.view(np.uint32)), \
                (rewrite.name, packets, int((got != want).sum()))
        if rewrite.corners == (0, 2, 1):
            continue
        if rewrite.permute:
            exact = winding_numbers_numpy(v, f, p)
            clear = np.abs(exact - 0.5) > WINDING_BOUND
            assert np.array_equal(other.contains(q)[clear], inside[clear])
        else:
            assert np.array_equal(other.contains(q), inside), rewrite.name


def test_winding_numbers_through_a_scene_of_instances():
    """Two placed copies of the teapot: its corners rotated, its winding reversed (the
    scene's winding numbers negated exactly), or meshes, placements and points scaled
    by 2^-40: the scene's winding numbers the same bits."""
    v, f = teapot()
    place = np.zeros((2, 3, 4))
    place[:, :, :3] = np.eye(3)
    place[1, :, 3] = [4.0, 0, 0]

    def scene(vv, ff, k):
        pl = place.copy()
        pl[:, :, 3] *= 2.0 ** k
        return lbvh.Scene([lbvh.build(vv, ff)], [0, 0], pl)
    p = invariance.winding_points(np.concatenate([v, v + np.float32([4, 0, 0])]), f, 800, 7)
    base = scene(v, f, 0).winding_numbers(p)
    assert np.abs(base).max() > 0.9                  # points inside the teapots
    for corners, k, sign in (((1, 2, 0), 0, 1), ((0, 2, 1), 0, -1), ((0, 1, 2), -40, 1)):
        other = scene(np.ldexp(v, k).astype(np.float32), np.ascontiguousarray(f[:, corners]), k)
        got = other.winding_numbers(np.ldexp(p, k).astype(np.float32))
        assert np.array_equal(got.view(np.uint32), (sign * base).view(np.uint32)), (corners, k)
