"""Ray queries (kernels/traverse.cl) against the float64 brute-force oracle (lbvh/oracle.py).

Bound on t: with u = 2^-24, the kernel's t may differ from the oracle's by
    |t_kernel - t_oracle| * |cos a| <= 16 u (t_oracle + s)
where a is the angle between the ray and the normal of the hit triangle and
s = (scene extent + max |origin component|) / |d| is the size of the numbers
the float32 test subtracts; the 1 / |cos a| factor is the conditioning of a
grazing hit. Observed: at most 2 u on these scenes, grazing rays included.
"""
from __future__ import annotations

import functools

import numpy as np
import pyopencl as cl
import pytest

import lbvh
from conftest import random_soup, shared_mesh, shipped_mesh
from lbvh.queries import traverse as tr
from lbvh.layout import is_leaf, make_nodes, node_depths
from lbvh.metrics.error_bound import t_bound  # the bound of the module docstring
from lbvh.verification.oracle import brute_force, hits_on
from lbvh.queries.wide import WIDTHS, read_records
from lbvh.verification import hard_cases


# -- scenes, trees and rays ----------------------------------------------------------

def _degenerate_mix():
    """Random triangles plus zero-area ones: a repeated index, repeated coordinates, collinear."""
    v, f = random_soup(200, seed=5)
    extra_v = np.float32([[0.2, 0.2, 0.5], [0.8, 0.7, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5],
                          [0.25, 0.5, 0.375], [0.5, 0.75, 0.625], [0.75, 1.0, 0.875]])
    base = len(v)
    extra_f = np.uint32([[base, base + 1, base], [base + 2, base + 3, base + 1],
                         [base + 4, base + 5, base + 6]])
    return np.vstack([v, extra_v]), np.vstack([f, extra_f])


SCENES = {
    "cornell": lambda: shipped_mesh("cornell_box_gkit.obj"),
    "suzanne": lambda: shipped_mesh("suzanne.obj"),
    "teapot": lambda: shipped_mesh("teapot.obj"),
    "soup": lambda: random_soup(600, seed=3),
    "degenerate": _degenerate_mix,
}


@functools.lru_cache(maxsize=None)
def scene(name):
    return SCENES[name]()


def median_split_tree(v, f, leaf_size=4):
    """A host-built tree (top-down median split, up to ``leaf_size`` triangles per
    leaf, preorder numbering) in the project's layout."""
    tri = v[f]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    centre = 0.5 * (lo + hi)
    lower, upper, children, ranges, order = [], [], [], [], []

    def node(prims):
        i = len(lower)
        lower.append(lo[prims].min(axis=0))
        upper.append(hi[prims].max(axis=0))
        children.append([-1, -1])
        ranges.append([0, 0])
        if len(prims) <= leaf_size:
            ranges[i] = [len(order), len(prims)]
            order.extend(prims.tolist())
            return i
        axis = int(np.argmax(centre[prims].max(axis=0) - centre[prims].min(axis=0)))
        prims = prims[np.argsort(centre[prims, axis], kind="stable")]
        half = len(prims) // 2
        left = node(prims[:half])
        children[i] = [left, node(prims[half:])]
        return i

    node(np.arange(len(f)))
    return make_nodes(np.array(lower), np.array(upper), np.array(children), np.array(ranges)), \
        np.array(order, np.int32)


TREES = ("lbvh30", "lbvh63", "lbvh_collapse", "sah", "host_median", "host_one_leaf")


@functools.lru_cache(maxsize=None)
def tree(scene_name, kind):
    v, f = scene(scene_name)
    if kind == "lbvh30":
        return lbvh.build(v, f, key_bits=30)
    if kind == "lbvh63":
        return lbvh.build(v, f, key_bits=63)
    if kind == "lbvh_collapse":      # leaves of several triangles
        return lbvh.build(v, f, collapse=True)
    if kind == "sah":                # the serial SAH reference, uploaded with from_arrays
        return lbvh.build(v, f, builder="sah")
    if kind == "host_median":
        nodes, order = median_split_tree(v, f)
    else:  # every triangle in one leaf, the root
        nodes = make_nodes(v[f].min(axis=(0, 1))[None], v[f].max(axis=(0, 1))[None],
                           [[-1, -1]], [[0, len(f)]])
        order = np.arange(len(f), dtype=np.int32)
    bvh = lbvh.BVH.from_arrays(nodes, order, 0, v, f, builder=kind)
    bvh.validate()
    return bvh


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def camera_rays(v, rng, n):
    """Rays from a sphere around the scene towards random points of its box."""
    lo, hi = v.min(0), v.max(0)
    centre, ext = (lo + hi) / 2, float((hi - lo).max())
    o = centre + _unit(rng.normal(size=(n, 3))) * 2 * ext
    return o.astype(np.float32), (lo + rng.random((n, 3)) * (hi - lo) - o).astype(np.float32)


def interior_rays(v, rng, n):
    """Rays from random points of the scene's box in random directions."""
    lo, hi = v.min(0), v.max(0)
    return (lo + rng.random((n, 3)) * (hi - lo)).astype(np.float32), \
        rng.normal(size=(n, 3)).astype(np.float32)


def axis_rays(v, rng, n):
    """Axis-aligned rays with every sign pattern of their zero components (+0.0 and -0.0)."""
    lo, hi = v.min(0), v.max(0)
    o = (lo - 0.1 * (hi - lo) + rng.random((n, 3)) * 1.2 * (hi - lo)).astype(np.float32)
    k = rng.integers(0, 3, n)
    d = np.where(rng.random((n, 3)) < 0.5, np.float32(0.0), np.float32(-0.0))
    d[np.arange(n), k] = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    return o, d.astype(np.float32)


def face_rays(bvh, rng, n):
    """Rays starting on a face of a node's box, a third of them lying in the face's plane
    (zero direction component along the face's axis: the 0 * inf = NaN case)."""
    nodes = rng.integers(0, bvh.tree.num_nodes, n)
    lo, hi = bvh.nodes["lower"][nodes], bvh.nodes["upper"][nodes]
    o = lo + rng.random((n, 3), dtype=np.float32) * (hi - lo)
    k = rng.integers(0, 3, n)
    rows = np.arange(n)
    o[rows, k] = np.where(rng.random(n) < 0.5, lo[rows, k], hi[rows, k])
    d = rng.normal(size=(n, 3)).astype(np.float32)
    flat = rng.random(n) < 1 / 3
    d[rows[flat], k[flat]] = np.where(rng.random(flat.sum()) < 0.5, 0.0, -0.0)
    return o.astype(np.float32), d


