"""Wide records (kernels/wide.cl) against their numpy twin (lbvh.queries.wide.wide_numpy).

The device numbers records level by level with an atomic counter, the twin
breadth first in order: records are compared through the binary node each one
starts from. Boxes are copies and the greedy choice is made on the same float32
areas, so everything else is compared exactly.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

import lbvh
from lbvh.layout import make_nodes
from lbvh.verification import meshes
from lbvh.queries import traverse as tr
from lbvh.queries.wide import WIDTHS, read_records, wide_numpy
from test_traverse import chain_tree, cyclic_tree, scene, tree

KINDS = ("lbvh30", "lbvh63", "lbvh_collapse", "sah", "host_median", "host_one_leaf")


def _fresh(kind, scene_name="teapot"):
    """A copy of a test tree without cached records (so widths do not interfere)."""
    t = tree(scene_name, kind)
    v, f = scene(scene_name)
    return lbvh.BVH.from_arrays(t.nodes, t.prim_order, t.root, v, f, builder=kind, validate=False)


def assert_equal_to_twin(bvh, width):
    wide = bvh.query_data.wide_records(width=width)
    twin = wide_numpy(bvh.nodes, bvh.root, width)
    assert wide.packed and wide.width == width
    assert wide.count == len(twin.record_node)
    assert wide.stack_need == twin.stack_need
    records, record_node = read_records(bvh.ctx, wide)
    assert sorted(record_node.tolist()) == sorted(twin.record_node.tolist())
    position = np.full(bvh.tree.num_nodes, -1)
    position[twin.record_node] = np.arange(len(twin.record_node))
    mine = twin.records[position[record_node]]
    # boxes, empty lanes included (+inf, -inf), bit for bit
    assert records[:, :6].tobytes() == mine[:, :6].tobytes()
    got_x, got_y = records[:, 6].view(np.int32), records[:, 7].view(np.int32)
    want_x, want_y = mine[:, 6].view(np.int32), mine[:, 7].view(np.int32)
    assert (got_y == want_y).all()
    # a leaf lane keeps its words; an internal lane names the record of the same node
    # the lanes kept for refits: the same binary nodes, lane by lane
    if wide.count:
        lanes = np.empty((wide.count, width), np.int32)
        cl.enqueue_copy(bvh.ctx.queue, lanes, wide.lanes, is_blocking=True)
        assert np.array_equal(lanes, twin.lanes[position[record_node]])
    present = twin.lanes[position[record_node]] >= 0
    inner = present & (want_y == 0)
    assert (got_x[~inner] == want_x[~inner]).all()
    assert (record_node[got_x[inner]] == twin.record_node[want_x[inner]]).all()
    root = bvh.nodes[bvh.root]
    if root["b"] < 0:
        assert (wide.root_x, wide.root_y, wide.count) == (root["a"], root["b"], 0)
    else:
        assert (wide.root_x, wide.root_y) == (0, 0) and record_node[0] == bvh.root
    return wide, twin


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("kind", KINDS)
def test_records_equal_their_numpy_twin(kind, width):
    assert_equal_to_twin(_fresh(kind), width)


@pytest.mark.parametrize("width", WIDTHS)
def test_twin_records_cover_the_tree_once(width):
    """Independent of the kernel: every node of the binary tree is a lane of exactly
    one record or the root, and every record but the root is one internal lane; a
    record has its width of lanes unless all its lanes are leaves."""
    bvh = _fresh("lbvh30", "suzanne")
    twin = wide_numpy(bvh.nodes, bvh.root, width)
    lanes = twin.lanes[twin.lanes >= 0]
    internal = bvh.nodes["b"] >= 0
    # binary nodes opened inside records appear in no lane
    opened = np.setdiff1d(np.flatnonzero(internal), twin.record_node)
    assert len(np.intersect1d(lanes, opened)) == 0
    assert len(lanes) == len(np.unique(lanes)) == bvh.tree.num_nodes - 1 - len(opened)
    assert set(lanes[internal[lanes]].tolist()) == set(twin.record_node[1:].tolist())
    used = (twin.lanes >= 0).sum(axis=1)
    all_leaves = ~(internal[np.maximum(twin.lanes, 0)] & (twin.lanes >= 0)).any(axis=1)
    assert ((used == width) | all_leaves).all()
    assert (used >= 2).all()
    # the records stand for every internal node: each opened (used - 1) of them
    assert (used - 1).sum() == internal.sum()


def test_the_largest_child_is_opened_first():
    """Four leaves under a root whose left child is much larger than the right:
    with width 3 the left child is opened, not the right one."""
    lower = np.float32([[0, 0, 0], [0, 0, 0], [9, 0, 0], [0, 0, 0], [5, 0, 0], [9, 0, 0], [9.5, 0, 0]])
    upper = np.float32([[10, 1, 1], [8, 1, 1], [10, 1, 1], [3, 1, 1], [8, 1, 1], [9.4, 1, 1], [10, 1, 1]])
    children = np.array([[1, 2], [3, 4], [5, 6], [-1, -1], [-1, -1], [-1, -1], [-1, -1]])
    ranges = np.array([[0, 0], [0, 0], [0, 0], [0, 1], [1, 1], [2, 1], [3, 1]])
    nodes = make_nodes(lower, upper, children, ranges)
    # with width 4 both are opened: the root record holds the four leaves
    twin = wide_numpy(nodes, 0, 4)
    assert twin.lanes.tolist() == [[3, 4, 5, 6]]
    # a three-lane step of the same rule, read off the twin's first opening
    from lbvh.queries.wide import _half_areas, _open_lanes, area_scale
    lanes = np.int32([[1, 2, -1]])
    step = _open_lanes(lanes, nodes["a"], nodes["b"], nodes["b"] >= 0,
                       _half_areas(nodes, area_scale(lower[0], upper[0])))
    assert step.tolist() == [[3, 4, 2]]


#: A known bug, not yet understood: the device's records of this soup differ from run to
#: run in their last lanes (seen at 2^-60 and 2^-40; 1 run in 2-3 fails, at 7af55c5 as
#: now): an unstable comparison or an uninitialised read in the device's wide records.
#: Kept running, reported when it fails, until it is fixed.
def lanes_by_node(bvh, wide) -> dict[int, list[int]]:
    """The device's lanes keyed by the binary node each record starts from: the
    device numbers records with an atomic counter, so their order is not kept."""
    from lbvh.queries.winding_moments import read_lanes
    _, record_node = read_records(bvh.ctx, wide)
    return dict(zip(record_node.tolist(), read_lanes(bvh.ctx, wide).tolist()))


@pytest.mark.parametrize("k", [-60, -40, 40])
def test_a_scene_at_any_power_of_two_scale_opens_the_same_lanes(k):
    """The boxes' areas are taken at the root's unit size (area_scale): a scene times
    2^k gets the same records, on the device and in the twin. Unscaled, the areas of
    this soup's nodes (a hundredth of its 0.01 extent) at 2^-60, below float32's normal
    range, opened other lanes on the device."""
    v, f = meshes.soup(20000, 5, 0.02, spread="normal")
    v = v * np.float32(0.01)
    base = lbvh.build(v, f, builder="sah")
    other = lbvh.build(np.ldexp(v, k).astype(np.float32), f, builder="sah")
    assert np.array_equal(base.prim_order, other.prim_order)
    a, b = base.query_data.wide_records(width=8), other.query_data.wide_records(width=8)
    assert lanes_by_node(base, a) == lanes_by_node(other, b)
    assert np.array_equal(wide_numpy(base.nodes, base.root, 8).lanes,
                          wide_numpy(other.nodes, other.root, 8).lanes)


def test_stack_need_is_the_deepest_sum_of_pushes():
    """A chain (each internal node has a leaf on the left): every record of width w
    holds w - 1 leaves and the chain's next internal node, so w - 1 pushes per record."""
    depth = 40
    bvh, _, _ = chain_tree(depth)
    for width in WIDTHS:
        fresh = lbvh.BVH.from_arrays(bvh.nodes, bvh.prim_order, bvh.root, bvh.vertices,
                                     bvh.faces, builder="chain")
        wide, twin = assert_equal_to_twin(fresh, width)
        records = -(-depth // (width - 1))
        assert wide.count == records
        assert wide.stack_need == depth


def test_a_cycle_is_refused_with_the_node_named():
    with pytest.raises(ValueError, match=r"node 0 is reached twice"):
        cyclic_tree().query_data.wide_records()


def test_bad_width_is_refused():
    with pytest.raises(ValueError, match=r"width: 3; expected one of \(4, 8\)"):
        _fresh("lbvh30").query_data.wide_records(width=3)


@pytest.mark.parametrize("define", ["CLANG_MOVMSK", "CLANG_CTZ"])
@pytest.mark.parametrize("any_hit", [False, True], ids=["closest", "any"])
def test_lane_helpers_by_clang_builtins_answer_as_the_portable_code(any_hit, define):
    """lane_bits by clang's vmovmskps builtin (CLANG_MOVMSK, taken where the target has
    AVX) and the lowest set lane by clang's count of trailing zeros (CLANG_CTZ), each
    set where the compiler is clang, give the same hits bit for bit as the portable
    bit tests; where the device's compiler is not clang the defines are 0."""
    v, f = lbvh.data.teapot()
    bvh = lbvh.build(v, f)
    rng = np.random.default_rng(3)
    o = (rng.uniform(-1, 1, (4000, 3)) * 6 + [0, 1.5, 0]).astype(np.float32)
    d = (rng.uniform(-1, 1, (4000, 3)) * [3, 1, 3] + [0, 1.5, 0] - o).astype(np.float32)
    rays = tr.check_rays(o, d)
    got = {}
    for value in (0, 1):
        out = tr.trace_buffers(bvh.query_data, tr.upload_rays(bvh.ctx, rays), any_hit=any_hit,
                               defines={define: value})
        got[value] = [np.asarray(a).view(np.uint32) for a in tr.read_hits(bvh.ctx, out)]
    for a, b in zip(got[0], got[1]):
        assert np.array_equal(a, b)
    assert (got[1][3].view(np.int32) >= 0).sum() > 1000   # rays that hit, and rays that miss
    assert (got[1][3].view(np.int32) < 0).sum() > 100
    assert tr.kernel_defines(bvh.ctx, any_hit, "watertight", False, 8)[define] == \
        int(bvh.ctx.compiler_is_clang)


def test_point_walks_answer_the_same_with_the_lane_builtins_and_without(monkeypatch):
    """Closest points and winding numbers through wide records take the lanes' bit mask
    and lowest lane by clang's builtins where the compiler is clang
    (lbvh.queries.wide.lane_defines: CLANG_MOVMSK, CLANG_CTZ) and by the portable bit
    tests elsewhere: the same distances, triangles and winding numbers bit for bit."""
    import lbvh.queries.closest as closest_module
    from lbvh.queries import wide as wide_module
    v, f = lbvh.data.teapot()
    bvh = lbvh.build(v, f)
    rng = np.random.default_rng(5)
    lo, hi = v.min(0), v.max(0)
    p = (lo - 0.2 * (hi - lo) + rng.uniform(0, 1, (20000, 3)) * 1.4 * (hi - lo)).astype(np.float32)
    got = {}
    for value in (0, 1):
        monkeypatch.setattr(closest_module, "lane_defines",
                            lambda ctx, v=value: {"CLANG_MOVMSK": v, "CLANG_CTZ": v})
        c = bvh.closest_points(p)
        got[value] = (c.distance.view(np.uint32), c.prim, bvh.winding_numbers(p).view(np.uint32))
    for a, b in zip(got[0], got[1]):
        assert np.array_equal(a, b)
    assert 0.02 < (bvh.winding_numbers(p) > 0.5).mean() < 0.98   # points inside and outside
    assert wide_module.lane_defines(bvh.ctx) == {"CLANG_MOVMSK": int(bvh.ctx.compiler_is_clang),
                                                 "CLANG_CTZ": int(bvh.ctx.compiler_is_clang)}
