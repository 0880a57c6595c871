"""Ray queries: closest hit and occlusion on the device (kernels/traverse.cl).

The host API is :func:`intersect` and :func:`occluded` (also reachable as
``bvh.intersect`` and ``bvh.occluded``); :func:`trace_buffers` is the
device-level entry for callers that keep their rays on the device.

Rays
    ``origins`` and ``directions`` are ``(N, 3)`` arrays (float32; float64 and
    integers are converted to float32). Directions need not be unit length: ``t``
    is measured in units of the direction's length, the hit point is
    ``origin + t * direction``. ``tmin`` and ``tmax`` are scalars or ``(N,)``
    arrays; a hit counts when ``tmin <= t <= tmax``.

Bad rays are refused before anything runs on the device, with a ``ValueError``
naming the first bad ray: NaN or infinite origins and directions (also values
beyond the float32 range), zero-length directions (after the float32
conversion), NaN, negative or infinite ``tmin``, NaN ``tmax``, ``tmin > tmax``,
wrong shapes or dtypes. The kernel itself terminates on any input (its loop is
bounded by the stack and by the node count); a NaN ray that reached it through
:func:`trace_buffers` is not traced: a miss with :data:`FLAG_NAN_RAY` set.

Stack
    The stack has room for the most entries an ordered traversal of the tree
    can hold (:func:`stack_need`), rounded up to one of :data:`STACK_BUCKETS`
    so that trees of similar depth share one compiled program. The last
    bucket, 768, holds the deepest LBVH (depth at most 95: 63 key bits and 32
    bits of index tie-break) at the most 8-wide records can push, 7 per level
    (665); a tree that needs more gets the last bucket: rays that would need more set
    their ``overflow`` flag (the subtree that did not fit is skipped), which
    the result counts. An overflow is never silent.

Wide records
    The kernel reads a tree through wide records (:mod:`lbvh.wide`): up to
    8 children per record on a CPU (4 elsewhere), their boxes in rows that one
    vector slab test covers, made on the device from any tree of the layout on
    its first query and cached on the tree (a refit rewrites their boxes). On
    the 2-core machine that traces primary rays 1.4-1.8x as fast as binary
    records of two children did (bunny, Sponza, a 1M-triangle terrain). A tree whose records
    would exceed the device's largest buffer is traversed through its own
    binary nodes. Likewise the faces are copied once in slot order
    (:func:`slot_faces_for`, 12 bytes per triangle), so that a leaf's
    triangles are read without a detour through ``prim_order``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from . import device as dev
from .geometry import real_array
from .ray_order import ray_order, worth_ordering
from .wide import wide_for

KERNEL_FILE = "traverse.cl"

#: Bits of the per-ray flag word written by the kernel.
FLAG_OVERFLOW = 1      # the stack was full: a subtree was skipped
FLAG_VISIT_LIMIT = 2   # more nodes visited than the tree has (a malformed, cyclic tree)
FLAG_NAN_RAY = 4       # NaN in the ray (only through trace_buffers): not traced

#: Stack sizes a program is compiled for; a tree uses the first that holds its stack_need.
STACK_BUCKETS = (32, 64, 96, 128, 192, 256, 384, 512, 768)

TRIANGLE_TESTS = {"watertight": 0, "moller": 1}

# Work-group size. On PoCL a work-group's work-items run as a loop on one core;
# groups of 1, 16, 64 and 256 rays, and work-items looping over 64 or 512 rays,
# measured the same within noise on the bunny (2 cores), so PoCL gets the GPU's 64.
_WORK_GROUP = 64

_UNIT_ROUNDOFF = 2.0 ** -24


@dataclass
class Hits:
    """Results of a ray query, one entry per ray (numpy arrays).

    Attributes:
        t: ``float32 (N,)`` distance along the direction, ``inf`` on a miss.
        prim: ``int32 (N,)`` triangle index in the caller's original numbering, ``-1`` on a miss.
        u, v: ``float32 (N,)`` barycentrics: the hit point is
            ``(1-u-v)*p0 + u*p1 + v*p2`` with ``p0, p1, p2 = vertices[faces[prim]]``; 0 on a miss.
        overflow: ``bool (N,)`` the traversal stack overflowed (or the tree is not a tree):
            the result of that ray may have missed a subtree.
        overflow_count: number of ``True`` in ``overflow``.
        nodes_visited: ``int32 (N,)`` with ``counters=True`` (else ``None``): the root plus
            every node the traversal descended into or popped; a node is a wide record
            (up to 8 children, :mod:`lbvh.wide`) or a leaf, or a binary node for trees
            traversed through their own nodes.
        tris_tested: ``int32 (N,)`` with ``counters=True`` (else ``None``).

    From :func:`occluded` with ``return_hits=True`` the hit is *a* hit in
    ``[tmin, tmax]``, not necessarily the closest.
    """
    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    overflow: np.ndarray
    overflow_count: int
    nodes_visited: np.ndarray | None = None
    tris_tested: np.ndarray | None = None

    @property
    def hit(self) -> np.ndarray:
        """``bool (N,)``: whether each ray hit something."""
        return self.prim >= 0

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class DeviceHits:
    """Device buffers written by :func:`trace_buffers` (``count`` rays).

    ``hits``: four planes of ``count`` float32 (t, u, v, primitive as int32 bits; see
    :func:`read_hits`); ``flags``: ``int32`` flag words;
    ``counters``: ``int32 (count, 2)`` (nodes visited, triangles tested) or ``None``;
    ``event``: the kernel's event.
    """
    count: int
    hits: cl.Buffer
    flags: cl.Buffer
    counters: cl.Buffer | None
    event: cl.Event


# -- validation -----------------------------------------------------------------

@dataclass
class Rays:
    """Checked rays, as the kernel reads them.

    ``origins``, ``directions``: ``float32 (N, 3)`` C-contiguous. ``tmin``,
    ``tmax``: ``float32``, each a 0-d array (one value for every ray) or ``(N,)``.
    """
    origins: np.ndarray
    directions: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray

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


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _as_float32(name: str, arr: np.ndarray) -> np.ndarray:
    """C-contiguous float32; values beyond the float32 range become infinite (refused later)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.ascontiguousarray(arr, dtype=np.float32)


