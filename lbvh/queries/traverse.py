"""Ray queries: closest hit and occlusion on the device (kernels/traverse.cl).

The host API is :func:`intersect` and :func:`occluded` (also reachable as
``bvh.intersect`` and ``bvh.occluded``); :func:`trace_buffers` is the
device-level entry for callers that keep their rays on the device.

Rays are checked and converted by :mod:`lbvh.queries.rays` (the conventions
are there): bad rays are refused before anything runs on the device, with a
``ValueError`` naming the first bad ray. The kernel itself terminates on any
input (its loop is bounded by the stack and by the node count); a NaN ray that
reached it through :func:`trace_buffers` is not traced: a miss with
:data:`FLAG_NAN_RAY` set.

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
    The kernel reads a tree through wide records (:mod:`lbvh.queries.wide`): up
    to 8 children per record on a CPU (4 elsewhere), their boxes in rows that one
    vector slab test covers, made on the device from any tree of the layout on
    its first query and kept by the :class:`lbvh.BVH` (a refit rewrites their boxes). On
    the 2-core machine that traces primary rays 1.4-1.8x as fast as binary
    records of two children did (bunny, Sponza, a 1M-triangle terrain). A tree whose records
    would exceed the device's largest buffer is traversed through its own
    binary nodes. Likewise the faces are copied once in slot order
    (:func:`order_faces`, 12 bytes per triangle), so that a leaf's
    triangles are read without a detour through ``prim_order``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from .rays import DeviceRays, Rays, check_rays, upload_rays
from .ray_order import ray_order, worth_ordering
from ..tree import Mesh, Tree
from .target import QueryTarget

KERNEL_FILE = "traverse.cl"

#: The query API (the rays' checks and upload come from :mod:`lbvh.queries.rays`).
__all__ = ["Hits", "DeviceHits", "Rays", "DeviceRays", "check_rays", "upload_rays", "intersect",
           "occluded", "trace_buffers", "read_hits", "stack_need", "stack_size_for",
           "order_faces", "FLAG_OVERFLOW", "FLAG_VISIT_LIMIT", "FLAG_NAN_RAY", "STACK_BUCKETS"]

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
            (up to 8 children, :mod:`lbvh.queries.wide`) or a leaf, or a binary node for trees
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


# -- programs -------------------------------------------------------------------

def stack_need(target: QueryTarget) -> int:
    """The most stack entries an ordered traversal of this tree can hold.

    Through wide records: their ``stack_need`` (a record pushes its children
    but the one it follows, so the most entries on the stack is the largest
    sum of that over the records of one root-to-leaf path; never less than
    the binary depth). Through the binary nodes: the tree's depth (one push
    per level).
    """
    wide = target.wide_records()
    if wide.packed:
        return wide.stack_need
    return target.traversal_depth()


def stack_size_for(target: QueryTarget) -> int:
    """Stack entries the kernel gets for this tree: :func:`stack_need` rounded up
    to a bucket (the last bucket if none holds it: then rays may overflow, flagged)."""
    need = stack_need(target)
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


def kernel_defines(ctx: dev.Context, any_hit: bool, triangle_test: str, counters: bool,
                   stack_size: int) -> dict[str, int | str]:
    """The -D defines of kernels/traverse.cl for a query (options checked here)."""
    if triangle_test not in TRIANGLE_TESTS:
        raise ValueError(f"triangle_test: {triangle_test!r}; expected one of "
                         f"{', '.join(TRIANGLE_TESTS)}")
    if not isinstance(stack_size, (int, np.integer)) or stack_size < 1:
        raise ValueError(f"stack_size: {stack_size!r}; expected a positive integer")
    return {"ANY_HIT": int(bool(any_hit)), "COUNTERS": int(bool(counters)),
            "TRIANGLE_TEST": TRIANGLE_TESTS[triangle_test], "STACK_SIZE": int(stack_size),
            "SLAB_PAD": slab_pad(ctx)}


def _launch(count: int) -> dev.Launch:
    """One ray per work-item everywhere, in work-groups of :data:`_WORK_GROUP`."""
    return dev.Launch(count, 1, max(1, -(-count // _WORK_GROUP) * _WORK_GROUP), _WORK_GROUP)


# -- faces in slot order ---------------------------------------------------------

def order_faces(tree: Tree, mesh: Mesh) -> cl.Buffer:
    """``uint32 (F, 3)`` on the device: ``faces[prim_order]``, the triangles in slot
    order as the kernel reads them (kernels/traverse.cl, order_faces); :class:`lbvh.BVH`
    makes it on first use and keeps it (a refit keeps faces and order)."""
    ctx = tree.ctx
    out = ctx.memory.alloc(12 * tree.num_prims, pooled=True)
    launch = ctx.launch(tree.num_prims, min_per_item=4096, gpu_per_item=1)
    dev.run(ctx, KERNEL_FILE, "order_faces", launch, mesh.faces_buf, tree.prim_order,
            tree.num_prims, launch.per_item, out, defines={})
    return out


# -- device-level entry -----------------------------------------------------------

def trace_buffers(target: QueryTarget, rays: DeviceRays, *, any_hit: bool = False,
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
    ctx, tree = target.ctx, target.tree
    if stack_size is None:
        stack_size = stack_size_for(target)
    wide = target.wide_records()
    count = int(rays.count)
    if hits is None:
        hits = ctx.memory.alloc(16 * count)
    if flags is None:
        flags = ctx.memory.alloc(4 * count)
    if counters and counter_buf is None:
        counter_buf = ctx.memory.alloc(8 * count)
    launch = _launch(count)
    ev = dev.run(ctx, KERNEL_FILE, "traverse", launch, tree.nodes, wide.buffer, tree.prim_order,
                 target.mesh.vertices_buf, target.slot_faces(), tree.root, wide.root_x,
                 wide.root_y, tree.num_nodes, rays.origins, rays.directions, rays.tmin, rays.tmax,
                 rays.interval_stride, order if order is not None else flags, hits, flags,
                 counter_buf if counters else flags, count, launch.per_item,
                 defines={**kernel_defines(ctx, any_hit, triangle_test, counters, stack_size),
                          "WIDE": int(wide.packed), "WIDTH": wide.width,
                          "RAY_ORDER": int(order is not None), **(defines or {})},
                 wait_for=wait_for)
    return DeviceHits(count, hits, flags, counter_buf if counters else None, ev)


def read_hits(ctx: dev.Context, out: DeviceHits) -> np.ndarray:
    """``float32 (4, count)``: the t, u, v and primitive (int32 bits) planes of ``out``."""
    planes = np.empty((4, out.count), np.float32)
    if out.count:
        cl.enqueue_copy(ctx.queue, planes, out.hits, wait_for=[out.event], is_blocking=True)
    return planes


# -- host API ---------------------------------------------------------------------

def _trace(target: QueryTarget, origins: Any, directions: Any, tmin: Any, tmax: Any, any_hit: bool,
           triangle_test: str, counters: bool, batch_size: int,
           stack_size: int | None) -> Hits:
    if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ValueError(f"batch_size: {batch_size!r}; expected a positive integer")
    rays = check_rays(origins, directions, tmin, tmax)
    n = len(rays)
    planes = np.empty((4, n), np.float32)
    flag = np.zeros(n, np.int32)
    count = np.zeros((n, 2), np.int32) if counters else None
    ctx, queue = target.ctx, target.ctx.queue
    batch = int(min(batch_size, max(n, 1)))
    lo, hi, stride = rays.kernel_intervals()
    per_ray = stride == 1
    ro = cl.mem_flags.READ_ONLY
    alloc = ctx.memory.alloc
    bufs = {"o": alloc(12 * batch, flags=ro), "d": alloc(12 * batch, flags=ro),
            "lo": alloc(4 * (batch if per_ray else 1), flags=ro),
            "hi": alloc(4 * (batch if per_ray else 1), flags=ro),
            "hits": alloc(16 * batch), "flags": alloc(4 * batch)}
    if counters:
        bufs["count"] = alloc(8 * batch)
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
            if worth_ordering(m, target.tree.num_nodes):
                order, ups = ray_order(ctx, bufs["o"], bufs["d"], m, *target.tree.root_box())
            result = trace_buffers(target, device_rays, any_hit=any_hit, triangle_test=triangle_test,
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
                ctx.memory.free(order)
    finally:
        ctx.memory.free(*bufs.values())
    overflow = flag != 0
    return Hits(t=planes[0], prim=planes[3].view(np.int32), u=planes[1], v=planes[2],
                overflow=overflow, overflow_count=int(overflow.sum()),
                nodes_visited=None if count is None else count[:, 0].copy(),
                tris_tested=None if count is None else count[:, 1].copy())


@dev.serialised
def intersect(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
              triangle_test: str = "watertight", counters: bool = False,
              batch_size: int = 1 << 20, stack_size: int | None = None) -> Hits:
    """Closest hit of each ray in ``[tmin, tmax]``.

    Args:
        target: an :class:`lbvh.BVH` (any builder; the kernel reads only docs/layout.md).
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
    return _trace(target, origins, directions, tmin, tmax, False, triangle_test, counters,
                  batch_size, stack_size)


@dev.serialised
def occluded(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
             triangle_test: str = "watertight", counters: bool = False,
             batch_size: int = 1 << 20, stack_size: int | None = None,
             return_hits: bool = False) -> np.ndarray | Hits:
    """Whether each ray hits anything in ``[tmin, tmax]`` (any-hit traversal, stops at the first).

    Arguments as :func:`intersect`. Returns ``bool (N,)``; with
    ``return_hits=True`` the full :class:`Hits` instead (``hits.hit`` is the
    answer, ``hits.overflow`` / ``hits.overflow_count`` report stack overflows,
    ``t, prim, u, v`` describe the hit that was found, not necessarily the closest).
    """
    hits = _trace(target, origins, directions, tmin, tmax, True, triangle_test, counters,
                  batch_size, stack_size)
    return hits if return_hits else hits.hit
