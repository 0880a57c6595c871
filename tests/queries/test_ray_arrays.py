"""Rays from wherever users hold them (issue 19, item 8): any host array, pyopencl
arrays on the BVH's context (traced in place, answers left on the device), and
the non-blocking calls.

Every answer is compared bit for bit with the plain numpy call on the same rays.
"""
from __future__ import annotations

import array
import threading

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array
import pytest

from lbvh.queries import traverse
from lbvh.queries.rays import check_rays, device_array_rays, device_invalid, invalid_mask
from lbvh.queries.traverse import DeviceHitArrays, Hits
from test_invalid_rays import good_rays, mixed_rays, teapot

FIELDS = ("t", "prim", "u", "v", "overflow", "invalid", "nodes_visited", "tris_tested")


def assert_same(got: Hits, want: Hits) -> None:
    for name in FIELDS:
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    assert got.overflow_count == want.overflow_count
    assert got.invalid_count == want.invalid_count


# -- host arrays of any kind ---------------------------------------------------------------

class InterfaceOnly:
    """Exposes a numpy array through ``__array_interface__`` alone."""

    def __init__(self, a):
        self._a = a
        self.__array_interface__ = a.__array_interface__


class DLPackOnly:
    """Exposes a numpy array through ``__dlpack__`` alone."""

    def __init__(self, a, device=(1, 0)):
        self._a, self._device = a, device

    def __dlpack__(self, **kwargs):
        return self._a.__dlpack__(**kwargs)

    def __dlpack_device__(self):
        return self._device


class ArrayOnly:
    """Exposes a numpy array through ``__array__`` alone."""

    def __init__(self, a):
        self._a = a

    def __array__(self, dtype=None, copy=None):
        return self._a if dtype is None else self._a.astype(dtype)


@pytest.mark.parametrize("wrap", [memoryview, InterfaceOnly, DLPackOnly, ArrayOnly],
                         ids=["memoryview", "array_interface", "dlpack", "array"])
def test_host_arrays_of_any_kind_are_read_without_a_copy(wrap):
    o, d = good_rays(200)
    rays = check_rays(wrap(o), wrap(d))
    assert np.shares_memory(rays.origins, o) and np.shares_memory(rays.directions, d)
    assert_same(teapot().intersect(wrap(o), wrap(d), counters=True),
                teapot().intersect(o, d, counters=True))
    hits = teapot().intersect(o, d)
    assert np.array_equal(hits.locations(wrap(o), wrap(d)), hits.locations(o, d), equal_nan=True)


def test_an_array_module_array_and_float64_are_converted():
    o, d = good_rays(30)
    flat = array.array("d", o.astype(np.float64).ravel())
    got = teapot().intersect(np.frombuffer(flat).reshape(-1, 3), d)
    assert_same(got, teapot().intersect(o, d))


def test_device_memory_that_is_not_opencl_is_refused_clearly():
    o, d = good_rays(4)
    with pytest.raises(ValueError, match=r"origins: .*device memory \(DLPack device type 2\)"):
        teapot().intersect(DLPackOnly(o, device=(2, 0)), d)


def test_torch_tensors_if_torch_is_installed():
    torch = pytest.importorskip("torch")
    o, d = good_rays(100)
    to, td = torch.from_numpy(o), torch.from_numpy(d)
    assert np.shares_memory(check_rays(to, td).origins, o)
    assert_same(teapot().intersect(to, td), teapot().intersect(o, d))


# -- pyopencl arrays -------------------------------------------------------------------

def on_device(*arrays):
    q = teapot().ctx.queue
    return [cl_array.to_device(q, np.ascontiguousarray(a)) for a in arrays]


