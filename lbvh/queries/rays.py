"""Rays as the traversal kernel reads them: checks, conversion to float32, upload.

``origins`` and ``directions`` are ``(N, 3)`` arrays (float32; float64 and
integers are converted to float32). Directions need not be unit length: ``t``
is measured in units of the direction's length, the hit point is
``origin + t * direction``. ``tmin`` and ``tmax`` are scalars or ``(N,)``
arrays; a hit counts when ``tmin <= t <= tmax``.

Where arrays come from (:func:`host_array`)
    Any host array: a numpy array, anything with ``__array_interface__`` or the
    buffer protocol (a ``memoryview``, an ``array.array``), anything with a
    CPU ``__dlpack__`` (a torch CPU tensor, a JAX CPU array: read through
    ``np.from_dlpack``), or ``__array__``; read without a copy where the dtype
    is float32 and the rows are C-contiguous. An array in device memory that
    is not a ``pyopencl.array.Array`` on the BVH's context (a CUDA tensor, a
    cupy array) is refused with a ``ValueError`` that says so: copy it to the
    host first. ``pyopencl.array.Array`` rays on the BVH's context are read in
    place on the device (:func:`device_array_rays`).

Bad rays
    NaN or infinite origins and directions (also values beyond the float32
    range), zero-length directions (after the float32 conversion), NaN,
    negative or infinite ``tmin``, NaN ``tmax``, ``tmin > tmax``. By default
    (``invalid_rays="raise"``) they are refused before anything runs on the
    device, with a ``ValueError`` naming the first bad ray. With
    ``invalid_rays="miss"`` they are not traced and come back as misses,
    flagged (:func:`invalid_mask` says which). Wrong shapes or dtypes always
    raise.

The checks cost a few passes over the arrays and make no temporary array as
long as no ray is bad; the per-ray mask is made only when one is. On the
device the same rules are checked by one kernel (:func:`device_invalid`,
whose numpy twin is :func:`invalid_mask`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from .. import device as dev
from ..mesh import real_array

#: What becomes of bad rays: refused with a ValueError, or reported as misses.
INVALID_RAYS = ("raise", "miss")
InvalidRays = Literal["raise", "miss"]

_DLPACK_CPU = 1    # DLDeviceType kDLCPU
_DLPACK_CPU_PINNED = 3


def check_invalid_rays(invalid_rays: Any) -> str:
    """The ``invalid_rays`` option, checked."""
    if not isinstance(invalid_rays, str) or invalid_rays not in INVALID_RAYS:
        raise ValueError(f"invalid_rays: {invalid_rays!r}; expected one of "
                         f"{', '.join(map(repr, INVALID_RAYS))}")
    return invalid_rays


def is_device_array(value: Any) -> bool:
    """Whether ``value`` is a ``pyopencl.array.Array`` (read in place on the device)."""
    return isinstance(value, cl_array.Array)


def _kind(value: Any) -> str:
    cls = type(value)
    module = cls.__module__.split(".")[0]
    return cls.__name__ if module == "builtins" else f"{module}.{cls.__name__}"


def host_array(name: str, value: Any) -> Any:
    """``value`` as something ``np.asarray`` reads without a copy where it can.

    numpy arrays, ``__array_interface__`` and buffer-protocol objects pass as
    they are; an object with only ``__dlpack__`` (or whose ``__array__`` would
    copy) and a CPU DLPack device is read through ``np.from_dlpack``. Device
    memory other than a ``pyopencl.array.Array`` raises ``ValueError``.
    """
    if isinstance(value, np.ndarray) or hasattr(value, "__array_interface__"):
        return value
    if is_device_array(value):
        raise ValueError(f"{name}: a pyopencl array where host arrays are read (origins and "
                         "directions decide: pass them as pyopencl arrays too, or this as a "
                         "host array, a.get())")
    if hasattr(value, "__dlpack__") and hasattr(value, "__dlpack_device__"):
        try:
            device_type = int(value.__dlpack_device__()[0])
        except Exception:   # an object that answers nothing sensible: let numpy try
            device_type = _DLPACK_CPU
        if device_type not in (_DLPACK_CPU, _DLPACK_CPU_PINNED):
            raise ValueError(f"{name}: a {_kind(value)} in device memory (DLPack device type "
                             f"{device_type}); lbvh reads host arrays and pyopencl arrays on the "
                             "BVH's context: copy it to the host first (e.g. tensor.cpu(), "
                             "cupy.asnumpy(a))")
        try:
            return np.from_dlpack(value)
        except (BufferError, TypeError, RuntimeError, ValueError):
            pass   # read-only or unusual strides: numpy's own conversion below
    if hasattr(value, "__cuda_array_interface__"):
        raise ValueError(f"{name}: a {_kind(value)} in CUDA memory; lbvh reads host arrays and "
                         "pyopencl arrays on the BVH's context: copy it to the host first")
    return value


def _real(name: str, value: Any) -> np.ndarray:
    return real_array(name, host_array(name, value))


@dataclass
class Rays:
    """Checked rays, as the kernel reads them.

    ``origins``, ``directions``: ``float32 (N, 3)`` C-contiguous. ``tmin``,
    ``tmax``: ``float32``, each a 0-d array (one value for every ray) or ``(N,)``.
    ``invalid``: ``None`` when every ray is good, else ``bool (N,)``, the bad rays
    (only with ``invalid_rays="miss"``).
    """
    origins: np.ndarray
    directions: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    invalid: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.origins)

    def intervals(self) -> tuple[np.ndarray, np.ndarray]:
        """``tmin`` and ``tmax`` as ``float32 (N,)`` arrays."""
        n = len(self)
        return np.broadcast_to(self.tmin, (n,)), np.broadcast_to(self.tmax, (n,))

    def kernel_intervals(self) -> tuple[np.ndarray, np.ndarray, int]:
        """``(tmin, tmax, stride)`` as the kernel reads them: C-contiguous ``(N,)``
        arrays with stride 1 when either varies per ray, else one value each, stride 0."""
        if self.tmin.ndim == 1 or self.tmax.ndim == 1:
            lo, hi = self.intervals()
            return np.ascontiguousarray(lo), np.ascontiguousarray(hi), 1
        return self.tmin.reshape(1), self.tmax.reshape(1), 0

    def take(self, index: np.ndarray) -> "Rays":
        """The rays ``index`` names (copies), all of them good if ``index`` says so."""
        def pick(a: np.ndarray) -> np.ndarray:
            return a if a.ndim == 0 else np.ascontiguousarray(a[index])
        return Rays(pick(self.origins), pick(self.directions), pick(self.tmin), pick(self.tmax))


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _as_float32(name: str, arr: np.ndarray) -> np.ndarray:
    """C-contiguous float32; values beyond the float32 range become infinite (refused later)."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.asarray(arr, dtype=np.float32)   # a scalar stays 0-d (ascontiguousarray: 1-d)
    return out if out.flags.c_contiguous else np.ascontiguousarray(out)


