"""Ray queries through a two-level scene of instances (kernels/instances.cl).

:class:`lbvh.Scene` holds the meshes' trees and the instances (a mesh and the
3x4 transform that places it); this module keeps what the kernel reads
(:class:`SceneBuffers`) and traces rays through it: the closest hit
(:func:`intersect_scene`) or any hit (``any_hit=True``). Rays are checked as
for :func:`lbvh.queries.traverse.intersect`.

The hit's ``t`` is along the ray as given in world space (the ray moved into
an instance's space keeps its parameter); ``prim`` is the triangle within its
mesh, ``instance`` the instance's index in the scene (``id`` its user id).
The answers are a flattened copy's (every instance's vertices transformed,
one mesh) up to rounding: the kernel moves the ray, a flattened copy moves
the vertices, so a ray within rounding of an edge may hit the neighbour, and
``t`` differs by the float32 rounding of the transform (the tests' bound:
``1e-5`` of the scene's extent over ``|d|``, a few hundred units of float32
rounding of the coordinates).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..tree import Tree
from .options import QueryOptions
from .rays import check_rays, is_device_array
from .traverse import DEFAULT_BATCH, kernel_defines, stack_bucket

KERNEL_FILE = "instances.cl"

__all__ = ["SceneBuffers", "SceneHits", "intersect_scene", "placement_rows"]

_WORK_GROUP = 64


@dataclass
class SceneBuffers:
    """What kernels/instances.cl reads of a scene, on the device.

    ``top``: the top-level tree over the instances' world boxes (its slots name
    instances). ``inverse``: ``float32 (I, 12)`` world-to-mesh transforms (M row by
    row, then c). ``nodes``: :data:`NODE_CHUNKS` node buffers ("chunks", each within
    the device's largest allocation; unused ones repeat the last), every mesh's tree
    in one of them, the meshes of a chunk one after the other, child indices offset
    within it. ``inst_root``: ``int32 (I,)`` each instance's chunk in bits
    :data:`ROOT_BITS` and up, the root node of its mesh within the chunk below.
    ``prim_order``, ``vertices``, ``slot_faces``: every mesh's slots and faces one
    after the other, indices offset. ``num_nodes``: the nodes of all chunks.
    ``depth``: the deepest tree of both levels (the stack's size). ``exact_leaves``:
    no mesh has spatial splits.
    ``placements``: ``float32 (I, 49)`` for the closest points
    (kernels/instance_closest.cl): the 12 entries of the mesh-to-world transform (A
    row by row, then b) rounded to float32, then the float32 roundings of what they
    left (with doubles the kernel adds the two: the float64 transform to about
    2^-48); the same 24 of its inverse; the square of A's least singular value,
    rounded down (:func:`placement_rows`). ``ids``, ``mesh_of``: ``(I,)`` host arrays,
    each instance's id and mesh, which the answers name.
    """
    top: Tree
    inverse: cl.Buffer
    inst_root: cl.Buffer
    nodes: tuple[cl.Buffer, ...]
    num_nodes: int
    prim_order: cl.Buffer
    vertices: cl.Buffer
    slot_faces: cl.Buffer
    depth: int
    exact_leaves: bool = True
    placements: cl.Buffer | None = None
    ids: np.ndarray | None = None
    mesh_of: np.ndarray | None = None


def placement_rows(transforms: np.ndarray) -> np.ndarray:
    """``float32 (I, 49)``: :class:`SceneBuffers`' ``placements`` of ``float64 (I, 3, 4)``
    object-to-world transforms."""
    a, b = transforms[:, :, :3], transforms[:, :, 3]
    inv = np.linalg.inv(a)
    rows = []
    for m in (np.concatenate([a.reshape(-1, 9), b], axis=1),
              np.concatenate([inv.reshape(-1, 9), -np.einsum("ijk,ik->ij", inv, b)], axis=1)):
        hi = m.astype(np.float32)
        rows += [hi, (m - hi).astype(np.float32)]   # what float32 left: hi + lo is float64's
    # sigma_min^2, below float64's own error of it, then rounded down to float32
    s2 = np.linalg.svd(a, compute_uv=False).min(axis=1) ** 2 * (1 - 1e-9)
    s2_32 = s2.astype(np.float32)
    s2_32 = np.where(s2_32 > s2, np.nextafter(s2_32, np.float32(0)), s2_32)
    rows.append(s2_32[:, None])
    return np.ascontiguousarray(np.concatenate(rows, axis=1), dtype=np.float32)


#: Node buffers a scene's kernels take (kernels/instance_ray.h, chunk_nodes): a mesh
#: in parts (lbvh.build_parts) passes the device's largest allocation by this much.
NODE_CHUNKS = 4
#: inst_root's bits below the chunk number: the root node within its chunk.
ROOT_BITS = 28


def node_chunks(node_counts: Sequence[int], per_chunk: int) -> list[int]:
    """The chunk of each mesh's tree: consecutive meshes packed greedily into node
    buffers of at most ``per_chunk`` nodes (the device's largest allocation) and
    ``2^ROOT_BITS``. Raises :class:`lbvh.DeviceError` where :data:`NODE_CHUNKS` do
    not hold them all."""
    per_chunk = min(int(per_chunk), 1 << ROOT_BITS)
    chunks, chunk, used = [], 0, 0
    for n in node_counts:
        if used and used + n > per_chunk:
            chunk, used = chunk + 1, 0
        if n > per_chunk or chunk >= NODE_CHUNKS:
            raise dev.DeviceError(
                f"lbvh: the scene's trees ({sum(node_counts):,} nodes) need more than "
                f"{NODE_CHUNKS} node buffers of the device's largest allocation "
                f"({per_chunk:,} nodes); place fewer or smaller meshes")
        chunks.append(chunk)
        used += n
    return chunks


@dataclass
class SceneHits:
    """Results of a ray query through a scene, one entry per ray (numpy arrays).

    Attributes:
        t: ``float32 (N,)`` distance along the world direction, ``inf`` on a miss.
        prim: ``int32 (N,)`` the triangle within its mesh, ``-1`` on a miss.
        u, v: ``float32 (N,)`` barycentrics on that triangle (in its mesh).
        instance: ``int32 (N,)`` the instance's index in the scene, ``-1`` on a miss.
        id: ``int64 (N,)`` the instance's id, ``-1`` on a miss.
        mesh: ``int32 (N,)`` the index of the instance's mesh, ``-1`` on a miss.
        overflow: ``bool (N,)`` a stack overflowed (flagged, never silent);
            ``overflow_count`` how many.
        nodes_visited, tris_tested: ``int32 (N,)`` with ``counters=True``.
        invalid: ``bool (N,)`` the ray was bad and not traced (``invalid_rays="miss"``).
    """
    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    instance: np.ndarray
    id: np.ndarray
    mesh: np.ndarray
    overflow: np.ndarray
    overflow_count: int
    nodes_visited: np.ndarray | None = None
    tris_tested: np.ndarray | None = None
    invalid: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """``bool (N,)``: whether each ray hit something."""
        return self.prim >= 0

    hit = mask

    def __len__(self) -> int:
        return len(self.t)


def intersect_scene(ctx: dev.Context, buffers: SceneBuffers, origins: Any, directions: Any,
                    tmin: Any = 0.0, tmax: Any = np.inf, *, any_hit: bool = False,
                    options: QueryOptions = QueryOptions()) -> SceneHits:
    """The closest hit (or with ``any_hit`` a hit) of each ray through the scene whose
    device data is ``buffers`` (:class:`lbvh.Scene` calls this with checked ``options``:
    its ``invalid_rays``, ``triangle_test``, ``counters`` and ``batch_size``; arguments
    as :func:`lbvh.queries.traverse.intersect`'s). The caller holds ``ctx.lock``."""
    triangle_test, counters = options.triangle_test, options.counters
    invalid_rays, batch_size = options.invalid_rays, options.batch(DEFAULT_BATCH)
    ids, mesh_of = buffers.ids, buffers.mesh_of
    origins, directions, tmin, tmax = (x.get() if is_device_array(x) else x
                                       for x in (origins, directions, tmin, tmax))
    rays = check_rays(origins, directions, tmin, tmax, invalid_rays=invalid_rays)
    n = len(rays)
    good = np.arange(n) if rays.invalid is None else np.flatnonzero(~rays.invalid)
    part = rays if rays.invalid is None else rays.take(good)
    planes = np.empty((5, len(part)), np.float32)
    flags = np.zeros(len(part), np.int32)
    count = np.zeros((len(part), 2), np.int32)
    defines = kernel_defines(ctx, any_hit, triangle_test, counters,
                             stack_bucket(buffers.depth + 1))
    if not buffers.exact_leaves:
        defines["EXACT_LEAVES"] = 0
    lo, hi, stride = part.kernel_intervals()
    mem, top = ctx.memory, buffers.top
    for start in range(0, len(part), int(batch_size)):
        stop = min(len(part), start + int(batch_size))
        m = stop - start
        bufs = {"o": mem.upload(part.origins[start:stop]),
                "d": mem.upload(part.directions[start:stop]),
                "lo": mem.upload(np.ascontiguousarray(lo[start:stop] if stride else lo)),
                "hi": mem.upload(np.ascontiguousarray(hi[start:stop] if stride else hi)),
                "hits": mem.alloc(20 * m), "flags": mem.alloc(4 * m), "count": mem.alloc(8 * m)}
        try:
            launch = dev.Launch(m, 1, -(-m // _WORK_GROUP) * _WORK_GROUP, _WORK_GROUP)
            ev = dev.run(ctx, KERNEL_FILE, "trace_instances", launch, top.nodes, top.prim_order,
                         top.root, top.num_nodes, buffers.inverse, buffers.inst_root,
                         *buffers.nodes, buffers.num_nodes, buffers.prim_order, buffers.vertices,
                         buffers.slot_faces, bufs["o"], bufs["d"], bufs["lo"], bufs["hi"], stride,
                         bufs["hits"], bufs["flags"], bufs["count"], m, defines=defines)
            for k in range(5):
                cl.enqueue_copy(ctx.queue, planes[k, start:stop], bufs["hits"],
                                src_offset=4 * k * m, wait_for=[ev], is_blocking=False)
            cl.enqueue_copy(ctx.queue, flags[start:stop], bufs["flags"], wait_for=[ev],
                            is_blocking=False)
            if counters:
                cl.enqueue_copy(ctx.queue, count[start:stop], bufs["count"], wait_for=[ev],
                                is_blocking=False)
            ctx.queue.finish()
        finally:
            mem.free(*bufs.values())
    out = SceneHits(t=np.full(n, np.inf, np.float32), prim=np.full(n, -1, np.int32),
                    u=np.zeros(n, np.float32), v=np.zeros(n, np.float32),
                    instance=np.full(n, -1, np.int32), id=np.full(n, -1, np.int64),
                    mesh=np.full(n, -1, np.int32), overflow=np.zeros(n, bool), overflow_count=0,
                    nodes_visited=np.zeros(n, np.int32) if counters else None,
                    tris_tested=np.zeros(n, np.int32) if counters else None,
                    invalid=np.zeros(n, bool) if rays.invalid is None else rays.invalid)
    out.t[good], out.u[good], out.v[good] = planes[0], planes[1], planes[2]
    out.prim[good] = planes[3].view(np.int32)
    inst = planes[4].view(np.int32)
    out.instance[good] = inst
    hit = inst >= 0
    out.id[good[hit]] = ids[inst[hit]]
    out.mesh[good[hit]] = mesh_of[inst[hit]]
    out.overflow[good] = flags != 0
    out.overflow_count = int(out.overflow.sum())
    if counters:
        out.nodes_visited[good], out.tris_tested[good] = count[:, 0], count[:, 1]
    return out
