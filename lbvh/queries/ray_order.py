"""Ray order on the device (kernels/ray_order.cl): coherent rays traced one after another.

A work-item of the traversal traces its rays in sequence, so a ray finds in
cache the nodes that the previous ray visited. Callers' rays come in any order
(scanlines, random samples); sorting them by a key of origin cell and
direction (Garanzha & Loop 2010) puts rays that visit the same nodes together.
The traversal then reads ray ``order[k]`` at step ``k`` and writes its answer in
the caller's slot: the results are the same in any order, only faster.

Only large batches over trees that do not fit in cache gain: sorting costs
about two passes over the rays, so :func:`worth_ordering` decides.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..device import Context, MemoryTracker, run
from ..device.sort import radix_sort

KERNEL_FILE = "ray_order.cl"
CELL_BITS = 5
#: Bits per axis of a query point's cell (kernels/ray_order.cl point_keys).
POINT_CELL_BITS = 10
#: Point batches with fewer points are answered as given.
MIN_POINTS = 1 << 14
#: Batches with fewer rays are traced as given.
MIN_RAYS = 1 << 16
#: Trees with fewer nodes are traced as given (their records stay in cache anyway).
MIN_NODES = 1 << 20


def worth_ordering(num_rays: int, num_nodes: int) -> bool:
    """Whether sorting a batch of rays is expected to pay for itself."""
    return num_rays >= MIN_RAYS and num_nodes >= MIN_NODES


def key_box(lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``float32 (4,)`` lower corner and per-axis ``1 / extent`` (0 for an empty or
    unbounded axis) of the box the origin cells divide: the scene's box."""
    lower = np.asarray(lower, np.float32)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        extent = np.asarray(upper, np.float32) - lower
        inv = np.where((extent > 0) & np.isfinite(extent), np.float32(1) / extent, np.float32(0))
    return (np.append(lower, np.float32(0)).astype(np.float32),
            np.append(inv, np.float32(0)).astype(np.float32))


def ray_order(ctx: Context, origins: cl.Buffer, directions: cl.Buffer, count: int,
              lower: np.ndarray, upper: np.ndarray) -> tuple[cl.Buffer, list[cl.Event]]:
    """``int32 (count,)`` device buffer: the rays' indices sorted by key (stable).

    ``origins`` and ``directions`` hold ``3 * count`` float32 (directions not
    zero: :func:`lbvh.queries.traverse.check_rays` refused those); ``lower``/``upper``
    is the scene's box. The caller releases the returned buffer.
    """
    mem = MemoryTracker(ctx)
    low, inv = key_box(lower, upper)
    keys = mem.alloc(4 * count, scratch=True)
    order = mem.alloc(4 * count)
    launch = ctx.launch(count, min_per_item=4096)
    ev = run(ctx, KERNEL_FILE, "ray_keys", launch, origins, directions, count, launch.per_item,
             low, inv, keys, order)
    result = radix_sort(ctx, mem, keys, order, count, 32)
    mem.free(result.keys)
    mem.close()
    return result.values, [ev, *result.events]


def point_order(ctx: Context, points: cl.Buffer, count: int, lower: np.ndarray,
                upper: np.ndarray) -> tuple[cl.Buffer, list[cl.Event]]:
    """``int32 (count,)`` device buffer: the query points' indices sorted by the Morton
    code of their cell in the box ``lower``/``upper`` (10 bits per axis; stable).
    The caller gives the returned buffer back to ``ctx.memory``."""
    mem = MemoryTracker(ctx)
    low, inv = key_box(lower, upper)
    keys = mem.alloc(4 * count, scratch=True)
    order = mem.alloc(4 * count)
    launch = ctx.launch(count, min_per_item=4096)
    ev = run(ctx, KERNEL_FILE, "point_keys", launch, points, count, launch.per_item, low, inv,
             keys, order)
    result = radix_sort(ctx, mem, keys, order, count, 32)
    mem.free(result.keys)
    mem.close()
    return result.values, [ev, *result.events]


def gather_points(ctx: Context, points: cl.Buffer, order: cl.Buffer, count: int,
                  wait_for: list[cl.Event] | None = None) -> tuple[cl.Buffer, cl.Event]:
    """``float32 (count, 3)`` device buffer: ``points[order]`` (``order`` from
    :func:`point_order`), for a kernel that answers the points in that order and reads
    them as one run. The caller gives the returned buffer back to ``ctx.memory``."""
    out = ctx.memory.alloc(12 * max(count, 1))
    launch = ctx.launch(count, min_per_item=4096)
    ev = run(ctx, KERNEL_FILE, "gather_points", launch, points, order, count, launch.per_item,
             out, wait_for=wait_for)
    return out, ev


def ordered_points(ctx: Context, points: cl.Buffer, count: int, lower: np.ndarray,
                   upper: np.ndarray) -> tuple[cl.Buffer, cl.Buffer, list[cl.Event]]:
    """:func:`point_order` then :func:`gather_points`, what the point queries' kernels
    take with ``POINT_ORDER=1``: ``(order, gathered points, events to wait for)``. The
    caller gives both buffers back to ``ctx.memory``."""
    order, ups = point_order(ctx, points, count, lower, upper)
    try:
        gathered, ev = gather_points(ctx, points, order, count, wait_for=ups)
    except BaseException:
        ctx.memory.free(order)
        raise
    return order, gathered, [ev]


# -- numpy twin ---------------------------------------------------------------------

def _cells(t: np.ndarray, bits: int = CELL_BITS) -> np.ndarray:
    top = np.float32((1 << bits) - 1)
    q = t * np.float32(1 << bits)
    q = np.where(q > 0, q, np.float32(0))
    return np.where(q < top, q, top).astype(np.uint32)


def _interleave(x: np.ndarray, y: np.ndarray, z: np.ndarray, bits: int = CELL_BITS) -> np.ndarray:
    code = np.zeros(len(x), np.uint32)
    for b in range(bits - 1, -1, -1):
        code = (code << 3) | (((x >> b) & 1) << 2) | (((y >> b) & 1) << 1) | ((z >> b) & 1)
    return code


def point_keys_numpy(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Twin of the ``point_keys`` kernel: ``uint32 (N,)`` keys, same float32 operations."""
    low, inv = key_box(lower, upper)
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        a = (np.asarray(points, np.float32) - low[:3]) * inv[:3]
    return _interleave(*(_cells(a[:, k], POINT_CELL_BITS) for k in range(3)), POINT_CELL_BITS)


def ray_keys_numpy(origins: np.ndarray, directions: np.ndarray, lower: np.ndarray,
                   upper: np.ndarray) -> np.ndarray:
    """Twin of the ``ray_keys`` kernel: ``uint32 (N,)`` keys, same float32 operations."""
    low, inv = key_box(lower, upper)
    o = np.asarray(origins, np.float32)
    d = np.asarray(directions, np.float32)
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        a = (o - low[:3]) * inv[:3]
        m = np.abs(d).max(axis=1, keepdims=True)
        u = (d / m + np.float32(1)) * np.float32(0.5)
    origin_code = _interleave(*(_cells(a[:, k]) for k in range(3)))
    direction_code = _interleave(*(_cells(u[:, k]) for k in range(3)))
    return (origin_code << (3 * CELL_BITS)) | direction_code
