"""Every hit along each ray through a scene of instances, and the hit counts
(kernels/instance_hits.cl).

:meth:`lbvh.Scene.count_hits` and :meth:`lbvh.Scene.all_hits` call these with
the scene's device data (:class:`lbvh.queries.instances.SceneBuffers`): the
arguments, checks and results of :func:`lbvh.queries.all_hits.count_hits` and
:func:`lbvh.queries.all_hits.all_hits`, and each hit also names its instance
(:class:`SceneAllHits`). The kernel walks the top level with the world ray,
moves the ray into each instance's space it reaches (``t`` kept) and counts or
keeps every hit of that mesh's tree in ``[tmin, tmax]``, with the watertight
test and its edge rule: a ray through an edge or a vertex shared by triangles
of one mesh crosses it once. The hits are a flattened copy's (every
instance's vertices transformed) up to rounding, as for
:func:`lbvh.queries.instances.intersect_scene`: a ray within rounding of an
edge may hit the neighbour, and ``t`` differs by the rounding of the
transform.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import device as dev
from .all_hits import (DEFAULT_BATCH, AllHits, HitWalk, _check_max_hits, _rays, assemble,
                       raise_on_overflow, run_passes)
from .instances import SceneBuffers
from .options import QueryOptions
from .rays import Rays

KERNEL_FILE = "instance_hits.cl"

__all__ = ["SceneAllHits", "count_scene_hits", "all_scene_hits", "DEFAULT_BATCH"]


@dataclass
class SceneAllHits(AllHits):
    """:class:`lbvh.AllHits` through a scene: ``prim`` is the triangle within its
    instance's mesh (or its ``face_ids`` number), ``u, v`` barycentrics on it; equal
    ``t``: the lower instance first.

    Attributes (besides :class:`lbvh.AllHits`'):
        instance: ``int32 (M,)`` the instance of each hit, its index in the scene.
        id: ``int64 (M,)`` that instance's id.
        mesh: ``int32 (M,)`` the index of its mesh.
    """
    instance: np.ndarray
    id: np.ndarray
    mesh: np.ndarray


def _run(ctx: dev.Context, buffers: SceneBuffers, rays: Rays, batch: int, cap: int | None):
    top = buffers.top
    head = (top.nodes, top.prim_order, top.root, top.num_nodes, buffers.inverse,
            buffers.inst_root, *buffers.nodes, buffers.num_nodes, buffers.prim_order,
            buffers.vertices, buffers.slot_faces)
    walk = HitWalk(KERNEL_FILE, "instance_hits", head, buffers.depth, instances=True)
    return run_passes(ctx, walk, rays, batch, cap)


def _collect(ctx: dev.Context, buffers: SceneBuffers, rays: Rays, batch: int,
             cap: int | None) -> tuple:
    """:func:`lbvh.queries.all_hits.assemble` of the scene's hits (a mesh with spatial
    splits: each (ray, instance, triangle) once, ``max_hits`` after)."""
    dedupe = not buffers.exact_leaves
    total, flags, kept = _run(ctx, buffers, rays, batch, -1 if dedupe or cap is None else cap)
    return assemble(rays, total, flags, kept, cap, dedupe)


def count_scene_hits(ctx: dev.Context, buffers: SceneBuffers, origins: Any, directions: Any,
                     tmin: Any = 0.0, tmax: Any = np.inf, *,
                     options: QueryOptions = QueryOptions()) -> np.ndarray:
    """``int32 (N,)``: how many times each ray crosses the scene in ``[tmin, tmax]``
    (arguments and errors as :func:`lbvh.queries.all_hits.count_hits`'s: a stack
    overflow raises ``RuntimeError``). The caller holds ``ctx.lock``."""
    batch = options.batch(DEFAULT_BATCH)
    rays = _rays(origins, directions, tmin, tmax, options.invalid_rays)
    if not buffers.exact_leaves:   # a triangle in several leaves: count it once
        fields = _collect(ctx, buffers, rays, batch, None)
        raise_on_overflow(fields[6].astype(np.int32), "count_hits")
        return fields[5].astype(np.int32)
    counts, flags = _run(ctx, buffers, rays, batch, None)[:2]
    raise_on_overflow(flags, "count_hits")
    return counts.astype(np.int32)


def all_scene_hits(ctx: dev.Context, buffers: SceneBuffers, origins: Any, directions: Any,
                   tmin: Any = 0.0, tmax: Any = np.inf, *, max_hits: int | None = None,
                   options: QueryOptions = QueryOptions()) -> SceneAllHits:
    """Every hit of each ray through the scene in ``[tmin, tmax]``, nearest first
    (arguments as :func:`lbvh.queries.all_hits.all_hits`'s; a ray whose stack overflowed
    is flagged in ``overflow``). The caller holds ``ctx.lock``."""
    cap = _check_max_hits(max_hits)
    batch = options.batch(DEFAULT_BATCH)
    rays = _rays(origins, directions, tmin, tmax, options.invalid_rays)
    ids, mesh_of = buffers.ids, buffers.mesh_of
    *fields, inst = _collect(ctx, buffers, rays, batch, cap)
    return SceneAllHits(*fields, instance=inst, id=ids[inst].astype(np.int64),
                        mesh=mesh_of[inst].astype(np.int32))