def _ray_vectors(name: str, value: Any, count: int | None) -> np.ndarray:
    """The caller's ``(N, 3)`` array, shape and dtype checked, as float32."""
    arr = real_array(name, value)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: shape {arr.shape}, expected (N, 3)")
    if count is not None and len(arr) != count:
        raise ValueError(f"{name}: {len(arr)} rays, but origins has {count}")
    return _as_float32(name, arr)


def _interval(name: str, value: Any, count: int) -> np.ndarray:
    """The caller's scalar or ``(N,)`` array, shape and dtype checked, as float32."""
    arr = real_array(name, value)
    if arr.ndim != 0 and arr.shape != (count,):
        raise ValueError(f"{name}: shape {arr.shape}, expected a scalar or ({count},)")
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


def check_rays(origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf) -> Rays:
    """Validate rays and convert them to the float32 arrays the kernel reads.

    Values are converted to float32 first and checked after (a float64 beyond the
    float32 range is refused). Raises ``ValueError`` naming the first bad ray (see
    the module docstring). Costs a few passes over the arrays (no copy when they
    are float32 and C-contiguous already).
    """
    given_o = real_array("origins", origins)
    o = _ray_vectors("origins", given_o, None)
    given_d = real_array("directions", directions)
    d = _ray_vectors("directions", given_d, len(o))
    n = len(o)
    lo, hi = _interval("tmin", tmin, n), _interval("tmax", tmax, n)
    ok = (n == 0 or (_all_finite(o) and _all_finite(d) and _all_nonzero_rows(d)
                     and _intervals_ok(lo, hi)))
    if not ok:
        _raise_first_bad(o, d, lo, hi, given_o, given_d)
    return Rays(o, d, lo, hi)


@dataclass
class DeviceRays:
    """Rays on the device (``count`` of them), as :func:`trace_buffers` reads them:
    ``origins``, ``directions`` float32 ``3 * count``; ``tmin``, ``tmax`` float32, one
    per ray (``interval_stride`` 1) or one for all (``interval_stride`` 0)."""
    count: int
    origins: cl.Buffer
    directions: cl.Buffer
    tmin: cl.Buffer
    tmax: cl.Buffer
    interval_stride: int

    def release(self) -> None:
        for buf in (self.origins, self.directions, self.tmin, self.tmax):
            buf.release()


def upload_rays(ctx: dev.Context, rays: Rays) -> DeviceRays:
    """Copy rays to new device buffers (no checks beyond :func:`check_rays`' types:
    the caller decides what it uploads)."""
    lo, hi, stride = rays.kernel_intervals()
    return DeviceRays(len(rays), dev.to_device(ctx, rays.origins), dev.to_device(ctx, rays.directions),
                      dev.to_device(ctx, lo), dev.to_device(ctx, hi), stride)


