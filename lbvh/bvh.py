"""The BVH object: device buffers plus documented numpy views (docs/layout.md)."""
from __future__ import annotations

import os
import weakref
from pathlib import Path
from typing import Any

import numpy as np
import pyopencl as cl

from . import device as dev
from .geometry import as_faces, as_vertices
from .layout import NODE_DTYPE, children_of, is_leaf, node_depths, parents_of, prim_range_of
from .report import BuildReport, tree_statistics
from .validate import BVHValidationError, validate_tree

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
        prim_order: ``int32 (num_prims,)``, original triangle index of each slot
        root:       ``int``
        vertices:   ``float32 (V, 3)`` and faces: ``uint32 (F, 3)``, the mesh
    """

    def __init__(self, ctx: dev.Context, vertices: np.ndarray, faces: np.ndarray,
                 vertices_buf: cl.Buffer, faces_buf: cl.Buffer, nodes_buf: cl.Buffer,
                 parent_buf: cl.Buffer, prim_order_buf: cl.Buffer, num_nodes: int, root: int,
                 builder: str, report: BuildReport | None = None,
                 leaf_nodes: np.ndarray | None = None, pooled: bool = False) -> None:
        """``pooled``: the node, parent and prim_order buffers go back to the
        context's pool when the tree is dropped (trees built on the device)."""
        self.ctx = ctx
        self.vertices = vertices
        self.faces = faces
        self.vertices_buf = vertices_buf
        self.faces_buf = faces_buf
        self.nodes_buf = nodes_buf
        self.parent_buf = parent_buf
        self.prim_order_buf = prim_order_buf
        self.num_nodes = int(num_nodes)
        self.num_prims = int(len(faces))
        self.root = int(root)
        self.builder = builder
        self.build_report = report
        # Leaves of a Karras tree are the contiguous block [F-1, 2F-1); other
        # builders pass the list of their leaf nodes for the device refit.
        self._leaf_nodes = leaf_nodes
        self._leaf_nodes_buf: cl.Buffer | None = None
        self._wide = None           # wide records of the traversal (lbvh.wide.wide_for)
        self._slot_faces = None     # faces in slot order, for the traversal (slot_faces_for)
        self._host: dict[str, np.ndarray] = {}
        # Buffers handed to the context's pool when the tree is dropped: the
        # build's outputs (``pooled``) and the traversal's wide records.
        self._pooled: list[tuple[cl.Buffer, int]] = []
        if pooled:
            sizes = (NODE_DTYPE.itemsize * self.num_nodes, 4 * self.num_nodes, 4 * self.num_prims)
            self._pooled += zip((nodes_buf, parent_buf, prim_order_buf), sizes)
        weakref.finalize(self, _give_back, ctx, self._pooled)

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
        if validate:
            validate_tree(nodes, parent, prim_order, root, vertices, faces)
        ctx = dev.get_context(device)
        leaf_nodes = np.flatnonzero(is_leaf(nodes)).astype(np.int32)
        rw = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
        with ctx.lock:
            return cls(ctx, vertices, faces, dev.to_device(ctx, vertices), dev.to_device(ctx, faces),
                       cl.Buffer(ctx.ctx, rw, hostbuf=nodes), cl.Buffer(ctx.ctx, rw, hostbuf=parent),
                       cl.Buffer(ctx.ctx, rw, hostbuf=prim_order), len(nodes), root, builder, report,
                       leaf_nodes=leaf_nodes)

    # -- numpy views ----------------------------------------------------------
    @dev.serialised
    def _fetch(self, name: str) -> np.ndarray:
        arr = self._host.get(name)
        if arr is None:
            if name == "nodes":
                arr = dev.from_device(self.ctx, self.nodes_buf, NODE_DTYPE, (self.num_nodes,))
            elif name == "parent":
                arr = dev.from_device(self.ctx, self.parent_buf, np.int32, (self.num_nodes,))
            elif name == "prim_order":
                arr = dev.from_device(self.ctx, self.prim_order_buf, np.int32, (self.num_prims,))
            else:
                nodes = self._fetch("nodes")
                arr = {"children": children_of, "prim_range": prim_range_of,
                       "is_leaf": is_leaf}[name](nodes)
            arr.setflags(write=False)
            self._host[name] = arr
        return arr

    nodes = property(lambda self: self._fetch("nodes"), doc="node records, NODE_DTYPE (num_nodes,)")
    parent = property(lambda self: self._fetch("parent"), doc="int32 (num_nodes,), -1 for the root")
    prim_order = property(lambda self: self._fetch("prim_order"), doc="int32 (num_prims,)")
    children = property(lambda self: self._fetch("children"), doc="int32 (num_nodes, 2)")
    prim_range = property(lambda self: self._fetch("prim_range"), doc="int32 (num_nodes, 2)")
    is_leaf = property(lambda self: self._fetch("is_leaf"), doc="bool (num_nodes,)")
    lower = property(lambda self: self.nodes["lower"], doc="float32 (num_nodes, 3)")
    upper = property(lambda self: self.nodes["upper"], doc="float32 (num_nodes, 3)")

    def depths(self) -> np.ndarray:
        """``int64 (num_nodes,)`` depth of every node, the root at 0."""
        return node_depths(self.parent, self.root)

    @property
    def leaf_nodes(self) -> np.ndarray:
        """``int32`` indices of the leaf nodes."""
        if self._leaf_nodes is None:
            return np.flatnonzero(self.is_leaf).astype(np.int32)
        return self._leaf_nodes

    # -- checks and reports ---------------------------------------------------
    def validate(self) -> None:
        """Check every invariant of docs/layout.md; raise ``BVHValidationError`` on the first violation."""
        validate_tree(self.nodes, self.parent, self.prim_order, self.root, self.vertices, self.faces)

    def report(self) -> BuildReport:
        """Build timings and tree statistics (depth, leaves, ...), as data."""
        stats = tree_statistics(self.nodes, self.parent, self.root)
        rep = self.build_report or BuildReport(device=self.ctx.name, builder=self.builder,
                                               num_triangles=self.num_prims)
        rep.update_stats(stats)
        return rep

    # -- animation ------------------------------------------------------------
    @dev.serialised
    def refit(self, vertices: Any) -> "BVH":
        """Recompute every box on the device for moved vertices (same faces, same topology).

        ``vertices`` is ``(V, 3)`` with the same V as the mesh the tree was
        built on.  On a bad input nothing changes and the tree stays usable.
        Returns ``self``.
        """
        from .refit import refit_boxes
        from .wide import refresh_wide

        v = as_vertices(vertices)
        if v.shape != self.vertices.shape:
            raise ValueError(f"vertices: shape {v.shape}, the tree was built over {self.vertices.shape}")
        new_buf = dev.to_device(self.ctx, v)
        refit_boxes(self.ctx, new_buf, self.faces_buf, self.prim_order_buf, self.nodes_buf,
                    self.parent_buf, self.num_prims, self.num_nodes, self._leaf_nodes_device())
        self.vertices_buf, self.vertices = new_buf, v
        self._host.clear()
        refresh_wide(self)   # the traversal's copies of the boxes
        return self

    def leaf_walks(self) -> tuple[cl.Buffer | None, int, int]:
        """Where bottom-up walks start: ``(device leaf list or None, first leaf, leaf count)``.

        Karras trees have their leaves in the block ``[F-1, 2F-1)`` and no list;
        other trees list their leaf nodes in an int32 device buffer.
        """
        if self._leaf_nodes is None:
            return None, self.num_prims - 1, self.num_prims
        return self._leaf_nodes_device(), 0, len(self._leaf_nodes)

    def _leaf_nodes_device(self) -> cl.Buffer | None:
        if self._leaf_nodes is None:
            return None
        if self._leaf_nodes_buf is None:
            self._leaf_nodes_buf = dev.to_device(self.ctx, self._leaf_nodes)
        return self._leaf_nodes_buf

    # -- ray queries (lbvh/traverse.py, kernels/traverse.cl) -------------------
    def intersect(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf,
                  **options: Any):
        """Closest hit of each ray; see :func:`lbvh.traverse.intersect`."""
        from .traverse import intersect
        return intersect(self, origins, directions, tmin, tmax, **options)

    def occluded(self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf,
                 **options: Any):
        """Whether each ray hits anything in [tmin, tmax]: ``bool (N,)``, or a
        :class:`lbvh.traverse.Hits` with ``return_hits=True``; see :func:`lbvh.traverse.occluded`."""
        from .traverse import occluded
        return occluded(self, origins, directions, tmin, tmax, **options)

    # -- persistence ------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write the tree and its mesh to a ``.npz`` file readable with plain numpy."""
        np.savez(Path(path), format_version=np.int32(SAVE_FORMAT_VERSION), nodes=self.nodes,
                 parent=self.parent, prim_order=self.prim_order, root=np.int32(self.root),
                 vertices=self.vertices, faces=self.faces, builder=np.str_(self.builder))

    def __repr__(self) -> str:
        return (f"<lbvh.BVH {self.builder}: {self.num_prims} triangles, {self.num_nodes} nodes "
                f"on {self.ctx.name}>")


