"""A two-level scene: meshes, each with its own BVH, placed as instances by transforms.

``lbvh.Scene(meshes, mesh_of, transforms, ids=None)`` takes the meshes' trees
(:class:`lbvh.BVH` objects, built as ever, on one device) and the instances:
for instance ``i`` the index ``mesh_of[i]`` of its mesh and the affine
transform ``transforms[i]`` (``(3, 4)`` or ``(4, 4)``, object to world:
``p_world = A p + b``) and an id (default ``i``). A mesh placed many times is
stored and built once. The top level is an LBVH over the instances' world
boxes (the eight corners of the mesh's root box transformed in float64,
rounded outwards to float32), built by the same device pipeline
(:func:`lbvh.builders.pipeline.build_tree`).

Queries: :meth:`Scene.intersect` (closest hit) and :meth:`Scene.occluded`
(any hit), with the rays of :func:`lbvh.queries.traverse.intersect`; hits
report the instance (index and id), the mesh, the triangle within it and
``t`` in world space (:class:`lbvh.queries.instances.SceneHits`).
:meth:`Scene.count_hits` and :meth:`Scene.all_hits` count or list every hit
of each ray as :meth:`lbvh.BVH.count_hits` and :meth:`lbvh.BVH.all_hits` do,
each hit with its instance (:class:`lbvh.queries.instance_hits.SceneAllHits`).
:meth:`Scene.closest_points` answers point queries in world space for any
invertible affine placement (:mod:`lbvh.queries.instance_closest`), and
:meth:`Scene.signed_distance` with it; :meth:`Scene.winding_numbers` sums each
instance's mesh's.
:meth:`Scene.set_transforms` moves instances: only the top level is built
again (milliseconds), never a mesh. :meth:`Scene.flattened` gives the one
mesh the scene stands for (every instance's vertices transformed), what the
tests compare the scene's answers with. ``lbvh.build`` makes a scene from a
``trimesh.Scene`` or a list of meshes.
"""
from __future__ import annotations

import weakref
from typing import Any, Sequence

import numpy as np
import pyopencl as cl

from . import device as dev
from .builders.bounds import round_outward
from .builders.options import LBVHOptions
from .builders.pipeline import build_tree
from .bvh import BVH
from .layout import NODE_DTYPE, is_leaf
from .mesh import real_array
from .queries.closest import check_points
from .queries.instance_closest import SceneClosest, closest_scene_points
from .queries.instance_hits import SceneAllHits, all_scene_hits, count_scene_hits
from .queries.instances import (NODE_CHUNKS, ROOT_BITS, SceneBuffers, SceneHits, intersect_scene,
                                node_chunks, placement_rows)
from .queries.options import QueryOptions, query_options
from .tree import Mesh

__all__ = ["Scene", "check_transforms"]


def chunk_nodes(ctx: dev.Context) -> int:
    """The most nodes one of a scene's node buffers holds: the device's largest
    allocation (read from the device) over the node's 32 bytes."""
    return int(ctx.memory.max_alloc) // NODE_DTYPE.itemsize


def is_similarity(a: np.ndarray) -> np.ndarray:
    """``bool (I,)``: which of the linear parts ``a`` (``(I, 3, 3)``) are a rotation or
    reflection times one scale (``A^T A = s^2 I``, to 1e-6 of ``s^2``)."""
    gram = np.einsum("ikj,ikl->ijl", a, a)
    s2 = np.trace(gram, axis1=1, axis2=2) / 3
    return np.abs(gram - s2[:, None, None] * np.eye(3)).max(axis=(1, 2)) <= 1e-6 * s2


def _upload_world_copy(ctx: dev.Context, vertices: np.ndarray, faces: np.ndarray):
    """(mesh, tree) of a world-space copy of an instance: the device LBVH."""
    mesh = Mesh.upload(ctx, vertices, faces)
    return mesh, build_tree(ctx, mesh, LBVHOptions())