# -- programs -------------------------------------------------------------------

def stack_need(bvh: Any) -> int:
    """The most stack entries an ordered traversal of this tree can hold.

    Through wide records: their ``stack_need`` (a record pushes its children
    but the one it follows, so the most entries on the stack is the largest
    sum of that over the records of one root-to-leaf path; never less than
    the binary depth). Through the binary nodes: the tree's depth (one push
    per level), cached on the tree as ``bvh._traverse_depth`` (the topology
    never changes after the build).
    """
    wide = wide_for(bvh)
    if wide.packed:
        return wide.stack_need
    depth = getattr(bvh, "_traverse_depth", None)
    if depth is None:
        depth = int(bvh.depths().max()) if bvh.num_nodes > 1 else 0
        bvh._traverse_depth = depth
    return depth


def stack_size_for(bvh: Any) -> int:
    """Stack entries the kernel gets for this tree: :func:`stack_need` rounded up
    to a bucket (the last bucket if none holds it: then rays may overflow, flagged)."""
    need = stack_need(bvh)
    for bucket in STACK_BUCKETS:
        if need <= bucket:
            return bucket
    return STACK_BUCKETS[-1]


def slab_pad(ctx: dev.Context) -> str:
    """The far-distance factor of the slab test as an OpenCL hex float literal.

    ``1 + 2 gamma(3)`` (Ize 2013) counts three roundings: the subtraction, the
    reciprocal and the product. Where the reciprocal is not correctly rounded
    (OpenCL allows 2.5 ulp) it counts as five more: ``1 + 2 gamma(7)``.
    """
    exact_div = bool(ctx.device.single_fp_config
                     & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT)
    n = 3 if exact_div else 7
    gamma = n * _UNIT_ROUNDOFF / (1 - n * _UNIT_ROUNDOFF)
    pad = np.float32(1 + 2 * gamma)
    if float(pad) < 1 + 2 * gamma:
        pad = np.nextafter(pad, np.float32(2))
    return float(pad).hex() + "f"


def _defines(ctx: dev.Context, any_hit: bool, triangle_test: str, counters: bool,
             stack_size: int) -> dict[str, int | str]:
    if triangle_test not in TRIANGLE_TESTS:
        raise ValueError(f"triangle_test: {triangle_test!r}; expected one of "
                         f"{', '.join(TRIANGLE_TESTS)}")
    if not isinstance(stack_size, (int, np.integer)) or stack_size < 1:
        raise ValueError(f"stack_size: {stack_size!r}; expected a positive integer")
    return {"ANY_HIT": int(bool(any_hit)), "COUNTERS": int(bool(counters)),
            "TRIANGLE_TEST": TRIANGLE_TESTS[triangle_test], "STACK_SIZE": int(stack_size),
            "SLAB_PAD": slab_pad(ctx)}


