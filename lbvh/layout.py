"""The node record shared by every builder, the device and the host (docs/pages/layout.md)."""
from __future__ import annotations

import numpy as np

#: One node: 32 bytes, two float4 on the device.  A leaf has ``b < 0``.
NODE_DTYPE = np.dtype([("lower", "<f4", (3,)), ("a", "<i4"),
                       ("upper", "<f4", (3,)), ("b", "<i4")])
assert NODE_DTYPE.itemsize == 32


def make_nodes(lower: np.ndarray, upper: np.ndarray, children: np.ndarray,
               prim_range: np.ndarray) -> np.ndarray:
    """Pack per-node arrays into node records.

    ``children`` is ``int32 (N, 2)`` with ``-1`` for leaves; ``prim_range`` is
    ``(first, count)`` per node, used where the node is a leaf.
    """
    lower = np.asarray(lower, np.float32)
    n = len(lower)
    nodes = np.zeros(n, NODE_DTYPE)
    nodes["lower"] = lower
    nodes["upper"] = np.asarray(upper, np.float32)
    children = np.asarray(children, np.int64)
    prim_range = np.asarray(prim_range, np.int64)
    leaf = children[:, 0] < 0
    nodes["a"] = np.where(leaf, prim_range[:, 0], children[:, 0])
    nodes["b"] = np.where(leaf, -prim_range[:, 1], children[:, 1])
    return nodes


def is_leaf(nodes: np.ndarray) -> np.ndarray:
    return nodes["b"] < 0


def children_of(nodes: np.ndarray) -> np.ndarray:
    """``int32 (N, 2)``: left and right child, ``-1`` for leaves."""
    leaf = is_leaf(nodes)
    out = np.stack([nodes["a"], nodes["b"]], axis=1).astype(np.int32)
    out[leaf] = -1
    return out


def prim_range_of(nodes: np.ndarray) -> np.ndarray:
    """``int32 (N, 2)``: ``(first, count)`` for leaves, ``(0, 0)`` for internal nodes."""
    leaf = is_leaf(nodes)
    out = np.zeros((len(nodes), 2), np.int32)
    out[leaf, 0] = nodes["a"][leaf]
    out[leaf, 1] = -nodes["b"][leaf]
    return out


def parents_of(nodes: np.ndarray, root: int) -> np.ndarray:
    """Parent links derived from the child links (``-1`` for the root and unreferenced nodes)."""
    parent = np.full(len(nodes), -1, np.int32)
    ch = children_of(nodes)
    internal = np.nonzero(ch[:, 0] >= 0)[0].astype(np.int32)
    parent[ch[internal, 0]] = internal
    parent[ch[internal, 1]] = internal
    return parent


def node_depths(parent: np.ndarray, root: int) -> np.ndarray:
    """Depth of each node (root = 0) by pointer jumping over the parent links.

    Runs O(log depth) vectorised passes. Links that do not reach the root (a
    cycle) raise ``ValueError`` instead of looping forever.
    """
    n = len(parent)
    depth = np.where(np.arange(n) == root, 0, 1).astype(np.int64)
    up = parent.astype(np.int64).copy()
    up[root] = -1
    for _ in range(max(n, 2).bit_length() + 2):
        active = up >= 0
        if not active.any():
            return depth
        idx = np.nonzero(active)[0]
        depth[idx] += depth[up[idx]]
        nxt = up.copy()
        nxt[idx] = up[up[idx]]
        up = nxt
    raise ValueError(f"parent links of node {int(np.flatnonzero(up >= 0)[0])} never reach "
                     f"the root {root} (a cycle)")
