"""Ray queries: closest hit and occlusion on the device (kernels/traverse.cl).

The host API is :func:`intersect` and :func:`occluded` (also reachable as
``bvh.intersect`` and ``bvh.occluded``), their non-blocking forms
:func:`intersect_async` and :func:`occluded_async` (a
``concurrent.futures.Future``); :func:`trace_buffers` is the device-level entry
for callers that keep their rays in their own buffers.

Rays are checked and converted by :mod:`lbvh.queries.rays` (the conventions
are there): bad rays are refused before anything runs on the device, with a
``ValueError`` naming the first bad ray, or with ``invalid_rays="miss"`` not
traced and reported as misses (``Hits.invalid``). Rays in
``pyopencl.array.Array`` objects on the BVH's context are checked on the
device, traced in place and answered by a :class:`DeviceHitArrays` whose
fields stay on the device. The kernel itself terminates on any input (its
loop is bounded by the stack and by the node count); a NaN ray that reached
it through :func:`trace_buffers` is not traced: a miss with
:data:`FLAG_NAN_RAY` set.

Results (:class:`Hits`): ``t`` (``inf`` on a miss), ``prim`` (``-1``), ``u``, ``v``,
``mask`` (hit or not), ``locations(origins, directions)`` and ``normals``
(NaN rows for misses), overflow and invalid flags, optional counters.

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

import dataclasses
import functools
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from .. import device as dev
from .rays import (DEVICE_KERNEL_FILE, DeviceRays, Rays, check_rays,
                   device_array_rays, device_invalid, host_array, is_device_array,
                   mark_invalid, read_device_rays, upload_rays)
from .exact import collinear
from .packets import PACKETS_FROM, packets_apply, trace_packets
from .ray_order import ray_order, worth_ordering
from ..tree import Mesh, Tree
from .options import NODE_ORDERS, TRIANGLE_TESTS, QueryOptions, query_options
from .target import QueryTarget, query_target
from .wide import lane_defines

KERNEL_FILE = "traverse.cl"

#: The query API (the rays' checks and upload come from :mod:`lbvh.queries.rays`).
__all__ = ["Hits", "DeviceHitArrays", "DeviceHits", "Rays", "DeviceRays", "check_rays",
           "upload_rays", "intersect", "occluded", "intersect_async", "occluded_async",
           "geometric_normals", "trace_buffers", "read_hits", "stack_need", "stack_size_for",
           "order_faces", "order_triangles", "order_triangles_numpy", "degenerate_triangles",
           "FLAG_OVERFLOW",
           "FLAG_VISIT_LIMIT", "FLAG_NAN_RAY", "STACK_BUCKETS"]

#: Bits of the per-ray flag word written by the kernel.
FLAG_OVERFLOW = 1      # the stack was full: a subtree was skipped
FLAG_VISIT_LIMIT = 2   # more nodes visited than the tree has (a malformed, cyclic tree)
FLAG_NAN_RAY = 4       # NaN in the ray (only through trace_buffers): not traced

#: Stack sizes a program is compiled for; a tree uses the first that holds its stack_need.
STACK_BUCKETS = (32, 64, 96, 128, 192, 256, 384, 512, 768)


#: Rays per kernel launch of the host API unless ``batch_size`` says otherwise.
DEFAULT_BATCH = 1 << 20

# The launch's shape. On a GPU: one ray per work-item, work-groups of 64. On a CPU
# (PoCL runs a work-group's work-items as a loop on one core): work-groups of one
# work-item that loops over up to _CPU_RAYS_PER_ITEM rays, its stack arrays staying
# hot. Same-process A/B, 15 rounds of 512x512 camera rays against groups of 64
# one-ray work-items: 1.12x on Sponza, 1.11x on the bunny, 1.03x on terrain-1m
# (Zen 3; 16 rays per item 1.02-1.11x, 256 1.04-1.10x; groups of 8 or 256
# one-ray work-items 0.94-1.04x). An earlier kernel measured no difference, and
# the closest-point walk (kernels/closest.cl) looping over 64 points per
# work-item none either (1.01x, 1.02x, 1.01x), so it keeps groups of 64.
_WORK_GROUP = 64
_CPU_RAYS_PER_ITEM = 64

_UNIT_ROUNDOFF = 2.0 ** -24


def geometric_normals(vertices: np.ndarray, faces: np.ndarray, prim: np.ndarray) -> np.ndarray:
    """``float32 (N, 3)``: the unit geometric normal of triangle ``prim[i]``,
    ``cross(p1 - p0, p2 - p0)`` normalised (``p0, p1, p2 = vertices[faces[prim]]``: the
    winding of the faces), computed in float64; NaN rows where ``prim`` is ``-1``."""
    prim = np.asarray(prim)
    out = np.full((len(prim), 3), np.nan, np.float32)
    hit = np.flatnonzero(prim >= 0)
    if len(hit):
        tri = np.asarray(vertices)[np.asarray(faces)[prim[hit]]].astype(np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        with np.errstate(invalid="ignore", divide="ignore"):
            out[hit] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return out


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
            traversed through their own nodes. 0 for an invalid ray (not traced).
        tris_tested: ``int32 (N,)`` with ``counters=True`` (else ``None``).
        invalid: ``bool (N,)`` the ray was bad and not traced (``invalid_rays="miss"``;
            all ``False`` otherwise): it reads as a miss.
        invalid_count: number of ``True`` in ``invalid``.
        mask: ``bool (N,)`` whether each ray hit something (``prim >= 0``; also ``hit``).
        normals: ``float32 (N, 3)`` unit geometric normals of the hit triangles (see
            :func:`geometric_normals`), NaN rows for misses; computed when read.
        geometry: ``(vertices, faces)`` the rays were traced against, what ``normals``
            reads: the mesh's own read-only arrays (no copy; a later refit does not
            change them); ``None`` for results not made by a query.

    :meth:`locations` gives the hit points. From :func:`occluded` with
    ``return_hits=True`` the hit is *a* hit in ``[tmin, tmax]``, not necessarily
    the closest.
    """
    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    overflow: np.ndarray
    overflow_count: int
    nodes_visited: np.ndarray | None = None
    tris_tested: np.ndarray | None = None
    invalid: np.ndarray | None = None
    invalid_count: int = 0
    geometry: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False,
                                                           compare=False)

    def __post_init__(self) -> None:
        if self.invalid is None:
            self.invalid = np.zeros(len(self.t), bool)

    @property
    def hit(self) -> np.ndarray:
        """``bool (N,)``: whether each ray hit something."""
        return self.prim >= 0

    @property
    def mask(self) -> np.ndarray:
        """``bool (N,)``: whether each ray hit something (the same as :attr:`hit`)."""
        return self.prim >= 0

    def locations(self, origins: Any, directions: Any) -> np.ndarray:
        """The hit points ``origin + t * direction``, ``(N, 3)``; NaN rows for misses.

        ``origins`` and ``directions`` are the rays the query traced (any host array
        :func:`lbvh.queries.rays.host_array` reads). The result is float64 when
        either is float64, else float32 (as the rays were traced).
        """
        o = np.asarray(host_array("origins", origins))
        d = np.asarray(host_array("directions", directions))
        for name, a in (("origins", o), ("directions", d)):
            if a.shape != (len(self), 3):
                raise ValueError(f"{name}: shape {a.shape}, expected ({len(self)}, 3): the rays "
                                 "of this result")
        dtype = np.float64 if np.float64 in (o.dtype, d.dtype) else np.float32
        out = np.array(d, dtype=dtype)
        with np.errstate(invalid="ignore", over="ignore"):
            out *= self.t[:, None]
            out += o
        out[~self.hit] = np.nan
        return out

    @property
    def normals(self) -> np.ndarray:
        """``float32 (N, 3)``: unit geometric normals of the hit triangles, NaN rows for
        misses (:func:`geometric_normals`)."""
        if self.geometry is None:
            raise ValueError("normals: this Hits holds no mesh (it was not made by a query); "
                             "use lbvh.queries.traverse.geometric_normals(vertices, faces, hits.prim)")
        return geometric_normals(*self.geometry, self.prim)

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class DeviceHitArrays:
    """Results of a query on ``pyopencl.array.Array`` rays: the fields of :class:`Hits`
    as pyopencl arrays on the BVH's queue, left on the device.

    ``t``, ``u``, ``v`` (float32), ``prim`` (int32), ``overflow``, ``invalid``, ``mask``
    (``bool``, one byte each: pyopencl's arithmetic does not take ``bool``, use
    ``.view(np.uint8)``), ``nodes_visited``, ``tris_tested`` (int32, or ``None``): the
    kernel's answers in place, each array carrying the event that writes it (``get()``
    waits for it). ``invalid_count`` is known when the call returns;
    :attr:`overflow_count` is read from the device when asked for (4 bytes).
    :meth:`get` copies everything to a :class:`Hits`.
    """
    t: cl_array.Array
    prim: cl_array.Array
    u: cl_array.Array
    v: cl_array.Array
    overflow: cl_array.Array
    invalid: cl_array.Array
    invalid_count: int
    mask: cl_array.Array
    nodes_visited: cl_array.Array | None
    tris_tested: cl_array.Array | None
    overflow_counter: cl_array.Array = field(repr=False)
    geometry: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False,
                                                           compare=False)

    @property
    def hit(self) -> cl_array.Array:
        """The same as :attr:`mask`."""
        return self.mask

    @property
    def overflow_count(self) -> int:
        """How many rays overflowed the stack (waits for the query)."""
        return int(self.overflow_counter.get()[0])

    def get(self) -> Hits:
        """Everything copied to the host, as the host API returns it (waits)."""
        def host(a: cl_array.Array | None) -> np.ndarray | None:
            return None if a is None else a.get()
        return Hits(t=self.t.get(), prim=self.prim.get(), u=self.u.get(), v=self.v.get(),
                    overflow=self.overflow.get(), overflow_count=self.overflow_count,
                    nodes_visited=host(self.nodes_visited), tris_tested=host(self.tris_tested),
                    invalid=self.invalid.get(), invalid_count=self.invalid_count,
                    geometry=self.geometry)

    def __len__(self) -> int:
        return self.t.shape[0]