def _check_vectors(name: str, shape: tuple[int, ...], count: int | None) -> None:
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"{name}: shape {shape}, expected (N, 3)")
    if count is not None and shape[0] != count:
        raise ValueError(f"{name}: {shape[0]} rays, but origins has {count}")


def _check_interval(name: str, shape: tuple[int, ...], count: int) -> None:
    if len(shape) != 0 and shape != (count,):
        raise ValueError(f"{name}: shape {shape}, expected a scalar or ({count},)")


def _ray_vectors(name: str, value: Any, count: int | None) -> np.ndarray:
    """The caller's ``(N, 3)`` array, shape and dtype checked, as float32."""
    arr = _real(name, value)
    _check_vectors(name, arr.shape, count)
    return _as_float32(name, arr)


def _interval(name: str, value: Any, count: int) -> np.ndarray:
    """The caller's scalar or ``(N,)`` array, shape and dtype checked, as float32."""
    arr = _real(name, value)
    _check_interval(name, arr.shape, count)
    return _as_float32(name, arr)


def _all_finite(a: np.ndarray) -> bool:
    """No NaN or infinity in ``a``: its minimum and maximum are finite (NaN propagates
    through both); two reductions without temporaries instead of an isfinite mask."""
    return a.size == 0 or bool(np.isfinite(a.min()) and np.isfinite(a.max()))


