"""Quality of a BVH in the project's layout (docs/pages/layout.md), whoever built it.

SAH cost (MacDonald & Booth 1990; Goldsmith & Salmon 1987), normalised by the
root's surface area so that trees of different scenes compare::

    cost = ( sum over internal nodes n of  C_node * A(n)
           + sum over leaves l         of  C_tri * count(l) * A(l) ) / A(root)

``A`` is the surface area of a node's box, computed in float64 (float32 areas
overflow for scenes near 1e19). The defaults ``C_node = C_tri = 1`` count one
box test and one triangle test as equally expensive. A tree whose root box has
no area (all triangles on one line or at one point) has every ratio taken as 1:
any ray that reaches the root reaches every node.

EPO, end-point overlap (Aila, Karras & Laine 2013, "On quality metrics of
bounding volume hierarchies", HPG): the part of the scene's surface that lies
inside boxes of nodes *not* holding it, weighted by the same constants::

    EPO = sum over nodes n of c(n) * sum over triangles t not below n of A(t ∩ box(n))
          / sum over triangles of A(t)

with ``c(n) = C_node`` for internal nodes and ``C_tri * count`` for leaves.
Here it is estimated by sampling: points drawn uniformly on the scene's
surface (area-weighted triangle, uniform barycentrics), each counting the
nodes whose closed box holds it although its triangle is not below them. The
mean is unbiased; its standard error is reported with it.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..layout import children_of, is_leaf, node_depths, parents_of, prim_range_of
from .cost import C_NODE, C_TRI, box_area
from ..report import tree_statistics

EPO_SAMPLES = 1 << 15
EPO_SEED = 2013


def _tree_arrays(tree: Any, root: int | None) -> tuple[np.ndarray, int]:
    """``(nodes, root)`` of a BVH, or of a node array with an optional root (default 0)."""
    if hasattr(tree, "nodes") and hasattr(tree, "root"):
        return tree.nodes, int(tree.root if root is None else root)
    nodes = np.asarray(tree)
    if nodes.dtype.names is None or not {"lower", "upper", "a", "b"} <= set(nodes.dtype.names):
        raise ValueError(f"tree: expected an lbvh.BVH or a node array of NODE_DTYPE, got {nodes.dtype}")
    return nodes, 0 if root is None else int(root)


def sah_cost(tree: Any, c_node: float = C_NODE, c_tri: float = C_TRI, *, root: int | None = None) -> float:
    """SAH cost of a tree, normalised by the root's area (formula in the module docstring).

    Args:
        tree: an :class:`lbvh.BVH`, or a node array of ``NODE_DTYPE`` (every
            record a node of the tree; ``root`` defaults to 0).
        c_node: cost of visiting an internal node (one box test), default 1.
        c_tri: cost of one ray-triangle test, default 1.

    Returns:
        The cost as a Python float; a tree of one leaf over F triangles costs ``c_tri * F``.
    """
    nodes, root = _tree_arrays(tree, root)
    area = box_area(nodes["lower"], nodes["upper"])
    leaf = is_leaf(nodes)
    weight = np.where(leaf, c_tri * prim_range_of(nodes)[:, 1].astype(np.float64), c_node)
    root_area = area[root]
    if root_area > 0:
        return float(np.sum(weight * area) / root_area)
    return float(np.sum(weight))


def memory_bytes(num_nodes: int, num_prims: int) -> int:
    """Device bytes of a tree: 32-byte nodes, int32 parent links and int32 prim_order."""
    return 32 * num_nodes + 4 * num_nodes + 4 * num_prims


def _preorder(nodes: np.ndarray, parent: np.ndarray, root: int) -> tuple[np.ndarray, np.ndarray]:
    """Pre-order number of each node and the size of its subtree, level by level.

    Node ``m`` lies below ``n`` (or is ``n``) exactly when
    ``pre[n] <= pre[m] < pre[n] + size[n]``.
    """
    children = children_of(nodes)
    leaf = is_leaf(nodes)
    depth = node_depths(parent, root)
    internal = np.flatnonzero(~leaf)
    levels = [internal[depth[internal] == d] for d in range(int(depth.max()) + 1)]
    size = np.ones(len(nodes), np.int64)
    for at in reversed(levels):
        size[at] = 1 + size[children[at, 0]] + size[children[at, 1]]
    pre = np.zeros(len(nodes), np.int64)
    for at in levels:
        left, right = children[at, 0], children[at, 1]
        pre[left] = pre[at] + 1
        pre[right] = pre[at] + 1 + size[left]
    return pre, size


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """Points uniform on the surface (float64) and the triangle of each; None if no area."""
    tri = vertices[faces].astype(np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    total = area.sum()
    if not total > 0:
        return None
    t = rng.choice(len(faces), size=count, p=area / total)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1  # fold the square onto the triangle: uniform barycentrics
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    points = tri[t, 0] + u[:, None] * e1[t] + v[:, None] * e2[t]
    return points, t


def epo_estimate(bvh: Any, c_node: float = C_NODE, c_tri: float = C_TRI, samples: int = EPO_SAMPLES,
                 seed: int = EPO_SEED) -> tuple[float, float]:
    """Sampled EPO of a BVH (module docstring) and its standard error.

    Each sample point descends the tree through every node whose closed box
    holds it; a node counts when the point's triangle is not below it. Cost
    grows with ``samples`` times the number of boxes a point lies in.
    Returns ``(epo, standard_error)``; ``(0.0, 0.0)`` for a scene without area.
    """
    nodes, root = bvh.nodes, int(bvh.root)
    drawn = _surface_samples(bvh.vertices, bvh.faces, int(samples), np.random.default_rng(seed))
    if drawn is None:
        return 0.0, 0.0
    points, tri = drawn
    parent = parents_of(nodes, root)
    pre, size = _preorder(nodes, parent, root)
    leaf = is_leaf(nodes)
    children = children_of(nodes)
    weight = np.where(leaf, c_tri * prim_range_of(nodes)[:, 1].astype(np.float64), c_node)
    # the leaf holding each triangle, through the slots of prim_order
    leaves = np.flatnonzero(leaf)
    ranges = prim_range_of(nodes)[leaves]
    by_first = np.argsort(ranges[:, 0], kind="stable")  # leaves tile the slots in this order
    slot_leaf = np.repeat(leaves[by_first], ranges[by_first, 1])
    owner = np.empty(len(bvh.faces), np.int64)
    owner[bvh.prim_order] = slot_leaf
    own_pre = pre[owner[tri]]
    lower = nodes["lower"].astype(np.float64)
    upper = nodes["upper"].astype(np.float64)
    overlap = np.zeros(len(points))
    sample = np.arange(len(points))
    node = np.full(len(points), root)
    while len(sample):
        p = points[sample]
        inside = np.all((p >= lower[node]) & (p <= upper[node]), axis=1)
        sample, node = sample[inside], node[inside]
        not_below = (own_pre[sample] < pre[node]) | (own_pre[sample] >= pre[node] + size[node])
        np.add.at(overlap, sample[not_below], weight[node[not_below]])
        down = ~leaf[node]
        sample = np.repeat(sample[down], 2)
        node = children[node[down]].ravel()
    stderr = overlap.std(ddof=1) / np.sqrt(len(overlap)) if len(overlap) > 1 else 0.0
    return float(overlap.mean()), float(stderr)


def tree_quality(bvh: Any, c_node: float = C_NODE, c_tri: float = C_TRI, *, epo: bool = True,
                 epo_samples: int = EPO_SAMPLES) -> dict:
    """Quality figures of a BVH, as a JSON-ready dict.

    Keys: ``sah_cost`` (normalised, see :func:`sah_cost`), ``c_node``, ``c_tri``,
    ``num_nodes``, ``num_leaves``, ``depth``, ``mean_leaf_depth``,
    ``leaf_size_histogram`` (leaf size -> number of leaves), ``memory_bytes``
    (nodes + parent links + prim_order) and, with ``epo``, ``epo``,
    ``epo_stderr`` and ``epo_samples`` (see :func:`epo_estimate`).
    """
    stats = tree_statistics(bvh.nodes, bvh.tree.read("parent"), bvh.root)
    out = {"sah_cost": sah_cost(bvh, c_node, c_tri), "c_node": float(c_node), "c_tri": float(c_tri),
           **stats, "memory_bytes": memory_bytes(bvh.tree.num_nodes, bvh.tree.num_prims)}
    if epo:
        value, err = epo_estimate(bvh, c_node, c_tri, samples=epo_samples)
        out.update(epo=value, epo_stderr=err, epo_samples=int(epo_samples))
    return out
