"""The public BVH: a facade over the mesh, the tree and the query data.

The device state is two values (:mod:`lbvh.tree`): the :class:`~lbvh.tree.Mesh`
and the :class:`~lbvh.tree.Tree` a builder made. The numpy views of
docs/pages/layout.md are made on first use and kept here; what the queries make of
the tree (wide records, faces in slot order, moments, depth) has its one owner in
:class:`lbvh.queries.data.QueryData`, which the BVH holds and gives to every query.
A refit renews what depends on the boxes. When a BVH is dropped its tree's buffers
and its query data's go back to the context's memory (:mod:`lbvh.device.memory`),
where the next build of the same size finds them.
"""
from __future__ import annotations

import os
from concurrent.futures import Future
from typing import Any

import numpy as np
import pyopencl.array as cl_array

from . import device as dev
from .builders.refit import refit_boxes
from .layout import NODE_DTYPE, children_of, is_leaf, parents_of, prim_range_of
from .mesh import as_faces, as_vertices
from .queries import all_hits as hits_along, closest, overlap, traverse, winding
from .queries.all_hits import AllHits
from .queries.closest import Closest
from .queries.overlap import Overlaps
from .queries.rays import InvalidRays
from .queries.traverse import DeviceHitArrays, Hits
from .queries.data import QueryData
from .report import BuildReport, tree_statistics
from .tree import Mesh, Tree, upload_tree
from .metrics.validate import BVHValidationError, validate_tree

SAVE_FORMAT_VERSION = 1