def grazing_rays(v, f, rng, n):
    """Rays at 0.05 to 2 degrees to a triangle's plane, aimed at a point inside it."""
    tri = v[f[rng.integers(0, len(f), n)]].astype(np.float64)
    p = (rng.dirichlet([1, 1, 1], n)[:, :, None] * tri).sum(1)
    normal = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) + 1e-30)
    tangent = _unit(tri[:, 1] - tri[:, 0] + 1e-30)
    angle = np.radians(rng.uniform(0.05, 2, n))[:, None]
    d = np.cos(angle) * tangent - np.sin(angle) * normal
    return (p - d * float(np.ptp(v, axis=0).max()) / 2).astype(np.float32), d.astype(np.float32)


@functools.lru_cache(maxsize=None)
def ray_set(scene_name, n=600, seed=0):
    v, f = scene(scene_name)
    rng = np.random.default_rng(seed)
    bvh = tree(scene_name, "lbvh30")
    parts = [camera_rays(v, rng, n), interior_rays(v, rng, n), axis_rays(v, rng, n),
             face_rays(bvh, rng, n), grazing_rays(v, f, rng, n // 2)]
    o = np.concatenate([p[0] for p in parts])
    d = np.concatenate([p[1] for p in parts])
    return o, d


@functools.lru_cache(maxsize=None)
def oracle(scene_name):
    v, f = scene(scene_name)
    o, d = ray_set(scene_name)
    return brute_force(v, f, o, d)


# -- comparison with the oracle --------------------------------------------------------

def assert_genuine_hits(v, f, o, d, got, slack):
    """Each hit's barycentrics name a point of its triangle that is on the ray:
    (1-u-v) p0 + u p1 + v p2 == o + t d within the t bound (all rays hit)."""
    tri = v[f[got.prim]].astype(np.float64)
    uu, vv = got.u[:, None].astype(np.float64), got.v[:, None].astype(np.float64)
    point = (1 - uu - vv) * tri[:, 0] + uu * tri[:, 1] + vv * tri[:, 2]
    ray_point = o + got.t[:, None].astype(np.float64) * d
    dn = np.linalg.norm(d, axis=1)
    gap = np.linalg.norm(point - ray_point, axis=1)
    assert (gap <= slack * dn + 1e-6 * np.abs(tri).max()).all()
    assert (got.u >= 0).all() and (got.v >= 0).all() and (got.u + got.v <= 1 + 1e-6).all()


def _subset(hits, keep):
    return tr.Hits(*(getattr(hits, k)[keep] for k in ("t", "prim", "u", "v", "overflow")), 0)


def check_boundary_rays(v, f, o, d, got, ref, tmin, tmax):
    """Rays with a hit at an end of [tmin, tmax] within the bound (a ray starting on a
    triangle: t = 0 up to rounding, on either side of it). Either result is right; the
    kernel's must be a genuine hit, not before the oracle's, and if it passed over the
    boundary triangle it must be the oracle's next hit."""
    h = got.hit
    assert_genuine_hits(v, f, o[h], d[h], _subset(got, h),
                        t_bound(v, f, o[h], d[h], got.t[h], got.prim[h]))
    s_ref = t_bound(v, f, o, d, np.where(ref.hit, ref.t, 0), ref.prim)
    assert (got.t >= np.minimum(ref.t, tmin + s_ref) - s_ref).all()
    passed = ref.hit & (ref.t - tmin <= s_ref) & (got.t > tmin + s_ref)
    if passed.any():
        nxt = brute_force(v, f, o[passed], d[passed], (tmin + 2 * s_ref)[passed], tmax[passed])
        assert (nxt.hit == got.hit[passed]).all()
        both = nxt.hit
        slack = t_bound(v, f, o[passed][both], d[passed][both], nxt.t[both], nxt.prim[both])
        assert (np.abs(got.t[passed][both] - nxt.t[both]) <= 2 * slack).all()


def assert_matches_oracle(v, f, o, d, got, ref, tmin=0.0, tmax=np.inf):
    """Same hit/miss, t within the bound, same triangle except on ties, consistent
    barycentrics; rays with a hit at an end of [tmin, tmax] go to check_boundary_rays."""
    tmin = np.broadcast_to(np.asarray(tmin, np.float64), (len(o),))
    tmax = np.broadcast_to(np.asarray(tmax, np.float64), (len(o),))
    t_got, t_ref = np.where(got.hit, got.t, 0.0), np.where(ref.hit, ref.t, 0.0)
    s_got = t_bound(v, f, o, d, t_got, got.prim)
    s_ref = t_bound(v, f, o, d, t_ref, ref.prim)
    boundary = ((got.hit & ((t_got - tmin <= s_got) | (tmax - t_got <= s_got)))
                | (ref.hit & ((t_ref - tmin <= s_ref) | (tmax - t_ref <= s_ref))))
    if boundary.any():
        b = boundary
        check_boundary_rays(v, f, o[b], d[b], _subset(got, b), _subset(ref, b), tmin[b], tmax[b])
        assert boundary.mean() < 0.15
        keep = ~boundary
        got, ref, o, d = _subset(got, keep), _subset(ref, keep), o[keep], d[keep]
    bad = np.flatnonzero(got.hit != ref.hit)
    assert len(bad) == 0, (f"{len(bad)} rays disagree on hit/miss, first ray {bad[0]}: "
                           f"o={o[bad[0]].tolist()} d={d[bad[0]].tolist()} kernel prim "
                           f"{got.prim[bad[0]]} t {got.t[bad[0]]}, oracle prim {ref.prim[bad[0]]} "
                           f"t {ref.t[bad[0]]}")
    hit = np.flatnonzero(ref.hit)
    slack = t_bound(v, f, o[hit], d[hit], ref.t[hit].astype(np.float64), ref.prim[hit])
    err = np.abs(got.t[hit].astype(np.float64) - ref.t[hit])
    worst = int(np.argmax(err / slack))
    assert (err <= slack).all(), (f"t off by {err[worst]:.3g} > {slack[worst]:.3g} on ray "
                                  f"{hit[worst]} (t = {ref.t[hit[worst]]})")
    # A different triangle only where the two tie: the oracle hits the kernel's
    # triangle too, at the same t within the bound.
    other = hit[got.prim[hit] != ref.prim[hit]]
    if len(other):
        t_other, _, _ = hits_on(v, f, o[other], d[other], got.prim[other])
        assert (np.abs(t_other - ref.t[other]) <= t_bound(v, f, o[other], d[other],
                                                           ref.t[other], ref.prim[other])).all()
    assert_genuine_hits(v, f, o[hit], d[hit], _subset(got, hit), slack)
    assert np.isinf(got.t[~ref.hit]).all() and (got.prim[~ref.hit] == -1).all()


@pytest.mark.parametrize("kind", TREES)
@pytest.mark.parametrize("name", sorted(SCENES))
def test_closest_hit_matches_the_oracle(name, kind):
    v, f = scene(name)
    o, d = ray_set(name)
    bvh = tree(name, kind)
    got = bvh.intersect(o, d)
    assert got.overflow_count == 0 and not got.overflow.any()
    assert got.t.dtype == np.float32 and got.prim.dtype == np.int32 and got.u.dtype == np.float32
    assert_matches_oracle(v, f, o, d, got, oracle(name))


@pytest.mark.parametrize("name", sorted(SCENES))
def test_any_hit_agrees_with_closest_hit(name):
    o, d = ray_set(name)
    bvh = tree(name, "lbvh30")
    closest = bvh.intersect(o, d)
    for kind in ("lbvh30", "host_median"):
        occ = tree(name, kind).occluded(o, d)
        assert occ.dtype == bool and (occ == closest.hit).all()


@pytest.mark.parametrize("kind", ["lbvh30", "lbvh_collapse", "sah", "host_median"])
@pytest.mark.parametrize("name", sorted(SCENES))
def test_global_order_gives_the_same_hits(name, kind):
    """order="global" (nearest pending node first, Kay & Kajiya) against the oracle, and
    against the ordered traversal: the same t on every ray, the same triangle but for ties."""
    v, f = scene(name)
    o, d = ray_set(name)
    bvh = tree(name, kind)
    got = bvh.intersect(o, d, order="global", counters=True)
    assert got.overflow_count == 0
    assert_matches_oracle(v, f, o, d, got, oracle(name))
    ordered = bvh.intersect(o, d, counters=True)
    assert np.array_equal(got.t, ordered.t)
    tie = got.prim != ordered.prim
    if tie.any():
        # the other triangle is hit at the same t within the stated bound; a relative
        # tolerance alone fails at t near 0 (a ray leaving a surface: on the H200 the
        # device's t was 1.2e-8 where float64 gives -5.7e-17)
        t_other, _, _ = hits_on(v, f, o[tie], d[tie], ordered.prim[tie])
        bound = t_bound(v, f, o[tie], d[tie], got.t[tie].astype(np.float64), ordered.prim[tie])
        assert (np.abs(t_other - got.t[tie]) <= bound).all()
    # best first never tests more triangles than it must: a node is entered only when no
    # pending node is nearer, so it enters no node that the ordered walk skips for good
    assert got.tris_tested.sum() <= ordered.tris_tested.sum() * 1.05 + 10


def test_global_order_heap_holds_the_frontier():
    """Best first keeps a whole frontier pending: on Sponza's median tree the ordered
    stack's size overflowed 0.4% of random rays; the heap gets more (and the same t)."""
    v, f = shared_mesh("crytek_sponza.obj")
    bvh = lbvh.build(v, f, builder="median")
    rng = np.random.default_rng(0)
    lo, hi = v.min(0), v.max(0)
    o = (lo + (hi - lo) * rng.uniform(0.2, 0.8, (50_000, 3))).astype(np.float32)
    d = rng.normal(size=(50_000, 3)).astype(np.float32)
    small = bvh.intersect(o, d, order="global", stack_size=tr.stack_size_for(bvh.query_data))
    assert small.overflow_count > 0            # the case this guards
    got = bvh.intersect(o, d, order="global")
    assert got.overflow_count == 0
    assert np.array_equal(got.t, bvh.intersect(o, d).t)


def test_global_order_overflow_is_flagged():
    bvh, v, f = chain_tree(40)
    o = np.float32([[41, 0, 0.5]] * 2)
    d = np.float32([[-1, 0, 0]] * 2)
    assert bvh.intersect(o, d, order="global").overflow_count == 0
    small = bvh.intersect(o, d, order="global", stack_size=4)
    assert small.overflow.all()


def test_any_hit_returns_a_real_hit_and_overflow_info():
    v, f = scene("teapot")
    o, d = ray_set("teapot")
    full = tree("teapot", "lbvh30").occluded(o, d, return_hits=True, counters=True)
    ref = oracle("teapot")
    assert (full.hit == ref.hit).all() and full.overflow_count == 0
    # the hit it found is a genuine hit, at or behind the closest one
    t_check, _, _ = hits_on(v, f, o[full.hit], d[full.hit], full.prim[full.hit])
    assert np.allclose(t_check, full.t[full.hit], rtol=1e-4, atol=1e-6)
    slack = t_bound(v, f, o[full.hit], d[full.hit], ref.t[full.hit], ref.prim[full.hit])
    assert (full.t[full.hit] >= ref.t[full.hit] - slack).all()


def _matches_float32_twin(got, v, f, o, d):
    """The kernel's hits against its float32 twin: the same rays hit, the same
    triangle for at least 98% of them (another only on an exact tie), and there
    t, u, v bit for bit. Returns the twin's hits and the rays of the same triangle."""
    twin = brute_force(v, f, o, d, dtype=np.float32)
    assert (got.hit == twin.hit).all()
    same = got.hit & (got.prim == twin.prim)
    assert same.sum() >= 0.98 * got.hit.sum()
    for field in ("t", "u", "v"):
        assert (getattr(got, field)[same] == getattr(twin, field)[same]).all(), field
    return twin, same


def test_kernel_equals_its_float32_twin_bit_for_bit(ctx):
    """Where arithmetic is exact: same triangle -> same t, u, v bits (FP_CONTRACT OFF,
    correctly rounded division)."""
    if not ctx.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
        pytest.skip("division is not correctly rounded on this device")
    for name in ("suzanne", "cornell"):
        v, f = scene(name)
        o, d = ray_set(name)
        got = tree(name, "lbvh63").intersect(o, d)
        twin, same = _matches_float32_twin(got, v, f, o, d)
        # another triangle only where the float32 twin's test decides a hit otherwise
        # than the kernel's exact one: then at the same t
        assert (got.t[got.hit & ~same] == twin.t[got.hit & ~same]).all()


def test_moller_trumbore_variant_agrees_away_from_edges():
    v, f = scene("suzanne")
    o, d = ray_set("suzanne")
    bvh = tree("suzanne", "lbvh30")
    ref = oracle("suzanne")
    got = bvh.intersect(o, d, triangle_test="moller")
    agree = got.hit == ref.hit
    assert agree.mean() > 0.995       # leaks are possible only at edges (test_watertight)
    both = got.hit & ref.hit & (got.prim == ref.prim)
    slack = t_bound(v, f, o[both], d[both], ref.t[both], ref.prim[both])
    assert (np.abs(got.t[both] - ref.t[both]) <= 4 * slack).all()


def test_tmin_tmax_are_respected():
    v, f = scene("teapot")
    o, d = ray_set("teapot")
    bvh = tree("teapot", "lbvh30")
    got = bvh.intersect(o, d)
    hit = got.hit
    t = got.t[hit]
    below = np.nextafter(t, np.float32(0))
    # both ends of [tmin, tmax] are inclusive, to the bit: the kernel's own t is
    # found again with tmin = t or tmax = t, and nothing lies before it
    assert bvh.occluded(o[hit], d[hit], 0.0, t).all()
    assert not bvh.occluded(o[hit], d[hit], 0.0, below).any()
    again = bvh.intersect(o[hit], d[hit], t, t)
    assert (again.t == t).all()
    past = bvh.intersect(o[hit], d[hit], np.nextafter(t, np.float32(np.inf)))
    assert (past.t > t).all()
    # random intervals, compared with the oracle under the same intervals
    rng = np.random.default_rng(7)
    tmin = (rng.random(len(o)) * np.where(got.hit, got.t * 1.5, 1.0)).astype(np.float32)
    tmax = (tmin + rng.random(len(o)) * 2 * float(np.ptp(v, axis=0).max())).astype(np.float32)
    ranged = bvh.intersect(o, d, tmin, tmax)
    assert ((ranged.t >= tmin) & (ranged.t <= tmax))[ranged.hit].all()
    assert_matches_oracle(v, f, o, d, ranged, brute_force(v, f, o, d, tmin, tmax), tmin, tmax)


def test_zero_components_and_flat_boxes_on_the_cornell_box():
    v, f = scene("cornell")
    bvh = tree("cornell", "lbvh30")
    flat = (bvh.nodes["upper"] == bvh.nodes["lower"]).any(axis=1) & is_leaf(bvh.nodes)
    assert flat.sum() >= 10          # the walls are axis-aligned: their leaves are flat boxes
    # rays from the middle of the room along each axis, with +0.0 and -0.0 elsewhere
    o, d = [], []
    for k in range(3):
        for sign in (1.0, -1.0):
            for zeros in ((0.0, 0.0), (-0.0, 0.0), (0.0, -0.0), (-0.0, -0.0)):
                dir_ = list(zeros)
                dir_.insert(k, sign)
                o.append([0.0, 1.0, 0.0])
                d.append(dir_)
    # rays lying in a wall's plane, starting on it (origin on a slab plane, zero component)
    for y in (0.0, 1.99):
        for dx, dz in ((1.0, -0.0), (-0.0, 1.0), (-1.0, 0.0), (0.6, -0.8)):
            o.append([0.1, y, 0.2])
            d.append([dx, 0.0, dz])
            o.append([0.1, y, 0.2])
            d.append([dx, -0.0, dz])
    o, d = np.float32(o), np.float32(d)
    for kind in TREES:
        got = tree("cornell", kind).intersect(o, d)
        assert_matches_oracle(v, f, o, d, got, brute_force(v, f, o, d))
        # the sign of a zero component changes nothing
        assert (got.t[:24].reshape(6, 4) == got.t[:24:4, None]).all()
        assert (got.prim[:24].reshape(6, 4) == got.prim[:24:4, None]).all()
        assert got.hit[:24].sum() == 20   # the room is open towards +z only


def test_counters_are_sane():
    o, d = ray_set("suzanne")
    bvh = tree("suzanne", "lbvh30")
    plain = bvh.intersect(o, d)
    assert plain.nodes_visited is None and plain.tris_tested is None
    got = bvh.intersect(o, d, counters=True)
    assert (got.t == plain.t).all() and (got.prim == plain.prim).all()
    assert got.nodes_visited.dtype == np.int32 and got.tris_tested.dtype == np.int32
    assert (got.nodes_visited >= 1).all() and (got.nodes_visited <= bvh.tree.num_nodes).all()
    assert (got.tris_tested[got.hit] >= 1).all() and (got.tris_tested >= 0).all()
    # every triangle test follows a leaf visit, one triangle per leaf in an LBVH
    assert (got.tris_tested <= got.nodes_visited).all()
    # one leaf holding everything: one node, every triangle tested, on every ray that enters it
    one = tree("suzanne", "host_one_leaf").intersect(o, d, counters=True)
    assert (one.nodes_visited == 1).all()
    assert set(np.unique(one.tris_tested)) <= {0, len(scene("suzanne")[1])}
    # any hit: the same rays hit; each stops at its first triangle hit, having visited the
    # leaf of every triangle it tested (its children in record order, not nearest first,
    # so per ray it may test more triangles than the closest-hit walk)
    any_ = bvh.occluded(o, d, counters=True, return_hits=True)
    assert (any_.hit == got.hit).all()
    assert (any_.tris_tested[any_.hit] >= 1).all()
    assert (any_.tris_tested <= any_.nodes_visited).all()
    assert (any_.nodes_visited >= 1).all() and (any_.nodes_visited <= bvh.tree.num_nodes).all()


def chain_tree(depth):
    """Triangles in the planes x = 0..depth in a chain: internal node i has the leaf of
    triangle i on the left and node i+1 on the right. Every triangle covers the point
    (y, z) = (0, 0.5) except the last, which only shares its box."""
    k = np.arange(depth + 1, dtype=np.float32)
    m1, p3 = np.full_like(k, -1), np.full_like(k, 3)
    third = np.where(k < depth, m1, p3)
    v = np.stack([np.stack([k, m1, m1], 1), np.stack([k, p3, m1], 1),
                  np.stack([k, third, p3], 1)], 1).reshape(-1, 3)
    f = np.arange(3 * (depth + 1), dtype=np.uint32).reshape(-1, 3)
    n_int = depth
    lower, upper, children, ranges = [], [], [], []
    for i in range(n_int):                       # internal nodes 0 .. depth-1
        lower.append([i, -1, -1])
        upper.append([depth, 3, 3])
        right = i + 1 if i + 1 < n_int else n_int + depth
        children.append([n_int + i, right])
        ranges.append([0, 0])
    for j in range(depth + 1):                   # leaves depth .. 2*depth
        lower.append([j, -1, -1])
        upper.append([j, 3, 3])
        children.append([-1, -1])
        ranges.append([j, 1])
    nodes = make_nodes(np.float32(lower), np.float32(upper), np.array(children), np.array(ranges))
    bvh = lbvh.BVH.from_arrays(nodes, np.arange(depth + 1, dtype=np.int32), 0, v, f,
                               builder="chain")
    return bvh, v, f


def test_stack_overflow_is_reported_never_silent():
    depth = 40
    bvh, v, f = chain_tree(depth)
    bvh.validate()
    assert int(node_depths(bvh.tree.read("parent"), bvh.root).max()) == depth
    # -x rays enter the chain's subtree before each level's leaf: every level pushes its
    # leaf, and the closest hit (triangle depth-1) is pushed last, by the deepest level
    o = np.float32([[depth + 1, 0, 0.5]] * 3 + [[-1, 0, 0.5]] * 3)
    d = np.float32([[-1, 0, 0]] * 3 + [[1, 0, 0]] * 3)
    tmin = np.float32([0, 1.5, 20.5, 0, 1.5, 20.5])
    ref = brute_force(v, f, o, d, tmin)
    auto = bvh.intersect(o, d, tmin)
    assert tr.stack_size_for(bvh.query_data) >= depth
    assert auto.overflow_count == 0
    assert_matches_oracle(v, f, o, d, auto, ref, tmin)
    small = bvh.intersect(o, d, tmin, stack_size=8)
    # the -x rays need a stack of about depth entries: flagged; the +x rays need one
    assert small.overflow.tolist() == [True] * 3 + [False] * 3
    assert small.overflow_count == 3
    ok = ~small.overflow
    assert (small.prim[ok] == ref.prim[ok]).all()
    # the ray whose hit was in a dropped subtree is wrong, and flagged
    assert ref.prim[0] == depth - 1 and small.prim[0] != ref.prim[0] and small.overflow[0]
    # any hit: a ray is hit or flagged, never silently missed (its wide walk takes the
    # chain's leaves in record order, ahead of the deeper levels, and may not overflow)
    occ = bvh.occluded(o, d, tmin, stack_size=8, return_hits=True)
    assert (occ.hit | occ.overflow).all()
    # the binary walk (nearest first) of the -x rays overflows, and says so
    binary = lbvh.BVH.from_arrays(bvh.nodes, bvh.prim_order, bvh.root, v, f, builder="chain")
    assert not binary.query_data.wide_records(max_bytes=0).packed
    occ = binary.occluded(o, d, tmin, stack_size=8, return_hits=True)
    assert occ.overflow.tolist()[:3] == [True] * 3 and (occ.hit | occ.overflow).all()


def test_deep_trees_get_a_deeper_stack():
    bvh, v, f = chain_tree(150)
    assert tr.stack_size_for(bvh.query_data) >= 150
    o = np.float32([[151, 0, 0.5]])
    d = np.float32([[-1, 0, 0]])
    got = bvh.intersect(o, d, 2.5)
    assert got.overflow_count == 0 and got.prim[0] == 148


def cyclic_tree():
    """One triangle under node 0, which lists itself as its right child: not a tree."""
    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    f = np.uint32([[0, 1, 2]])
    nodes = make_nodes(np.float32([[0, 0, 0], [0, 0, 0]]), np.float32([[1, 1, 0], [1, 1, 0]]),
                       np.array([[1, 0], [-1, -1]]), np.array([[0, 0], [0, 1]]))
    return lbvh.BVH.from_arrays(nodes, np.int32([0]), 0, v, f, builder="cyclic", validate=False)


def test_kernel_terminates_on_a_cyclic_tree_and_flags_nan_rays():
    # the visit limit stops the loop
    bvh = cyclic_tree()
    # making wide records of it is refused, naming the node reached twice
    with pytest.raises(ValueError, match=r"node 0 is reached twice"):
        bvh.intersect(np.float32([[0.2, 0.2, 1]]), np.float32([[0, 0, -1]]))
    # through its binary nodes (the fallback of trees too large for records) it is traced
    assert not bvh.query_data.wide_records(max_bytes=0).packed
    got = bvh.intersect(np.float32([[0.2, 0.2, 1]]), np.float32([[0, 0, -1]]), stack_size=32,
                        counters=True)
    assert got.overflow[0] and got.nodes_visited[0] <= bvh.tree.num_nodes + 1
    # a NaN ray handed to the device entry directly (the host API refuses it) terminates
    good = tree("teapot", "lbvh30")
    rays = tr.check_rays(np.zeros((2, 3)), np.ones((2, 3)))
    rays.directions[0] = np.nan
    rays.origins[1] = np.nan
    out = tr.trace_buffers(good, tr.upload_rays(good.ctx, rays), counters=True)
    out.event.wait()
    counts = np.empty((2, 2), np.int32)
    cl.enqueue_copy(good.ctx.queue, counts, out.counters, is_blocking=True)
    flags = np.empty(2, np.int32)
    cl.enqueue_copy(good.ctx.queue, flags, out.flags, is_blocking=True)
    # not traced (a NaN distance passes every slab test) and flagged, a miss
    assert (counts[:, 0] == 1).all() and (flags == tr.FLAG_NAN_RAY).all()
    assert (tr.read_hits(good.ctx, out)[3].view(np.int32) == -1).all()


def test_batches_float64_input_and_empty_input():
    o, d = ray_set("suzanne")
    bvh = tree("suzanne", "lbvh30")
    whole = bvh.intersect(o, d)
    batched = bvh.intersect(o.astype(np.float64), d.astype(np.float64), batch_size=777)
    for field in ("t", "prim", "u", "v"):
        assert (getattr(whole, field) == getattr(batched, field)).all()
    programs = bvh.ctx.compiled_programs()
    bvh.intersect(o[:10], d[:10])
    assert bvh.ctx.compiled_programs() == programs      # compiled once per context
    empty = bvh.intersect(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0 and empty.overflow_count == 0
    assert bvh.occluded(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_degenerate_triangles_are_never_hit():
    v, f = scene("degenerate")
    bvh = tree("degenerate", "lbvh30")
    zero_area = np.arange(len(f) - 3, len(f))
    # aim at vertices, edge midpoints and inner points of the zero-area triangles
    targets = np.concatenate([v[f[zero_area]].reshape(-1, 3),
                              v[f[zero_area]].mean(axis=1),
                              0.5 * (v[f[zero_area, 0]] + v[f[zero_area, 2]])])
    rng = np.random.default_rng(2)
    o = (targets[None] + _unit(rng.normal(size=(20, 1, 3))) * 2).reshape(-1, 3).astype(np.float32)
    d = (np.tile(targets, (20, 1)) - o).astype(np.float32)
    for test in ("watertight", "moller"):
        got = bvh.intersect(o, d, triangle_test=test, tmax=1.5)
        assert not np.isin(got.prim, zero_area).any()


BAD_RAYS = [
    (dict(origins=[[0, 0, 0], [np.nan, 0, 0]]), "origins: ray 1"),
    (dict(origins=[[0, 0, 0], [np.inf, 0, 0]]), "origins: ray 1"),
    (dict(origins=np.array([[0, 0, 0], [1e300, 0, 0]])), "origins: ray 1"),
    (dict(directions=[[1, 0, 0], [0, 0, np.nan]]), "directions: ray 1"),
    (dict(directions=[[1, 0, 0], [0, 0, 0]]), "directions: ray 1 has a zero-length"),
    (dict(directions=[[1, 0, 0], [-0.0, 0, 0]]), "directions: ray 1 has a zero-length"),
    (dict(directions=np.array([[1, 0, 0], [1e-50, 0, 0]])), "directions: ray 1 has a zero-length"),
    (dict(tmin=[0, -1]), "tmin: ray 1 has a negative tmin"),
    (dict(tmin=[0, np.nan]), "tmin: ray 1 is NaN"),
    (dict(tmax=[np.nan, 1]), "tmax: ray 0 is NaN"),
    (dict(tmin=np.inf, tmax=np.inf), "tmin: ray 0 has an infinite tmin"),
    (dict(tmin=[0, 3], tmax=[1, 2]), r"tmin/tmax: ray 1 has tmin 3.0 > tmax 2.0"),
    (dict(origins=[[0, 0], [0, 0]]), r"origins: shape \(2, 2\)"),
    (dict(origins=[0, 0, 0]), r"origins: shape \(3,\)"),
    (dict(directions=[[1, 0, 0]]), "directions: 1 rays, but origins has 2"),
    (dict(tmin=[0, 0, 0]), r"tmin: shape \(3,\)"),
    (dict(origins=np.array([[0, 0, 0], [0, 0, 0]], dtype=complex)), "origins: dtype complex128"),
    (dict(directions=[["a", 0, 0], [1, 0, 0]]), "directions: dtype"),
]


@pytest.mark.parametrize("bad, message", BAD_RAYS)
def test_bad_rays_raise_value_error_naming_the_first(bad, message):
    bvh = tree("cornell", "lbvh30")
    args = dict(origins=[[0, 1, 0], [0, 1, 0]], directions=[[1, 0, 0], [0, 1, 0]], tmin=0.0,
                tmax=np.inf)
    args.update(bad)
    with pytest.raises(ValueError, match=message):
        bvh.intersect(args["origins"], args["directions"], args["tmin"], args["tmax"])
    with pytest.raises(ValueError, match=message):
        bvh.occluded(args["origins"], args["directions"], args["tmin"], args["tmax"])


@pytest.mark.parametrize("option, message", [
    (dict(triangle_test="fast"), "triangle_test"), (dict(batch_size=0), "batch_size"),
    (dict(stack_size=0), "stack_size"), (dict(order="random"), "order: 'random'")])
def test_bad_options_raise_value_error(option, message):
    bvh = tree("cornell", "lbvh30")
    with pytest.raises(ValueError, match=message):
        bvh.intersect([[0, 1, 0]], [[1, 0, 0]], **option)


def test_oracle_culling_never_changes_a_result():
    v, f = scene("suzanne")
    o, d = ray_set("suzanne")
    pick = np.random.default_rng(4).choice(len(o), 300, replace=False)
    full = brute_force(v, f, o[pick], d[pick], cull=False)
    culled = oracle("suzanne")
    for field in ("t", "prim", "u", "v"):
        assert (getattr(full, field) == getattr(culled, field)[pick]).all()


def test_conference_zero_area_triangles_are_never_hit():
    """The conference room ships 53,627 zero-area triangles: rays aimed at them hit
    their neighbours or nothing, exactly as the oracle says."""
    v, f = shared_mesh("conference.obj")
    tri = v[f].astype(np.float64)
    zero = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) == 0
    rng = np.random.default_rng(9)
    aim = np.flatnonzero(zero)[rng.choice(zero.sum(), 300, replace=False)]
    targets = tri[aim].mean(axis=1)
    o = (targets + _unit(rng.normal(size=(300, 3))) * 0.05 * float(np.ptp(v, axis=0).max()))
    o, d = o.astype(np.float32), (targets - o).astype(np.float32)
    bvh = lbvh.build(v, f)
    got = bvh.intersect(o, d)
    assert got.hit.any() and not zero[got.prim[got.hit]].any()
    assert_matches_oracle(v, f, o, d, got, brute_force(v, f, o, d))


# -- wide records and the binary fallback ------------------------------------------

@pytest.mark.parametrize("kind", ["lbvh30", "lbvh_collapse", "sah", "host_median"])
def test_faces_in_slot_order_equal_their_numpy_twin(kind):
    bvh = tree("teapot", kind)
    got = np.empty((bvh.mesh.num_prims, 3), np.uint32)
    cl.enqueue_copy(bvh.ctx.queue, got, bvh.query_data.slot_faces(), is_blocking=True)
    assert np.array_equal(got, bvh.faces[bvh.prim_order])


@pytest.mark.parametrize("kind", ["lbvh30", "lbvh_collapse", "sah", "host_median"])
def test_triangles_in_slot_order_equal_their_numpy_twin(kind):
    from lbvh.queries.traverse import order_triangles_numpy
    bvh = tree("teapot", kind)
    got = np.empty((bvh.tree.num_prims, 3, 3), np.float32)
    cl.enqueue_copy(bvh.ctx.queue, got, bvh.query_data.slot_triangles(), is_blocking=True)
    want = order_triangles_numpy(bvh.vertices, bvh.faces, bvh.prim_order)
    assert want.shape == (bvh.tree.num_prims, 3, 3)
    assert np.array_equal(got.view(np.uint32), want.view(np.uint32))


@pytest.mark.parametrize("name", ["zero_area_mix", "slivers", "one_point", "far_from_origin",
                                  "far_from_origin_1e7"])
def test_slot_triangles_make_the_degenerate_ones_points(name):
    """order_triangles writes a degenerate triangle (ray_triangle.h degenerate(), the
    float32 twin traverse.degenerate_triangles) as its first corner three times and every
    other one as it is, bit for bit its twin's; the every-hit walk, which reads them
    and so leaves the degenerate test out (DEGENERATE_TEST=0), finds the hits of the
    twin, which keeps it."""
    from lbvh.queries.traverse import order_triangles_numpy
    from lbvh.verification.oracle import all_hits_brute, degenerate_triangles
    c = hard_cases.CASES[name]()
    bvh = lbvh.build(c.vertices, c.faces)
    got = np.empty((bvh.tree.num_prims, 3, 3), np.float32)
    cl.enqueue_copy(bvh.ctx.queue, got, bvh.query_data.slot_triangles(), is_blocking=True)
    want = order_triangles_numpy(bvh.vertices, bvh.faces, bvh.prim_order)
    assert np.array_equal(got.view(np.uint32), want.view(np.uint32))
    slot_faces = bvh.faces[bvh.prim_order]
    with np.errstate(all="ignore"):
        point = degenerate_triangles(bvh.vertices, slot_faces, np.float32)
    assert point.any()
    plain = bvh.vertices[slot_faces]
    assert np.array_equal(got[~point], plain[~point])
    assert (got[point] == plain[point][:, :1]).all()
    # the rays of the case and rays at the triangles' corners: the twin's hits, which
    # keeps the degenerate test (oracle.all_hits_brute in float32)
    rng = np.random.default_rng(3)
    v64 = bvh.vertices.astype(np.float64)
    pick = rng.integers(0, len(v64), (3, 400))
    o2 = (v64[pick[0]] + v64[pick[1]]) / 2      # between two vertices, towards a third
    d2 = v64[pick[2]] - o2
    o = np.concatenate([c.origins[:400], o2]).astype(np.float32)
    d = np.concatenate([c.directions[:400], d2]).astype(np.float32)
    keep = (d != 0).any(axis=1) & np.isfinite(d).all(axis=1)
    o, d = o[keep], d[keep]
    twin = all_hits_brute(bvh.vertices, bvh.faces, o, d, dtype=np.float32)
    assert (twin.total.sum() > 0) == (not point.all())   # one_point: nothing to hit
    assert np.array_equal(bvh.count_hits(o, d), twin.total)
    every = bvh.all_hits(o, d)
    assert np.array_equal(every.offsets, twin.offsets) and np.array_equal(every.prim, twin.prim)
    assert np.array_equal(every.t, twin.t)


def _same_hits(a, b, v, f, o, d, context):
    """The same t bit for bit; the same triangle, or one hit at exactly that t too
    (rays through a shared edge: the first triangle met wins, and the order of the
    visits differs)."""
    assert (a.t == b.t).all() and (a.hit == b.hit).all(), context
    other = a.prim != b.prim
    assert other.sum() <= 0.02 * a.hit.sum(), context
    for hits in (a, b):
        t32, _, _ = hits_on(v, f, o[other], d[other], hits.prim[other], dtype=np.float32)
        assert (t32 == a.t[other]).all(), context
    same = ~other
    assert (a.u[same] == b.u[same]).all() and (a.v[same] == b.v[same]).all(), context


def test_traversal_through_the_nodes_equals_the_wide_records():
    """The fallback for trees whose records could exceed the largest device buffer
    (WIDE=0) and both record widths give the same hits, bit for bit, up to ties."""
    o, d = ray_set("teapot")
    v, f = scene("teapot")
    for kind in ("lbvh30", "sah", "host_median"):
        packed = tree("teapot", kind)
        plain = lbvh.BVH.from_arrays(packed.nodes, packed.prim_order, packed.root, v, f, builder=kind)
        assert not plain.query_data.wide_records(max_bytes=0).packed
        binary = plain.intersect(o, d, counters=True)
        for width in WIDTHS:
            four = lbvh.BVH.from_arrays(packed.nodes, packed.prim_order, packed.root, v, f,
                                        builder=kind)
            assert four.query_data.wide_records(width=width).packed
            got = four.intersect(o, d, counters=True)
            _same_hits(got, binary, v, f, o, d, (kind, width))
            assert (four.occluded(o, d) == plain.occluded(o, d)).all()
            # a wide record stands for up to width - 1 binary nodes
            assert got.nodes_visited.sum() < binary.nodes_visited.sum()


def test_refit_rewrites_the_wide_records_boxes():
    """Records copy the boxes: after a refit the next query must see the moved mesh.
    The records keep their lanes (one launch, no new records) and take the new boxes."""
    v, f = scene("suzanne")
    o, d = ray_set("suzanne")
    bvh = lbvh.build(v, f)
    before = bvh.intersect(o, d)
    first = bvh.query_data.wide_records()
    lanes_before = dev_lanes(bvh, first)
    rng = np.random.default_rng(3)
    moved = (v + np.float32([0.0, 0.0, 0.5])
             + rng.normal(0, 0.02, v.shape).astype(np.float32)).astype(np.float32)
    bvh.refit(moved)
    assert bvh.query_data.wide_records() is first
    assert np.array_equal(dev_lanes(bvh, first), lanes_before)
    records, _ = read_records(bvh.ctx, first)
    lanes = lanes_before
    present = lanes >= 0
    nodes = bvh.nodes
    for row, (field, axis) in enumerate([("lower", 0), ("upper", 0), ("lower", 1), ("upper", 1),
                                         ("lower", 2), ("upper", 2)]):
        want = nodes[field][np.maximum(lanes, 0), axis]
        assert np.array_equal(records[:, row][present], want[present]), (field, axis)
    got = bvh.intersect(o, d)
    fresh = lbvh.build(moved, f).intersect(o, d)
    _same_hits(got, fresh, moved, f, o, d, "refit")
    assert not (got.t[before.hit] == before.t[before.hit]).all()


def dev_lanes(bvh, wide):
    lanes = np.empty((wide.count, wide.width), np.int32)
    cl.enqueue_copy(bvh.ctx.queue, lanes, wide.lanes, is_blocking=True)
    return lanes


def test_a_child_index_out_of_range_is_refused_before_tracing():
    """from_arrays refuses such a tree; one corrupted on the device is caught by the
    packing kernel, with the node named, before any ray runs."""
    v, f = scene("suzanne")
    bvh = lbvh.build(v, f)
    cl.enqueue_copy(bvh.ctx.queue, bvh.tree.nodes, np.int32([10**6]), dst_offset=32 * 5 + 28,
                    is_blocking=True)    # node 5's right child
    with pytest.raises(ValueError, match=rf"node 5 has a child index outside \[0, {bvh.tree.num_nodes}\)"):
        bvh.intersect(np.float32([[0.2, 0.2, 1]]), np.float32([[0, 0, -1]]))


def test_per_ray_intervals_across_batches():
    o, d = ray_set("suzanne")
    bvh = tree("suzanne", "lbvh30")
    full = bvh.intersect(o, d)
    rng = np.random.default_rng(7)
    tmax = np.where(rng.random(len(o)) < 0.5, np.inf, full.t * 0.5).astype(np.float32)
    tmax[~np.isfinite(tmax)] = np.inf
    whole = bvh.intersect(o, d, 0.0, tmax)
    batched = bvh.intersect(o, d, 0.0, tmax, batch_size=97)
    assert (whole.prim == batched.prim).all() and (whole.t == batched.t).all()
    cut = tmax < full.t
    assert not whole.hit[cut & full.hit].any() or (whole.t[cut & whole.hit] <= tmax[cut & whole.hit]).all()
    assert (whole.prim[~cut] == full.prim[~cut]).all()


def test_kernel_equals_its_twin_on_rays_with_tiny_direction_components(ctx):
    """Rays whose minor direction components are 1e-45 .. 1e-30 against the major one
    (shears below float32's range: the test in double; 1/d overflowing: the slab
    test's near planes at FLT_MAX): same hits as the float32 twin, t bit for bit,
    and every answer right by lbvh.check against the float64 oracle."""
    if not ctx.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
        pytest.skip("division is not correctly rounded on this device")
    from lbvh.verification import rules as check
    from lbvh.verification.hard_cases import make_case

    v, f = scene("suzanne")
    lo, hi = v.min(axis=0), v.max(axis=0)
    rng = np.random.default_rng(7)
    n = 2000
    o = (lo + rng.random((n, 3)) * (hi - lo)).astype(np.float32)
    major = rng.integers(0, 3, n)
    d = (rng.choice([1e-45, -1e-45, 3e-42, -1e-40, 1e-38, 1e-30, 0.0], (n, 3))
         * rng.choice([1.0, 0.5], (n, 3)))
    d[np.arange(n), major] = rng.choice([1.0, -1.0, 1e7, -3e20], n)
    d = d.astype(np.float32)
    got = tree("suzanne", "lbvh63").intersect(o, d)
    _matches_float32_twin(got, v, f, o, d)
    case = make_case("tiny components", v, f, "test", (o, d))
    judge = check.Judge(case, check.reference(case))
    assert not check.compare_closest(judge, got.prim, got.t, got.overflow).wrong.any()


@pytest.mark.parametrize("per_ray_interval", [False, True])
def test_one_batch_in_host_memory_answers_as_batches_do(ctx, per_ray_interval):
    """On a CPU one batch is traced in the caller's arrays themselves (no copy either
    way); in several batches through device buffers. Same answers, bit for bit, for
    closest and any hits; the inputs, read-only ones included, are left as they were."""
    v, f = random_soup(2000, seed=41)
    bvh = lbvh.build(v, f)
    rng = np.random.default_rng(42)
    n = 3001
    o = rng.random((n, 3), dtype=np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    tmin = rng.uniform(0, 0.2, n).astype(np.float32) if per_ray_interval else 0.0
    tmax = rng.uniform(0.3, 2.0, n).astype(np.float32) if per_ray_interval else np.inf
    o_before, d_before = o.copy(), d.copy()
    o.flags.writeable = False
    whole = bvh.intersect(o, d, tmin, tmax)
    parts = bvh.intersect(o, d, tmin, tmax, batch_size=1000)
    for name in ("t", "u", "v", "prim", "overflow"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(parts, name), err_msg=name)
    assert whole.hit.any() and not whole.hit.all()
    np.testing.assert_array_equal(bvh.occluded(o, d, tmin, tmax),
                                  bvh.occluded(o, d, tmin, tmax, batch_size=1000))
    np.testing.assert_array_equal(o, o_before)
    np.testing.assert_array_equal(d, d_before)
    # the answers are the caller's own arrays, not views of memory the library reuses
    again = bvh.intersect(o[::-1].copy(), d[::-1].copy(), tmin, tmax)
    np.testing.assert_array_equal(whole.t, parts.t)
    assert not np.shares_memory(again.t, whole.t)