def check_transforms(transforms: Any, count: int | None = None) -> np.ndarray:
    """``float64 (I, 3, 4)`` affine transforms from ``(I, 3, 4)`` or ``(I, 4, 4)`` (whose
    last rows must be ``0 0 0 1``), finite and invertible, or a ``ValueError`` naming the
    first bad one."""
    t = real_array("transforms", transforms).astype(np.float64)
    if t.ndim != 3 or t.shape[1:] not in ((3, 4), (4, 4)):
        raise ValueError(f"transforms: shape {t.shape}, expected (I, 3, 4) or (I, 4, 4)")
    if count is not None and len(t) != count:
        raise ValueError(f"transforms: {len(t)} of them for {count} instances")
    if t.shape[1] == 4:
        bottom = np.abs(t[:, 3] - [0, 0, 0, 1]).max(axis=1) != 0
        if bottom.any():
            i = int(np.flatnonzero(bottom)[0])
            raise ValueError(f"transforms: instance {i} is not affine (last row "
                             f"{t[i, 3].tolist()}, expected [0, 0, 0, 1])")
        t = t[:, :3]
    bad = ~np.isfinite(t).all(axis=(1, 2))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"transforms: instance {i} has a NaN or infinite entry")
    det = np.linalg.det(t[:, :, :3])
    scale = np.abs(t[:, :, :3]).max(axis=(1, 2)) ** 3
    singular = ~(np.abs(det) > 1e-12 * scale)
    if singular.any():
        i = int(np.flatnonzero(singular)[0])
        raise ValueError(f"transforms: instance {i} is singular (determinant {det[i]:.3g}): "
                         "it would flatten its mesh")
    return np.ascontiguousarray(t)