class BVH:
    """A bounding volume hierarchy over a triangle mesh.

    The tree lives on the device (``nodes_buf``, ``parent_buf``,
    ``prim_order_buf`` plus the mesh's ``vertices_buf`` and ``faces_buf``);
    the numpy attributes below are copied from it on first use and cached.

    Attributes (numpy, read-only views of one host copy):
        nodes:      structured ``(num_nodes,)`` of :data:`lbvh.layout.NODE_DTYPE`
        lower, upper: ``float32 (num_nodes, 3)`` box corners
        children:   ``int32 (num_nodes, 2)``, ``-1`` for leaves
        prim_range: ``int32 (num_nodes, 2)``, ``(first, count)`` of leaves
        is_leaf:    ``bool (num_nodes,)``
        parent:     ``int32 (num_nodes,)``, ``-1`` for the root
        prim_order: ``int32 (num_slots,)``, original triangle index of each slot (a
                    triangle has one slot, or several in a tree with spatial splits)
        root:       ``int``
        vertices:   ``float32 (V, 3)`` and faces: ``uint32 (F, 3)``, the mesh
    """

    def __init__(self, mesh: Mesh, tree: Tree) -> None:
        """Own ``tree`` (over ``mesh``): its buffers go back to the context's memory
        when this BVH is dropped. Made by :func:`lbvh.build`, :meth:`from_arrays`
        and :func:`lbvh.load`."""
        self.mesh = mesh
        self.tree = tree
        self._host: dict[str, np.ndarray] = {}
        # The query data owns the tree's buffers with its own: when this BVH (and
        # with it its query data) is dropped they go back to the context's memory in
        # one hand-over, as one dropped tree's, which the next build of the same
        # size takes (lbvh.device.memory).
        self._queries = QueryData(mesh, tree, owns_tree=True)

    # -- what the tree and mesh say ---------------------------------------------
    ctx = property(lambda self: self.tree.ctx, doc="the :class:`lbvh.device.Context`")
    root = property(lambda self: self.tree.root, doc="index of the root node")
    num_nodes = property(lambda self: self.tree.num_nodes)
    num_prims = property(lambda self: self.mesh.num_prims, doc="triangles of the mesh")
    num_slots = property(lambda self: self.tree.num_prims,
                         doc="slots of prim_order: num_prims, or more with spatial splits")
    builder = property(lambda self: self.tree.builder, doc="what built the tree")
    build_report = property(lambda self: self.tree.report, doc="the build's figures, or None")
    nodes_buf = property(lambda self: self.tree.nodes, doc="device node records")
    parent_buf = property(lambda self: self.tree.parent, doc="device int32 parents")
    prim_order_buf = property(lambda self: self.tree.prim_order, doc="device int32 order")
    vertices = property(lambda self: self.mesh.vertices, doc="float32 (V, 3)")
    faces = property(lambda self: self.mesh.faces, doc="uint32 (F, 3)")
    vertices_buf = property(lambda self: self.mesh.vertices_buf)
    faces_buf = property(lambda self: self.mesh.faces_buf)

    # -- construction from host arrays (other builders, load) ----------------
    @classmethod
    def from_arrays(cls, nodes: np.ndarray, prim_order: np.ndarray, root: int,
                    vertices: np.ndarray, faces: np.ndarray, *, builder: str,
                    device: Any = None, report: BuildReport | None = None,
                    validate: bool = True) -> "BVH":
        """Upload a tree built on the host in the project's layout.

        With ``validate`` (the default) the tree is checked first and a broken
        one raises ``BVHValidationError`` (a ``ValueError``) before anything is
        uploaded.
        """
        nodes = np.ascontiguousarray(nodes, dtype=NODE_DTYPE)
        prim_order = np.ascontiguousarray(prim_order, dtype=np.int32)
        vertices = as_vertices(vertices)
        faces = as_faces(faces, len(vertices))
        root = int(root)
        if not 0 <= root < len(nodes):
            raise BVHValidationError(f"invalid BVH: root {root} outside [0, {len(nodes)})")
        kids = children_of(nodes)
        outside = (kids >= len(nodes)).any(axis=1) | ((kids < 0) & ~is_leaf(nodes)[:, None]).any(axis=1)
        if outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise BVHValidationError(f"invalid BVH: node {i} has child index {kids[i].tolist()} "
                                     f"outside [0, {len(nodes)})")
        parent = parents_of(nodes, root)
        # a triangle in several slots: spatial splits (builder="sbvh")
        clipped = len(prim_order) != len(faces) or builder.startswith("sbvh")
        if validate:
            validate_tree(nodes, parent, prim_order, root, vertices, faces, clipped)
        ctx = dev.get_context(device)
        with ctx.lock:
            mesh = Mesh.upload(ctx, vertices, faces)
            return cls(mesh, upload_tree(ctx, nodes, parent, prim_order, root, builder, report,
                                         clipped_leaves=clipped))

    # -- numpy views ----------------------------------------------------------
    @dev.serialised
    def _fetch(self, name: str) -> np.ndarray:
        arr = self._host.get(name)
        if arr is None:
            tree = self.tree
            if name == "nodes":
                arr = dev.from_device(self.ctx, tree.nodes, NODE_DTYPE, (tree.num_nodes,))
            elif name == "parent":
                arr = dev.from_device(self.ctx, tree.parent, np.int32, (tree.num_nodes,))
            elif name == "prim_order":
                arr = dev.from_device(self.ctx, tree.prim_order, np.int32, (tree.num_prims,))
            else:
                nodes = self._fetch("nodes")
                arr = {"children": children_of, "prim_range": prim_range_of,
                       "is_leaf": is_leaf}[name](nodes)
            arr.setflags(write=False)
            self._host[name] = arr
        return arr

    nodes = property(lambda self: self._fetch("nodes"), doc="node records, NODE_DTYPE (num_nodes,)")
    parent = property(lambda self: self._fetch("parent"), doc="int32 (num_nodes,), -1 for the root")
    prim_order = property(lambda self: self._fetch("prim_order"), doc="int32 (num_slots,)")
    children = property(lambda self: self._fetch("children"), doc="int32 (num_nodes, 2)")
    prim_range = property(lambda self: self._fetch("prim_range"), doc="int32 (num_nodes, 2)")
    is_leaf = property(lambda self: self._fetch("is_leaf"), doc="bool (num_nodes,)")
    lower = property(lambda self: self.nodes["lower"], doc="float32 (num_nodes, 3)")
    upper = property(lambda self: self.nodes["upper"], doc="float32 (num_nodes, 3)")

    @property
    def leaf_nodes(self) -> np.ndarray:
        """``int32`` indices of the leaf nodes."""
        if self.tree.leaf_nodes is None:
            return np.flatnonzero(self.is_leaf).astype(np.int32)
        return self.tree.leaf_nodes

    # -- checks and reports ---------------------------------------------------
    def validate(self) -> None:
        """Check every invariant of docs/pages/layout.md; raise ``BVHValidationError`` on the first violation."""
        validate_tree(self.nodes, self.parent, self.prim_order, self.root, self.vertices, self.faces,
                      self.tree.clipped_leaves)

    def report(self) -> BuildReport:
        """Build timings and tree statistics (depth, leaves, ...), as data."""
        stats = tree_statistics(self.nodes, self.parent, self.root)
        rep = self.build_report or BuildReport(device=self.ctx.name, builder=self.builder,
                                               num_triangles=self.num_prims)
        rep.update_stats(stats)
        return rep

    # -- the query data (lbvh.queries.data) -----------------------------------------
    @property
    def query_data(self) -> QueryData:
        """What the queries need of the tree beyond it, made on first use and owned
        there (:class:`lbvh.queries.data.QueryData`: the wide records, the faces and
        triangles in slot order, the winding numbers' moments and walk, the depth);
        the query modules' functions take it (:mod:`lbvh.queries.target`)."""
        return self._queries

    # -- animation ------------------------------------------------------------
    @dev.serialised
    def refit(self, vertices: Any) -> "BVH":
        """Recompute every box on the device for moved vertices (same faces, same topology).

        ``vertices`` is ``(V, 3)`` with the same V as the mesh the tree was
        built on.  On a bad input nothing changes and the tree stays usable.
        Returns ``self``.
        """
        if self.tree.clipped_leaves:
            raise ValueError("refit: this tree has spatial splits (builder='sbvh'), whose leaf "
                             "boxes are parts of triangles that a refit would not know; build "
                             "it again")
        v = as_vertices(vertices)
        if v.shape != self.vertices.shape:
            raise ValueError(f"vertices: shape {v.shape}, the tree was built over {self.vertices.shape}")
        mesh = self.mesh.with_vertices(self.ctx, v)
        tree = self.tree
        refit_boxes(self.ctx, mesh.vertices_buf, mesh.faces_buf, tree.prim_order, tree.nodes,
                    tree.parent, tree.num_prims, tree.num_nodes, tree.leaf_walks()[0])
        self.mesh = mesh
        self._host.clear()
        self._queries.refit(mesh)   # what the queries made of the old boxes
        return self

    # -- ray queries (lbvh/queries/traverse.py, kernels/traverse.cl) ------------
    def intersect(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                  triangle_test: traverse.TriangleTest = "watertight", counters: bool = False,
                  batch_size: int = traverse.DEFAULT_BATCH, stack_size: int | None = None,
                  invalid_rays: InvalidRays = "raise",
                  order: traverse.NodeOrder = "ordered") -> Hits | DeviceHitArrays:
        return traverse.intersect(self._queries, origins, directions, tmin, tmax,
                                  triangle_test=triangle_test, counters=counters,
                                  batch_size=batch_size, stack_size=stack_size,
                                  invalid_rays=invalid_rays, order=order)

    def occluded(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                 triangle_test: traverse.TriangleTest = "watertight", counters: bool = False,
                 batch_size: int = traverse.DEFAULT_BATCH, stack_size: int | None = None,
                 return_hits: bool = False, invalid_rays: InvalidRays = "raise"
                 ) -> np.ndarray | Hits | cl_array.Array | DeviceHitArrays:
        return traverse.occluded(self._queries, origins, directions, tmin, tmax,
                                 triangle_test=triangle_test, counters=counters,
                                 batch_size=batch_size, stack_size=stack_size,
                                 return_hits=return_hits, invalid_rays=invalid_rays)

    def intersect_async(self, origins: Any, directions: Any, tmin: Any = 0.0,
                        tmax: Any = np.inf, *, triangle_test: traverse.TriangleTest = "watertight",
                        counters: bool = False, batch_size: int = traverse.DEFAULT_BATCH,
                        stack_size: int | None = None, invalid_rays: InvalidRays = "raise",
                        order: traverse.NodeOrder = "ordered"
                        ) -> "Future[Hits | DeviceHitArrays]":
        return traverse.intersect_async(self._queries, origins, directions, tmin, tmax,
                                        triangle_test=triangle_test, counters=counters,
                                        batch_size=batch_size, stack_size=stack_size,
                                        invalid_rays=invalid_rays, order=order)

    def occluded_async(self, origins: Any, directions: Any, tmin: Any = 0.0,
                       tmax: Any = np.inf, *, triangle_test: traverse.TriangleTest = "watertight",
                       counters: bool = False, batch_size: int = traverse.DEFAULT_BATCH,
                       stack_size: int | None = None, return_hits: bool = False,
                       invalid_rays: InvalidRays = "raise") -> "Future[Any]":
        return traverse.occluded_async(self._queries, origins, directions, tmin, tmax,
                                       triangle_test=triangle_test, counters=counters,
                                       batch_size=batch_size, stack_size=stack_size,
                                       return_hits=return_hits, invalid_rays=invalid_rays)

    intersect.__doc__ = traverse.query_doc("intersect", target=False)
    occluded.__doc__ = traverse.query_doc("occluded", target=False)
    intersect_async.__doc__ = traverse.async_doc("intersect")
    occluded_async.__doc__ = traverse.async_doc("occluded")

    # -- every hit (lbvh/queries/all_hits.py, kernels/all_hits.cl) ---------------
    def count_hits(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                   signed: bool = False, batch_size: int = hits_along.DEFAULT_BATCH,
                   invalid_rays: InvalidRays = "raise") -> np.ndarray:
        """``int32 (N,)``: how many times each ray crosses the mesh in ``[tmin, tmax]``, a
        crossing through a shared edge or vertex once (``signed``: +1 leaving a
        triangle by its front, -1 entering by it); see
        :func:`lbvh.queries.all_hits.count_hits`."""
        return hits_along.count_hits(self._queries, origins, directions, tmin, tmax, signed=signed,
                                     batch_size=batch_size, invalid_rays=invalid_rays)

    def all_hits(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                 max_hits: int | None = None, batch_size: int = hits_along.DEFAULT_BATCH,
                 invalid_rays: InvalidRays = "raise") -> AllHits:
        """Every hit of each ray in ``[tmin, tmax]``, nearest first, as flat arrays with
        per-ray offsets (at most ``max_hits`` per ray, the nearest); see
        :func:`lbvh.queries.all_hits.all_hits`."""
        return hits_along.all_hits(self._queries, origins, directions, tmin, tmax, max_hits=max_hits,
                                   batch_size=batch_size, invalid_rays=invalid_rays)

    # -- point queries (lbvh/queries/closest.py, kernels/closest.cl) ------------
    def closest_points(self, points: Any, max_distance: float = np.inf, *,
                       batch_size: int = 1 << 20) -> Closest:
        """The closest point of the mesh to each query point within ``max_distance``:
        distance, point, triangle and barycentrics; see
        :func:`lbvh.queries.closest.closest_points`."""
        return closest.closest_points(self._queries, points, max_distance, batch_size=batch_size)

    # -- inside and signed distance (lbvh/queries/winding.py, kernels/winding.cl) ----
    def winding_numbers(self, points: Any, *, beta: float = winding.DEFAULT_BETA,
                        node_error: float = winding.NODE_ERROR) -> np.ndarray:
        """``float32 (N,)``: the generalised winding number of each point (1 inside a
        closed mesh, 0 outside); see :func:`lbvh.queries.winding.winding_numbers`."""
        return winding.winding_numbers(self._queries, points, beta=beta, node_error=node_error)

    def contains(self, points: Any, *, beta: float | None = None) -> np.ndarray:
        """``bool (N,)``: whether each point is inside the mesh (winding number > 1/2);
        see :mod:`lbvh.queries.winding` for what it answers on an open mesh, and
        :func:`lbvh.queries.winding.contains` for ``beta``."""
        return winding.contains(self._queries, points, beta=beta)

    def signed_distance(self, points: Any, *, beta: float | None = None) -> np.ndarray:
        """``float32 (N,)``: the distance to the mesh, negative inside (Open3D's and
        warp's convention); see :func:`lbvh.queries.winding.signed_distance`."""
        return winding.signed_distance(self._queries, points, beta=beta)

    def overlapping(self, lower: Any, upper: Any) -> Overlaps:
        """The triangles whose boxes overlap each query box ``[lower[i], upper[i]]``, as
        flat arrays with offsets; see :func:`lbvh.queries.overlap.overlapping`."""
        return overlap.overlapping(self._queries, lower, upper)

    # -- persistence ------------------------------------------------------------
    def __reduce__(self) -> tuple:
        """Pickling: the tree's and the mesh's host arrays travel (as :meth:`save` writes
        them), not the device buffers; unpickling uploads them to the default device of
        the process that unpickles (``$LBVH_DEVICE`` or PoCL's CPU device; a worker of a
        cluster uses its own), without validating again."""
        return (_unpickle_bvh, (self.nodes, self.prim_order, self.root, self.vertices,
                                self.faces, self.builder, self.build_report))

    def save(self, path: str | os.PathLike) -> None:
        """Write the tree and its mesh to ``path`` exactly (no suffix is added; ``.npz``
        is the custom), an ``.npz`` archive readable with plain numpy; :func:`lbvh.load`
        reads it back."""
        with open(path, "wb") as out:   # a file object: numpy adds no ".npz" to the name
            np.savez(out, format_version=np.int32(SAVE_FORMAT_VERSION), nodes=self.nodes,
                     parent=self.parent, prim_order=self.prim_order, root=np.int32(self.root),
                     vertices=self.vertices, faces=self.faces, builder=np.str_(self.builder))

    def __repr__(self) -> str:
        return (f"<lbvh.BVH {self.builder}: {self.num_prims} triangles, {self.num_nodes} nodes "
                f"on {self.ctx.name}>")


def _unpickle_bvh(nodes: np.ndarray, prim_order: np.ndarray, root: int, vertices: np.ndarray,
                  faces: np.ndarray, builder: str, report: BuildReport | None) -> BVH:
    """The inverse of :meth:`BVH.__reduce__` (the arrays were valid when pickled)."""
    return BVH.from_arrays(nodes, prim_order, root, vertices, faces, builder=builder,
                           report=report, validate=False)
