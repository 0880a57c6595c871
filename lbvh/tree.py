"""The values every builder and optimiser takes and returns: a mesh and a tree on the device.

A :class:`Mesh` is the triangles (host copies and device buffers); a
:class:`Tree` is a hierarchy over them in the layout of docs/pages/layout.md: node
records, parents and the primitive order on the device, with its root, sizes
and where its leaves are. Builders (:mod:`lbvh.builders`) make a ``Tree``
from a ``Mesh``; optimisers (treelet restructuring, the leaf collapse) take
one and return one. Neither is a public object: :class:`lbvh.BVH` is the
facade over a mesh, a tree and the query caches, and it alone owns them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import pyopencl as cl

from .device import Context, from_device
from .layout import NODE_DTYPE
from .report import BuildReport


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh on the device.

    ``vertices``: ``float32 (V, 3)`` and ``faces``: ``uint32 (F, 3)``, checked
    (:mod:`lbvh.mesh`) and read-only; ``vertices_buf``, ``faces_buf`` their
    device copies.
    """
    vertices: np.ndarray
    faces: np.ndarray
    vertices_buf: cl.Buffer
    faces_buf: cl.Buffer

    @property
    def num_prims(self) -> int:
        return len(self.faces)

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``float64 (3,)`` lower and upper corners of the vertices' box (on the host,
        once: the vertices never change, a refit makes another mesh)."""
        if not len(self.vertices):
            return np.zeros(3), np.zeros(3)
        return (self.vertices.min(axis=0).astype(np.float64),
                self.vertices.max(axis=0).astype(np.float64))

    @classmethod
    def upload(cls, ctx: Context, vertices: np.ndarray, faces: np.ndarray) -> "Mesh":
        """Copy checked host arrays to the device."""
        return cls(vertices, faces, ctx.memory.upload(vertices), ctx.memory.upload(faces))

    def with_vertices(self, ctx: Context, vertices: np.ndarray) -> "Mesh":
        """The same faces over new (checked) vertices of the same shape, uploaded."""
        return Mesh(vertices, self.faces, ctx.memory.upload(vertices), self.faces_buf)


@dataclass(frozen=True)
class Tree:
    """A tree on the device in the layout of docs/pages/layout.md.

    Attributes:
        ctx: the context its buffers belong to.
        nodes: ``num_nodes`` records of :data:`lbvh.layout.NODE_DTYPE`.
        parent: ``int32 (num_nodes,)``, ``-1`` at the root.
        prim_order: ``int32 (num_prims,)``, the original triangle of each slot.
        root, num_nodes, num_prims: as named.
        leaf_nodes: ``int32`` indices of the leaf nodes, or ``None`` for a
            Karras tree, whose leaves are the block ``[F-1, 2F-1)``.
        leaf_nodes_buf: the same list on the device (``None`` with it).
        builder: the name of what made it (``"lbvh"``, ``"sah+collapse"``...).
        report: the build's figures, if it was built here.
        clipped_leaves: the tree has spatial splits (``builder="sbvh"``): a triangle may
            have several slots, and a leaf's box holds the parts of its triangles, not
            their whole boxes (docs/pages/layout.md).
    """
    ctx: Context
    nodes: cl.Buffer
    parent: cl.Buffer
    prim_order: cl.Buffer
    root: int
    num_nodes: int
    num_prims: int
    builder: str
    leaf_nodes: np.ndarray | None = None
    leaf_nodes_buf: cl.Buffer | None = None
    report: BuildReport | None = field(default=None, compare=False)
    clipped_leaves: bool = False

    def leaf_walks(self) -> tuple[cl.Buffer | None, int, int]:
        """Where bottom-up walks start: ``(device leaf list or None, first leaf, leaf count)``."""
        if self.leaf_nodes is None:
            return None, self.num_prims - 1, self.num_prims
        return self.leaf_nodes_buf, 0, len(self.leaf_nodes)

    @property
    def num_leaves(self) -> int:
        return self.num_prims if self.leaf_nodes is None else len(self.leaf_nodes)

    def buffers(self) -> list[cl.Buffer]:
        """The device buffers this tree holds (its owner gives them back)."""
        own = [self.nodes, self.parent, self.prim_order]
        return own + ([self.leaf_nodes_buf] if self.leaf_nodes_buf is not None else [])

    def read(self, name: str) -> np.ndarray:
        """A host copy of one of the tree's arrays, read from the device: ``"nodes"``
        (``NODE_DTYPE (num_nodes,)``), ``"parent"`` (``int32 (num_nodes,)``, -1 at
        the root) or ``"prim_order"`` (``int32 (num_prims,)``)."""
        shapes = {"nodes": (self.nodes, NODE_DTYPE, self.num_nodes),
                  "parent": (self.parent, np.int32, self.num_nodes),
                  "prim_order": (self.prim_order, np.int32, self.num_prims)}
        if name not in shapes:
            raise ValueError(f"name: {name!r}; a tree holds {', '.join(map(repr, shapes))}")
        buf, dtype, n = shapes[name]
        with self.ctx.lock:
            return from_device(self.ctx, buf, dtype, (n,))

    def root_record(self) -> np.ndarray:
        """The root's node record (:data:`lbvh.layout.NODE_DTYPE`), read from the device."""
        record = np.empty(1, NODE_DTYPE)
        cl.enqueue_copy(self.ctx.queue, record, self.nodes,
                        src_offset=NODE_DTYPE.itemsize * self.root, is_blocking=True)
        return record[0]

    def root_words(self) -> tuple[int, int]:
        """The root record's ``a`` and ``b`` words."""
        record = self.root_record()
        return int(record["a"]), int(record["b"])

    def root_box(self) -> tuple[np.ndarray, np.ndarray]:
        """``float32 (3,)`` lower and upper corner of the root's box."""
        record = self.root_record()
        return record["lower"].copy(), record["upper"].copy()


def upload_tree(ctx: Context, nodes: np.ndarray, parent: np.ndarray, prim_order: np.ndarray,
                root: int, builder: str, report: BuildReport | None = None,
                clipped_leaves: bool = False) -> Tree:
    """A tree built on the host (``NODE_DTYPE`` nodes, ``int32`` parents and order),
    copied to the device; its leaf list is taken from the nodes."""
    leaves = np.flatnonzero(nodes["b"] < 0).astype(np.int32)
    rw = cl.mem_flags.READ_WRITE
    mem = ctx.memory
    return Tree(ctx, mem.upload(nodes, flags=rw), mem.upload(parent, flags=rw),
                mem.upload(prim_order, flags=rw), int(root), len(nodes), len(prim_order), builder,
                leaves, mem.upload(leaves), report, clipped_leaves)
