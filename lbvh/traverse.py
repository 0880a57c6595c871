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
bounded by the stack and by the node count), so a NaN ray that reached it
through :func:`trace_buffers` costs at most one visit per node.

Stack
    The stack has room for the deepest path of the tree (``bvh.depths().max()``,
    cached on the tree), rounded up to one of :data:`STACK_BUCKETS` so that trees
    of similar depth share one compiled program. A tree deeper than the last
    bucket gets the last bucket: rays that would need more set their
    ``overflow`` flag (the subtree that did not fit is skipped), which the
    result counts. An overflow is never silent.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from . import device as dev
from .geometry import real_array

KERNEL_FILE = "traverse.cl"

#: One ray on the device: a float8 (origin.xyz, tmin, direction.xyz, tmax).
RAY_DTYPE = np.dtype([("origin", "<f4", (3,)), ("tmin", "<f4"),
                      ("direction", "<f4", (3,)), ("tmax", "<f4")])
#: One result on the device: a float4 (t, u, v, as_float(prim)).
HIT_DTYPE = np.dtype([("t", "<f4"), ("u", "<f4"), ("v", "<f4"), ("prim", "<i4")])
assert RAY_DTYPE.itemsize == 32 and HIT_DTYPE.itemsize == 16

#: Bits of the per-ray flag word written by the kernel.
FLAG_OVERFLOW = 1      # the stack was full: a subtree was skipped
FLAG_VISIT_LIMIT = 2   # more nodes visited than the tree has (a malformed, cyclic tree)

#: Stack sizes a program is compiled for; a tree uses the first that holds its depth.
STACK_BUCKETS = (32, 64, 96, 128, 192, 256)

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
            every node the traversal descended into or popped.
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

    ``hits``: :data:`HIT_DTYPE` records; ``flags``: ``int32`` flag words;
    ``counters``: ``int32 (count, 2)`` (nodes visited, triangles tested) or ``None``;
    ``event``: the kernel's event.
    """
    count: int
    hits: cl.Buffer
    flags: cl.Buffer
    counters: cl.Buffer | None
    event: cl.Event


# -- validation -----------------------------------------------------------------

def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _ray_vectors(name: str, value: Any, count: int | None) -> np.ndarray:
    """The caller's ``(N, 3)`` array, shape and dtype checked (values are checked packed)."""
    arr = real_array(name, value)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: shape {arr.shape}, expected (N, 3)")
    if count is not None and len(arr) != count:
        raise ValueError(f"{name}: {len(arr)} rays, but origins has {count}")
    return arr


def _interval(name: str, value: Any, count: int) -> np.ndarray:
    """The caller's scalar or ``(N,)`` array, shape and dtype checked."""
    arr = real_array(name, value)
    if arr.ndim != 0 and arr.shape != (count,):
        raise ValueError(f"{name}: shape {arr.shape}, expected a scalar or ({count},)")
    return arr


def _raise_first_bad(rays: np.ndarray, origins: np.ndarray, directions: np.ndarray) -> None:
    """Name the first problem of packed rays (slow path, only after the fast checks failed)."""
    for name, cols, given in (("origins", slice(0, 3), origins), ("directions", slice(4, 7), directions)):
        bad = ~np.isfinite(rays[:, cols]).all(axis=1)
        if bad.any():
            i = _first_bad(bad)
            raise ValueError(f"{name}: ray {i} has a NaN, infinite or beyond-float32 component "
                             f"{given[i].tolist()}")
    zero = ~(rays[:, 4:7] != 0).any(axis=1)
    if zero.any():
        raise ValueError(f"directions: ray {_first_bad(zero)} has a zero-length direction "
                         "(after conversion to float32)")
    lo, hi = rays[:, 3], rays[:, 7]
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


