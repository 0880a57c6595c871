"""The query data: what the queries need of a tree beyond the tree itself, with one owner.

A :class:`QueryData` holds, for one tree over one mesh, everything the query
kernels read that the builders do not make, each made on its first use and kept:

* the wide records the walks read (:mod:`lbvh.queries.wide`);
* the faces in slot order (:func:`lbvh.queries.traverse.order_faces`) and each slot's
  triangle's corners (:func:`lbvh.queries.traverse.order_triangles`);
* the winding numbers' moments (:mod:`lbvh.queries.winding_moments`) and the copy of the
  tree that the winding walk runs on (a restructured LBVH, :mod:`lbvh.queries.winding`);
* the tree's depth (the stack the walks are compiled for).

It owns their buffers: a refit of the tree's boxes (:meth:`refit`) renews what depends
on them, and when the QueryData is dropped its buffers go back to the context's memory.
:class:`lbvh.BVH` holds one (``bvh.query_data``) and gives it to every query; it is the
:class:`lbvh.queries.target.QueryTarget` the query modules take. Every method holds the
context's lock (several threads may query one BVH).
"""
from __future__ import annotations

import weakref

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..builders.refit import refit_boxes
from ..builders.restructure import restructured
from ..layout import node_depths
from ..tree import Mesh, Tree
from . import traverse, winding
from .wide import Wide, make_wide, release_wide, wide_buffers, write_records
from .winding_moments import make_moments


class QueryData:
    """The query data of ``tree`` over ``mesh`` (see the module docstring).

    ``owns_tree``: the tree's buffers go back with this object's, in one hand-over
    (a BVH's query data, and the winding walk's copy); otherwise the tree's owner
    keeps them.
    """

    def __init__(self, mesh: Mesh, tree: Tree, *, owns_tree: bool = False) -> None:
        self.mesh = mesh
        self.tree = tree
        self._wide: Wide | None = None
        self._slot_faces: cl.Buffer | None = None
        self._slot_triangles: cl.Buffer | None = None
        self._moments: tuple[Wide, cl.Buffer] | None = None
        self._depth: int | None = None
        self._winding: QueryData | None = None
        # everything handed back when this object is dropped (appended as made)
        self._owned: list[cl.Buffer] = tree.buffers() if owns_tree else []
        weakref.finalize(self, tree.ctx.memory.dropped, self._owned)

    @property
    def ctx(self) -> dev.Context:
        """The tree's :class:`lbvh.device.Context`."""
        return self.tree.ctx

    @dev.serialised
    def wide_records(self, width: int | None = None, max_bytes: int | None = None) -> Wide:
        """The walks' wide records (:mod:`lbvh.queries.wide`), made on first use; records
        of another ``width`` (4 or 8) replace them, and ``max_bytes`` as
        :func:`~lbvh.queries.wide.make_wide` takes it."""
        cached = self._wide
        if cached is not None and (width is None or cached.width == width or not cached.packed) \
                and max_bytes is None:
            return cached
        wide = make_wide(self.tree, width, max_bytes)
        self._drop_wide()
        self._wide = wide
        self._owned.extend(wide_buffers(wide))
        return wide

    @dev.serialised
    def slot_faces(self) -> cl.Buffer:
        """``uint32 (F, 3)`` faces in slot order on the device, made on first use."""
        if self._slot_faces is None:
            self._slot_faces = traverse.order_faces(self.tree, self.mesh)
            self._owned.append(self._slot_faces)
        return self._slot_faces

    @dev.serialised
    def slot_triangles(self) -> cl.Buffer:
        """``float32 (F, 3, 3)`` each slot's triangle's corners on the device
        (:func:`lbvh.queries.traverse.order_triangles`), made on first use; a refit,
        which moves the vertices, renews it."""
        if self._slot_triangles is None:
            self._slot_triangles = traverse.order_triangles(self.tree, self.mesh)
            self._owned.append(self._slot_triangles)
        return self._slot_triangles

    @dev.serialised
    def winding_moments(self) -> cl.Buffer:
        """The moments of the winding numbers on the device, made on first use
        (:func:`lbvh.queries.winding_moments.make_moments`) for the walk that
        :func:`lbvh.queries.closest.walk_of` picks: per wide record where the records
        are packed, else per node; a refit, or records of another width, renew them."""
        wide = self.wide_records()
        if self._moments is None or self._moments[0] is not wide:
            self._drop_moments()
            buf = make_moments(self.ctx, self.tree, self.mesh, wide, winding.DEFAULT_ORDER)
            self._moments = (wide, buf)
            self._owned.append(buf)
        return self._moments[1]

    @dev.serialised
    def winding_target(self) -> "QueryData":
        """The query data the winding-number walk runs on: for an LBVH tree without
        treelet rounds (:func:`lbvh.queries.winding.walks_a_copy`) that of a copy of the
        tree after :data:`~lbvh.queries.winding.WINDING_TREELET_ROUNDS` rounds of treelet
        restructuring, over the same mesh, made on first use, refitted with this one and
        walked through records of this one's width; otherwise this object itself."""
        if not winding.walks_a_copy(self.tree.builder) or self.mesh.num_prims < 3:
            return self
        if self._winding is None:
            copy = restructured(self.tree, winding.WINDING_TREELET_ROUNDS,
                                winding.WINDING_TREELET_LEAVES)
            self._winding = QueryData(self.mesh, copy, owns_tree=True)
        if self._wide is not None:
            self._winding.wide_records(width=self._wide.width)
        return self._winding

    @dev.serialised
    def traversal_depth(self) -> int:
        """The tree's depth, 0 for a root leaf (its topology never changes)."""
        if self._depth is None:
            tree = self.tree
            if tree.num_nodes > 1:
                parent = dev.from_device(self.ctx, tree.parent, np.int32, (tree.num_nodes,))
                self._depth = int(node_depths(parent, tree.root).max())
            else:
                self._depth = 0
        return self._depth

    @dev.serialised
    def refit(self, mesh: Mesh) -> None:
        """The tree's boxes were refitted to ``mesh`` (the same faces over moved
        vertices): renew what was made of the old boxes and vertices (the wide
        records' boxes now, the moments and the slots' corners on their next use) and
        refit the winding walk's copy to ``mesh`` too."""
        self.mesh = mesh
        self._drop_moments()
        self._drop_slot_triangles()
        if self._wide is not None:
            write_records(self.tree, self._wide)
        copy = self._winding
        if copy is not None:
            refit_boxes(mesh, copy.tree)
            copy.refit(mesh)

    # -- giving back one cache's buffers ----------------------------------------------
    def _drop_wide(self) -> None:
        wide, self._wide = self._wide, None
        if wide is not None:
            gone = {id(b) for b in wide_buffers(wide)}
            self._owned[:] = [b for b in self._owned if id(b) not in gone]
            release_wide(self.ctx.memory, wide)

    def _drop_slot_triangles(self) -> None:
        held, self._slot_triangles = self._slot_triangles, None
        if held is not None:
            self._free(held)

    def _drop_moments(self) -> None:
        held, self._moments = self._moments, None
        if held is not None:
            self._free(held[1])

    def _free(self, buf: cl.Buffer) -> None:
        """Give back one cache's buffer now (no longer dropped with this object)."""
        self._owned[:] = [b for b in self._owned if b is not buf]
        self.ctx.memory.free(buf)