@pytest.mark.parametrize("query", ["intersect", "occluded"])
def test_pyopencl_rays_are_traced_in_place_and_answers_stay_on_the_device(query):
    bvh = teapot()
    o, d = good_rays(700, seed=4)
    o[::5] += 1000
    extra = {} if query == "intersect" else {"return_hits": True}
    call = getattr(bvh, query)
    want = call(o, d, counters=True, **extra)
    do, dd = on_device(o, d)
    got = call(do, dd, counters=True, **extra)
    assert isinstance(got, DeviceHitArrays) and len(got) == 700
    for name in ("t", "prim", "u", "v", "overflow", "invalid", "mask", "nodes_visited"):
        arr = getattr(got, name)
        assert isinstance(arr, cl_array.Array) and arr.context == bvh.ctx.ctx, name
    assert got.prim.dtype == np.int32 and got.mask.dtype == bool and got.t.dtype == np.float32
    host = got.get()
    assert_same(host, want)
    assert np.array_equal(got.mask.get(), want.mask)
    assert np.array_equal(host.normals, want.normals, equal_nan=True)
    if query == "occluded":
        answer = bvh.occluded(do, dd)
        assert isinstance(answer, cl_array.Array) and np.array_equal(answer.get(), want.hit)


@pytest.mark.parametrize("intervals", ["scalars", "host arrays", "device arrays", "mixed"])
def test_pyopencl_rays_with_every_kind_of_interval(intervals):
    bvh = teapot()
    o, d = good_rays(300, seed=5)
    rng = np.random.default_rng(5)
    lo = (rng.random(300) * 0.5).astype(np.float32)
    hi = (0.9 + rng.random(300) * 0.2).astype(np.float32)
    # rays aimed at points on the mesh hit at t = 1 (exactly, for many): tmax just
    # below leaves some of them out, so that both hits and misses are checked
    if intervals == "scalars":
        lo, hi = np.float32(0.3), np.float32(0.999)
    args = {"scalars": (lo, hi), "host arrays": (lo, hi), "device arrays": on_device(lo, hi),
            "mixed": (on_device(lo)[0], 0.999)}[intervals]
    want = bvh.intersect(o, d, lo, 0.999 if intervals == "mixed" else hi)
    assert 0.1 < want.hit.mean() < 0.95
    assert_same(bvh.intersect(*on_device(o, d), *args).get(), want)


def test_pyopencl_float64_offset_and_other_queue_arrays():
    bvh = teapot()
    o, d = good_rays(400, seed=6)
    want = bvh.intersect(o[100:], d[100:])
    other_queue = cl.CommandQueue(bvh.ctx.ctx)
    do = cl_array.to_device(other_queue, o.astype(np.float64))[100:]    # converted, at an offset
    dd = cl_array.to_device(other_queue, d)[100:]
    assert do.offset and dd.offset
    assert_same(bvh.intersect(do, dd).get(), want)
    # the inputs are left as they were (converted copies are the query's own)
    assert np.array_equal(do.get(), o[100:].astype(np.float64))


