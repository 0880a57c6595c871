"""One owner of device memory: every buffer, build or query, is counted, so peaks are true."""
from __future__ import annotations

import ast
import gc
from pathlib import Path

import numpy as np

import lbvh
from conftest import random_soup
from lbvh.layout import NODE_DTYPE

PACKAGE = Path(lbvh.__file__).resolve().parent


def test_only_the_memory_module_makes_buffers():
    """No module of the package calls ``pyopencl.Buffer(...)`` itself."""
    makers = []
    for path in PACKAGE.rglob("*.py"):
        if path.relative_to(PACKAGE).as_posix() == "device/memory.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and ast.unparse(node.func) in ("cl.Buffer",
                                                                         "pyopencl.Buffer"):
                makers.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    assert not makers, makers


def test_a_build_with_collapse_reports_the_peak_of_both_trees(ctx):
    """The collapse writes its tree while the built one is alive: both count."""
    v, f = random_soup(20000, seed=5)
    plain = lbvh.build(v, f)
    bvh = lbvh.build(v, f, collapse=True)
    n = len(f)
    both = NODE_DTYPE.itemsize * (2 * n - 1 + bvh.tree.num_nodes)
    assert bvh.report().peak_device_bytes >= both > plain.report().peak_device_bytes


def test_queries_are_counted_and_give_everything_back(ctx):
    v, f = random_soup(5000, seed=6)
    bvh = lbvh.build(v, f)
    rng = np.random.default_rng(0)
    o = rng.random((20000, 3), dtype=np.float32)
    d = rng.normal(size=(20000, 3)).astype(np.float32)
    bvh.intersect(o[:10], d[:10])          # caches made: wide records, faces in slot order
    gc.collect()
    ctx.memory.reset_peak()
    held = ctx.memory.in_use
    bvh.intersect(o, d, batch_size=5000)
    # in batches, each batch's rays (2 x 12 B), hits (16 B) and flags (4 B) per ray were
    # on the device
    assert ctx.memory.peak - held >= 44 * 5000
    assert ctx.memory.in_use == held        # and were given back
    ctx.memory.reset_peak()
    one = bvh.intersect(o, d)                # one batch
    if ctx.is_cpu:
        # read and written in place in the host's arrays: no device memory at all
        assert ctx.memory.peak == held
    else:
        assert ctx.memory.peak - held >= 44 * len(o)
    assert ctx.memory.in_use == held
    batched = bvh.intersect(o, d, batch_size=5000)
    np.testing.assert_array_equal(one.t, batched.t)
    np.testing.assert_array_equal(one.prim, batched.prim)


def test_a_buffer_dropped_without_free_is_counted_out(ctx):
    gc.collect()
    before = ctx.memory.in_use
    buf = ctx.memory.alloc(1 << 16)
    assert ctx.memory.in_use == before + (1 << 16)
    del buf
    gc.collect()
    assert ctx.memory.in_use == before
    released = ctx.memory.alloc(1 << 12)
    released.release()                      # released by its holder: counted out at once
    assert ctx.memory.in_use == before


def test_a_dropped_bvh_gives_its_tree_and_caches_back(ctx):
    v, f = random_soup(3000, seed=7)
    gc.collect()
    before = ctx.memory.in_use
    bvh = lbvh.build(v, f)
    bvh.intersect(v[:4], np.ones((4, 3), np.float32))
    assert ctx.memory.in_use > before
    del bvh
    gc.collect()
    assert ctx.memory.in_use == before


def test_host_outputs_are_aligned_views_that_one_map_reads(ctx):
    """DeviceMemory.host_outputs: one block of host memory, an array per spec at a
    multiple of the device's sub-buffer alignment (read from the device), a sub-buffer
    on each; what the device writes to the sub-buffers is the arrays' after one map of
    the block. An empty spec is refused."""
    import pyopencl as cl
    import pytest
    from lbvh import device as dev

    mem = ctx.memory
    assert mem.sub_align == ctx.device.mem_base_addr_align // 8
    specs = (((4, 3), np.float32), ((3,), np.int32), ((5,), np.uint8))
    out = mem.host_outputs(*specs)
    try:
        base = out.block.ctypes.data
        for (shape, dtype), a, b in zip(specs, out.arrays, out.buffers):
            assert a.shape == shape and a.dtype == dtype and a.flags.c_contiguous
            assert (a.ctypes.data - base) % mem.sub_align == 0 and b.size == a.nbytes
        for k, b in enumerate(out.buffers):
            cl.enqueue_fill_buffer(ctx.queue, b, np.uint8(k + 1), 0, b.size)
        dev.read_host_views(ctx.queue, [(out.block_buffer, out.block)])
        for k, a in enumerate(out.arrays):
            assert (a.view(np.uint8) == k + 1).all()
    finally:
        out.release()
    with pytest.raises(ValueError, match="empty"):
        mem.host_outputs(((0, 3), np.float32))
