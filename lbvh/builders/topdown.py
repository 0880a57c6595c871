"""The course's first two builders: top-down object splits at the median and at the midpoint.

Both are host references (numpy), built top down like the SAH reference
(:mod:`lbvh.builders.sah`), level by level over all open nodes at once; they
differ only in where a node is split:

``builder="median"`` (:func:`median_tree`)
    along the longest axis of the node's box, at the median of the
    primitives' centres: the first ``n // 2`` in centre order (ties by
    index) go left. A balanced tree, depth ``ceil(log2(F / leaf))``.
``builder="midpoint"`` (:func:`midpoint_tree`)
    along the longest axis of the box of the primitives' centres, at its
    middle: centres below the middle go left. Where every centre lies on one
    side (equal centres) the node is split at the median instead, so the
    build always ends.

A centre is ``lo * 0.5 + hi * 0.5`` of the triangle's box (float32, as the
LBVH and the SAH reference compute it); a node's box is the union of its
primitives' boxes. A node of at most ``max_leaf_size`` primitives is a leaf
(default 1, as the LBVH's leaves: the course's trees). Ties between axes of
equal extent go to the lower axis. Nodes are numbered level by level from
the root 0; leaves hold contiguous slots of ``prim_order``.
"""
from __future__ import annotations

import time
from typing import Literal

import numpy as np

from .. import device as dev
from ..layout import NODE_DTYPE, parents_of
from ..report import BuildReport
from ..tree import Mesh, Tree, upload_tree
from .bounds import triangle_boxes_numpy
from .options import SplitOptions

Rule = Literal["median", "midpoint"]
RULES = ("median", "midpoint")


def _segment_boxes(values_lo: np.ndarray, values_hi: np.ndarray, offsets: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Min of ``values_lo`` and max of ``values_hi`` over each segment starting at ``offsets``."""
    return (np.minimum.reduceat(values_lo, offsets, axis=0),
            np.maximum.reduceat(values_hi, offsets, axis=0))


def split_tree(lo: np.ndarray, hi: np.ndarray, rule: Rule, max_leaf_size: int = 1
               ) -> tuple[np.ndarray, np.ndarray]:
    """Build the tree of ``rule`` ("median" or "midpoint") over primitive boxes.

    Args:
        lo, hi: ``float32 (F, 3)`` primitive boxes, ``F >= 1``.
        max_leaf_size: nodes of at most this many primitives are leaves.

    Returns:
        ``nodes`` (``NODE_DTYPE``, root 0) and ``prim_order`` (``int32 (F,)``).
    """
    if rule not in RULES:
        raise ValueError(f"rule: {rule!r}; expected one of {', '.join(RULES)}")
    lo = np.ascontiguousarray(lo, np.float32)
    hi = np.ascontiguousarray(hi, np.float32)
    n = len(lo)
    half = np.float32(0.5)
    centre = lo * half + hi * half
    perm = np.arange(n, dtype=np.int64)
    nodes = np.zeros(max(2 * n - 1, 1), NODE_DTYPE)
    start, count, ids = np.array([0]), np.array([n]), np.array([0])
    next_id = 1
    while len(start):
        m = int(count.sum())
        offsets = np.cumsum(count) - count
        seg_of = np.repeat(np.arange(len(start)), count)
        pos = start[seg_of] + (np.arange(m) - offsets[seg_of])
        p = perm[pos]
        box_lo, box_hi = _segment_boxes(lo[p], hi[p], offsets)
        nodes["lower"][ids], nodes["upper"][ids] = box_lo, box_hi
        leaf = count <= max_leaf_size
        nodes["a"][ids[leaf]], nodes["b"][ids[leaf]] = start[leaf], -count[leaf]
        split = ~leaf
        if not split.any():
            break
        # the elements of the nodes to split, and each node's axis
        keep = split[seg_of]
        p, pos, seg = p[keep], pos[keep], seg_of[keep]
        start, count, ids = start[split], count[split], ids[split]
        seg = np.searchsorted(np.flatnonzero(split), seg)   # renumbered 0..S-1
        offsets = np.cumsum(count) - count
        c = centre[p].astype(np.float64)
        if rule == "median":
            extent = box_hi[split].astype(np.float64) - box_lo[split].astype(np.float64)
        else:
            c_lo, c_hi = _segment_boxes(c, c, offsets)
            extent = c_hi - c_lo
        axis = np.argmax(extent, axis=1)        # the first of equal extents
        key = c[np.arange(len(p)), axis[seg]]
        order = np.lexsort((p, key, seg))        # by node, then centre, then index
        k = count // 2
        if rule == "midpoint":
            middle = 0.5 * (c_lo[np.arange(len(start)), axis] + c_hi[np.arange(len(start)), axis])
            below = key < middle[seg]
            left = np.bincount(seg, weights=below, minlength=len(start)).astype(np.int64)
            ok = (left > 0) & (left < count)
            k = np.where(ok, left, k)
            # below the middle first (stable: centre order inside each side); the
            # nodes without a split by the middle keep the centre order: the median
            side = np.where(ok[seg], ~below, False)
            order = np.lexsort((p, key, side, seg))
        perm[pos] = p[order]
        left_ids = next_id + 2 * np.arange(len(start))
        next_id += 2 * len(start)
        nodes["a"][ids], nodes["b"][ids] = left_ids, left_ids + 1
        start = np.stack([start, start + k], axis=1).ravel()
        count = np.stack([k, count - k], axis=1).ravel()
        ids = np.stack([left_ids, left_ids + 1], axis=1).ravel()
    return nodes[:next_id], perm.astype(np.int32)


def median_tree(lo: np.ndarray, hi: np.ndarray, max_leaf_size: int = 1
                ) -> tuple[np.ndarray, np.ndarray]:
    """The median split tree (see the module docstring)."""
    return split_tree(lo, hi, "median", max_leaf_size)


def midpoint_tree(lo: np.ndarray, hi: np.ndarray, max_leaf_size: int = 1
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The midpoint split tree (see the module docstring)."""
    return split_tree(lo, hi, "midpoint", max_leaf_size)


def build_tree(ctx: dev.Context, mesh: Mesh, rule: Rule,
               options: SplitOptions = SplitOptions()) -> Tree:
    """Build the tree of ``rule`` on the host and upload it (``lbvh.build(builder=rule)``).

    ``mesh`` holds checked host arrays. The report's ``wall_seconds`` is the host
    build time, ``upload_seconds`` the upload. The caller holds ``ctx.lock``.
    """
    t0 = time.perf_counter()
    lo, hi = triangle_boxes_numpy(mesh.vertices, mesh.faces)
    nodes, prim_order = split_tree(lo, hi, rule, int(options.max_leaf_size))
    wall = time.perf_counter() - t0
    report = BuildReport(device=ctx.name, builder=rule, num_triangles=mesh.num_prims,
                         wall_seconds=wall, input_bytes=mesh.vertices.nbytes + mesh.faces.nbytes)
    t1 = time.perf_counter()
    tree = upload_tree(ctx, nodes, parents_of(nodes, 0), prim_order, 0, rule, report)
    ctx.queue.finish()
    report.upload_seconds = time.perf_counter() - t1
    return tree