def test_pyopencl_arrays_empty_and_bad_layouts():
    bvh = teapot()
    empty = bvh.intersect(*on_device(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)))
    assert len(empty) == 0 and empty.overflow_count == 0 and len(empty.get()) == 0
    o, d = good_rays(8)
    do, dd = on_device(o, d)
    other = cl.Context([bvh.ctx.device])
    elsewhere = cl_array.to_device(cl.CommandQueue(other), o)
    cases = [
        ((elsewhere, dd), "origins: a pyopencl array on another OpenCL context"),
        ((do, d), "directions: a numpy.ndarray, but origins is a pyopencl array"),
        ((o, dd), "origins: a numpy.ndarray, but directions is a pyopencl array"),
        ((on_device(o[:, :2])[0], dd), r"origins: shape \(8, 2\)"),
        ((do, dd[:4]), "directions: 4 rays, but origins has 8"),
        ((do, dd, 0.0, on_device(np.ones(3, np.float32))[0]), r"tmax: shape \(3,\)"),
        ((on_device(o.astype(np.complex64))[0], dd), "origins: dtype complex64"),
        ((o, d, on_device(np.zeros(8, np.float32))[0]), "tmin: a pyopencl array where host arrays"),
        ((cl_array.to_device(bvh.ctx.queue, o.T.copy()).T, dd), "non-contiguous"),   # Fortran order
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            bvh.intersect(*args)


def test_the_device_check_equals_its_numpy_twin():
    """Every rule of rays.py checked on the device (kernel lbvh_ray_validity) flags
    exactly the rays invalid_mask flags: -0.0, denormals and the largest float32
    included."""
    bvh = teapot()
    o, d, lo, hi, bad = mixed_rays(2000, seed=9)
    for intervals in ((lo, hi), (np.float32(0.0), np.float32(np.inf)), (np.float32(2.0), np.float32(1.0))):
        host = check_rays(o, d, *intervals, invalid_rays="miss")
        want = invalid_mask(host.origins, host.directions, host.tmin, host.tmax)
        given = device_array_rays(bvh.ctx, *on_device(o, d), *intervals)
        mask, count = device_invalid(bvh.ctx, given.rays, given.wait_for)
        assert np.array_equal(mask.get(), want) and count == int(want.sum())
    assert np.array_equal(want, np.ones(len(o), bool))   # tmin > tmax everywhere


def test_pyopencl_bad_rays_raise_as_host_ones_or_come_back_as_misses():
    bvh = teapot()
    o, d, lo, hi, bad = mixed_rays(900, seed=2)
    with pytest.raises(ValueError) as host_error:
        bvh.intersect(o, d, lo, hi)
    with pytest.raises(ValueError) as device_error:
        bvh.intersect(*on_device(o, d, lo, hi))
    assert str(device_error.value) == str(host_error.value)
    for query, extra in (("intersect", {}), ("occluded", {"return_hits": True})):
        call = getattr(bvh, query)
        want = call(o, d, lo, hi, invalid_rays="miss", counters=True, **extra)
        got = call(*on_device(o, d, lo, hi), invalid_rays="miss", counters=True, **extra)
        assert got.invalid_count == int(bad.sum()) > 0
        assert_same(got.get(), want)


# -- non-blocking calls ------------------------------------------------------------------

def test_futures_give_the_blocking_answers_and_their_errors():
    bvh = teapot()
    o, d = good_rays(2000, seed=8)
    want = bvh.intersect(o, d, counters=True)
    blocked = bvh.occluded(o, d, tmax=0.9)
    futures = [bvh.intersect_async(o, d, counters=True) for _ in range(6)]
    futures += [bvh.occluded_async(o, d, tmax=0.9)]
    device = bvh.intersect_async(*on_device(o, d))
    for f in futures[:6]:
        assert_same(f.result(timeout=120), want)
    assert np.array_equal(futures[6].result(timeout=120), blocked)
    assert_same(device.result(timeout=120).get(), bvh.intersect(o, d))
    bad = o.copy()
    bad[3, 0] = np.nan
    failing = bvh.intersect_async(bad, d)
    with pytest.raises(ValueError, match="origins: ray 3"):
        failing.result(timeout=120)
    assert bvh.intersect_async(bad, d, invalid_rays="miss").result(timeout=120).invalid_count == 1


def test_futures_run_off_the_calling_thread():
    bvh = teapot()
    o, d = good_rays(50)
    seen = []
    original = bvh.ctx.lock

    with original:   # while this thread holds the device, the query waits for it
        future = bvh.intersect_async(o, d)
        future.add_done_callback(lambda f: seen.append(threading.current_thread().name))
        assert not future.done()
    future.result(timeout=120)
    assert seen and seen[0].startswith("lbvh-query")


def test_pyopencl_rays_ordered_on_the_device_give_the_same_answers(monkeypatch):
    """Large batches over large trees are sorted first (lbvh/queries/ray_order.py):
    forced here for the device path; with a bad ray among them they are not."""
    bvh = teapot()
    o, d, lo, hi, bad = mixed_rays(1500, seed=11)
    good = ~bad
    want = bvh.intersect(o[good], d[good], lo[good], hi[good])
    orders = []
    monkeypatch.setattr(traverse, "worth_ordering", lambda rays, nodes: True)
    monkeypatch.setattr(traverse, "ray_order",
                        lambda *args, real=traverse.ray_order: orders.append(args[3]) or real(*args))
    assert_same(bvh.intersect(*on_device(o[good], d[good], lo[good], hi[good])).get(), want)
    assert orders == [int(good.sum())]
    missed = bvh.intersect(*on_device(o, d, lo, hi), invalid_rays="miss").get()
    assert missed.t[good].tobytes() == want.t.tobytes() and missed.invalid_count == bad.sum()
    assert len(orders) == 1