def _give_back(ctx: dev.Context, buffers: list[tuple[cl.Buffer, int]]) -> None:
    if buffers:
        ctx.dropped(buffers)


def load(path: str | os.PathLike, device: Any = None) -> BVH:
    """Read a tree written by :meth:`BVH.save` and upload it to the device."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:  # OSError, ValueError, zipfile.BadZipFile, EOFError...
        raise ValueError(f"{path}: not a saved lbvh BVH ({type(exc).__name__}: {exc})") from None
    with data:
        missing = {"format_version", "nodes", "prim_order", "root", "vertices", "faces"} - set(data.files)
        if missing:
            raise ValueError(f"{path}: not a saved lbvh BVH (missing {sorted(missing)})")
        if int(data["format_version"]) != SAVE_FORMAT_VERSION:
            raise ValueError(f"{path}: format version {int(data['format_version'])}, "
                             f"this lbvh reads {SAVE_FORMAT_VERSION}")
        nodes = data["nodes"]
        if nodes.dtype != NODE_DTYPE:
            raise ValueError(f"{path}: nodes have dtype {nodes.dtype}, expected {NODE_DTYPE}")
        builder = str(data["builder"]) if "builder" in data.files else "loaded"
        try:
            bvh = BVH.from_arrays(nodes, data["prim_order"], int(data["root"]), data["vertices"],
                                  data["faces"], builder=builder, device=device)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    return bvh