def pack_rays(origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf) -> np.ndarray:
    """Validate rays and pack them as :data:`RAY_DTYPE` records ``(N,)`` for the device.

    Values are converted to float32 first and checked after (a float64 beyond the
    float32 range is refused). Raises ``ValueError`` naming the first bad ray (see
    the module docstring).
    """
    o = _ray_vectors("origins", origins, None)
    d = _ray_vectors("directions", directions, len(o))
    n = len(o)
    lo, hi = _interval("tmin", tmin, n), _interval("tmax", tmax, n)
    rays = np.empty((n, 8), np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        rays[:, 0:3] = o
        rays[:, 3] = lo
        rays[:, 4:7] = d
        rays[:, 7] = hi
    # One pass per condition over all rays; only a failure looks for the first bad ray.
    ok = (np.isfinite(rays[:, :7]).all()
          and ((rays[:, 4] != 0) | (rays[:, 5] != 0) | (rays[:, 6] != 0)).all()
          and ((rays[:, 3] >= 0) & (rays[:, 3] <= rays[:, 7])).all())
    if not ok:
        _raise_first_bad(rays, o, d)
    return rays.view(RAY_DTYPE).reshape(n)


# -- programs -------------------------------------------------------------------

def stack_size_for(bvh: Any) -> int:
    """Stack entries the kernel gets for this tree: its depth rounded up to a bucket.

    Ordered traversal pushes at most one node per level, so the tree's depth
    (edges from the root to the deepest leaf) is enough. Cached on the tree as
    ``bvh._traverse_depth`` (the topology never changes after the build; a
    refit keeps it).
    """
    depth = getattr(bvh, "_traverse_depth", None)
    if depth is None:
        depth = int(bvh.depths().max()) if bvh.num_nodes > 1 else 0
        bvh._traverse_depth = depth
    for bucket in STACK_BUCKETS:
        if depth <= bucket:
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


# -- device-level entry -----------------------------------------------------------

def trace_buffers(bvh: Any, rays: cl.Buffer, count: int, *, any_hit: bool = False,
                  triangle_test: str = "watertight", counters: bool = False,
                  stack_size: int | None = None, hits: cl.Buffer | None = None,
                  flags: cl.Buffer | None = None, counter_buf: cl.Buffer | None = None,
                  wait_for: list[cl.Event] | None = None,
                  defines: dict[str, int | str] | None = None) -> DeviceHits:
    """Trace ``count`` rays already on the device; nothing is read back.

    ``rays`` holds :data:`RAY_DTYPE` records (see :func:`pack_rays`) that the
    caller has validated. Output buffers are allocated unless given: ``hits``
    (16 bytes per ray), ``flags`` (4), ``counter_buf`` (8, with ``counters``).
    ``defines`` adds or overrides -D defines of kernels/traverse.cl (tests, experiments).
    """
    ctx = bvh.ctx
    if stack_size is None:
        stack_size = stack_size_for(bvh)
    knl = ctx.kernel(KERNEL_FILE, "traverse",
                     {**_defines(ctx, any_hit, triangle_test, counters, stack_size),
                      **(defines or {})})
    count = int(count)
    if hits is None:
        hits = dev.empty(ctx, HIT_DTYPE.itemsize * count)
    if flags is None:
        flags = dev.empty(ctx, 4 * count)
    if counters and counter_buf is None:
        counter_buf = dev.empty(ctx, 8 * count)
    per_item, global_size, local = _launch(count)
    ev = knl(ctx.queue, (global_size,), local, bvh.nodes_buf, bvh.prim_order_buf,
             bvh.vertices_buf, bvh.faces_buf, np.int32(bvh.root), np.int32(bvh.num_nodes),
             rays, hits, flags, counter_buf if counters else flags, np.int32(count),
             np.int32(per_item), wait_for=wait_for)
    return DeviceHits(count, hits, flags, counter_buf if counters else None, ev)


# -- host API ---------------------------------------------------------------------

def _trace(bvh: Any, origins: Any, directions: Any, tmin: Any, tmax: Any, any_hit: bool,
           triangle_test: str, counters: bool, batch_size: int,
           stack_size: int | None) -> Hits:
    if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ValueError(f"batch_size: {batch_size!r}; expected a positive integer")
    rays = pack_rays(origins, directions, tmin, tmax)
    n = len(rays)
    out = np.empty(n, HIT_DTYPE)
    flag = np.zeros(n, np.int32)
    count = np.zeros((n, 2), np.int32) if counters else None
    ctx = bvh.ctx
    batch = int(min(batch_size, max(n, 1)))
    ray_buf = dev.empty(ctx, RAY_DTYPE.itemsize * batch, cl.mem_flags.READ_ONLY)
    hit_buf = dev.empty(ctx, HIT_DTYPE.itemsize * batch)
    flag_buf = dev.empty(ctx, 4 * batch)
    count_buf = dev.empty(ctx, 8 * batch) if counters else None
    try:
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            up = cl.enqueue_copy(ctx.queue, ray_buf, rays[start:stop], is_blocking=False)
            result = trace_buffers(bvh, ray_buf, stop - start, any_hit=any_hit,
                                   triangle_test=triangle_test, counters=counters,
                                   stack_size=stack_size, hits=hit_buf, flags=flag_buf,
                                   counter_buf=count_buf, wait_for=[up])
            cl.enqueue_copy(ctx.queue, out[start:stop], hit_buf, wait_for=[result.event])
            cl.enqueue_copy(ctx.queue, flag[start:stop], flag_buf, wait_for=[result.event])
            if counters:
                cl.enqueue_copy(ctx.queue, count[start:stop], count_buf, wait_for=[result.event])
            ctx.queue.finish()
    finally:
        for buf in (ray_buf, hit_buf, flag_buf, count_buf):
            if buf is not None:
                buf.release()
    overflow = flag != 0
    return Hits(t=out["t"].copy(), prim=out["prim"].copy(), u=out["u"].copy(), v=out["v"].copy(),
                overflow=overflow, overflow_count=int(overflow.sum()),
                nodes_visited=None if count is None else count[:, 0].copy(),
                tris_tested=None if count is None else count[:, 1].copy())


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
