"""Packets of 8 rays (kernels/packet_traverse.cl) against their twin, the single-ray
walk of kernels/traverse.cl: the same t, u, v and triangle bit for bit for closest
hits (ties included: the lowest index at exactly the same t), the same rays hit for
any hits, the same flags; on every builder, the hard cases and fuzzed meshes."""
from __future__ import annotations

import dataclasses

import numpy as np
import pyopencl as cl
import pytest
from hypothesis import given, strategies as st

import lbvh
from lbvh.queries import traverse as tr
from lbvh.queries.packets import PACKET
from lbvh.queries.ray_order import ray_order
from lbvh.queries.rays import check_rays, upload_rays
from lbvh.verification import hard_cases, runner
from lbvh.verification.oracle import brute_force

import test_fuzz
from test_traverse import SCENES, TREES, ray_set, tree


def trace(bvh, o, d, tmin=0.0, tmax=np.inf, *, any_hit=False, packets, ordered=True,
          stack_size=None):
    """``(int32 (4, N) planes' bits, int32 (N,) flags)`` of one walk on the device,
    the rays in their Morton order where ``ordered`` (packets are neighbours in it)."""
    ctx = bvh.ctx
    rays = upload_rays(ctx, check_rays(o, d, tmin, tmax))
    order = None
    wait = []
    if ordered and rays.count:
        order, wait = ray_order(ctx, rays.origins, rays.directions, rays.count,
                                *bvh.tree.root_box())
    try:
        out = tr.trace_buffers(bvh.query_data,
                               dataclasses.replace(rays, order=order, ready=tuple(wait)),
                               any_hit=any_hit, packets=packets, stack_size=stack_size)
        planes = tr.read_hits(ctx, out)
        flags = np.empty(rays.count, np.int32)
        cl.enqueue_copy(ctx.queue, flags, out.flags, wait_for=[out.event], is_blocking=True)
    finally:
        if order is not None:
            ctx.memory.free(order)
        rays.release()
    return planes.view(np.int32), flags


def assert_same(bvh, o, d, tmin=0.0, tmax=np.inf, *, ordered=True, stack_size=None,
                context=""):
    """Closest hits bit for bit and flags equal; any hits: the same rays hit."""
    single = trace(bvh, o, d, tmin, tmax, packets=False, ordered=ordered, stack_size=stack_size)
    packed = trace(bvh, o, d, tmin, tmax, packets=True, ordered=ordered, stack_size=stack_size)
    differ = np.flatnonzero((single[0] != packed[0]).any(axis=0))
    assert len(differ) == 0, f"{context}: {len(differ)} rays differ, first {differ[:5]}"
    assert np.array_equal(single[1], packed[1]), context
    single_any = trace(bvh, o, d, tmin, tmax, any_hit=True, packets=False, ordered=ordered,
                       stack_size=stack_size)
    packed_any = trace(bvh, o, d, tmin, tmax, any_hit=True, packets=True, ordered=ordered,
                       stack_size=stack_size)
    assert np.array_equal(single_any[0][3] >= 0, packed_any[0][3] >= 0), context
    assert np.array_equal(single_any[1], packed_any[1]), context
    # an any hit is a hit of the closest-hit walk's set: it hits where the closest does
    assert np.array_equal(packed_any[0][3] >= 0, single[0][3] >= 0), context
    return single


