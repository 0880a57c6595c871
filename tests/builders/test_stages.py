"""Each pipeline kernel against its numpy or pure Python twin.

Exact comparisons throughout: bounds and refit are min/max of floats, the Morton
quantisation uses the same float32 operations (correctly rounded division on
PoCL), and sorting, emission and duplicate counting are integer work.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

from conftest import random_soup, shared_mesh, shipped_mesh
from lbvh import device as dev
from lbvh.builders.bounds import (centroid_bounds_numpy, triangle_bounds, triangle_boxes_numpy,
                         triangle_centres_numpy)
from lbvh.builders.emit import emit_hierarchy, emit_hierarchy_python
from lbvh.layout import NODE_DTYPE, children_of, node_depths
from lbvh.builders.morton import KEY_DTYPE, count_duplicates, morton_codes, morton_codes_numpy
from lbvh.builders.refit import refit_from_boxes, refit_numpy
from lbvh.tree import Tree
from lbvh.device.sort import (LOCAL_BITS, MSD_MIN_KEYS, SCRATCH_BYTES, digit_shifts, expected_mask,
                       msd_plan, radix_sort, radix_sort_numpy)


def upload(ctx, v, f):
    return dev.to_device(ctx, v), dev.to_device(ctx, f)


def read(ctx, buf, dtype, n):
    return dev.from_device(ctx, buf, dtype, (n,))


def device_codes(ctx, v, f, key_bits, per_item=None):
    mem = dev.MemoryTracker(ctx)
    vb, fb = upload(ctx, v, f)
    boxes, box, _ = triangle_bounds(ctx, mem, vb, fb, len(f))
    keys, values, _ = morton_codes(ctx, mem, boxes, box, len(f), key_bits, per_item)
    tri_boxes = dev.from_device(ctx, boxes, np.float32, (len(f), 2, 4))[:, :, :3]
    lo, hi = triangle_boxes_numpy(v, f)
    assert np.array_equal(tri_boxes[:, 0], lo) and np.array_equal(tri_boxes[:, 1], hi)
    bounds = dev.from_device(ctx, box, np.float32, (2, 4))[:, :3]
    return bounds, read(ctx, keys, KEY_DTYPE[key_bits], len(f)), read(ctx, values, np.uint32, len(f))


MESHES = {
    "teapot": lambda: shipped_mesh("teapot.obj"),
    "cornell": lambda: shipped_mesh("cornell_box_gkit.obj"),
    "soup": lambda: random_soup(20000, seed=3),
    "flat_z": lambda: (random_soup(3000, seed=4)[0] * np.float32([1, 1, 0]), random_soup(3000)[1]),
    "line_x": lambda: (random_soup(3000, seed=5)[0] * np.float32([1, 0, 0]), random_soup(3000)[1]),
    "one_point": lambda: (np.full((30, 3), 7.5, np.float32), np.arange(30, dtype=np.uint32).reshape(10, 3)),
    "huge": lambda: (random_soup(2000, seed=6)[0] * np.float32(1e38) - np.float32(5e37), random_soup(2000)[1]),
    "tiny": lambda: (random_soup(2000, seed=7)[0] * np.float32(1e-30), random_soup(2000)[1]),
    "far": lambda: (random_soup(2000, seed=8)[0] + np.float32(3e6), random_soup(2000)[1]),
}


@pytest.mark.parametrize("name", sorted(MESHES))
@pytest.mark.parametrize("key_bits", [32, 64])
@pytest.mark.parametrize("per_item", [None, 1, 13])
def test_bounds_and_morton_codes_match_numpy_exactly(ctx, name, key_bits, per_item):
    """Chunks of 8 codes at a time (the CPU's), one at a time (a GPU's), misaligned ones."""
    v, f = MESHES[name]()
    bounds, keys, values = device_codes(ctx, v, f, key_bits, per_item)
    assert np.array_equal(bounds, centroid_bounds_numpy(v, f))
    expected = morton_codes_numpy(triangle_centres_numpy(v, f), bounds, key_bits)
    assert keys.dtype == expected.dtype
    mismatch = np.flatnonzero(keys != expected)
    assert mismatch.size == 0, f"{mismatch.size} codes differ, first at {mismatch[:5]}"
    assert np.array_equal(values, np.arange(len(f)))
    limit = 1 << (30 if key_bits == 32 else 63)
    assert int(keys.max()) < limit


def test_zero_extent_axes_give_zero_cells(ctx):
    v, f = MESHES["line_x"]()
    _, keys, _ = device_codes(ctx, v, f, 32)
    # only x varies: y and z bits (positions 1 and 0 of each triple) are zero
    yz_mask = sum(3 << (3 * b) for b in range(10))
    assert not np.any(keys & np.uint32(yz_mask))
    _, keys, _ = device_codes(ctx, *MESHES["one_point"](), 64)
    assert np.all(keys == 0)


def sort_on_device(ctx, keys, values, key_bits, radix_bits=None):
    mem = dev.MemoryTracker(ctx)
    kb = cl.Buffer(ctx.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=keys)
    vb = cl.Buffer(ctx.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=values)
    res = radix_sort(ctx, mem, kb, vb, len(keys), key_bits, radix_bits=radix_bits)
    return read(ctx, res.keys, keys.dtype, len(keys)), read(ctx, res.values, np.uint32, len(keys)), res.passes


@pytest.mark.parametrize("radix_bits", [8, 11])  # the GPU's and the CPU's digit widths
@pytest.mark.parametrize("key_bits", [32, 64])
@pytest.mark.parametrize("n, spread", [(1, 30), (2, 30), (1000, 3), (70001, 30), (70001, 63), (300000, 12)])
def test_radix_sort_matches_stable_argsort(ctx, key_bits, n, spread, radix_bits):
    rng = np.random.default_rng(n + spread)
    dtype = KEY_DTYPE[key_bits]
    top = min(spread, 63 if key_bits == 64 else 32)
    keys = (rng.integers(0, 1 << top, n, dtype=np.uint64)).astype(dtype)
    values = rng.permutation(n).astype(np.uint32)  # stability shows through the values
    got_k, got_v, passes = sort_on_device(ctx, keys, values, key_bits, radix_bits)
    exp_k, exp_v = radix_sort_numpy(keys, values)
    assert np.array_equal(got_k, exp_k)
    assert np.array_equal(got_v, exp_v)


def test_radix_sort_skips_uniform_digits(ctx):
    n = 50000
    rng = np.random.default_rng(1)
    # only bits 11..18 vary: one 11-bit digit, two 8-bit digits
    keys = ((rng.integers(0, 256, n).astype(np.uint64) << 11) | 0xAB0007FF).astype(np.uint32)
    values = np.arange(n, dtype=np.uint32)
    got_k, got_v, passes = sort_on_device(ctx, keys, values, 32, radix_bits=11)
    assert passes == 1
    _, got_v8, passes8 = sort_on_device(ctx, keys, values, 32, radix_bits=8)
    assert passes8 == 2 and np.array_equal(got_v8, got_v)
    exp_k, exp_v = radix_sort_numpy(keys, values)
    assert np.array_equal(got_k, exp_k) and np.array_equal(got_v, exp_v)
    equal = np.full(1000, 0xDEADBEEF, np.uint32)
    got_k, got_v, passes = sort_on_device(ctx, equal, np.arange(1000, dtype=np.uint32), 32)
    assert passes == 0 and np.array_equal(got_v, np.arange(1000))
    assert digit_shifts(0xFF00, 32, 8) == [8] and digit_shifts(1 << 62, 64, 8) == [56]
    assert digit_shifts(0xFF00, 32, 11) == [0, 11] and digit_shifts(1 << 62, 64, 11) == [55]


@pytest.mark.parametrize("key_bits", [32, 64])
def test_msd_buckets_of_very_different_sizes_sort_stably(ctx, key_bits):
    """The CPU path's buckets: most keys share the top digit (one bucket too large
    for sort_buckets' private scratch: the passes alternate through the arrays),
    a few spread over the others (through the scratch), duplicates everywhere
    (stability shows through the values)."""
    rng = np.random.default_rng(key_bits)
    n = 3 * MSD_MIN_KEYS
    top = 29 if key_bits == 32 else 62
    keys = rng.integers(0, 1 << 12, n).astype(np.uint64) << (top - 20)   # duplicates
    few = rng.random(n) < 0.05
    keys[few] |= rng.integers(1, 1 << 11, few.sum()).astype(np.uint64) << (top - 10)
    keys = keys.astype(KEY_DTYPE[key_bits])
    values = rng.permutation(n).astype(np.uint32)
    got_k, got_v, passes = sort_on_device(ctx, keys, values, key_bits)
    exp_k, exp_v = radix_sort_numpy(keys, values)
    assert np.array_equal(got_k, exp_k) and np.array_equal(got_v, exp_v)
    if ctx.is_cpu:
        plan = msd_plan(int(np.bitwise_or.reduce(keys)) ^ int(np.bitwise_and.reduce(keys)), n, 11, True)
        assert plan is not None and passes == 1 + len(plan[1])


@pytest.mark.parametrize("key_bits", [32, 64])
def test_speculative_passes_run_only_when_the_mask_is_the_expected_one(ctx, key_bits):
    """The CPU path queues the passes for expected_mask() before reading the real
    mask. Keys with every code bit varying use them (key_bits + 4 kernels); keys
    with one bit fewer must leave them idle, the input untouched, and sort with
    the real plan (4 more kernels). Duplicates make a disturbed input order show."""
    if not ctx.is_cpu:
        pytest.skip("the speculative plan is the CPU path's")
    rng = np.random.default_rng(7)
    n = MSD_MIN_KEYS + 1001
    full = expected_mask(key_bits)
    for mask, kernels in ((full, 5), (full >> 1, 9)):
        keys = rng.integers(0, 1 << 12, n).astype(np.uint64) * np.uint64(mask // 4095)
        keys[:2] = (0, mask)  # exactly `mask` varies
        keys = (keys & np.uint64(mask)).astype(KEY_DTYPE[key_bits])
        values = rng.permutation(n).astype(np.uint32)
        mem = dev.MemoryTracker(ctx)
        rw = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
        res = radix_sort(ctx, mem, cl.Buffer(ctx.ctx, rw, hostbuf=keys),
                         cl.Buffer(ctx.ctx, rw, hostbuf=values), n, key_bits)
        assert len(res.events) == kernels, hex(mask)
        exp_k, exp_v = radix_sort_numpy(keys, values)
        assert np.array_equal(read(ctx, res.keys, keys.dtype, n), exp_k)
        assert np.array_equal(read(ctx, res.values, np.uint32, n), exp_v)


def test_sort_kernels_do_nothing_when_the_speculated_mask_is_wrong(ctx):
    """The device-side guard itself: with partial ANDs and ORs whose varying bits
    differ from `expected`, the histogram, record scatter and bucket kernels
    write nothing."""
    k = {name: ctx.kernel("sort.cl", name, {"KEY_BITS": 32, "RADIX_BITS": 11, "LOCAL_BITS": LOCAL_BITS,
                                           "SCRATCH_BYTES": SCRATCH_BYTES})
         for name in ("digit_histogram", "scatter_records", "sort_buckets")}
    n = 5000
    keys = np.arange(n, dtype=np.uint32)[::-1].copy()
    rw = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    buf = lambda a: cl.Buffer(ctx.ctx, rw, hostbuf=a)
    and_or = buf(np.array([0, 0xFF], np.uint32))    # one partial: bits 0..7 vary
    sentinel = np.full(2048, 7, np.uint32)
    for expected, written in ((0xFE, False), (0xFF, True)):
        guard = (and_or, np.int32(1), np.uint32(expected))
        counts, totals = buf(sentinel.copy()), buf(np.zeros(2048, np.uint32))
        records = buf(np.zeros(n, np.uint64))
        src_k, src_v = buf(keys), buf(np.arange(n, dtype=np.uint32))
        k["digit_histogram"](ctx.queue, (1,), None, src_k, np.int32(n), np.int32(n), np.int32(0),
                             np.int32(1), counts, *guard)
        k["scatter_records"](ctx.queue, (1,), None, src_k, src_v, records, np.int32(n),
                             np.int32(n), np.int32(0), np.int32(1), counts, totals, *guard)
        one_bucket = buf(np.array([n] + [0] * 2047, np.uint32))
        in_bucket = buf(np.arange(n, dtype=np.uint64) << np.uint64(32))   # records: keys 0..n-1
        b_k, b_v = buf(np.zeros(n, np.uint32)), buf(np.zeros(n, np.uint32))
        k["sort_buckets"](ctx.queue, (1,), None, in_bucket, b_k, b_v, np.int32(n), np.int32(n),
                          one_bucket, buf(np.int32([0])), np.int32(1), *guard)
        ctx.queue.finish()
        assert (not np.array_equal(read(ctx, counts, np.uint32, 2048), sentinel)) == written
        assert read(ctx, records, np.uint64, n).any() == written
        assert read(ctx, b_k, np.uint32, n).any() == written


def test_msd_plan():
    # 30 varying bits: one 11-bit MSD digit at bit 19, in-cache digits at 0 and 10
    assert LOCAL_BITS == 10
    assert msd_plan((1 << 30) - 1, MSD_MIN_KEYS, 11, True) == (19, [0, 10])
    assert msd_plan((1 << 30) - 1, MSD_MIN_KEYS - 1, 11, True) is None     # few keys: LSD
    assert msd_plan((1 << 30) - 1, MSD_MIN_KEYS, 8, False) is None         # a GPU: LSD
    assert msd_plan(0x7FF << 5, MSD_MIN_KEYS, 11, True) is None            # one digit suffices
    # constant low bits are skipped in the buckets too
    assert msd_plan(((1 << 11) - 1) << 40 | 1 << 35, MSD_MIN_KEYS, 11, True) == (40, [30])


def garbage_in_the_pool(ctx, nbytes):
    """A pooled buffer of ``nbytes`` full of -7, for the next allocation of that size:
    what a kernel must write cannot come from fresh zero pages by luck."""
    buf = ctx.memory.alloc(nbytes)
    cl.enqueue_fill_buffer(ctx.queue, buf, np.int32(-7), 0, nbytes)
    ctx.queue.finish()
    ctx.memory.free(buf, to_pool=True)


def emitted_tree(ctx, sorted_keys, key_bits, per_item=None, lanes=None):
    n = len(sorted_keys)
    mem = dev.MemoryTracker(ctx)
    kb = dev.to_device(ctx, sorted_keys)
    garbage_in_the_pool(ctx, NODE_DTYPE.itemsize * (2 * n - 1))
    nodes, parent, _ = emit_hierarchy(ctx, mem, kb, n, key_bits, per_item, lanes=lanes)
    return dev.from_device(ctx, nodes, NODE_DTYPE, (2 * n - 1,)), read(ctx, parent, np.int32, 2 * n - 1)


KEY_SETS = {
    "distinct": lambda rng, n, top: np.unique(rng.integers(0, 1 << top, n * 2, dtype=np.uint64))[:n],
    "many_equal": lambda rng, n, top: np.sort(rng.integers(0, 8, n, dtype=np.uint64)),
    "all_equal": lambda rng, n, top: np.full(n, 12345, np.uint64),
    "full_width": lambda rng, n, top: np.unique(rng.integers(0, 1 << (32 if top <= 32 else 64), n * 2,
                                                            dtype=np.uint64))[-n:],
    "runs": lambda rng, n, top: np.sort(rng.integers(0, 1 << top, n // 50 + 1, dtype=np.uint64)[rng.integers(0, n // 50 + 1, n)]),
}


@pytest.mark.parametrize("lanes", [8, 1])  # the CPU's vectors, a GPU's one node per work-item
@pytest.mark.parametrize("key_bits", [32, 64])
@pytest.mark.parametrize("kind", sorted(KEY_SETS))
@pytest.mark.parametrize("n, per_item", [(2, None), (3, None), (17, None), (1025, None),
                                         (3000, None), (3000, 1), (1025, 13), (17, 9)])
def test_emission_matches_serial_karras(ctx, key_bits, kind, n, per_item, lanes):
    """Groups of eight nodes (the CPU's), one group per work-item, and chunks that cut
    the groups short or start them unaligned; and the scalar form a GPU runs."""
    if lanes == 8 and not ctx.is_cpu:
        pytest.skip("the vector form is the CPU's; a GPU runs the scalar one (NVIDIA's "
                    "compiler emitted some of the vector form's nodes wrong: kernels/emit.cl)")
    rng = np.random.default_rng(n)
    top = 30 if key_bits == 32 else 63
    keys = np.sort(KEY_SETS[kind](rng, n, top)).astype(KEY_DTYPE[key_bits])
    n = len(keys)
    nodes, parent = emitted_tree(ctx, keys, key_bits, per_item, lanes)
    children, parent_py = emit_hierarchy_python(keys, key_bits)
    assert np.array_equal(children_of(nodes), children)
    assert np.array_equal(parent, parent_py)
    leaves = nodes[n - 1:]
    assert np.array_equal(leaves["a"], np.arange(n)) and np.all(leaves["b"] == -1)
    # the far end of each internal node's range of slots, left for the build's refit
    first, last = slot_ranges(children, parent_py, n)
    far = nodes["lower"][: n - 1, 0].view(np.int32)
    ends = np.arange(n - 1)
    assert np.all((first[: n - 1] == ends) | (last[: n - 1] == ends))
    assert np.array_equal(far, np.where(first[: n - 1] == ends, last[: n - 1], first[: n - 1]))
    # and the zero the build's refit counts arrivals in
    assert (nodes["lower"][: n - 1, 1].view(np.int32) == 0).all()


@pytest.mark.parametrize("lanes", [8, 1])
@pytest.mark.parametrize("scene", ["teapot", "soup", "bunny"])
def test_emission_of_a_mesh_matches_serial_karras(ctx, scene, lanes):
    """A mesh's own sorted Morton codes: long ranges next to pairs of leaves in one
    group of eight, the case that NVIDIA's compiler got wrong in the vector form (the
    scalar form is what a GPU runs): on the bunny, 366 groups whose lanes 0, 1, 4 and 5
    hold pairs of leaves and lanes 2, 3, 6 and 7 longer ranges."""
    if lanes == 8 and not ctx.is_cpu:
        pytest.skip("the vector form is the CPU's; a GPU runs the scalar one (kernels/emit.cl)")
    v, f = shared_mesh("stanford-bunny.obj") if scene == "bunny" else MESHES[scene]()
    keys = np.sort(morton_codes_numpy(triangle_centres_numpy(v, f), centroid_bounds_numpy(v, f), 32))
    nodes, parent = emitted_tree(ctx, keys, 32, None, lanes)
    children, parent_py = emit_hierarchy_python(keys, 32)
    assert np.array_equal(children_of(nodes), children)
    assert np.array_equal(parent, parent_py)


def slot_ranges(children, parent, n):
    """First and last slot under each node of a Karras-numbered tree, from its links."""
    depth = node_depths(parent, 0 if n > 1 else 0)
    first = np.full(2 * n - 1, -1, np.int64)
    last = np.full(2 * n - 1, -1, np.int64)
    first[n - 1:] = last[n - 1:] = np.arange(n)
    internal = np.arange(n - 1)
    for level in range(int(depth.max()), -1, -1):
        at = internal[depth[internal] == level]
        first[at] = first[children[at, 0]]
        last[at] = last[children[at, 1]]
    return first, last


def test_single_key_emits_one_leaf(ctx):
    nodes, parent = emitted_tree(ctx, np.array([5], np.uint32), 32)
    assert len(nodes) == 1 and nodes["a"][0] == 0 and nodes["b"][0] == -1 and parent[0] == -1


@pytest.mark.parametrize("scene", ["teapot", "soup", "one_point", "huge"])
def test_duplicate_count_matches_numpy(ctx, scene):
    v, f = MESHES[scene]()
    _, keys, values = device_codes(ctx, v, f, 32)
    sorted_keys = np.sort(keys)
    mem = dev.MemoryTracker(ctx)
    count, _ = count_duplicates(ctx, mem, dev.to_device(ctx, sorted_keys), len(keys), 32)
    assert count == int(np.sum(sorted_keys[1:] == sorted_keys[:-1]))


@pytest.mark.parametrize("scene", ["teapot", "cornell", "flat_z", "huge", "tiny"])
def test_device_refit_is_bit_identical_to_serial_refit(ctx, scene):
    import lbvh
    v, f = MESHES[scene]()
    bvh = lbvh.build(v, f)
    lower, upper = refit_numpy(bvh.nodes, bvh.tree.read("parent"), bvh.root, bvh.prim_order, v, f)
    assert np.array_equal(bvh.nodes["lower"], lower) and np.array_equal(bvh.nodes["upper"], upper)
    # and again after the vertices moved (the animation path)
    rng = np.random.default_rng(0)
    moved = (v + rng.normal(0, 0.05, v.shape).astype(np.float32) * (np.abs(v).max() + 1e-30)).astype(np.float32)
    bvh.refit(moved)
    lower, upper = refit_numpy(bvh.nodes, bvh.tree.read("parent"), bvh.root, bvh.prim_order, moved, f)
    assert np.array_equal(bvh.nodes["lower"], lower) and np.array_equal(bvh.nodes["upper"], upper)
    bvh.validate()


@pytest.mark.parametrize("per_item", [1, 2, 3, 64, 1000])
@pytest.mark.parametrize("scene", ["teapot", "same_point"])
def test_build_refit_is_bit_identical_for_any_chunk_length(ctx, scene, per_item):
    """The build's refit skips the atomics of nodes inside one chunk (KARRAS_RANGES):
    whichever way the leaves are cut into chunks, the boxes are the serial refit's."""
    if scene == "same_point":  # every code equal: the tree follows the index tie-break
        v, f = np.full((3, 3), 7.5, np.float32), np.tile(np.arange(3, dtype=np.uint32), (3000, 1))
    else:
        v, f = MESHES[scene]()
    n = len(f)
    mem = dev.MemoryTracker(ctx)
    vb, fb = upload(ctx, v, f)
    boxes, box, _ = triangle_bounds(ctx, mem, vb, fb, n)
    keys, values, _ = morton_codes(ctx, mem, boxes, box, n, 32)
    result = radix_sort(ctx, mem, keys, values, n, 32)
    garbage_in_the_pool(ctx, NODE_DTYPE.itemsize * (2 * n - 1))
    nodes, parent, _ = emit_hierarchy(ctx, mem, result.keys, n, 32, write_leaves=False)
    # whatever the unwritten leaf records held (-7 here), the refit writes them whole
    # no counter array: the straddling nodes count their arrivals in their lower.y word
    refit_from_boxes(Tree(ctx, nodes, parent, result.values, 0, 2 * n - 1, n, "lbvh"), boxes,
                     None, karras_ranges=True, per_item=per_item)
    tree = dev.from_device(ctx, nodes, NODE_DTYPE, (2 * n - 1,))
    parents = read(ctx, parent, np.int32, 2 * n - 1)
    order = read(ctx, result.values, np.int32, n)
    assert np.array_equal(tree["a"][n - 1:], np.arange(n)) and (tree["b"][n - 1:] == -1).all()
    lower, upper = refit_numpy(tree, parents, 0, order, v, f)
    assert np.array_equal(tree["lower"], lower) and np.array_equal(tree["upper"], upper)
    assert per_item < n  # chunk boundaries are crossed
    mem.close()