def _launch(count: int) -> tuple[int, int, tuple[int]]:
    """(rays per work-item, global size, local size): one ray per work-item everywhere."""
    return 1, max(1, -(-count // _WORK_GROUP) * _WORK_GROUP), (_WORK_GROUP,)


# -- faces in slot order ---------------------------------------------------------

def slot_faces_for(bvh: Any) -> cl.Buffer:
    """``uint32 (F, 3)`` on the device: ``faces[prim_order]``, the triangles in slot
    order as the kernel reads them (kernels/traverse.cl, order_faces), made on
    first use and cached on the tree (a refit keeps faces and order)."""
    cached = getattr(bvh, "_slot_faces", None)
    if cached is not None:
        return cached
    ctx = bvh.ctx
    nbytes = 12 * bvh.num_prims
    out = dev.pooled_or_empty(ctx, nbytes)
    launch = ctx.launch(bvh.num_prims, min_per_item=4096, gpu_per_item=1)
    ctx.kernel(KERNEL_FILE, "order_faces", {})(
        ctx.queue, (launch.global_size,), launch.local, bvh.faces_buf, bvh.prim_order_buf,
        np.int32(bvh.num_prims), np.int32(launch.per_item), out)
    bvh._pooled.append((out, nbytes))   # back to the pool with the tree
    bvh._slot_faces = out
    return out


# -- device-level entry -----------------------------------------------------------

def root_box(bvh: Any) -> tuple[np.ndarray, np.ndarray]:
    """``float32 (3,)`` lower and upper corner of the root's box, read from the device."""
    record = np.empty(8, np.float32)
    cl.enqueue_copy(bvh.ctx.queue, record, bvh.nodes_buf, src_offset=32 * bvh.root,
                    is_blocking=True)
    return record[:3], record[4:7]


def trace_buffers(bvh: Any, rays: DeviceRays, *, any_hit: bool = False,
                  triangle_test: str = "watertight", counters: bool = False,
                  stack_size: int | None = None, hits: cl.Buffer | None = None,
                  flags: cl.Buffer | None = None, counter_buf: cl.Buffer | None = None,
                  wait_for: list[cl.Event] | None = None, order: cl.Buffer | None = None,
                  defines: dict[str, int | str] | None = None) -> DeviceHits:
    """Trace rays already on the device; nothing is read back.

    ``rays`` (see :func:`upload_rays`) must have passed :func:`check_rays`.
    Output buffers are allocated unless given: ``hits`` (16 bytes per ray: four
    planes of ``count`` float32, t, u, v and the primitive as int32), ``flags`` (4),
    ``counter_buf`` (8, with ``counters``). ``order`` (int32 per ray, a
    permutation, see :mod:`lbvh.ray_order`) sets the order the rays are traced
    in; the answers stay in the rays' own slots. ``defines`` adds or overrides
    -D defines of kernels/traverse.cl (tests, experiments).
    """
    ctx = bvh.ctx
    if stack_size is None:
        stack_size = stack_size_for(bvh)
    wide = wide_for(bvh)
    knl = ctx.kernel(KERNEL_FILE, "traverse",
                     {**_defines(ctx, any_hit, triangle_test, counters, stack_size),
                      "WIDE": int(wide.packed), "WIDTH": wide.width,
                      "RAY_ORDER": int(order is not None), **(defines or {})})
    count = int(rays.count)
    if hits is None:
        hits = dev.empty(ctx, 16 * count)
    if flags is None:
        flags = dev.empty(ctx, 4 * count)
    if counters and counter_buf is None:
        counter_buf = dev.empty(ctx, 8 * count)
    per_item, global_size, local = _launch(count)
    ev = knl(ctx.queue, (global_size,), local, bvh.nodes_buf, wide.buffer, bvh.prim_order_buf,
             bvh.vertices_buf, slot_faces_for(bvh), np.int32(bvh.root), np.int32(wide.root_x),
             np.int32(wide.root_y), np.int32(bvh.num_nodes), rays.origins, rays.directions,
             rays.tmin, rays.tmax, np.int32(rays.interval_stride),
             order if order is not None else flags, hits, flags,
             counter_buf if counters else flags, np.int32(count), np.int32(per_item),
             wait_for=wait_for)
    return DeviceHits(count, hits, flags, counter_buf if counters else None, ev)


def read_hits(ctx: dev.Context, out: DeviceHits) -> np.ndarray:
    """``float32 (4, count)``: the t, u, v and primitive (int32 bits) planes of ``out``."""
    planes = np.empty((4, out.count), np.float32)
    if out.count:
        cl.enqueue_copy(ctx.queue, planes, out.hits, wait_for=[out.event], is_blocking=True)
    return planes


# -- host API ---------------------------------------------------------------------

def _trace(bvh: Any, origins: Any, directions: Any, tmin: Any, tmax: Any, any_hit: bool,
           triangle_test: str, counters: bool, batch_size: int,
           stack_size: int | None) -> Hits:
    if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ValueError(f"batch_size: {batch_size!r}; expected a positive integer")
    rays = check_rays(origins, directions, tmin, tmax)
    n = len(rays)
    planes = np.empty((4, n), np.float32)
    flag = np.zeros(n, np.int32)
    count = np.zeros((n, 2), np.int32) if counters else None
    ctx, queue = bvh.ctx, bvh.ctx.queue
    batch = int(min(batch_size, max(n, 1)))
    lo, hi, stride = rays.kernel_intervals()
    per_ray = stride == 1
    ro = cl.mem_flags.READ_ONLY
    bufs = {"o": dev.empty(ctx, 12 * batch, ro), "d": dev.empty(ctx, 12 * batch, ro),
            "lo": dev.empty(ctx, 4 * (batch if per_ray else 1), ro),
            "hi": dev.empty(ctx, 4 * (batch if per_ray else 1), ro),
            "hits": dev.empty(ctx, 16 * batch), "flags": dev.empty(ctx, 4 * batch)}
    if counters:
        bufs["count"] = dev.empty(ctx, 8 * batch)
    try:
        if not per_ray:
            cl.enqueue_copy(queue, bufs["lo"], lo)
            cl.enqueue_copy(queue, bufs["hi"], hi)
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            m = stop - start
            ups = [cl.enqueue_copy(queue, bufs["o"], rays.origins[start:stop], is_blocking=False),
                   cl.enqueue_copy(queue, bufs["d"], rays.directions[start:stop], is_blocking=False)]
            if per_ray:
                ups += [cl.enqueue_copy(queue, bufs["lo"], lo[start:stop], is_blocking=False),
                        cl.enqueue_copy(queue, bufs["hi"], hi[start:stop], is_blocking=False)]
            device_rays = DeviceRays(m, bufs["o"], bufs["d"], bufs["lo"], bufs["hi"], stride)
            order = None
            if worth_ordering(m, bvh.num_nodes):
                order, ups = ray_order(ctx, bufs["o"], bufs["d"], m, *root_box(bvh))
            result = trace_buffers(bvh, device_rays, any_hit=any_hit, triangle_test=triangle_test,
                                   counters=counters, stack_size=stack_size, hits=bufs["hits"],
                                   flags=bufs["flags"], counter_buf=bufs.get("count"),
                                   wait_for=ups, order=order)
            for k in range(4):
                cl.enqueue_copy(queue, planes[k, start:stop], bufs["hits"], src_offset=4 * k * m,
                                wait_for=[result.event], is_blocking=False)
            cl.enqueue_copy(queue, flag[start:stop], bufs["flags"], wait_for=[result.event],
                            is_blocking=False)
            if counters:
                cl.enqueue_copy(queue, count[start:stop], bufs["count"], wait_for=[result.event],
                                is_blocking=False)
            queue.finish()
            if order is not None:
                order.release()
    finally:
        for buf in bufs.values():
            buf.release()
    overflow = flag != 0
    return Hits(t=planes[0], prim=planes[3].view(np.int32), u=planes[1], v=planes[2],
                overflow=overflow, overflow_count=int(overflow.sum()),
                nodes_visited=None if count is None else count[:, 0].copy(),
                tris_tested=None if count is None else count[:, 1].copy())


@dev.serialised
def intersect(bvh: Any, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
              triangle_test: str = "watertight", counters: bool = False,
              batch_size: int = 1 << 20, stack_size: int | None = None) -> Hits:
    """Closest hit of each ray in ``[tmin, tmax]``.

    Args:
        bvh: an :class:`lbvh.BVH` (any builder; the kernel reads only docs/layout.md).
        origins, directions: ``(N, 3)`` float arrays (converted to float32).
        tmin, tmax: scalars or ``(N,)`` arrays, ``0 <= tmin <= tmax``; ``tmax`` may be ``inf``.
        triangle_test: ``"watertight"`` (Woop 2013, default) or ``"moller"`` (Moller-Trumbore).
        counters: also return nodes visited and triangles tested per ray.
        batch_size: rays per kernel launch; device memory is about 60 bytes per ray of a batch.
        stack_size: override the stack size chosen from the tree's depth (for tests).

    Returns:
        :class:`Hits`. Among triangles hit at exactly the same ``t`` the one
        found first wins.

    Raises:
        ValueError: a bad ray (named) or a bad option.
    """
    return _trace(bvh, origins, directions, tmin, tmax, False, triangle_test, counters,
                  batch_size, stack_size)


@dev.serialised
def occluded(bvh: Any, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
             triangle_test: str = "watertight", counters: bool = False,
             batch_size: int = 1 << 20, stack_size: int | None = None,
             return_hits: bool = False) -> np.ndarray | Hits:
    """Whether each ray hits anything in ``[tmin, tmax]`` (any-hit traversal, stops at the first).

    Arguments as :func:`intersect`. Returns ``bool (N,)``; with
    ``return_hits=True`` the full :class:`Hits` instead (``hits.hit`` is the
    answer, ``hits.overflow`` / ``hits.overflow_count`` report stack overflows,
    ``t, prim, u, v`` describe the hit that was found, not necessarily the closest).
    """
    hits = _trace(bvh, origins, directions, tmin, tmax, True, triangle_test, counters,
                  batch_size, stack_size)
    return hits if return_hits else hits.hit
