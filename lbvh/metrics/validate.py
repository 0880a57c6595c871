"""Host-side checker of a BVH in the project's layout (docs/pages/layout.md).

It reads only the public arrays, so it checks any builder's tree the same way,
and raises :class:`BVHValidationError` with the first violation it finds.
"""
from __future__ import annotations

import numpy as np

from ..layout import children_of, is_leaf, prim_range_of


def triangle_boxes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``float32 (F, 3)`` min and max corners of each triangle (exact). The validator
    takes the boxes itself, not from the builders' bounds stage it checks."""
    tri = vertices[faces]
    return tri.min(axis=1), tri.max(axis=1)


class BVHValidationError(ValueError):
    """A BVH broke one of the invariants of docs/pages/layout.md."""


def _fail(msg: str) -> None:
    raise BVHValidationError(f"invalid BVH: {msg}")


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def validate_tree(nodes: np.ndarray, parent: np.ndarray, prim_order: np.ndarray, root: int,
                  vertices: np.ndarray, faces: np.ndarray, clipped_leaves: bool = False) -> None:
    """Check every invariant of docs/pages/layout.md; raise on the first violation.

    ``clipped_leaves``: a tree with spatial splits (``builder="sbvh"``): a triangle may
    have several slots (at least one), and a leaf's box holds the parts of its
    triangles: it must meet each one's box, and every triangle's corners, edge
    midpoints and centre must lie in the box of some leaf that holds it.
    """
    num_nodes = len(nodes)
    num_tris = len(faces)
    num_prims = len(prim_order) if clipped_leaves else num_tris
    if num_nodes == 0:
        _fail("no nodes")
    if not 0 <= root < num_nodes:
        _fail(f"root {root} outside [0, {num_nodes})")
    if parent.shape != (num_nodes,):
        _fail(f"parent has shape {parent.shape}, expected ({num_nodes},)")
    leaf = is_leaf(nodes)
    children = children_of(nodes)
    internal = np.flatnonzero(~leaf)
    num_leaves = int(leaf.sum())

    # 1. binary tree with leaves - 1 internal nodes
    if len(internal) != num_leaves - 1:
        _fail(f"{len(internal)} internal nodes for {num_leaves} leaves (expected {num_leaves - 1})")
    kids = children[internal]
    bad = (kids < 0) | (kids >= num_nodes)
    if bad.any():
        i = _first(bad.any(axis=1))
        _fail(f"internal node {internal[i]} has child index {kids[i].tolist()} outside [0, {num_nodes})")

    # 2. parent links, one parent per node, everything reachable from the root
    if parent[root] != -1:
        _fail(f"root {root} has parent {parent[root]} (expected -1)")
    times_child = np.bincount(kids.ravel(), minlength=num_nodes)
    if times_child[root]:
        _fail(f"root {root} is the child of another node")
    twice = times_child > 1
    if twice.any():
        _fail(f"node {_first(twice)} is the child of {times_child[_first(twice)]} nodes")
    orphan = times_child == 0
    orphan[root] = False
    if orphan.any():
        _fail(f"node {_first(orphan)} is nobody's child (tree not connected)")
    for side in (0, 1):
        wrong = parent[kids[:, side]] != internal
        if wrong.any():
            i = _first(wrong)
            c = kids[i, side]
            _fail(f"node {c} has parent {parent[c]}, but it is a child of {internal[i]}")
    seen = np.zeros(num_nodes, bool)
    frontier = np.array([root])
    for _ in range(num_nodes + 1):
        if len(frontier) == 0:
            break
        if seen[frontier].any():
            _fail(f"node {frontier[seen[frontier]][0]} is reached twice (cycle)")
        seen[frontier] = True
        frontier = children[frontier][~leaf[frontier]].ravel()
    if not seen.all():
        _fail(f"node {_first(~seen)} is not reachable from the root (cycle)")

    # 3. primitives: a permutation, tiled exactly by the leaves' ranges
    if prim_order.shape != (num_prims,):
        _fail(f"prim_order has shape {prim_order.shape}, expected ({num_prims},)")
    if num_prims and (prim_order.min() < 0 or prim_order.max() >= num_tris):
        _fail(f"prim_order holds indices outside [0, {num_tris})")
    hits = np.bincount(prim_order.astype(np.int64), minlength=num_tris)
    wrong_count = hits < 1 if clipped_leaves else hits != 1
    if wrong_count.any():
        t = _first(wrong_count)
        _fail(f"triangle {t} appears {hits[t]} times in prim_order")
    ranges = prim_range_of(nodes)[leaf]
    leaf_ids = np.flatnonzero(leaf)
    if (ranges[:, 1] < 1).any():
        _fail(f"leaf {leaf_ids[_first(ranges[:, 1] < 1)]} has no primitive")
    order = np.argsort(ranges[:, 0], kind="stable")
    starts = ranges[order, 0].astype(np.int64)
    ends = starts + ranges[order, 1]
    expected_starts = np.concatenate([[0], ends[:-1]])
    if (starts != expected_starts).any() or ends[-1] != num_prims:
        i = _first(starts != expected_starts) if (starts != expected_starts).any() else len(order) - 1
        _fail(f"leaf {leaf_ids[order[i]]} covers slots [{starts[i]}, {ends[i]}), "
              f"leaves must tile [0, {num_prims}) exactly")

    # 4. boxes: finite, ordered, nested, and leaves exact
    lo, hi = nodes["lower"], nodes["upper"]
    nonfinite = ~(np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1))
    if nonfinite.any():
        _fail(f"node {_first(nonfinite)} has a non-finite box")
    inverted = (lo > hi).any(axis=1)
    if inverted.any():
        _fail(f"node {_first(inverted)} has lower > upper")
    for side, name in ((0, "left"), (1, "right")):
        c = kids[:, side]
        outside = (lo[c] < lo[internal]).any(axis=1) | (hi[c] > hi[internal]).any(axis=1)
        if outside.any():
            i = _first(outside)
            _fail(f"node {internal[i]} box does not contain its {name} child {c[i]}")
    tlo, thi = triangle_boxes(vertices, faces)
    if clipped_leaves:
        _check_clipped_leaves(nodes, prim_order, leaf_ids, ranges, vertices, faces, tlo, thi)
        return
    slot_lo, slot_hi = tlo[prim_order], thi[prim_order]
    first = ranges[:, 0]
    leaf_lo = np.minimum.reduceat(slot_lo, first[order], axis=0)
    leaf_hi = np.maximum.reduceat(slot_hi, first[order], axis=0)
    ids = leaf_ids[order]
    wrong = (leaf_lo != lo[ids]).any(axis=1) | (leaf_hi != hi[ids]).any(axis=1)
    if wrong.any():
        i = _first(wrong)
        _fail(f"leaf {ids[i]} box {lo[ids[i]].tolist()}..{hi[ids[i]].tolist()} is not the exact "
              f"box of its triangles {leaf_lo[i].tolist()}..{leaf_hi[i].tolist()}")