def _all_nonzero_rows(d: np.ndarray) -> bool:
    """Every row of float32 ``d`` has a nonzero component: the OR of the three bit
    patterns, sign bit dropped, is nonzero."""
    bits = d.view(np.uint32)
    return bool((((bits[:, 0] | bits[:, 1] | bits[:, 2]) << np.uint32(1)) != 0).all())


def _intervals_ok(lo: np.ndarray, hi: np.ndarray) -> bool:
    with np.errstate(invalid="ignore"):
        return bool(not np.isnan(hi).any() and (lo >= 0).all() and np.isfinite(lo).all()
                    and (lo <= hi).all())


def invalid_mask(origins: np.ndarray, directions: np.ndarray, tmin: np.ndarray,
                 tmax: np.ndarray) -> np.ndarray:
    """``bool (N,)``: the rays the checks refuse (the module docstring's list), of
    float32 ``(N, 3)`` C-contiguous origins and directions and float32 intervals
    (scalars or ``(N,)``). The numpy twin of :func:`device_invalid`'s kernel."""
    n = len(origins)
    lo, hi = np.broadcast_to(tmin, (n,)), np.broadcast_to(tmax, (n,))
    bits = directions.view(np.uint32)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(origins).all(axis=1)
        bad |= ~np.isfinite(directions).all(axis=1)
        bad |= ((bits[:, 0] | bits[:, 1] | bits[:, 2]) << np.uint32(1)) == 0
        bad |= np.isnan(hi) | ~(lo >= 0) | np.isinf(lo) | ~(lo <= hi)
    return bad


def _raise_first_bad(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     given_o: np.ndarray, given_d: np.ndarray) -> None:
    """Name the first problem of converted rays (slow path, only after the fast checks failed)."""
    for name, vec, given in (("origins", o, given_o), ("directions", d, given_d)):
        bad = ~np.isfinite(vec).all(axis=1)
        if bad.any():
            i = _first_bad(bad)
            raise ValueError(f"{name}: ray {i} has a NaN, infinite or beyond-float32 component "
                             f"{given[i].tolist()}")
    zero = ~(d != 0).any(axis=1)
    if zero.any():
        raise ValueError(f"directions: ray {_first_bad(zero)} has a zero-length direction "
                         "(after conversion to float32)")
    lo, hi = np.broadcast_to(lo, (len(o),)), np.broadcast_to(hi, (len(o),))
    for name, col in (("tmin", lo), ("tmax", hi)):
        if np.isnan(col).any():
            raise ValueError(f"{name}: ray {_first_bad(np.isnan(col))} is NaN")
    checks = ((lo < 0, "tmin: ray {i} has a negative tmin {lo}"),
              (np.isinf(lo), "tmin: ray {i} has an infinite tmin"),
              (lo > hi, "tmin/tmax: ray {i} has tmin {lo} > tmax {hi}"))
    for bad, message in checks:
        if bad.any():
            i = _first_bad(bad)
            raise ValueError(message.format(i=i, lo=float(lo[i]), hi=float(hi[i])))


#: Largest finite float32.
_FLOAT32_MAX = float(np.finfo(np.float32).max)
#: Up to this many rays, :func:`_plain_rays` checks with whole-array masks (a few numpy
#: calls) rather than the temporary-free reductions of the general path.
_PLAIN_RAYS = 4096


def _plain_interval(value: Any) -> float | None:
    """A Python or numpy real scalar that float32 holds (or an infinity, or NaN) as
    the float it becomes in float32; ``None`` for anything else."""
    if isinstance(value, bool) or not isinstance(value, (float, int, np.floating, np.integer)):
        return None
    x = float(value)
    if abs(x) > _FLOAT32_MAX and x not in (np.inf, -np.inf):
        return None   # rounds to float32's largest value or to infinity: the general path
    return float(np.float32(x))


