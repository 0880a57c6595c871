"""Kernel launches (lbvh.device.launch.run): arguments reach the kernel as given.

``run`` declares a kernel's scalar argument types to pyopencl from the values of
its first call (pyopencl then packs them itself, many times faster than its
generic path); these tests check that every later call's values, and values of
other types, still reach the kernel. The kernel is a small file of the test's
own, compiled by PoCL like the package's.
"""
from __future__ import annotations

import threading

import numpy as np
import pyopencl as cl
import pytest

from lbvh import device as dev
from lbvh.device import programs
from lbvh.device.launch import arg_type

SOURCE = """
__kernel void args(__global float *out, const int i, const uint u, const float f,
                   const float4 v, __global const float *in) {
    out[0] = (float)i;
    out[1] = (float)u;
    out[2] = f;
    out[3] = v.x + 2.0f * v.y + 4.0f * v.z + 8.0f * v.w;
    out[4] = in[0];
}

__kernel void scalars(__global float *out, const int i, const float f) {
    out[0] = (float)i;
    out[1] = f;
}
"""


@pytest.fixture
def kernels(tmp_path, monkeypatch):
    (tmp_path / "launch_args.cl").write_text(SOURCE)
    monkeypatch.setattr(programs, "kernels_dir", lambda: tmp_path)
    return tmp_path


def launch(ctx: dev.Context, out: cl.Buffer, i, u, f, v, value: float) -> np.ndarray:
    src = ctx.memory.upload(np.array([value], np.float32))
    try:
        dev.run(ctx, "launch_args.cl", "args", ctx.launch_chunks(1, 1), out, i, u, f, v, src)
        got = np.empty(5, np.float32)
        cl.enqueue_copy(ctx.queue, got, out, is_blocking=True)
        return got
    finally:
        ctx.memory.free(src)


def test_every_call_passes_its_own_values(kernels, ctx):
    out = ctx.memory.alloc(4 * 5)
    try:
        rng = np.random.default_rng(5)
        for k in range(20):
            i = int(rng.integers(-1000, 1000))
            u = np.uint32(rng.integers(0, 1000))
            f = float(rng.uniform(-5, 5))
            v = rng.uniform(-1, 1, 4).astype(np.float32)
            value = float(np.float32(rng.uniform()))
            # Python and numpy scalars in turn: the same argument types either way
            got = launch(ctx, out, i if k % 2 else np.int32(i), u, f if k % 3 else np.float32(f),
                         v, value)
            expect = [i, float(u), np.float32(f), v[0] + 2 * v[1] + 4 * v[2] + 8 * v[3], value]
            np.testing.assert_array_equal(got, np.array(expect, np.float32))
    finally:
        ctx.memory.free(out)


def test_a_value_of_another_size_is_refused_as_before(kernels, ctx):
    out = ctx.memory.alloc(4 * 5)
    try:
        v = np.zeros(4, np.float32)
        launch(ctx, out, 1, np.uint32(2), 3.0, v, 4.0)
        # an int64 where the kernel takes an int: the runtime refuses its size
        with pytest.raises(cl.Error, match="INVALID_ARG_SIZE"):
            launch(ctx, out, np.int64(1), np.uint32(2), 3.0, v, 4.0)
        # and the kernel's declared types follow the values again afterwards
        got = launch(ctx, out, 7, np.uint32(8), 9.0, v, 10.0)
        np.testing.assert_array_equal(got[[0, 1, 2, 4]], np.float32([7, 8, 9, 10]))
    finally:
        ctx.memory.free(out)


def test_declared_types_follow_the_values_without_vector_arguments(kernels, ctx):
    """A kernel of scalars and buffers only: run() skips re-declaring while the values'
    Python types repeat, and re-declares when they change (an int64 is refused by the
    runtime, then an int32 passes again)."""
    out = ctx.memory.alloc(8)
    got = np.empty(2, np.float32)

    def call(i, f):
        dev.run(ctx, "launch_args.cl", "scalars", ctx.launch_chunks(1, 1), out, i, f)
        cl.enqueue_copy(ctx.queue, got, out, is_blocking=True)
        return got.tolist()
    try:
        for k in range(5):
            assert call(k if k % 2 else np.int32(k), float(k) / 2) == [k, k / 2]
        with pytest.raises(cl.Error, match="INVALID_ARG_SIZE"):
            call(np.int64(1), 1.0)
        assert call(7, np.float32(3.5)) == [7, 3.5]
        with pytest.raises(cl.Error, match="INVALID_ARG_SIZE"):
            call(1, np.float64(1.0))
        assert call(np.int32(9), 4.5) == [9, 4.5]
    finally:
        ctx.memory.free(out)


def test_threads_launching_one_kernel_each_get_their_own_values(kernels, ctx):
    """The arguments of a shared kernel object are state until its launch: run() sets
    and queues them under the context's lock, so threads never see each other's."""
    failures: list[str] = []

    def work(seed: int) -> None:
        out = ctx.memory.alloc(4 * 5)
        try:
            for k in range(30):
                i = seed * 1000 + k
                got = launch(ctx, out, i, np.uint32(k), float(seed), np.full(4, seed, np.float32),
                             float(k))
                if got[0] != i or got[1] != k or got[2] != seed or got[4] != k:
                    failures.append(f"thread {seed} call {k}: {got}")
        finally:
            ctx.memory.free(out)

    threads = [threading.Thread(target=work, args=(s,)) for s in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures, failures[:3]


def test_argument_types():
    assert arg_type(np.int32(1)) == np.dtype(np.int32)
    assert arg_type(np.float64(1)) == np.dtype(np.float64)
    assert arg_type(np.zeros(4, np.float32)) == np.dtype((np.void, 16))
    assert arg_type(object()) is None
