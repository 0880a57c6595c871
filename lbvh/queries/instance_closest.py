"""Closest points through a scene of placed meshes, in world space
(kernels/instance_closest.cl).

:meth:`lbvh.Scene.closest_points` calls :func:`closest_scene_points` with the
scene's device data (:class:`lbvh.queries.instances.SceneBuffers`, whose
``placements`` holds the transforms both ways). The kernel answers each
point in world space for any invertible affine placement (rotations,
reflections, shears, non-uniform scales): a best-first walk of the top level
by the distance to the instances' world boxes and, at an instance, of its
mesh's tree with each node box bounded in world space and each triangle's
vertices moved to world space before the exact point-triangle distance of
:mod:`lbvh.queries.closest` (in double where the device has it).

Accuracy: against the float64 brute force over the flattened scene's
triangles (:meth:`lbvh.Scene.flattened` and
:func:`lbvh.queries.closest.closest_points_numpy`), the distance is within
:func:`lbvh.metrics.error_bound.scene_closest_distance_bound` (the mesh's
bound plus the flattened copy's float32 rounding of its world vertices, which
the kernel does not make: it transforms in double). Where two triangles (of
one instance or of overlapping instances) are equally near within that
bound, either may be named.

Points and ``max_distance`` are checked as for :func:`lbvh.queries.closest.closest_points`
(a ``ValueError`` naming the first bad point); a stack overflow, which needs a
tree deeper than its reported depth, raises ``RuntimeError`` naming how many
points it cost: an answer is never silently short.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from .closest import _max_distance, check_points
from .instances import SceneBuffers
from .ray_order import MIN_POINTS, ordered_points
from .traverse import stack_bucket

KERNEL_FILE = "instance_closest.cl"

__all__ = ["SceneClosest", "closest_scene_points"]

#: Bits of the per-point flag word (kernels/instance_closest.cl).
FLAG_OVERFLOW = 1
FLAG_VISIT_LIMIT = 2

_WORK_GROUP = 64


class SceneClosest(tuple):
    """The closest points through a scene, one entry per query point; unpacks as
    ``(distance, points, instance, prim)``.

    Attributes:
        distance: ``float32 (N,)`` world distance, ``inf`` where nothing is within
            ``max_distance``.
        points: ``float32 (N, 3)`` the closest point in world space (NaN where none).
        instance: ``int32 (N,)`` the instance's index in the scene, ``-1`` where none.
        prim: ``int32 (N,)`` the triangle within the instance's mesh (or its
            ``face_ids`` number), ``-1`` where none.
        u, v: ``float32 (N,)`` barycentrics of the point on that triangle,
            ``(1-u-v)*p0 + u*p1 + v*p2`` with ``p0, p1, p2`` its vertices (in its mesh's
            space or in world space alike: an affine map keeps barycentrics); 0 where none.
        id: ``int64 (N,)`` the instance's id, ``-1`` where none.
        mesh: ``int32 (N,)`` the index of its mesh, ``-1`` where none.
    """

    def __new__(cls, distance: np.ndarray, points: np.ndarray, instance: np.ndarray,
                prim: np.ndarray, u: np.ndarray, v: np.ndarray, id: np.ndarray,
                mesh: np.ndarray) -> "SceneClosest":
        self = super().__new__(cls, (distance, points, instance, prim))
        self.u, self.v, self.id, self.mesh = u, v, id, mesh
        return self

    def __reduce__(self) -> tuple:
        return (SceneClosest, (*self, self.u, self.v, self.id, self.mesh))

    distance = property(lambda self: self[0])
    points = property(lambda self: self[1])
    instance = property(lambda self: self[2])
    prim = property(lambda self: self[3])

    @property
    def found(self) -> np.ndarray:
        """``bool (N,)``: a triangle was within ``max_distance``."""
        return self.instance >= 0


def _raise_on_overflow(flags: np.ndarray) -> None:
    bad = (flags & (FLAG_OVERFLOW | FLAG_VISIT_LIMIT)) != 0
    if bad.any():
        raise RuntimeError(f"closest_points: the traversal stack overflowed for "
                           f"{int(bad.sum())} points (first: point {int(np.flatnonzero(bad)[0])}); "
                           "a tree is deeper than the kernel's stack")


def closest_scene_points(ctx: dev.Context, buffers: SceneBuffers, ids: np.ndarray,
                         mesh_of: np.ndarray, points: Any, max_distance: float = np.inf, *,
                         batch_size: int = 1 << 20,
                         extra_defines: dict[str, int] | None = None) -> SceneClosest:
    """The closest point of the scene to each point within ``max_distance``, in world
    space (arguments as :func:`lbvh.queries.closest.closest_points`'s;
    ``extra_defines``: tests' -D defines, e.g. ``NO_FP64``). The caller holds
    ``ctx.lock``.

    Raises:
        ValueError: a bad point (named), a bad ``max_distance`` or ``batch_size``.
        RuntimeError: a traversal stack overflowed (a tree deeper than reported).
    """
    p = check_points(points)
    limit = _max_distance(max_distance)
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
            or batch_size < 1:
        raise ValueError(f"batch_size: {batch_size!r}; expected a positive integer")
    if buffers.placements is None:
        raise ValueError("buffers: no placements (SceneBuffers.placements)")
    n = len(p)
    out = {"distance": np.empty(n, np.float32), "points": np.empty((n, 3), np.float32),
           "prim": np.empty(n, np.int32), "instance": np.empty(n, np.int32),
           "bary": np.empty((n, 2), np.float32), "flags": np.empty(n, np.int32)}
    top = buffers.top
    batch = int(min(batch_size, max(n, 1)))
    mem = ctx.memory
    bufs = {"points": mem.alloc(12 * batch, flags=cl.mem_flags.READ_ONLY),
            "distance": mem.alloc(4 * batch), "points_out": mem.alloc(12 * batch),
            "prim": mem.alloc(4 * batch), "instance": mem.alloc(4 * batch),
            "bary": mem.alloc(8 * batch), "flags": mem.alloc(4 * batch)}
    base = {"STACK_SIZE": stack_bucket(buffers.depth + 1), **(extra_defines or {})}
    order = sorted_points = None
    try:
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            m = stop - start
            ups = [cl.enqueue_copy(ctx.queue, bufs["points"], p[start:stop], is_blocking=False)]
            order = sorted_points = None
            if m >= MIN_POINTS:   # nearby points one after another, read as one run, as closest.py
                order, sorted_points, ups = ordered_points(ctx, bufs["points"], m,
                                                           *top.root_box())
            launch = dev.Launch(m, 1, -(-m // _WORK_GROUP) * _WORK_GROUP, _WORK_GROUP)
            ev = dev.run(ctx, KERNEL_FILE, "instance_closest", launch, top.nodes, top.prim_order,
                         top.root, top.num_nodes, buffers.placements, buffers.inst_root,
                         *buffers.nodes, buffers.num_nodes, buffers.prim_order, buffers.vertices,
                         buffers.slot_faces,
                         bufs["points"] if order is None else sorted_points,
                         order if order is not None else bufs["flags"], limit, m,
                         bufs["distance"], bufs["points_out"], bufs["prim"], bufs["instance"],
                         bufs["bary"], bufs["flags"],
                         defines={**base, "POINT_ORDER": int(order is not None)}, wait_for=ups)
            for name, buf in (("distance", "distance"), ("points", "points_out"),
                              ("prim", "prim"), ("instance", "instance"), ("bary", "bary"),
                              ("flags", "flags")):
                cl.enqueue_copy(ctx.queue, out[name][start:stop], bufs[buf], wait_for=[ev],
                                is_blocking=False)
            ctx.queue.finish()
            mem.free(order, sorted_points)
            order = sorted_points = None
    finally:
        mem.free(*bufs.values(), order, sorted_points)
    _raise_on_overflow(out["flags"])
    inst = out["instance"]
    found = inst >= 0
    return SceneClosest(out["distance"], out["points"], inst, out["prim"],
                        out["bary"][:, 0].copy(), out["bary"][:, 1].copy(),
                        np.where(found, ids[np.maximum(inst, 0)], -1).astype(np.int64),
                        np.where(found, mesh_of[np.maximum(inst, 0)], -1).astype(np.int32))