@pytest.mark.parametrize("key_bits", [30, 63])
def test_refit_boxes_hold_no_negative_zero_and_equal_the_twin_bit_for_bit(ctx, key_bits):
    """Signed zeros: min and max by comparisons keep whichever of -0.0 and +0.0 comes
    first, so a node's box once depended on which child's walk arrived second (the
    teapot's lower.z flipped sign in 15 of 400 builds with another process running).
    The leaf boxes now hold +0.0 for -0.0, and the sign of every zero is the twin's."""
    import lbvh
    v, f = shipped_mesh("teapot.obj")
    assert np.signbit(v[v == 0]).any()   # the case: the teapot has -0.0 coordinates
    v = v.copy()
    v[::7][v[::7] == 0] = np.float32(-0.0)   # and more of them
    bvh = lbvh.build(v, f, key_bits=key_bits)
    for box in (bvh.nodes["lower"], bvh.nodes["upper"]):
        assert not np.signbit(box[box == 0]).any()
    lower, upper = refit_numpy(bvh.nodes, bvh.tree.read("parent"), bvh.root, bvh.prim_order, v, f)
    assert np.array_equal(bvh.nodes["lower"].view(np.int32), lower.view(np.int32))
    assert np.array_equal(bvh.nodes["upper"].view(np.int32), upper.view(np.int32))