@dataclass
class DeviceHits:
    """Device buffers written by :func:`trace_buffers` (``count`` rays).

    ``hits``: four planes of ``count`` float32 (t, u, v, primitive as int32 bits; see
    :func:`read_hits`); ``flags``: ``int32`` flag words;
    ``counters``: ``int32 (count, 2)`` (nodes visited, triangles tested) or ``None``;
    ``event``: the last kernel's event (the answers are written when it is done);
    ``kernels``: the events of every kernel of the walk (the packets' and the single-ray
    walk's, :mod:`lbvh.queries.packets`), whose device times add up to the walk's.
    """
    count: int
    hits: cl.Buffer
    flags: cl.Buffer
    counters: cl.Buffer | None
    event: cl.Event
    kernels: list[cl.Event] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.kernels:
            self.kernels = [self.event]


# -- programs -------------------------------------------------------------------

def stack_need(target: QueryTarget) -> int:
    """The most stack entries an ordered traversal of this tree can hold.

    Through wide records: their ``stack_need`` (a record pushes its children
    but the one it follows, so the most entries on the stack is the largest
    sum of that over the records of one root-to-leaf path; never less than
    the binary depth). Through the binary nodes: the tree's depth (one push
    per level).
    """
    target = query_target(target)   # a BVH gives its query data
    wide = target.wide_records()
    if wide.packed:
        return wide.stack_need
    return target.traversal_depth()