def grid_rays(v, side=48, offset=(0.3, 2.0, 0.7), span=0.125):
    """Coherent rays: from one point outside the box through a side x side grid of
    ``span`` times the box's size about its centre, row by row (a camera's, which the
    packets take together)."""
    v = np.asarray(v, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre, size = (lo + hi) / 2, float((hi - lo).max()) or 1.0
    eye = centre + size * np.asarray(offset)
    s = span * ((np.arange(side) + 0.5) / side - 0.5)
    gx, gy = np.meshgrid(s, s)
    target = centre + size * np.column_stack([gx.ravel(), np.zeros(side * side), gy.ravel()])
    d = target - eye
    return np.tile(eye, (len(d), 1)).astype(np.float32), d.astype(np.float32)


def deferred_share(bvh, o, d):
    """The share of rays the packets leave to the single-ray walk (not coherent)."""
    from lbvh.queries.packets import trace_packets
    ctx = bvh.ctx
    rays = upload_rays(ctx, check_rays(o, d))
    n = rays.count
    hits, flags, deferred = (ctx.memory.alloc(16 * n), ctx.memory.alloc(4 * n),
                             ctx.memory.alloc(4 * n))
    defines = tr.kernel_defines(ctx, False, "watertight", False, tr.stack_size_for(bvh.query_data))
    ev = trace_packets(bvh.query_data, rays, any_hit=False, defines=defines, hits=hits, flags=flags,
                       deferred=deferred)
    out = np.empty(n, np.int32)
    cl.enqueue_copy(ctx.queue, out, deferred, wait_for=[ev], is_blocking=True)
    ctx.memory.free(hits, flags, deferred)
    rays.release()
    assert set(np.unique(out[out >= 0])) <= set(range(n))
    return float(np.mean(out >= 0))


@pytest.mark.parametrize("kind", TREES)
@pytest.mark.parametrize("name", sorted(SCENES))
def test_packets_equal_the_single_ray_walk(name, kind):
    """Coherent rays (a grid seen from one point: packets) and the scattered rays
    of test_traverse (mostly left to the single-ray walk)."""
    v, _ = SCENES[name]()
    o, d = grid_rays(v)
    assert_same(tree(name, kind), o, d, context=f"{name}/{kind}/grid")
    o, d = ray_set(name)
    assert_same(tree(name, kind), o, d, context=f"{name}/{kind}")


def test_coherent_packets_go_together_and_scattered_rays_alone():
    """The grid's packets are traced as packets; rays in no order are left to the
    single-ray walk (only speed depends on it)."""
    v, f = SCENES["teapot"]()
    bvh = tree("teapot", "lbvh30")
    o, d = grid_rays(v)
    assert deferred_share(bvh, o, d) < 0.05
    perm = np.random.default_rng(1).permutation(len(o))
    assert deferred_share(bvh, o[perm], d[perm]) > 0.9


@pytest.mark.parametrize("builder", sorted(runner.BUILDERS))
def test_packets_equal_the_single_ray_walk_on_every_builder(builder):
    """Every builder's tree, spatial splits' clipped leaves included, on the teapot."""
    v, f = SCENES["teapot"]()
    o, d = ray_set("teapot")
    bvh = runner.build_with(builder, v, f, o, d)
    assert_same(bvh, o, d, context=builder)


#: The hard cases traced both ways; those that force a tiny stack are checked apart.
HARD = [name for name in hard_cases.CASES if name != "over_2_24_triangles"]


@pytest.mark.parametrize("name", HARD)
def test_packets_equal_the_single_ray_walk_on_the_hard_cases(name):
    case = hard_cases.make(name)
    bvh = lbvh.build(case.vertices, case.faces)
    if case.stack_size is not None:
        # a forced stack too small: both walks flag the rays whose subtrees they drop
        for any_hit in (False, True):
            _, flags = trace(bvh, case.origins, case.directions, case.tmin, case.tmax,
                             any_hit=any_hit, packets=True, stack_size=case.stack_size)
            assert (flags & tr.FLAG_OVERFLOW).any(), name
        return
    assert_same(bvh, case.origins, case.directions, case.tmin, case.tmax, context=name)
    with np.errstate(over="ignore", invalid="ignore"):
        o, d = grid_rays(case.vertices)   # coherent rays: traced as packets
    if np.isfinite(o).all() and np.isfinite(d).all() and (d != 0).any(axis=1).all():
        assert_same(bvh, o, d, context=f"{name}/grid")
    # in the rays' own order too (packets of neighbours in the case's listing)
    assert_same(bvh, case.origins, case.directions, case.tmin, case.tmax, ordered=False,
                context=name)


def test_ties_go_to_the_lowest_index_in_both_walks():
    """Copies of a triangle, listed in a shuffled order among others: every ray that
    hits them gets the copy of the lowest index, as the twin (the brute force) does,
    whatever the tree and the walk."""
    rng = np.random.default_rng(4)
    tri = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    others = rng.random((60, 3, 3)).astype(np.float32) + np.float32([2, 2, 0])
    soup = np.concatenate([np.repeat(tri[None], 12, axis=0), others])
    perm = rng.permutation(len(soup))
    v = soup[perm].reshape(-1, 3)
    f = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
    copies = np.flatnonzero(perm < 12)
    o = np.column_stack([rng.random((300, 2)) * 0.5, np.ones(300)]).astype(np.float32)
    d = np.float32([0, 0, -1]) + np.zeros((300, 3), np.float32)
    twin = brute_force(v, f, o, d)
    assert (twin.prim == copies.min()).all()
    for builder in ("lbvh30", "sah", "lbvh-auto-collapse"):
        bvh = runner.build_with(builder, v, f)
        single = assert_same(bvh, o, d, context=builder)
        assert (single[0][3] == copies.min()).all(), builder
        assert (bvh.intersect(o, d).prim == copies.min()).all(), builder


@pytest.mark.parametrize("count", [1, 2, 7, 8, 9, 15, 16, 17, 63, 65])
def test_short_packets(count):
    """Counts that leave the last packet short (its lanes past the end not traced)."""
    o, d = ray_set("suzanne")
    assert_same(tree("suzanne", "lbvh30"), o[:count], d[:count], ordered=count > 1,
                context=str(count))


def test_per_ray_intervals_and_nan_rays():
    """Per-ray tmin and tmax; a NaN ray that reaches the kernel (through
    trace_buffers) is flagged and not traced in a packet as alone."""
    v, f = SCENES["suzanne"]()
    o, d = ray_set("suzanne")
    rng = np.random.default_rng(2)
    lo = (rng.random(len(o)) * 2).astype(np.float32)
    hi = (lo + rng.random(len(o)) * 3).astype(np.float32)
    bvh = tree("suzanne", "lbvh30")
    assert_same(bvh, o, d, lo, hi, context="intervals")
    rays = upload_rays(bvh.ctx, check_rays(o[:20], d[:20]))
    bad = d[:20].copy()
    bad[5] = np.nan
    cl.enqueue_copy(bvh.ctx.queue, rays.directions, bad, is_blocking=True)
    flags = []
    for packets in (False, True):
        out = tr.trace_buffers(bvh.query_data, rays, packets=packets)
        planes = tr.read_hits(bvh.ctx, out)
        flag = np.empty(20, np.int32)
        cl.enqueue_copy(bvh.ctx.queue, flag, out.flags, wait_for=[out.event], is_blocking=True)
        assert flag[5] == tr.FLAG_NAN_RAY and planes[3].view(np.int32)[5] == -1
        flags.append((planes.view(np.int32), flag))
    assert np.array_equal(flags[0][0], flags[1][0]) and np.array_equal(flags[0][1], flags[1][1])
    rays.release()


def test_the_public_calls_answer_as_the_single_ray_walk():
    """bvh.intersect and bvh.occluded (which take packets for ordered rays on a CPU)
    give the single-ray walk's answers."""
    o, d = ray_set("teapot")
    o, d = np.tile(o, (2, 1)), np.tile(d, (2, 1))
    bvh = tree("teapot", "lbvh30")
    single = trace(bvh, o, d, packets=False)[0]
    hits = bvh.intersect(o, d)
    assert np.array_equal(hits.t.view(np.int32), single[0])
    assert np.array_equal(hits.prim, single[3])
    assert np.array_equal(bvh.occluded(o, d), single[3] >= 0)


def test_packets_refuse_what_they_cannot_do():
    bvh = tree("teapot", "lbvh30")
    o, d = ray_set("teapot")
    rays = upload_rays(bvh.ctx, check_rays(o[:8], d[:8]))
    with pytest.raises(ValueError, match="packets=True"):
        tr.trace_buffers(bvh.query_data, rays, packets=True, counters=True)
    with pytest.raises(ValueError, match="packets=True"):
        tr.trace_buffers(bvh.query_data, rays, packets=True, order="global")
    rays.release()
    assert PACKET == 8


@test_fuzz.FUZZ
@given(data=st.data())
def test_packets_equal_the_single_ray_walk_on_fuzzed_meshes(data):
    v, f = data.draw(test_fuzz.meshes())
    o, d = data.draw(test_fuzz.rays_for(v))
    for builder in ("lbvh30", "sah"):
        bvh = runner.build_with(builder, v, f)
        assert_same(bvh, o, d, context=builder)
        # the same rays in packets of 8 from one origin (forced together where they
        # stay within the box: tiny meshes make most such packets coherent)
        assert_same(bvh, np.repeat(o[:1], len(d), axis=0), d, ordered=False, context=builder)
