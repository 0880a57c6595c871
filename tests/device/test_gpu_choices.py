"""The GPU's code paths against PoCL's CPU. Where the tests' device (``LBVH_DEVICE``)
is a GPU, that GPU; elsewhere PoCL's CPU device in a context whose ``is_cpu`` is
False, so that it takes every choice the package makes for a GPU (emit.cl's
scalar form, the sort's small chunks, 4-wide records, work-groups of 64). Its
trees must be the CPU's node for node and its answers the same.

On PoCL alone this cannot catch a GPU compiler's own mistakes (the NVIDIA H200's
run found the emission's vector form wrong there: bench/results/device-nvidia-cuda-*);
on a GPU with PoCL beside it, it does. It keeps the GPU's paths, which CI never
runs on a GPU, from drifting from the CPU's.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

import lbvh
from conftest import pocl_cpu_device, random_soup, shipped_mesh
from lbvh import device as dev
from lbvh.builders.refit import refit_numpy
from lbvh.device import programs
from lbvh.metrics.error_bound import WINDING_BOUND

SCENES = {"teapot": lambda: shipped_mesh("teapot.obj"),
          "soup": lambda: random_soup(20000, seed=11)}


@pytest.fixture(scope="module")
def cpu_ctx(ctx):
    """PoCL's CPU device with the CPU's choices (the tests' context where it is PoCL)."""
    if ctx.is_cpu:
        return ctx
    return dev.get_context(pocl_cpu_device(f"{ctx.name} is compared with PoCL's CPU"))


@pytest.fixture(scope="module")
def gpu_ctx(ctx):
    """The tests' device where it is a GPU, else PoCL's CPU taking the GPU's choices."""
    if not ctx.is_cpu:
        return ctx
    gpu = dev.Context(dev.find_device(None))   # its own program cache
    gpu.is_cpu = False
    return gpu


def _inputs(v, n_rays=4000, n_points=2000):
    rng = np.random.default_rng(5)
    lo, hi = v.min(0), v.max(0)
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    origins = (centre + rng.normal(size=(n_rays, 3)) * size).astype(np.float32)
    targets = (centre + rng.normal(size=(n_rays, 3)) * size * 0.1).astype(np.float32)
    points = (centre + rng.normal(size=(n_points, 3)) * size * 0.3).astype(np.float32)
    return origins, targets - origins, points, size


@pytest.mark.parametrize("scene", sorted(SCENES))
@pytest.mark.parametrize("key_bits", [30, 63])
def test_gpu_choices_build_the_cpu_choices_tree(cpu_ctx, gpu_ctx, scene, key_bits):
    v, f = SCENES[scene]()
    cpu = lbvh.build(v, f, device=cpu_ctx, key_bits=key_bits)
    gpu = lbvh.build(v, f, device=gpu_ctx, key_bits=key_bits)
    gpu.validate()
    assert np.array_equal(gpu.nodes.view(np.int32), cpu.nodes.view(np.int32))
    assert np.array_equal(gpu.prim_order, cpu.prim_order)
    # the sort's counters no longer cost hundreds of bytes a key on a GPU
    assert gpu.report().peak_device_bytes <= cpu.report().peak_device_bytes * 1.25


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_gpu_choices_answer_as_the_cpu_choices(cpu_ctx, gpu_ctx, scene):
    v, f = SCENES[scene]()
    cpu = lbvh.build(v, f, device=cpu_ctx)
    gpu = lbvh.build(v, f, device=gpu_ctx)
    o, d, p, size = _inputs(v)
    a, b = gpu.intersect(o, d), cpu.intersect(o, d)
    for name in ("t", "prim", "u", "v"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(gpu.count_hits(o, d), cpu.count_hits(o, d))
    a, b = gpu.all_hits(o, d), cpu.all_hits(o, d)
    for name in ("offsets", "t", "prim", "u", "v"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    a, b = gpu.closest_points(p), cpu.closest_points(p)
    # the same distance and point; where several triangles share the closest point
    # (a vertex or an edge), 4-wide and 8-wide records may name different ones
    assert np.array_equal(a.distance, b.distance) and np.array_equal(a.points, b.points)
    # the hierarchical winding numbers group the triangles by record: 4-wide and
    # 8-wide records approximate differently, each within the stated bound of the
    # exact sum, so within twice it of each other
    wa, wb = gpu.winding_numbers(p), cpu.winding_numbers(p)
    assert np.abs(wa - wb).max() <= 2 * WINDING_BOUND
    a, b = gpu.overlapping(p - size * 0.01, p + size * 0.01), cpu.overlapping(p - size * 0.01, p + size * 0.01)
    assert np.array_equal(a.offsets, b.offsets) and np.array_equal(a.prims, b.prims)


def test_bottom_up_walks_across_work_groups_equal_their_twins(gpu_ctx):
    """The walks of a node's two children may run in different work-groups, so the
    fence around their handshake must reach the whole device (common.h's
    device_fence). With OpenCL's mem_fence, a work-group fence on NVIDIA (membar.cta),
    5 of 10 builds of this 4M-triangle soup on the H200 had 13 to 43 node boxes that
    missed part of a child; with membar.gl, 0 of 10. On a GPU the test builds that
    soup five times; on PoCL (the GPU's choices, one coherent memory) a smaller one
    twice, to keep the path's answers tied to the twin."""
    gpu = not gpu_ctx.device.type & cl.device_type.CPU
    n, builds = (4_000_000, 5) if gpu else (300_000, 2)
    v, f = random_soup(n, seed=3)
    twin = topology = None
    for _ in range(builds):
        bvh = lbvh.build(v, f, device=gpu_ctx)
        words = bvh.nodes.view(np.int32).reshape(-1, 8)[:, [3, 7]]
        if twin is None:
            twin = refit_numpy(bvh.nodes, bvh.tree.read("parent"), bvh.root, bvh.prim_order, v, f)
            topology = words.copy()
        assert np.array_equal(words, topology)          # the emission is deterministic
        bad = ~((bvh.nodes["lower"] == twin[0]).all(1) & (bvh.nodes["upper"] == twin[1]).all(1))
        assert not bad.any(), (f"{int(bad.sum())} node boxes differ from the serial refit's "
                               f"(first: node {int(np.flatnonzero(bad)[0])})")


def test_device_fence_reaches_the_whole_device_on_gpus_that_have_one():
    """The choice of common.h's DEVICE_FENCE by device kind, vendor and OpenCL C
    (the kernels' side of it is checked on the device itself, above and below)."""
    class Feature:
        def __init__(self, name):
            self.name = name

    class Device:                       # the fields build_options reads
        def __init__(self, kind, vendor, c_version="OpenCL C 1.2", features=None):
            self.type, self.vendor, self.opencl_c_version = kind, vendor, c_version
            self.single_fp_config = 0
            self.features = None if features is None else [Feature(n) for n in features]

        def get_info(self, what):        # OpenCL C's features: OpenCL 3.0 devices only
            if self.features is None:
                raise ValueError("no such query before OpenCL 3.0")
            return self.features

    gpu, cpu = cl.device_type.GPU, cl.device_type.CPU
    scoped = ("__opencl_c_atomic_scope_device", "__opencl_c_atomic_order_acq_rel")
    assert programs.device_fence(Device(gpu, "NVIDIA Corporation")) == programs.FENCE_NVIDIA
    assert programs.device_fence(Device(cpu, "NVIDIA Corporation")) == programs.FENCE_MEM_FENCE
    assert programs.device_fence(Device(cpu, "GenuineIntel", features=scoped)) == programs.FENCE_MEM_FENCE
    amd20 = Device(gpu, "Advanced Micro Devices, Inc.", "OpenCL C 2.0")
    intel30 = Device(gpu, "Intel(R) Corporation", "OpenCL C 1.2", scoped)
    for device, std in ((amd20, "CL2.0"), (intel30, "CL3.0")):
        assert programs.device_fence(device) == programs.FENCE_DEVICE_SCOPE
        assert programs.build_options(device, {})[0] == f"-cl-std={std}"
    # OpenCL 3.0 without both features, or OpenCL C 1.2 alone: no device-scope fence
    for plain in (Device(gpu, "Some GPU", "OpenCL C 3.0", scoped[:1]),
                  Device(gpu, "Some GPU", "OpenCL C 1.2")):
        assert programs.device_scope_std(plain) is None
        assert programs.device_fence(plain) == programs.FENCE_MEM_FENCE
        assert programs.build_options(plain, {})[0] == "-cl-std=CL1.2"
        with pytest.raises(dev.DeviceError, match="DEVICE_FENCE=2 needs OpenCL C 2.0"):
            programs.build_options(plain, {}, programs.FENCE_DEVICE_SCOPE)


def test_every_kernel_is_compiled_with_the_devices_fence(ctx):
    options = ctx.build_options({"A": 1})
    assert f"-DDEVICE_FENCE={programs.device_fence(ctx.device)}" in options and "-DA=1" in options


def _same_walks(ctx_a, ctx_b, seed: int) -> None:
    """Every bottom-up walk gives the same bits in both contexts: the trees of the
    build's refit, the treelets and the collapse, the winding moments (through the
    winding numbers) and a refit after the vertices moved."""
    v, f = random_soup(50_000, seed=seed)
    points = _inputs(v)[2]
    for options in ({}, {"treelet_rounds": 1}, {"collapse": True}):
        a = lbvh.build(v, f, device=ctx_a, **options)
        b = lbvh.build(v, f, device=ctx_b, **options)
        a.validate()
        assert np.array_equal(a.nodes.view(np.int32), b.nodes.view(np.int32)), options
        assert np.array_equal(a.winding_numbers(points), b.winding_numbers(points)), options
    moved = v + np.float32(0.01) * np.sin(v).astype(np.float32)
    a.refit(moved)
    b.refit(moved)
    assert np.array_equal(a.nodes.view(np.int32), b.nodes.view(np.int32))


def test_the_device_scope_fence_gives_the_same_trees(cpu_ctx):
    """DEVICE_FENCE=2 (OpenCL C 3.0's device-scope fence, for GPUs other than
    NVIDIA's), compiled as OpenCL C 3.0 where PoCL has the features: the trees of
    every bottom-up walk equal those of the CPU's choices (_same_walks)."""
    if programs.device_scope_std(cpu_ctx.device) is None:
        pytest.skip(f"{cpu_ctx.name} has no device-scope fence (OpenCL C 2.0, or 3.0's features)")
    scoped = dev.Context(cpu_ctx.device)          # its own programs, compiled with the fence
    scoped.fence = programs.FENCE_DEVICE_SCOPE
    assert "-DDEVICE_FENCE=2" in scoped.build_options({})
    assert not {"-cl-std=CL1.2"} & set(scoped.build_options({}))
    _same_walks(scoped, cpu_ctx, seed=4)


def test_walks_as_one_work_group_give_the_same_trees(gpu_ctx):
    """On a GPU whose fence does not reach other work-groups (OpenCL C 1.2 alone, not
    NVIDIA's), the bottom-up walks run as one work-group (Context.walk_launch): every
    walk's results equal those of the usual launches (_same_walks; the GPU's choices
    on PoCL where the tests' device is not a GPU)."""
    one = dev.Context(gpu_ctx.device)
    one.is_cpu = False
    one.fence_reaches_device = False
    launch = one.walk_launch(100_000)
    assert launch.global_size == launch.local_size <= 256
    assert launch.per_item * launch.global_size >= 100_000
    _same_walks(one, gpu_ctx, seed=6)