def _plain_rays(origins: Any, directions: Any, tmin: Any, tmax: Any) -> Rays | None:
    """:func:`check_rays` of the common small call, in a few numpy calls: float32
    C-contiguous ``(N, 3)`` arrays (N at most :data:`_PLAIN_RAYS`), scalar intervals,
    every ray good. ``None`` where any of that fails: the general path then checks (and
    names the problem) as before. The same rules, so the same rays pass."""
    if type(origins) is not np.ndarray or type(directions) is not np.ndarray:
        return None
    if origins.dtype != np.float32 or directions.dtype != np.float32 \
            or origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape \
            or len(origins) > _PLAIN_RAYS or not origins.flags.c_contiguous \
            or not directions.flags.c_contiguous:
        return None
    lo, hi = _plain_interval(tmin), _plain_interval(tmax)
    if lo is None or hi is None or not (0 <= lo < np.inf and lo <= hi):   # NaN fails too
        return None
    if not (np.isfinite(origins).all() and np.isfinite(directions).all()
            and (directions != 0).any(axis=1).all()):
        return None
    return Rays(origins, directions, np.array(lo, np.float32), np.array(hi, np.float32))


def check_rays(origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
               invalid_rays: InvalidRays = "raise") -> Rays:
    """Validate rays and convert them to the float32 arrays the kernel reads.

    Values are converted to float32 first and checked after (a float64 beyond the
    float32 range is refused). With ``invalid_rays="raise"`` a bad ray raises
    ``ValueError`` naming the first one; with ``"miss"`` the result's ``invalid``
    marks the bad rays (see the module docstring). Shapes and dtypes always
    raise. Costs a few passes over the arrays (no copy when they are float32 and
    C-contiguous already, no temporary while every ray is good).
    """
    check_invalid_rays(invalid_rays)
    fast = _plain_rays(origins, directions, tmin, tmax)
    if fast is not None:
        return fast
    given_o = _real("origins", origins)
    o = _ray_vectors("origins", given_o, None)
    given_d = _real("directions", directions)
    d = _ray_vectors("directions", given_d, len(o))
    n = len(o)
    lo, hi = _interval("tmin", tmin, n), _interval("tmax", tmax, n)
    ok = (n == 0 or (_all_finite(o) and _all_finite(d) and _all_nonzero_rows(d)
                     and _intervals_ok(lo, hi)))
    if ok:
        return Rays(o, d, lo, hi)
    if invalid_rays == "raise":
        _raise_first_bad(o, d, lo, hi, given_o, given_d)
    return Rays(o, d, lo, hi, invalid_mask(o, d, lo, hi))


@dataclass
class DeviceRays:
    """Rays on the device (``count`` of them), as :func:`trace_buffers` reads them:
    ``origins``, ``directions`` float32 ``3 * count``; ``tmin``, ``tmax`` float32, one
    per ray (``interval_stride`` 1) or one for all (``interval_stride`` 0). ``order``:
    ``int32`` per ray, the order they are traced in (a permutation, see
    :mod:`lbvh.queries.ray_order`; the answers stay in the rays' own slots), or None;
    ``ready``: the events that write these buffers, which a walk waits for."""
    count: int
    origins: cl.Buffer
    directions: cl.Buffer
    tmin: cl.Buffer
    tmax: cl.Buffer
    interval_stride: int
    order: cl.Buffer | None = None
    ready: tuple = ()

    def release(self) -> None:
        """Release the buffers now (their memory counts them out)."""
        for buf in (self.origins, self.directions, self.tmin, self.tmax):
            buf.release()


def upload_rays(ctx: dev.Context, rays: Rays) -> DeviceRays:
    """Copy rays to new device buffers (no checks beyond :func:`check_rays`' types:
    the caller decides what it uploads)."""
    lo, hi, stride = rays.kernel_intervals()
    up = ctx.memory.upload
    return DeviceRays(len(rays), up(rays.origins), up(rays.directions), up(lo), up(hi), stride)


# -- rays in pyopencl arrays ------------------------------------------------------------

@dataclass
class ArrayRays:
    """Rays read from ``pyopencl.array.Array`` inputs (:func:`device_array_rays`).

    ``rays``: what the kernel reads (the caller's own buffers where they are float32,
    C-contiguous and start at their buffer's beginning, else converted copies,
    which are released when the last reference goes: the runtime keeps a buffer
    until the commands queued on it are done); ``wait_for``: the inputs'
    pending events and the conversions'; ``sources``: the input arrays.
    """
    rays: DeviceRays
    wait_for: list[cl.Event]
    sources: list[cl_array.Array]


#: kernels/device_rays.cl: rays in the caller's device arrays.
DEVICE_KERNEL_FILE = "device_rays.cl"

