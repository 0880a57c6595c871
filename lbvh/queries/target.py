"""What a query needs of the tree it runs on: the interface the query modules see
(they never import the facade, which imports them). :class:`lbvh.queries.data.QueryData`
is the one implementation; :class:`lbvh.BVH` holds one (``bvh.query_data``) and gives
it to every query."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import pyopencl as cl

from ..device import Context
from ..tree import Mesh, Tree

if TYPE_CHECKING:
    from .wide import Wide


class QueryTarget(Protocol):
    """A tree with its mesh and its query data (:class:`lbvh.queries.data.QueryData`)."""
    ctx: Context
    tree: Tree
    mesh: Mesh

    def wide_records(self, width: int | None = None, max_bytes: int | None = None) -> "Wide":
        """The tree's wide records (:func:`lbvh.queries.wide.make_wide`), cached."""

    def slot_faces(self) -> cl.Buffer:
        """The faces in slot order (:func:`lbvh.queries.traverse.order_faces`), cached."""

    def slot_triangles(self) -> cl.Buffer:
        """The triangles' corners in slot order
        (:func:`lbvh.queries.traverse.order_triangles`), cached until a refit."""

    def traversal_depth(self) -> int:
        """The tree's depth (0 for a root leaf), cached."""

    def winding_target(self) -> "QueryTarget":
        """The target the winding-number walk runs on (:mod:`lbvh.queries.winding`):
        itself, or the query data of a restructured copy of its tree over the same
        mesh, cached."""

    def winding_moments(self) -> cl.Buffer:
        """The moments of the winding numbers (:func:`lbvh.queries.winding_moments.make_moments`),
        cached."""


def query_target(target: Any) -> QueryTarget:
    """What a query runs on: an :class:`lbvh.BVH`'s query data (``bvh.query_data``), or
    a query target as it is (the query modules' functions take either)."""
    return getattr(target, "query_data", target)