def _check_clipped_leaves(nodes: np.ndarray, prim_order: np.ndarray, leaf_ids: np.ndarray,
                          ranges: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                          tlo: np.ndarray, thi: np.ndarray) -> None:
    """The leaves of a tree with spatial splits: each slot's leaf box meets its triangle's
    box, and each triangle's seven sample points lie in the box of one of its leaves."""
    counts = ranges[:, 1].astype(np.int64)
    leaf_of_slot = np.empty(len(prim_order), np.int64)
    leaf_of_slot[np.repeat(ranges[:, 0].astype(np.int64), counts) + _within(counts)] = \
        np.repeat(leaf_ids, counts)
    lo, hi = nodes["lower"][leaf_of_slot], nodes["upper"][leaf_of_slot]
    t = prim_order.astype(np.int64)
    apart = ((lo > thi[t]) | (hi < tlo[t])).any(axis=1)
    if apart.any():
        s = _first(apart)
        _fail(f"leaf {leaf_of_slot[s]} holds triangle {t[s]} but its box does not meet the "
              "triangle's")
    p = vertices.astype(np.float64)[faces.astype(np.int64)]
    samples = np.concatenate([p, 0.5 * (p + p[:, [1, 2, 0]]), p.mean(axis=1, keepdims=True)],
                             axis=1)                                  # (F, 7, 3)
    inside = ((samples[t] >= lo[:, None].astype(np.float64)) &
              (samples[t] <= hi[:, None].astype(np.float64))).all(axis=2)   # (R, 7)
    covered = np.zeros((len(faces), 7), bool)
    np.logical_or.at(covered, t, inside)
    missing = ~covered.all(axis=1)
    if missing.any():
        i = _first(missing)
        _fail(f"triangle {i} has a point in no box of the leaves that hold it")


def _within(counts: np.ndarray) -> np.ndarray:
    """Offsets 0, 1, ... inside each leaf's range, leaf by leaf."""
    return np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