#: Element types of device arrays converted to float32 on the device (float32 at the
#: start of its buffer is read in place).
DEVICE_SOURCE_TYPES = {np.dtype(np.float32): "float", np.dtype(np.float64): "double",
                       np.dtype(np.int32): "int",
                       np.dtype(np.uint32): "uint", np.dtype(np.int64): "long",
                       np.dtype(np.uint64): "ulong"}


def _items(count: int) -> dev.Launch:
    """One item per work-item, in groups of 64 (the kernels stop at ``count``)."""
    return dev.Launch(count, 1, max(1, -(-count // 64) * 64), 64)


def _to_float32(ctx: dev.Context, arr: cl_array.Array, events: list[cl.Event]) -> cl.Buffer:
    """A float32 C-contiguous copy of ``arr`` in a new buffer, converted on the device
    on ``ctx``'s queue (the conversion's event appended to ``events``)."""
    buf = ctx.memory.alloc(4 * arr.size)
    if arr.size:
        ctype = DEVICE_SOURCE_TYPES[arr.dtype]
        defines = {"SRC_T": ctype, **({"SRC_IS_DOUBLE": 1} if ctype == "double" else {})}
        first, rest = divmod(arr.offset, arr.dtype.itemsize)
        if rest:
            raise ValueError(f"a pyopencl array at byte offset {arr.offset}, not a multiple of "
                             f"its element size {arr.dtype.itemsize}")
        events.append(dev.run(ctx, DEVICE_KERNEL_FILE, "to_float32", _items(arr.size),
                              arr.base_data, first, buf, arr.size, defines=defines,
                              wait_for=arr.events or None))
    return buf


def _device_input(ctx: dev.Context, name: str, arr: cl_array.Array, wait_for: list[cl.Event]) -> cl.Buffer:
    """The kernel's float32 buffer for one pyopencl array (context, dtype, layout checked)."""
    if arr.context.int_ptr != ctx.ctx.int_ptr:
        raise ValueError(f"{name}: a pyopencl array on another OpenCL context; pass arrays made "
                         f"on the BVH's context (bvh.ctx.ctx, {ctx.name}) or host arrays")
    if arr.dtype not in DEVICE_SOURCE_TYPES:
        raise ValueError(f"{name}: dtype {arr.dtype} is not a type lbvh reads from a pyopencl "
                         "array (expected float32, float64, int32, uint32, int64 or uint64)")
    if arr.dtype == np.float64 and not ctx.device.double_fp_config:
        raise ValueError(f"{name}: a float64 pyopencl array, but {ctx.name} has no doubles; "
                         "convert it to float32")
    if not arr.flags.c_contiguous:
        raise ValueError(f"{name}: a non-contiguous pyopencl array (strides {arr.strides}); "
                         "pass a C-contiguous one")
    wait_for.extend(arr.events)
    if arr.dtype == np.float32 and arr.offset == 0:
        return arr.base_data
    return _to_float32(ctx, arr, wait_for)


def device_array_rays(ctx: dev.Context, origins: cl_array.Array, directions: cl_array.Array,
                      tmin: Any = 0.0, tmax: Any = np.inf) -> ArrayRays:
    """Rays held in ``pyopencl.array.Array`` objects on ``ctx``, ready for the kernel.

    ``origins`` and ``directions``: ``(N, 3)`` pyopencl arrays of a real type
    (float32 is read in place; others are converted on the device), C-contiguous.
    ``tmin``, ``tmax``: scalars, host ``(N,)`` arrays or pyopencl ``(N,)`` arrays.
    Shapes, dtypes and contexts are checked here (``ValueError``); values are
    checked by :func:`device_invalid`.
    """
    wait_for: list[cl.Event] = []
    sources = [origins, directions]
    for name, arr in (("origins", origins), ("directions", directions)):
        if not is_device_array(arr):
            raise ValueError(f"{name}: a {_kind(arr)}, but "
                             f"{'directions' if name == 'origins' else 'origins'} is a "
                             "pyopencl array; pass both as pyopencl arrays or both as host arrays")
    _check_vectors("origins", origins.shape, None)
    n = origins.shape[0]
    _check_vectors("directions", directions.shape, n)
    o = _device_input(ctx, "origins", origins, wait_for)
    d = _device_input(ctx, "directions", directions, wait_for)
    intervals = []   # (buffer, one value per ray, the host value of a scalar)
    for name, value in (("tmin", tmin), ("tmax", tmax)):
        if is_device_array(value):
            _check_interval(name, value.shape, n)
            per = value.ndim == 1
            intervals.append((_device_input(ctx, name, value.reshape(value.size),
                                            wait_for), per, None))
            sources.append(value)
        else:
            host = _interval(name, value, n)
            buf = ctx.memory.upload(host)
            intervals.append((buf, host.ndim == 1, None if host.ndim else host.reshape(1)))
    per_ray = any(per for _, per, _ in intervals)
    if per_ray:   # one stride for both: a scalar is filled out on the device
        for k, (buf, per, value) in enumerate(intervals):
            if not per:
                if value is None:   # a 0-d pyopencl array: its value is read first
                    value = np.empty(1, np.float32)
                    cl.enqueue_copy(ctx.queue, value, buf, wait_for=wait_for, is_blocking=True)
                full = ctx.memory.alloc(4 * n)
                if n:
                    cl.enqueue_fill_buffer(ctx.queue, full, np.float32(value[0]), 0, 4 * n)
                intervals[k] = (full, True, None)
    rays = DeviceRays(n, o, d, intervals[0][0], intervals[1][0], int(per_ray))
    return ArrayRays(rays, wait_for, sources)


def device_invalid(ctx: dev.Context, rays: DeviceRays,
                   wait_for: list[cl.Event] | None = None) -> tuple[cl_array.Array, int]:
    """``(bool (N,) pyopencl array of the bad rays, how many)``: the checks of
    :func:`check_rays` run on the device (kernels/device_rays.cl ray_validity; its
    twin is :func:`invalid_mask`). The count is read back (4 bytes; this waits
    for the check)."""
    n = rays.count
    bad = cl_array.Array(ctx.queue, (n,), np.bool_, data=ctx.memory.alloc(max(n, 4)))
    if n == 0:
        return bad, 0
    count_buf = ctx.memory.alloc(4)
    try:
        fill = cl.enqueue_fill_buffer(ctx.queue, count_buf, np.int32(0), 0, 4)
        ev = dev.run(ctx, DEVICE_KERNEL_FILE, "ray_validity", _items(n), rays.origins,
                     rays.directions, rays.tmin, rays.tmax, rays.interval_stride, n,
                     bad.base_data, count_buf, wait_for=list(wait_for or []) + [fill])
        bad.add_event(ev)
        count = np.zeros(1, np.int32)
        cl.enqueue_copy(ctx.queue, count, count_buf, wait_for=[ev], is_blocking=True)
    finally:
        ctx.memory.free(count_buf)
    return bad, int(count[0])


def read_device_rays(ctx: dev.Context, rays: DeviceRays) -> Rays:
    """The rays copied back to the host (to name the first bad one; a blocking read)."""
    n, q = rays.count, ctx.queue
    o, d = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    lo = np.empty(n if rays.interval_stride else 1, np.float32)
    hi = np.empty_like(lo)
    for host, buf in ((o, rays.origins), (d, rays.directions), (lo, rays.tmin), (hi, rays.tmax)):
        if host.size:
            cl.enqueue_copy(q, host, buf, is_blocking=True)
    if not rays.interval_stride:
        lo, hi = lo.reshape(()), hi.reshape(())
    return Rays(o, d, lo, hi)


def mark_invalid(ctx: dev.Context, rays: DeviceRays, bad: cl_array.Array) -> DeviceRays:
    """The same rays with per-ray intervals whose ``tmin`` is NaN where ``bad`` is set:
    the kernel reports those as misses without tracing them (FLAG_NAN_RAY)."""
    n = rays.count
    lo_buf, hi_buf = ctx.memory.alloc(4 * n), ctx.memory.alloc(4 * n)
    dev.run(ctx, DEVICE_KERNEL_FILE, "mark_invalid", _items(n), rays.tmin, rays.tmax,
            rays.interval_stride, bad.base_data, n, lo_buf, hi_buf, wait_for=bad.events or None)
    return DeviceRays(n, rays.origins, rays.directions, lo_buf, hi_buf, 1)