def test_refit_with_opencl_prefetch_equals_the_clang_builtin(ctx, monkeypatch):
    """CLANG_PREFETCH=0 (OpenCL's prefetch, for non-clang compilers) builds and gives
    the same boxes; so does the builtin that PoCL gets (where the compiler is clang:
    no other knows __builtin_prefetch)."""
    import lbvh
    v, f = MESHES["soup"]()
    trees = []
    for clang in (True, False) if ctx.compiler_is_clang else (False, False):
        monkeypatch.setattr(ctx, "compiler_is_clang", clang)
        bvh = lbvh.build(v, f, device=ctx)
        lower, upper = refit_numpy(bvh.nodes, bvh.tree.read("parent"), bvh.root, bvh.prim_order, v, f)
        assert np.array_equal(bvh.nodes["lower"], lower) and np.array_equal(bvh.nodes["upper"], upper)
        trees.append(bvh.nodes)
    assert np.array_equal(trees[0].view(np.int32), trees[1].view(np.int32))


def test_refit_of_a_host_tree_with_multi_triangle_leaves(ctx):
    """The refit kernel also serves trees whose leaves are listed (other builders)."""
    import lbvh
    from lbvh.layout import make_nodes
    v, f = shipped_mesh("suzanne.obj")
    n = len(f)
    # root 0 with two leaves holding the two halves of the triangles
    children = np.array([[1, 2], [-1, -1], [-1, -1]])
    ranges = np.array([[0, 0], [0, n // 2], [n // 2, n - n // 2]])
    nodes = make_nodes(np.zeros((3, 3)), np.zeros((3, 3)), children, ranges)
    bvh = lbvh.BVH.from_arrays(nodes, np.arange(n), 0, v, f, builder="hand-made", validate=False)
    bvh.refit(v)
    bvh.validate()
    lower, upper = refit_numpy(bvh.nodes, bvh.tree.read("parent"), 0, bvh.prim_order, v, f)
    assert np.array_equal(bvh.nodes["lower"], lower) and np.array_equal(bvh.nodes["upper"], upper)