class Scene:
    """Instances of meshes placed by transforms, with a top-level BVH over them.

    Attributes:
        meshes: the meshes' :class:`lbvh.BVH` objects (each built once).
        mesh_of: ``int32 (I,)`` the mesh of each instance.
        transforms: ``float64 (I, 3, 4)`` object-to-world transforms (read-only view).
        ids: ``int64 (I,)`` the instances' ids; ``names`` their names (a trimesh
            scene's node names; default the ids as text).
        face_ids: ``None``, or per mesh ``int32 (F_k,)``: the number hits give each of its
            triangles instead of its index in the mesh (:func:`lbvh.api.build_parts`: the
            parts of one mesh report the mesh's own triangle numbers).
        top: the top-level :class:`lbvh.BVH` over the instances' world boxes.
    """

    def __init__(self, meshes: Sequence[BVH], mesh_of: Any, transforms: Any,
                 ids: Any = None, names: Sequence[str] | None = None,
                 face_ids: Sequence[np.ndarray] | None = None) -> None:
        meshes = list(meshes)
        if not meshes:
            raise ValueError("meshes: none given")
        for k, m in enumerate(meshes):
            if not isinstance(m, BVH):
                raise ValueError(f"meshes: item {k} is a {type(m).__name__}, expected an "
                                 "lbvh.BVH (lbvh.build makes them)")
        ctx = meshes[0].ctx
        if any(m.ctx is not ctx for m in meshes):
            raise ValueError("meshes: built on different devices; build them on one")
        which = real_array("mesh_of", mesh_of)
        if which.ndim != 1 or not np.issubdtype(which.dtype, np.integer):
            raise ValueError(f"mesh_of: shape {which.shape} dtype {which.dtype}, expected "
                             "(I,) integers")
        if len(which) == 0:
            raise ValueError("mesh_of: no instances")
        outside = (which < 0) | (which >= len(meshes))
        if outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise ValueError(f"mesh_of: instance {i} names mesh {int(which[i])}, outside "
                             f"[0, {len(meshes)})")
        t = check_transforms(transforms, len(which))
        if ids is None:
            ids = np.arange(len(which))
        ids = real_array("ids", ids)
        if ids.shape != which.shape or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"ids: shape {ids.shape} dtype {ids.dtype}, expected ({len(which)},) "
                             "integers")
        if len(np.unique(ids)) != len(ids):
            raise ValueError("ids: not unique")
        if names is not None and len(names) != len(which):
            raise ValueError(f"names: {len(names)} of them for {len(which)} instances")
        self.names = list(names) if names is not None else [str(x) for x in ids.tolist()]
        if face_ids is not None:
            if len(face_ids) != len(meshes):
                raise ValueError(f"face_ids: {len(face_ids)} arrays for {len(meshes)} meshes")
            face_ids = [np.asarray(x, np.int32) for x in face_ids]
            for k, (m, x) in enumerate(zip(meshes, face_ids)):
                if x.shape != (m.mesh.num_prims,):
                    raise ValueError(f"face_ids: mesh {k} has {m.mesh.num_prims} triangles, "
                                     f"its face_ids shape {x.shape}")
        self.face_ids = face_ids
        self.meshes = meshes
        self.mesh_of = which.astype(np.int32)
        self.ids = ids.astype(np.int64)
        self.mesh_of.setflags(write=False)
        self.ids.setflags(write=False)
        self.ctx = ctx
        self._index = {int(x): i for i, x in enumerate(self.ids)}
        with ctx.lock:
            self._upload_meshes()
            self._place(t)

    # -- device data -------------------------------------------------------------
    def _upload_meshes(self) -> None:
        """Every mesh's tree and faces, one after the other, indices offset."""
        nodes, orders, verts, slot_faces, roots = [], [], [], [], []
        node_base = slot_base = vertex_base = 0
        depth = 0
        chunks = node_chunks([bvh.tree.num_nodes for bvh in self.meshes], chunk_nodes(self.ctx))
        previous = 0
        for bvh, chunk in zip(self.meshes, chunks):
            if chunk != previous:   # a new chunk: its nodes numbered from 0
                node_base, previous = 0, chunk
            n = bvh.nodes.copy()
            leaf = is_leaf(n)
            n["a"] += np.where(leaf, slot_base, node_base).astype(np.int32)
            n["b"] += np.where(leaf, 0, node_base).astype(np.int32)
            nodes.append(n)
            order = np.asarray(bvh.prim_order)
            # hits name the triangle within its mesh, or its face_ids entry (parts of one mesh)
            orders.append(order if self.face_ids is None else self.face_ids[len(orders)][order])
            slot_faces.append((bvh.faces[order].astype(np.int64) + vertex_base).astype(np.uint32))
            verts.append(bvh.vertices)
            roots.append((chunk << ROOT_BITS) | (node_base + bvh.root))
            depth = max(depth, bvh.query_data.traversal_depth())
            node_base += bvh.tree.num_nodes
            slot_base += bvh.mesh.num_prims
            vertex_base += len(bvh.vertices)
        up = self.ctx.memory.upload
        self._chunks = [up(np.concatenate([n for n, c in zip(nodes, chunks) if c == k]))
                        for k in range(chunks[-1] + 1)]
        self._num_nodes = int(sum(bvh.tree.num_nodes for bvh in self.meshes))
        self._prim_order = up(np.concatenate(orders).astype(np.int32))
        self._vertices = up(np.concatenate(verts))
        self._slot_faces = up(np.concatenate(slot_faces))
        self._mesh_roots = np.array(roots, np.int32)
        self._mesh_depth = depth
        self._inst_root = up(self._mesh_roots[self.mesh_of])
        self._owned: list[cl.Buffer] = [*self._chunks, self._prim_order, self._vertices,
                                        self._slot_faces, self._inst_root]
        weakref.finalize(self, self.ctx.memory.dropped, self._owned)

    def _place(self, transforms: np.ndarray) -> None:
        """Set the transforms: the inverses, the world boxes and the top level."""
        old_transforms = getattr(self, "_transforms", None)
        copies = getattr(self, "_world_copies", {})
        if old_transforms is not None:   # world copies of instances that moved are stale
            moved = (old_transforms != transforms).any(axis=(1, 2))
            copies = {i: c for i, c in copies.items() if not moved[i]}
        self._world_copies: dict[int, BVH] = copies
        self._open: dict[int, bool] = getattr(self, "_open", {})
        self._transforms = transforms
        self._transforms.setflags(write=False)
        a, b = transforms[:, :, :3], transforms[:, :, 3]
        inv = np.linalg.inv(a)
        inverse = np.concatenate([inv.reshape(-1, 9), -np.einsum("ijk,ik->ij", inv, b)], axis=1)
        roots = [m.root for m in self.meshes]
        lo = np.stack([m.nodes["lower"][r] for m, r in zip(self.meshes, roots)]).astype(np.float64)
        hi = np.stack([m.nodes["upper"][r] for m, r in zip(self.meshes, roots)]).astype(np.float64)
        corners = np.stack([np.where(np.array([(c >> k) & 1 for k in range(3)], bool), hi, lo)
                            for c in range(8)], axis=1)          # (meshes, 8, 3)
        world = np.einsum("ijk,imk->imj", a, corners[self.mesh_of]) + b[:, None, :]
        wlo, whi = round_outward(world.min(axis=1), world.max(axis=1))
        # The top level: the pipeline over one "triangle" per instance, (lo, hi, hi),
        # whose box is the instance's world box and whose centre is the box's.
        v = np.stack([wlo, whi, whi], axis=1).reshape(-1, 3)
        f = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
        mesh = Mesh.upload(self.ctx, v, f)
        self.top = BVH(mesh, build_tree(self.ctx, mesh, LBVHOptions()))
        olds = [getattr(self, "_inverse", None), getattr(self, "_placements", None)]
        self._inverse = self.ctx.memory.upload(inverse.astype(np.float32))
        self._placements = self.ctx.memory.upload(placement_rows(transforms))
        for old in olds:
            if old is not None:
                self._owned.remove(old)
                self.ctx.memory.free(old)
        self._owned += [self._inverse, self._placements]

    def _buffers(self) -> SceneBuffers:
        nodes = tuple(self._chunks[min(k, len(self._chunks) - 1)] for k in range(NODE_CHUNKS))
        return SceneBuffers(self.top.tree, self._inverse, self._inst_root, nodes,
                            self._num_nodes, self._prim_order, self._vertices, self._slot_faces,
                            max(self._mesh_depth, self.top.query_data.traversal_depth()),
                            not any(m.tree.clipped_leaves for m in self.meshes), self._placements,
                            self.ids, self.mesh_of)

    # -- what it holds -------------------------------------------------------------
    @property
    def transforms(self) -> np.ndarray:
        return self._transforms

    @property
    def num_instances(self) -> int:
        return len(self.mesh_of)

    @property
    def num_triangles(self) -> int:
        """Triangles in world space: every instance's, counted once per instance."""
        return int(sum(self.meshes[m].mesh.num_prims for m in self.mesh_of))

    @dev.serialised
    def set_transforms(self, ids: Any, transforms: Any) -> "Scene":
        """Move the instances ``ids`` (their ids) to ``transforms`` (``(K, 3, 4)`` or
        ``(K, 4, 4)``); only the top level is built again. On a bad input nothing
        changes. Returns ``self``."""
        ids = np.atleast_1d(real_array("ids", ids))
        t = check_transforms(transforms, len(ids))
        rows = []
        for x in ids.tolist():
            if x not in self._index:
                raise ValueError(f"ids: no instance has id {x}")
            rows.append(self._index[x])
        new = self._transforms.copy()
        new[rows] = t
        self._place(new)
        return self

    @dev.serialised
    def flattened(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The one mesh the scene stands for: ``float32 (V, 3)`` vertices (every
        instance's, transformed in float64), ``uint32 (F, 3)`` faces and ``int32 (F,)``
        the instance of each face; instance by instance, each one's faces in its mesh's
        order (with ``face_ids``, the parts of one mesh: that mesh's order).
        :meth:`flat_prim` maps hits to these faces."""
        verts, faces, owner = [], [], []
        base = 0
        for i, m in enumerate(self.mesh_of):
            mesh = self.meshes[m]
            t = self._transforms[i]
            verts.append(mesh.vertices.astype(np.float64) @ t[:, :3].T + t[:, 3])
            faces.append(mesh.faces.astype(np.int64) + base)
            owner.append(np.full(len(mesh.faces), i, np.int32))
            base += len(mesh.vertices)
        v = np.concatenate(verts).astype(np.float32)
        f, who = np.concatenate(faces).astype(np.uint32), np.concatenate(owner)
        if self.face_ids is not None:   # the mesh's own order
            where = np.concatenate([self.face_ids[m] for m in self.mesh_of])
            back = np.empty_like(where)
            back[where] = np.arange(len(where))
            f, who = f[back], who[back]
        return v, f, who

    def flat_prim(self, hits: SceneHits) -> np.ndarray:
        """``int64 (N,)``: each hit's face in :meth:`flattened`'s faces, ``-1`` on a miss."""
        return self.flat_faces(np.where(hits.mask, hits.instance, -1), hits.prim)

    # -- ray queries ---------------------------------------------------------------
    def intersect(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                  options: QueryOptions | None = None, **fields: Any) -> SceneHits:
        """Closest hit of each ray in ``[tmin, tmax]``: :class:`SceneHits` (arguments as
        :meth:`lbvh.BVH.intersect`'s; ``options``: the fields of :class:`lbvh.QueryOptions`
        but for ``stack_size``, ``order`` ``"ordered"`` only: the scene kernel has no
        global order)."""
        opts = query_options("scene_intersect", options, fields)
        if opts.order != "ordered":
            raise ValueError(f"order: {opts.order!r}; a scene's traversal is 'ordered' only")
        with self.ctx.lock:
            return intersect_scene(self.ctx, self._buffers(), origins, directions, tmin, tmax,
                                   options=opts)

    def occluded(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                 return_hits: bool = False, options: QueryOptions | None = None,
                 **fields: Any) -> np.ndarray | SceneHits:
        """Whether each ray hits anything in ``[tmin, tmax]`` (``bool (N,)``), or with
        ``return_hits`` the :class:`SceneHits` of the hit found (not the closest);
        ``options``: ``invalid_rays``, ``triangle_test`` and ``batch_size`` of
        :class:`lbvh.QueryOptions`."""
        opts = query_options("scene_occluded", options, fields)
        with self.ctx.lock:
            hits = intersect_scene(self.ctx, self._buffers(), origins, directions, tmin, tmax,
                                   any_hit=True, options=opts)
        return hits if return_hits else hits.mask

    def count_hits(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                   options: QueryOptions | None = None, **fields: Any) -> np.ndarray:
        """``int32 (N,)``: how many times each ray crosses the scene in ``[tmin, tmax]``,
        a crossing through an edge or a vertex shared by triangles of a mesh once
        (arguments as :meth:`lbvh.BVH.count_hits`'s, ``options`` its ``invalid_rays`` and
        ``batch_size``; a stack overflow raises ``RuntimeError``); see
        :mod:`lbvh.queries.instance_hits`."""
        opts = query_options("hits", options, fields)
        with self.ctx.lock:
            return count_scene_hits(self.ctx, self._buffers(), origins, directions, tmin, tmax,
                                    options=opts)

    def all_hits(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                 max_hits: int | None = None, options: QueryOptions | None = None,
                 **fields: Any) -> SceneAllHits:
        """Every hit of each ray in ``[tmin, tmax]``, nearest first, as flat arrays with
        per-ray offsets (at most ``max_hits`` per ray, the nearest), each with its
        instance (:class:`lbvh.queries.instance_hits.SceneAllHits`: ``instance``, ``id``,
        ``mesh`` beside ``t``, ``prim``, ``u``, ``v``; arguments as
        :meth:`lbvh.BVH.all_hits`'s, ``options`` its ``invalid_rays`` and ``batch_size``)."""
        opts = query_options("hits", options, fields)
        with self.ctx.lock:
            return all_scene_hits(self.ctx, self._buffers(), origins, directions, tmin, tmax,
                                  max_hits=max_hits, options=opts)

    def flat_faces(self, instance: Any, prim: Any) -> np.ndarray:
        """``int64``: the faces of :meth:`flattened` that hits ``(instance, prim)`` name
        (``-1`` where ``instance`` is ``-1``); :meth:`flat_prim` for :class:`SceneHits`."""
        instance, prim = np.asarray(instance), np.asarray(prim)
        if self.face_ids is not None:
            return np.where(instance >= 0, prim, -1).astype(np.int64)
        counts = np.array([self.meshes[m].mesh.num_prims for m in self.mesh_of], np.int64)
        base = np.concatenate([[0], np.cumsum(counts)[:-1]])
        return np.where(instance >= 0, base[np.maximum(instance, 0)] + prim, -1)

    # -- point queries -------------------------------------------------------------
    def closest_points(self, points: Any, max_distance: float = np.inf, *,
                       batch_size: int = 1 << 20) -> SceneClosest:
        """The closest point of the scene to each point within ``max_distance``, in world
        space, for any invertible affine placements (shears, non-uniform scales and
        reflections too): one device kernel walks the top level and each instance's
        mesh tree with the node boxes and triangles moved to world space
        (:mod:`lbvh.queries.instance_closest`).

        Error bound: against the float64 brute force over :meth:`flattened`'s triangles
        (:func:`lbvh.queries.closest.closest_points_numpy`), ``|distance - d_ref|`` is
        within :func:`lbvh.metrics.error_bound.scene_closest_distance_bound` of the
        flattened vertices and the points: the mesh's bound (4 units of float32
        rounding of ``|p| + max |vertex|``) plus one unit of ``max |vertex|`` for the
        flattened copy's own rounding of its world vertices to float32 (the kernel
        transforms the float32 mesh vertices in double). Where two triangles are equally
        near within it (overlapping instances), either may be named.

        Returns:
            :class:`lbvh.queries.instance_closest.SceneClosest`, which unpacks as
            ``(distance float32 (N,), points float32 (N, 3), instance int32 (N,),
            prim int32 (N,))``: ``inf``, NaN, ``-1`` and ``-1`` where nothing is within
            ``max_distance``; ``prim`` is the triangle within the instance's mesh (or its
            ``face_ids`` number). Its attributes add ``u``, ``v`` (barycentrics on that
            triangle, in mesh or world space alike), ``id`` and ``mesh``.

        Raises:
            ValueError: a bad point (named) or ``max_distance``.
            RuntimeError: a traversal stack overflowed (never silently short).
        """
        with self.ctx.lock:
            return closest_scene_points(self.ctx, self._buffers(), self.ids, self.mesh_of,
                                        points, max_distance, batch_size=batch_size)

    @dev.serialised
    def winding_numbers(self, points: Any) -> np.ndarray:
        """``float32 (N,)``: the generalised winding number of the scene, the sum of its
        instances', each within its mesh's bound (:data:`~lbvh.metrics.error_bound.
        WINDING_BOUND`) of the exact sum over the instance's world triangles, for any
        placement. An instance placed by a similarity, or of a closed mesh (whose winding
        number is a degree, kept by any affine map), is its mesh's winding number at the
        point moved into its space, negated for a reflection; an open mesh placed by
        another map (a shear, a non-uniform scale) changes its solid angles, so that
        instance is answered by a copy of its world triangles, built on first use and
        kept until it moves."""
        p = check_points(points).astype(np.float64)
        w = np.zeros(len(p))
        a, b = self._transforms[:, :, :3], self._transforms[:, :, 3]
        inv = np.linalg.inv(a)
        sign = np.sign(np.linalg.det(a))
        similar = is_similarity(a)
        for i in range(self.num_instances):
            mesh = self.meshes[self.mesh_of[i]]
            if similar[i] or not self._is_open(int(self.mesh_of[i])):
                local = ((p - b[i]) @ inv[i].T).astype(np.float32)
                w += sign[i] * mesh.winding_numbers(local)
            else:
                w += self._world_copy(i).winding_numbers(p.astype(np.float32))
        return w.astype(np.float32)

    def _is_open(self, m: int) -> bool:
        """Whether mesh ``m`` has a boundary edge (one of a single face), cached."""
        if m not in self._open:
            f = np.asarray(self.meshes[m].faces, np.int64)
            e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
            _, counts = np.unique(e, axis=0, return_counts=True)
            self._open[m] = bool((counts == 1).any())
        return self._open[m]

    def _world_copy(self, i: int) -> BVH:
        """Instance ``i``'s triangles in world space as a BVH of their own (the LBVH),
        kept until the instance moves (:meth:`set_transforms`)."""
        copy = self._world_copies.get(i)
        if copy is None:
            mesh = self.meshes[self.mesh_of[i]]
            t = self._transforms[i]
            v = np.asarray(mesh.vertices, np.float64) @ t[:, :3].T + t[:, 3]
            copy = BVH(*_upload_world_copy(self.ctx, v.astype(np.float32),
                                           np.asarray(mesh.faces)))
            self._world_copies[i] = copy
        return copy

    def contains(self, points: Any) -> np.ndarray:
        """``bool (N,)``: winding number of the scene > 1/2 (:meth:`winding_numbers`)."""
        return self.winding_numbers(points) > 0.5

    def signed_distance(self, points: Any) -> np.ndarray:
        """``float32 (N,)``: the distance to the scene (:meth:`closest_points`, in world
        space for any affine placement), negative inside (:meth:`contains`: the sign is
        exact where the winding numbers are, so for closed meshes under any placement,
        for open ones under similarities)."""
        distance = self.closest_points(points)[0]
        return np.where(self.contains(points), -distance, distance)

    def __reduce__(self) -> tuple:
        """Pickling: the meshes (each :class:`lbvh.BVH` pickles its arrays), the instances
        and their transforms travel; unpickling builds the top level on the unpickling
        process's default device."""
        return (Scene, (self.meshes, self.mesh_of, self._transforms, self.ids, self.names,
                        self.face_ids))

    def __repr__(self) -> str:
        return (f"<lbvh.Scene: {self.num_instances} instances of {len(self.meshes)} meshes, "
                f"{self.num_triangles:,} triangles in world space on {self.ctx.name}>")