#: How many times the ordered traversal's stack the heap of order="global" gets: best
#: first keeps a whole frontier pending, not one path's siblings (Sponza's median tree
#: overflowed 0.4% of random rays with the ordered stack's 96 entries, none with 256).
GLOBAL_ORDER_STACK_FACTOR = 4


def stack_size_for(target: QueryTarget, node_order: str = "ordered") -> int:
    """Stack entries the kernel gets for this tree: :func:`stack_need` rounded up
    to a bucket (the last bucket if none holds it: then rays may overflow, flagged);
    for ``node_order="global"`` :data:`GLOBAL_ORDER_STACK_FACTOR` times that."""
    target = query_target(target)   # a BVH gives its query data
    factor = GLOBAL_ORDER_STACK_FACTOR if node_order == "global" else 1
    return stack_bucket(factor * stack_need(target))


def stack_bucket(need: int) -> int:
    """The first of :data:`STACK_BUCKETS` that holds ``need`` entries, else the last."""
    return next((b for b in STACK_BUCKETS if need <= b), STACK_BUCKETS[-1])


def slab_pad(ctx: dev.Context) -> str:
    """The far-distance factor of the slab test as an OpenCL hex float literal.

    ``1 + 2 gamma(3)`` (Ize 2013) counts three roundings: the subtraction, the
    reciprocal and the product. Where the reciprocal is not correctly rounded
    (OpenCL allows 2.5 ulp) it counts as five more: ``1 + 2 gamma(7)``.
    """
    return _slab_pad(bool(ctx.device.single_fp_config
                          & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT))


@functools.lru_cache(maxsize=None)
def _slab_pad(exact_div: bool) -> str:
    """:func:`slab_pad` given whether the device's division is correctly rounded
    (computed once: every query's defines ask for it)."""
    n = 3 if exact_div else 7
    gamma = n * _UNIT_ROUNDOFF / (1 - n * _UNIT_ROUNDOFF)
    pad = np.float32(1 + 2 * gamma)
    if float(pad) < 1 + 2 * gamma:
        pad = np.nextafter(pad, np.float32(2))
    return float(pad).hex() + "f"


def kernel_defines(ctx: dev.Context, any_hit: bool, triangle_test: str, counters: bool,
                   stack_size: int, node_order: str = "ordered") -> dict[str, int | str]:
    """The -D defines of kernels/traverse.cl for a query (options checked here)."""
    if node_order not in NODE_ORDERS:
        raise ValueError(f"order: {node_order!r}; expected one of {', '.join(NODE_ORDERS)}")
    if triangle_test not in TRIANGLE_TESTS:
        raise ValueError(f"triangle_test: {triangle_test!r}; expected one of "
                         f"{', '.join(TRIANGLE_TESTS)}")
    if not isinstance(stack_size, (int, np.integer)) or stack_size < 1:
        raise ValueError(f"stack_size: {stack_size!r}; expected a positive integer")
    defines = {"ANY_HIT": int(bool(any_hit)), "COUNTERS": int(bool(counters)),
               "TRIANGLE_TEST": TRIANGLE_TESTS[triangle_test], "STACK_SIZE": int(stack_size),
               "SLAB_PAD": slab_pad(ctx), **lane_defines(ctx)}
    if NODE_ORDERS[node_order] and not any_hit:
        defines["ORDER_GLOBAL"] = 1
    return defines


