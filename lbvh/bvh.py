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
from .layout import NODE_DTYPE, children_of, is_leaf, parents_of
from .mesh import as_faces, as_vertices
from .queries import all_hits as hits_along, closest, overlap, traverse, winding
from .queries.all_hits import AllHits
from .queries.closest import Closest
from .queries.overlap import Overlaps
from .queries.options import QueryOptions
from .queries.traverse import DeviceHitArrays, Hits
from .queries.data import QueryData
from .report import BuildReport, tree_statistics
from .tree import Mesh, Tree, upload_tree
from .metrics.validate import BVHValidationError, validate_tree

SAVE_FORMAT_VERSION = 1


class BVH:
    """A bounding volume hierarchy over a triangle mesh.

    The tree lives on the device (:attr:`tree`, a :class:`lbvh.tree.Tree`: its
    ``nodes``, ``parent`` and ``prim_order`` buffers) over the mesh (:attr:`mesh`, a
    :class:`lbvh.tree.Mesh`: ``vertices_buf`` and ``faces_buf``); what the queries
    make of it has its owner in :attr:`query_data`.

    Attributes (numpy, read-only views of one host copy, made on first use):
        nodes:      structured ``(num_nodes,)`` of :data:`lbvh.layout.NODE_DTYPE`
                    (``nodes["lower"]``, ``nodes["upper"]``: ``float32 (num_nodes, 3)``)
        prim_order: ``int32 (num_slots,)``, original triangle index of each slot (a
                    triangle has one slot, or several in a tree with spatial splits)
        root:       ``int``
        vertices:   ``float32 (V, 3)`` and faces: ``uint32 (F, 3)``, the mesh

    The rest of the layout is derived from ``nodes`` by :mod:`lbvh.layout`
    (``children_of``, ``prim_range_of``, ``is_leaf``, ``parents_of``); the device's
    own parents are ``bvh.tree.read("parent")``. Counts: ``bvh.tree.num_nodes``,
    ``bvh.tree.num_prims`` (slots), ``bvh.mesh.num_prims`` (triangles); what built
    it: ``bvh.tree.builder`` and :meth:`report`.
    """

    def __init__(self, mesh: Mesh, tree: Tree) -> None:
        """Own ``tree`` (over ``mesh``): its buffers go back to the context's memory
        when this BVH is dropped. Made by :func:`lbvh.build`, :meth:`from_arrays`
        and :func:`lbvh.load`."""
        self._mesh = mesh
        self._tree = tree
        self._host: dict[str, np.ndarray] = {}
        # The query data owns the tree's buffers with its own: when this BVH (and
        # with it its query data) is dropped they go back to the context's memory in
        # one hand-over, as one dropped tree's, which the next build of the same
        # size takes (lbvh.device.memory).
        self._queries = QueryData(mesh, tree, owns_tree=True)

    # -- the two values and what they say -----------------------------------------
    mesh = property(lambda self: self._mesh,
                    doc="the :class:`lbvh.tree.Mesh` (host arrays and device buffers)")
    tree = property(lambda self: self._tree,
                    doc="the :class:`lbvh.tree.Tree` a builder made (device buffers, counts)")
    ctx = property(lambda self: self._tree.ctx, doc="the :class:`lbvh.device.Context`")
    root = property(lambda self: self._tree.root, doc="index of the root node")
    vertices = property(lambda self: self._mesh.vertices, doc="float32 (V, 3)")
    faces = property(lambda self: self._mesh.faces, doc="uint32 (F, 3)")

    # -- construction from host arrays (other builders, load) ----------------
    @classmethod
    def from_arrays(cls, nodes: np.ndarray, prim_order: np.ndarray, root: int,
                    vertices: np.ndarray, faces: np.ndarray, *, builder: str,
                    device: Any = None, validate: bool = True) -> "BVH":
        """Upload a tree built on the host in the project's layout (``nodes`` of
        :data:`lbvh.layout.NODE_DTYPE`, ``int32`` ``prim_order``, the ``root``'s index)
        over ``vertices`` and ``faces``; ``builder`` names what made it.

        With ``validate`` (the default) the tree is checked first and a broken
        one raises ``BVHValidationError`` (a ``ValueError``) before anything is
        uploaded.
        """
        return cls(*_upload(nodes, prim_order, root, vertices, faces, builder, device, validate))

    # -- numpy views ----------------------------------------------------------
    @dev.serialised
    def _fetch(self, name: str) -> np.ndarray:
        arr = self._host.get(name)
        if arr is None:
            arr = self._tree.read(name)
            arr.setflags(write=False)
            self._host[name] = arr
        return arr

    nodes = property(lambda self: self._fetch("nodes"), doc="node records, NODE_DTYPE (num_nodes,)")
    prim_order = property(lambda self: self._fetch("prim_order"), doc="int32 (num_slots,)")

    # -- checks and reports ---------------------------------------------------
    def validate(self) -> None:
        """Check every invariant of docs/pages/layout.md; raise ``BVHValidationError`` on the first violation."""
        validate_tree(self.nodes, self._fetch("parent"), self.prim_order, self.root,
                      self.vertices, self.faces, self._tree.clipped_leaves)

    def report(self) -> BuildReport:
        """Build timings and tree statistics (depth, leaves, ...), as data."""
        stats = tree_statistics(self.nodes, self._fetch("parent"), self.root)
        rep = self._tree.report or BuildReport(device=self.ctx.name, builder=self._tree.builder,
                                               num_triangles=self._mesh.num_prims)
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
        if self._tree.clipped_leaves:
            raise ValueError("refit: this tree has spatial splits (builder='sbvh'), whose leaf "
                             "boxes are parts of triangles that a refit would not know; build "
                             "it again")
        v = as_vertices(vertices)
        if v.shape != self.vertices.shape:
            raise ValueError(f"vertices: shape {v.shape}, the tree was built over {self.vertices.shape}")
        mesh = self._mesh.with_vertices(self.ctx, v)
        tree = self._tree
        refit_boxes(mesh, tree)
        self._mesh = mesh
        self._host.clear()
        self._queries.refit(mesh)   # what the queries made of the old boxes
        return self

    # -- ray queries (lbvh/queries/traverse.py, kernels/traverse.cl) ------------
    def intersect(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                  options: QueryOptions | None = None, **fields: Any) -> Hits | DeviceHitArrays:
        return traverse.intersect(self._queries, origins, directions, tmin, tmax,
                                  options=options, **fields)

    def occluded(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                 return_hits: bool = False, options: QueryOptions | None = None, **fields: Any
                 ) -> np.ndarray | Hits | cl_array.Array | DeviceHitArrays:
        return traverse.occluded(self._queries, origins, directions, tmin, tmax,
                                 return_hits=return_hits, options=options, **fields)

    def intersect_async(self, origins: Any, directions: Any, tmin: Any = 0.0,
                        tmax: Any = np.inf, *, options: QueryOptions | None = None,
                        **fields: Any) -> "Future[Hits | DeviceHitArrays]":
        return traverse.intersect_async(self._queries, origins, directions, tmin, tmax,
                                        options=options, **fields)

    def occluded_async(self, origins: Any, directions: Any, tmin: Any = 0.0,
                       tmax: Any = np.inf, *, return_hits: bool = False,
                       options: QueryOptions | None = None, **fields: Any) -> "Future[Any]":
        return traverse.occluded_async(self._queries, origins, directions, tmin, tmax,
                                       return_hits=return_hits, options=options, **fields)

    intersect.__doc__ = traverse.query_doc("intersect", target=False)
    occluded.__doc__ = traverse.query_doc("occluded", target=False)
    intersect_async.__doc__ = traverse.async_doc("intersect")
    occluded_async.__doc__ = traverse.async_doc("occluded")

    # -- every hit (lbvh/queries/all_hits.py, kernels/all_hits.cl) ---------------
    def count_hits(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                   signed: bool = False, options: QueryOptions | None = None,
                   **fields: Any) -> np.ndarray:
        """``int32 (N,)``: how many times each ray crosses the mesh in ``[tmin, tmax]``, a
        crossing through a shared edge or vertex once (``signed``: +1 leaving a
        triangle by its front, -1 entering by it; ``options``: ``invalid_rays`` and
        ``batch_size`` of :class:`lbvh.QueryOptions`); see
        :func:`lbvh.queries.all_hits.count_hits`."""
        return hits_along.count_hits(self._queries, origins, directions, tmin, tmax, signed=signed,
                                     options=options, **fields)

    def all_hits(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf, *,
                 max_hits: int | None = None, options: QueryOptions | None = None,
                 **fields: Any) -> AllHits:
        """Every hit of each ray in ``[tmin, tmax]``, nearest first, as flat arrays with
        per-ray offsets (at most ``max_hits`` per ray, the nearest; ``options``:
        ``invalid_rays`` and ``batch_size`` of :class:`lbvh.QueryOptions`); see
        :func:`lbvh.queries.all_hits.all_hits`."""
        return hits_along.all_hits(self._queries, origins, directions, tmin, tmax, max_hits=max_hits,
                                   options=options, **fields)

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
                                self.faces, self._tree.builder, self._tree.report))

    def save(self, path: str | os.PathLike) -> None:
        """Write the tree and its mesh to ``path`` exactly (no suffix is added; ``.npz``
        is the custom), an ``.npz`` archive readable with plain numpy; :func:`lbvh.load`
        reads it back."""
        with open(path, "wb") as out:   # a file object: numpy adds no ".npz" to the name
            np.savez(out, format_version=np.int32(SAVE_FORMAT_VERSION), nodes=self.nodes,
                     parent=self._fetch("parent"), prim_order=self.prim_order,
                     root=np.int32(self.root), vertices=self.vertices, faces=self.faces,
                     builder=np.str_(self._tree.builder))

    def __repr__(self) -> str:
        return (f"<lbvh.BVH {self._tree.builder}: {self._mesh.num_prims} triangles, "
                f"{self._tree.num_nodes} nodes "
                f"on {self.ctx.name}>")


def _unpickle_bvh(nodes: np.ndarray, prim_order: np.ndarray, root: int, vertices: np.ndarray,
                  faces: np.ndarray, builder: str, report: BuildReport | None) -> BVH:
    """The inverse of :meth:`BVH.__reduce__` (the arrays were valid when pickled)."""
    return BVH(*_upload(nodes, prim_order, root, vertices, faces, builder, None, False, report))


def _upload(nodes: np.ndarray, prim_order: np.ndarray, root: int, vertices: np.ndarray,
            faces: np.ndarray, builder: str, device: Any, validate: bool,
            report: BuildReport | None = None) -> tuple[Mesh, Tree]:
    """:meth:`BVH.from_arrays`: the checked arrays, uploaded (with the build's
    ``report`` where one travels with them: unpickling)."""
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
        return mesh, upload_tree(ctx, nodes, parent, prim_order, root, builder, report,
                                 clipped_leaves=clipped)