def _launch(ctx: dev.Context, count: int) -> dev.Launch:
    """On a GPU one ray per work-item in work-groups of :data:`_WORK_GROUP`; on a CPU
    work-groups of one work-item over up to :data:`_CPU_RAYS_PER_ITEM` rays, fewer
    where that leaves a core without work (``ctx.work_items()`` chunks at least)."""
    if ctx.is_cpu:
        per = max(1, min(_CPU_RAYS_PER_ITEM, -(-count // ctx.work_items())))
        return ctx.launch_chunks(count, per)
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


def degenerate_triangles(vertices: np.ndarray, faces: np.ndarray, dtype=None) -> np.ndarray:
    """``bool (F,)``: zero-area triangles, which no ray hits: those whose corners lie
    exactly on a line (repeated corners included), as the kernel decides it on a
    device with doubles (kernels/ray_triangle.h ``degenerate``; twin
    :func:`lbvh.queries.exact.collinear`). ``dtype`` is accepted for older callers
    and ignored: the test is exact."""
    return collinear(vertices, faces)


def order_triangles(tree: Tree, mesh: Mesh) -> cl.Buffer:
    """``float32 (F, 3, 3)`` on the device: ``vertices[faces[prim_order]]``, each slot's
    triangle as its three corners, a degenerate one (kernels/ray_triangle.h
    ``degenerate``: zero area, which no ray hits) as its first corner three times
    (kernels/traverse.cl, order_triangles; twin:
    :func:`order_triangles_numpy`), 36 bytes per slot, which the every-hit walk reads
    instead of going through the faces (kernels/every_hit.h ``SLOT_TRIANGLES``).
    :class:`lbvh.BVH` makes it on first use and keeps it until a refit moves the
    vertices."""
    ctx = tree.ctx
    out = ctx.memory.alloc(36 * max(tree.num_prims, 1), pooled=True)
    launch = ctx.launch(tree.num_prims, min_per_item=4096, gpu_per_item=1)
    dev.run(ctx, KERNEL_FILE, "order_triangles", launch, mesh.vertices_buf, mesh.faces_buf,
            tree.prim_order, tree.num_prims, launch.per_item, out, defines={})
    return out


def order_triangles_numpy(vertices: np.ndarray, faces: np.ndarray,
                          prim_order: np.ndarray) -> np.ndarray:
    """Twin of :func:`order_triangles`: ``float32 (S, 3, 3)``, the same values (copies),
    a degenerate triangle (:func:`degenerate_triangles`, the kernel's test) as its
    first corner three times."""
    v = np.asarray(vertices, np.float32)
    slot_faces = np.asarray(faces)[np.asarray(prim_order)]
    out = v[slot_faces]
    with np.errstate(over="ignore", invalid="ignore"):   # edges past float32, as the kernel
        point = degenerate_triangles(v, slot_faces)
    out[point] = out[point][:, :1]
    return out


# -- device-level entry -----------------------------------------------------------

@dataclass
class HitBuffers:
    """Where :func:`trace_buffers` writes, each allocated for the call where ``None``:
    ``hits`` (16 bytes per ray: four planes of ``count`` float32, t, u, v and the
    primitive as int32), ``flags`` (4), ``counters`` (8, with the ``counters`` option),
    ``scratch`` (4: the rays the packets leave to the single-ray walk)."""
    hits: cl.Buffer | None = None
    flags: cl.Buffer | None = None
    counters: cl.Buffer | None = None
    scratch: cl.Buffer | None = None


def trace_buffers(target: QueryTarget, rays: DeviceRays, *, any_hit: bool = False,
                  options: QueryOptions | None = None, outputs: HitBuffers | None = None,
                  defines: dict[str, int | str] | None = None, packets: bool | None = None,
                  **fields: Any) -> DeviceHits:
    """Trace rays already on the device; nothing is read back.

    ``rays`` (see :func:`upload_rays`) must have passed :func:`check_rays`; their
    ``order`` and ``ready`` events are honoured. ``options`` (or its fields as
    keywords): ``triangle_test``, ``counters``, ``stack_size`` and ``order`` (the
    order nodes are visited in, :data:`NODE_ORDERS`) of :class:`lbvh.QueryOptions`.
    ``outputs``: the buffers to write (:class:`HitBuffers`). ``defines`` adds or
    overrides -D defines of kernels/traverse.cl (tests, experiments). ``packets``:
    trace by packets of 8 rays (:mod:`lbvh.queries.packets`: the same answers bit for
    bit), ``None`` where :func:`lbvh.queries.packets.packets_apply` says so.
    """
    return _trace_buffers(target, rays, any_hit, query_options("trace", options, fields),
                          outputs or HitBuffers(), defines, packets)


def _trace_buffers(target: QueryTarget, rays: DeviceRays, any_hit: bool, opts: QueryOptions,
                   out: HitBuffers, defines: dict[str, int | str] | None,
                   packets: bool | None) -> DeviceHits:
    """:func:`trace_buffers` with checked options (the host calls of this module)."""
    triangle_test, counters, node_order = opts.triangle_test, opts.counters, opts.order
    stack_size = opts.stack_size
    hits, flags, counter_buf, scratch = out.hits, out.flags, out.counters, out.scratch
    order, wait_for = rays.order, list(rays.ready)
    target = query_target(target)   # a BVH gives its query data
    ctx, tree = target.ctx, target.tree
    if stack_size is None:
        stack_size = stack_size_for(target, node_order)
    wide = target.wide_records()
    count = int(rays.count)
    if hits is None:
        hits = ctx.memory.alloc(16 * count)
    if flags is None:
        flags = ctx.memory.alloc(4 * count)
    if counters and counter_buf is None:
        counter_buf = ctx.memory.alloc(8 * count)
    all_defines = {**kernel_defines(ctx, any_hit, triangle_test, counters, stack_size, node_order),
                   "WIDE": int(wide.packed), "WIDTH": wide.width,
                   "RAY_ORDER": int(order is not None),
                   **({"EXACT_LEAVES": 0} if tree.clipped_leaves else {}), **(defines or {})}
    can = packets_apply(ctx, bool(all_defines["WIDE"]), int(all_defines["WIDTH"]), counters,
                        "global" if all_defines.get("ORDER_GLOBAL") else node_order)
    if packets and not can:
        raise ValueError("packets=True: packets run on a CPU device through 8-wide records, "
                         "without counters, in the default node order")
    deferred = None
    kernels: list[cl.Event] = []
    if packets or (packets is None and can and count >= PACKETS_FROM):
        # packets where they are coherent; the rays of the others, listed in
        # `deferred`, go through the single-ray walk next (lbvh.queries.packets)
        deferred = scratch if scratch is not None else ctx.memory.alloc(4 * count)
        ev = trace_packets(target, rays, any_hit=any_hit, defines=all_defines, hits=hits,
                           flags=flags, deferred=deferred)
        order, wait_for, kernels = deferred, [ev], [ev]
        all_defines["RAY_ORDER"] = 1
    launch = _launch(ctx, count)
    ev = dev.run(ctx, KERNEL_FILE, "traverse", launch, tree.nodes, wide.buffer, tree.prim_order,
                 target.mesh.vertices_buf, target.slot_faces(), tree.root, wide.root_x,
                 wide.root_y, tree.num_nodes, rays.origins, rays.directions, rays.tmin, rays.tmax,
                 rays.interval_stride, order if order is not None else flags, hits, flags,
                 counter_buf if counters else flags, count, launch.per_item,
                 defines=all_defines, wait_for=wait_for)
    if deferred is not None and deferred is not scratch:
        ctx.memory.free(deferred)   # released once the walk that reads it is done
    return DeviceHits(count, hits, flags, counter_buf if counters else None, ev, kernels + [ev])


def read_hits(ctx: dev.Context, out: DeviceHits) -> np.ndarray:
    """``float32 (4, count)``: the t, u, v and primitive (int32 bits) planes of ``out``."""
    planes = np.empty((4, out.count), np.float32)
    if out.count:
        cl.enqueue_copy(ctx.queue, planes, out.hits, wait_for=[out.event], is_blocking=True)
    return planes


# -- host API ---------------------------------------------------------------------

def _trace(target: QueryTarget, origins: Any, directions: Any, tmin: Any, tmax: Any, any_hit: bool,
           opts: QueryOptions) -> Hits | DeviceHitArrays:
    """Trace the rays with checked options: host arrays in batches, pyopencl arrays in
    place."""
    if is_device_array(origins) or is_device_array(directions):
        return _trace_arrays(target, origins, directions, tmin, tmax, any_hit, opts)
    rays = check_rays(origins, directions, tmin, tmax, invalid_rays=opts.invalid_rays)
    geometry = (target.mesh.vertices, target.mesh.faces)
    if rays.invalid is None:
        hits = _trace_rays(target, rays, any_hit, opts)
        hits.geometry = geometry
        return hits
    # invalid_rays="miss" and some rays are bad: the good ones are traced alone
    good = np.flatnonzero(~rays.invalid)
    part = _trace_rays(target, rays.take(good), any_hit, opts)
    n = len(rays)
    hits = Hits(t=np.full(n, np.inf, np.float32), prim=np.full(n, -1, np.int32),
                u=np.zeros(n, np.float32), v=np.zeros(n, np.float32), overflow=np.zeros(n, bool),
                overflow_count=part.overflow_count,
                nodes_visited=None if part.nodes_visited is None else np.zeros(n, np.int32),
                tris_tested=None if part.tris_tested is None else np.zeros(n, np.int32),
                invalid=rays.invalid, invalid_count=n - len(good), geometry=geometry)
    for name in ("t", "prim", "u", "v", "overflow", "nodes_visited", "tris_tested"):
        if getattr(part, name) is not None:
            getattr(hits, name)[good] = getattr(part, name)
    return hits


def _trace_rays(target: QueryTarget, rays: Rays, any_hit: bool, opts: QueryOptions) -> Hits:
    """Trace checked rays, all good, in batches of the options' ``batch_size``."""
    n = len(rays)
    counters, batch_size = opts.counters, opts.batch(DEFAULT_BATCH)
    if target.ctx.is_cpu and 0 < n <= batch_size and not counters:
        return _trace_in_place(target, rays, any_hit, opts)
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
        if not per_ray:   # lo, hi live until the last batch's finish: not blocking
            cl.enqueue_copy(queue, bufs["lo"], lo, is_blocking=False)
            cl.enqueue_copy(queue, bufs["hi"], hi, is_blocking=False)
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            m = stop - start
            ups = [cl.enqueue_copy(queue, bufs["o"], rays.origins[start:stop], is_blocking=False),
                   cl.enqueue_copy(queue, bufs["d"], rays.directions[start:stop], is_blocking=False)]
            if per_ray:
                ups += [cl.enqueue_copy(queue, bufs["lo"], lo[start:stop], is_blocking=False),
                        cl.enqueue_copy(queue, bufs["hi"], hi[start:stop], is_blocking=False)]
            order = None
            if worth_ordering(m, target.tree.num_nodes):
                order, ups = ray_order(ctx, bufs["o"], bufs["d"], m, *target.tree.root_box())
            device_rays = DeviceRays(m, bufs["o"], bufs["d"], bufs["lo"], bufs["hi"], stride,
                                     order, tuple(ups))
            result = _trace_buffers(target, device_rays, any_hit, opts,
                                    HitBuffers(bufs["hits"], bufs["flags"], bufs.get("count")),
                                    None, None)
            if m == n:   # one batch: the four planes are the buffer as it is, one copy
                cl.enqueue_copy(queue, planes, bufs["hits"], wait_for=[result.event],
                                is_blocking=False)
            else:
                for k in range(4):
                    cl.enqueue_copy(queue, planes[k, start:stop], bufs["hits"],
                                    src_offset=4 * k * m, wait_for=[result.event],
                                    is_blocking=False)
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
    return _hits_of(planes, flag, count)


def _hits_of(planes: np.ndarray, flag: np.ndarray, count: np.ndarray | None = None) -> Hits:
    """:class:`Hits` from the kernel's four planes (t, u, v, prim), its flags and, with
    counters, its ``(nodes, triangles)`` per ray."""
    overflow = flag != 0
    return Hits(t=planes[0], prim=planes[3].view(np.int32), u=planes[1], v=planes[2],
                overflow=overflow, overflow_count=int(overflow.sum()),
                nodes_visited=None if count is None else count[:, 0].copy(),
                tris_tested=None if count is None else count[:, 1].copy())


def _trace_in_place(target: QueryTarget, rays: Rays, any_hit: bool, opts: QueryOptions) -> Hits:
    """:func:`_trace_rays` in one batch on a device that shares the host's memory (a
    CPU): the kernel reads the checked rays' arrays and writes the answers' arrays
    themselves (:meth:`lbvh.device.DeviceMemory.host_view`), where the batches copy
    both ways (24 MB in, 20 MB out for 1M rays: 1.07x through ``bvh.intersect`` on the
    bunny's camera rays, Zen 3). The answers (the four planes and the flags) are one
    block of host memory, read back by one map
    (:meth:`lbvh.device.DeviceMemory.host_outputs`): a small call waits once."""
    n = len(rays)
    ctx, memory = target.ctx, target.ctx.memory
    lo, hi, stride = rays.kernel_intervals()
    bufs: list[cl.Buffer] = []
    out = None
    order = None
    read = False
    try:
        for a in (rays.origins, rays.directions, lo, hi):
            bufs.append(memory.host_view(a))
        # the answers, and the packets' scratch (the rays they leave to the single-ray
        # walk): one block of host memory, no device memory
        out = memory.host_outputs(((4, n), np.float32), ((n,), np.int32), ((n,), np.int32),
                                  readable=True)
        planes, flag, _ = out.arrays
        ups: list[cl.Event] = []
        if worth_ordering(n, target.tree.num_nodes):
            order, ups = ray_order(ctx, bufs[0], bufs[1], n, *target.tree.root_box())
        device_rays = DeviceRays(n, *bufs, stride, order, tuple(ups))
        result = _trace_buffers(target, device_rays, any_hit, opts,
                                HitBuffers(out.buffers[0], out.buffers[1],
                                           scratch=out.buffers[2]), None, None)
        dev.read_host_views(ctx.queue, [(out.block_buffer, out.block)], wait_for=[result.event])
        read = True
    finally:
        # The map waited for the kernel: what is still queued is the unmap of a read
        # mapping, which writes nothing (a finish here waited for it: 60-80 us of a
        # one-ray call on PoCL). A failure on the way may leave commands that read or
        # write the arrays: those are waited for.
        if not read:
            ctx.queue.finish()
        if order is not None:
            memory.free(order)
        for b in bufs:
            b.release()
        if out is not None:
            out.release()
    return _hits_of(planes, flag)


# -- rays in pyopencl arrays ----------------------------------------------------

def _trace_arrays(target: QueryTarget, origins: Any, directions: Any, tmin: Any, tmax: Any,
                  any_hit: bool, opts: QueryOptions) -> DeviceHitArrays:
    """Trace rays held in pyopencl arrays without a host round trip of the rays or the
    results: the values are checked on the device (:func:`lbvh.queries.rays.device_invalid`:
    a 4-byte read of how many are bad), bad ones raise (their first named, read back)
    or are reported as misses (their ``tmin`` set to NaN: the kernel does not trace them)."""
    ctx, q = target.ctx, target.ctx.queue
    counters, invalid_rays = opts.counters, opts.invalid_rays
    given = device_array_rays(ctx, origins, directions, tmin, tmax)
    rays, n = given.rays, given.rays.count
    order = None
    bad, bad_count = device_invalid(ctx, rays, given.wait_for)
    if bad_count and invalid_rays == "raise":
        host = read_device_rays(ctx, rays)   # named as the host checks name it
        check_rays(host.origins, host.directions, host.tmin, host.tmax)
        raise AssertionError("the device found a bad ray that check_rays accepts")
    wait_for = list(given.wait_for) + list(bad.events)
    if bad_count:
        rays = mark_invalid(ctx, rays, bad)
    elif worth_ordering(n, target.tree.num_nodes):
        order, events = ray_order(ctx, rays.origins, rays.directions, n,
                                  *target.tree.root_box())
        wait_for += events
    if n:
        out = _trace_buffers(target, dataclasses.replace(rays, order=order, ready=tuple(wait_for)),
                             any_hit, opts, HitBuffers(), None, None)
    else:   # nothing to launch; the options are checked all the same
        kernel_defines(ctx, any_hit, opts.triangle_test, counters, opts.stack_size or 1, opts.order)
        out = DeviceHits(0, ctx.memory.alloc(16), ctx.memory.alloc(4),
                         ctx.memory.alloc(8) if counters else None, cl.enqueue_marker(q))
    done = [out.event]

    def plane(k: int, dtype: type) -> cl_array.Array:
        return cl_array.Array(q, (n,), dtype, data=out.hits, offset=4 * k * n, events=done)

    def new(dtype: type, size: int = n) -> cl_array.Array:
        return cl_array.Array(q, (size,), dtype,
                              data=ctx.memory.alloc(np.dtype(dtype).itemsize * size))

    prim = plane(3, np.int32)
    overflow, mask, counter = new(np.bool_), new(np.bool_), new(np.int32, 1)
    nodes = tris = None
    if counters:
        nodes, tris = new(np.int32), new(np.int32)
    fill = cl.enqueue_fill_buffer(q, counter.base_data, np.int32(0), 0, 4)
    if n:   # kernels/device_rays.cl hits_from_flags; unused counter arguments get a placeholder
        post = dev.run(ctx, DEVICE_KERNEL_FILE, "hits_from_flags", dev.Launch(
            n, 1, -(-n // 64) * 64, 64), out.flags, out.hits,
            bad.base_data, n, overflow.base_data, mask.base_data, counter.base_data,
            out.counters if counters else out.flags, nodes.base_data if counters else out.flags,
            tris.base_data if counters else out.flags, defines={"COUNTERS": int(counters)},
            wait_for=done + [fill])
        done = [post]
    else:
        done = [fill]
    for arr in (overflow, mask, counter) + ((nodes, tris) if counters else ()):
        arr.add_event(done[0])
    for source in given.sources:   # pyopencl writes to the inputs wait for the query
        source.add_event(out.event)
    # The query's own buffers (converted rays, intervals, the order) go with their last
    # reference: the runtime keeps a buffer until the commands reading it are done.
    return DeviceHitArrays(t=plane(0, np.float32), prim=prim, u=plane(1, np.float32),
                           v=plane(2, np.float32), overflow=overflow, invalid=bad,
                           invalid_count=bad_count, mask=mask, nodes_visited=nodes,
                           tris_tested=tris, overflow_counter=counter,
                           geometry=(target.mesh.vertices, target.mesh.faces))


# -- the public calls ---------------------------------------------------------------

_ARGS_DOC = """
        origins, directions: ``(N, 3)`` arrays, float32 (float64 and integers are
            converted): numpy arrays or any host array (``__array_interface__``,
            the buffer protocol, a CPU ``__dlpack__``, ``__array__``; read without a
            copy where they are float32 and C-contiguous), or ``pyopencl.array.Array``
            on the BVH's context (``bvh.ctx.ctx``): then the rays are read and the
            results left on the device (:class:`DeviceHitArrays`).
        tmin, tmax: scalars or ``(N,)`` arrays, ``0 <= tmin <= tmax``; ``tmax`` may be ``inf``.
        options: a :class:`lbvh.QueryOptions` (``None``: the defaults), or its fields as
            keywords: ``invalid_rays`` (``"raise"``, default, or ``"miss"``: bad rays
            come back as misses with ``invalid`` set and counted in ``invalid_count``),
            ``triangle_test`` (``"watertight"``, default, or ``"moller"``),
            ``counters`` (nodes visited and triangles tested per ray), ``batch_size``
            (rays per launch of host arrays; about 60 bytes of device memory per ray
            of a batch), ``stack_size`` (tests){order}."""

_RAISES_DOC = """
    Raises:
        ValueError: a bad ray (named; unless ``invalid_rays="miss"``), a bad shape,
        dtype or option, pyopencl arrays on another context.
"""

_INTERSECT_SUMMARY = "Closest hit of each ray in ``[tmin, tmax]``."
_INTERSECT_ARGS = ""
_ORDER_DOC = """, and
            ``order``: ``"ordered"`` (default): depth first, the nearest child first;
            ``"global"``: always the nearest pending node of all (a heap, Kay & Kajiya
            1986), stopping when it lies beyond the closest hit. The same hits;
            ``counters`` show the nodes each visits"""
_INTERSECT_RETURNS = """
    Returns:
        :class:`Hits` (:class:`DeviceHitArrays` for pyopencl rays). Among triangles hit
        at exactly the same ``t`` the one of the lowest index wins: the answer is the
        same whatever the tree, the builder or the walk (by packets or ray by ray).
"""
_OCCLUDED_SUMMARY = ("Whether each ray hits anything in ``[tmin, tmax]`` (any-hit traversal, "
                     "stops at the first).")
_OCCLUDED_ARGS = """
        return_hits: return the full :class:`Hits` instead of the answer alone."""
_OCCLUDED_RETURNS = """
    Returns:
        ``bool (N,)`` (a ``bool`` pyopencl array for pyopencl rays; an invalid ray is
        ``False`` with ``invalid_rays="miss"``); with ``return_hits=True`` the
        :class:`Hits` (:class:`DeviceHitArrays`): ``hits.hit`` is the answer,
        ``hits.overflow`` / ``hits.overflow_count`` report stack overflows,
        ``t, prim, u, v`` describe the hit that was found, not necessarily the closest.
"""
_TARGET_DOC = """
        target: an :class:`lbvh.BVH` (any builder; the kernel reads only docs/pages/layout.md)."""


def query_doc(which: str, *, target: bool) -> str:
    """The docstring of the ``which`` query (``"intersect"`` or ``"occluded"``), with the
    ``target`` argument (this module's functions) or without (:class:`lbvh.BVH`'s methods)."""
    summary, extra, returns = {
        "intersect": (_INTERSECT_SUMMARY, _INTERSECT_ARGS, _INTERSECT_RETURNS),
        "occluded": (_OCCLUDED_SUMMARY, _OCCLUDED_ARGS, _OCCLUDED_RETURNS)}[which]
    args = _ARGS_DOC.format(order=_ORDER_DOC if which == "intersect" else "")
    return (f"{summary}\n\n    Args:{_TARGET_DOC if target else ''}{args}{extra}\n"
            f"{returns}{_RAISES_DOC}")


def async_doc(which: str) -> str:
    """The docstring of the non-blocking form of the ``which`` query."""
    return (f":func:`{which}` on a worker thread: returns at once a "
            "``concurrent.futures.Future`` whose ``result()`` is what the call returns (or "
            "raises what it raises). Calls on one device take turns on its queue; the "
            "arrays are read by the worker thread: leave them unchanged until the future "
            "is done. Arguments as the blocking call.")


@dev.serialised
def intersect(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0,
              tmax: Any = np.inf, *, options: QueryOptions | None = None,
              **fields: Any) -> Hits | DeviceHitArrays:
    target = query_target(target)   # a BVH gives its query data
    return _trace(target, origins, directions, tmin, tmax, False,
                  query_options("intersect", options, fields))


@dev.serialised
def occluded(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0,
             tmax: Any = np.inf, *, return_hits: bool = False,
             options: QueryOptions | None = None, **fields: Any
             ) -> np.ndarray | Hits | cl_array.Array | DeviceHitArrays:
    target = query_target(target)   # a BVH gives its query data
    hits = _trace(target, origins, directions, tmin, tmax, True,
                  query_options("occluded", options, fields))
    return hits if return_hits else hits.hit


intersect.__doc__ = query_doc("intersect", target=True)
occluded.__doc__ = query_doc("occluded", target=True)


# -- non-blocking calls -----------------------------------------------------------

_EXECUTOR: ThreadPoolExecutor | None = None
_EXECUTOR_LOCK = threading.Lock()


def _executor() -> ThreadPoolExecutor:
    """The threads that run non-blocking queries (made on first use). Queries on one
    device take turns on its queue; the rays' host checks of several run in parallel."""
    global _EXECUTOR
    with _EXECUTOR_LOCK:
        if _EXECUTOR is None:
            _EXECUTOR = ThreadPoolExecutor(max_workers=4, thread_name_prefix="lbvh-query")
        return _EXECUTOR


def intersect_async(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0,
                    tmax: Any = np.inf, *, options: QueryOptions | None = None,
                    **fields: Any) -> "Future[Hits | DeviceHitArrays]":
    target = query_target(target)   # a BVH gives its query data
    opts = query_options("intersect", options, fields)   # bad options raise here, at once
    return _executor().submit(intersect, target, origins, directions, tmin, tmax, options=opts)


def occluded_async(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0,
                   tmax: Any = np.inf, *, return_hits: bool = False,
                   options: QueryOptions | None = None, **fields: Any) -> "Future[Any]":
    target = query_target(target)   # a BVH gives its query data
    opts = query_options("occluded", options, fields)
    return _executor().submit(occluded, target, origins, directions, tmin, tmax,
                              return_hits=return_hits, options=opts)


intersect_async.__doc__ = async_doc("intersect")
occluded_async.__doc__ = async_doc("occluded")
