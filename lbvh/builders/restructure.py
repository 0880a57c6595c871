"""Treelet restructuring on the device (kernels/restructure.cl): better trees from the LBVH.

Karras & Aila 2013 rebuild every small subtree (a *treelet* of up to seven
leaves) with the topology of least SAH cost, bottom-up, in place. The Karras
2012 tree splits at Morton-code boundaries, which ignores the triangles'
sizes; a round of restructuring takes most of the gap to a full SAH build
(bench/bench_builders.py measures it) for a fraction of the build time.

Works on any tree in the project's layout: only internal nodes change
(children, boxes, parent links); leaves, slots and ``prim_order`` stay, so the
root stays where it was and the tree still validates. Subtrees stop being
contiguous runs of slots, which the leaf collapse takes into account.

:func:`restructure_python` is the serial twin: the same treelets in post
order, the same float32 operations, bit for bit.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pyopencl as cl

from ..device import Scope, run
from ..tree import Tree
from ..layout import NODE_DTYPE
from ..metrics.cost import C_NODE, C_TRI, box_scale, scaled_half_area
from .refit import clear_arrivals

KERNEL_FILE = "restructure.cl"
#: Leaves per treelet by default (Karras & Aila 2013 use 7; 2**7 subsets fit in
#: private memory). Fewer leaves cost far less (the search over partitions grows as
#: 3**leaves) for a smaller gain per round: measured in bench/bench_traverse.py.
TREELET_LEAVES = 7
#: The sizes a treelet may have: below 3 leaves there is one topology only.
TREELET_SIZES = range(3, TREELET_LEAVES + 1)
#: After the first round, only subtrees of at least this many leaves (doubled in
#: each further round) are rebuilt (:func:`round_min_leaves`).
TREELET_MIN_LEAVES = 14


def restructure_treelets(tree: Tree, scratch: tuple[cl.Buffer, cl.Buffer, cl.Buffer],
                         rounds: int, *, c_node: float = C_NODE, c_tri: float = C_TRI,
                         leaves: int = TREELET_LEAVES,
                         min_leaves: int = TREELET_MIN_LEAVES) -> list[cl.Event]:
    """``rounds`` bottom-up restructuring passes over ``tree``, whose boxes are final.

    ``scratch`` is ``cost`` (``float32`` per node), ``arrivals`` and ``sizes``
    (``int32`` per node). The leaves are the tree's (:meth:`lbvh.tree.Tree.leaf_walks`);
    ``leaves``: leaves per treelet (:data:`TREELET_SIZES`); ``min_leaves``: see
    :func:`round_min_leaves`.
    """
    ctx, nodes, parent, num_nodes, root = tree.ctx, tree.nodes, tree.parent, tree.num_nodes, tree.root
    cost, arrivals, sizes = scratch
    leaf_nodes, leaf_first, num_leaves = tree.leaf_walks()
    events = []
    launch = ctx.walk_launch(num_leaves, min_per_item=256)
    use_list = leaf_nodes is not None
    for r in range(rounds):
        events.append(clear_arrivals(ctx, arrivals, num_nodes))
        events.append(run(ctx, KERNEL_FILE, "restructure_treelets", launch, nodes, parent, cost,
                          arrivals, sizes, leaf_nodes if use_list else arrivals, use_list,
                          leaf_first, num_leaves, launch.per_item, root, np.float32(c_node),
                          np.float32(c_tri), np.int32(round_min_leaves(r, min_leaves)),
                          defines={"TREELET_LEAVES": check_treelet_leaves(leaves)}))
    return events


def round_min_leaves(r: int, min_leaves: int = TREELET_MIN_LEAVES) -> int:
    """The smallest subtree (in BVH leaves) whose root round ``r`` (from 0) rebuilds
    as a treelet: every node in the first round, ``min_leaves * 2**(r - 1)`` in
    round ``r >= 1`` (0: every node in every round). A later round's gain is in the
    upper levels: the lower ones were rebuilt by the first round."""
    if r == 0 or min_leaves == 0:
        return 0
    return min(min_leaves << (r - 1), 1 << 30)


def restructure(tree: Tree, rounds: int, mem: Scope, c_node: float = C_NODE,
                c_tri: float = C_TRI, leaves: int = TREELET_LEAVES,
                min_leaves: int = TREELET_MIN_LEAVES) -> tuple[Tree, list[cl.Event]]:
    """The optimiser: ``rounds`` of treelet restructuring of ``tree`` in place (its
    boxes final), with treelets of ``leaves`` leaves; returns the tree, renamed
    ``<builder>+treelets<rounds>`` (``+treelets<rounds>-<leaves>`` for another size
    than :data:`TREELET_LEAVES`), and the events. Scratch comes from ``mem``."""
    if not rounds:
        return tree, []
    cost = mem.alloc(4 * tree.num_nodes, scratch=True)
    arrivals = mem.alloc(4 * tree.num_nodes, scratch=True)
    sizes = mem.alloc(4 * tree.num_nodes, scratch=True)
    events = restructure_treelets(tree, (cost, arrivals, sizes), rounds, c_node=c_node,
                                  c_tri=c_tri, leaves=leaves, min_leaves=min_leaves)
    mem.free(cost, arrivals, sizes)
    size = "" if leaves == TREELET_LEAVES else f"-{leaves}"
    return dataclasses.replace(tree, builder=f"{tree.builder}+treelets{rounds}{size}"), events


def restructured(tree: Tree, rounds: int, leaves: int = TREELET_LEAVES,
                 min_leaves: int = TREELET_MIN_LEAVES) -> Tree:
    """The optimiser on a copy: a new tree (new buffers: nodes, parent, slots, leaf list)
    after ``rounds`` of :func:`restructure`; ``tree`` is not modified. The caller holds
    ``ctx.lock`` and owns the buffers of the tree returned (``Tree.buffers``)."""
    ctx, memory = tree.ctx, tree.ctx.memory
    copies: list[cl.Buffer] = []
    try:
        for buf in tree.buffers():
            copies.append(memory.alloc(buf.size))
            cl.enqueue_copy(ctx.queue, copies[-1], buf)
        copy = dataclasses.replace(
            tree, nodes=copies[0], parent=copies[1], prim_order=copies[2],
            leaf_nodes_buf=copies[3] if tree.leaf_nodes_buf is not None else None, report=None)
        with memory.scope() as mem:
            copy, _ = restructure(copy, rounds, mem, leaves=leaves, min_leaves=min_leaves)
            mem.close()
        ctx.queue.finish()
    except BaseException:
        memory.free(*copies)
        raise
    return copy


def check_rounds(rounds: object) -> int:
    """The number of restructuring rounds as an int >= 0, or a ValueError naming it."""
    if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 0:
        raise ValueError(f"treelet_rounds: {rounds!r}; expected an integer >= 0")
    return int(rounds)


def check_treelet_leaves(leaves: object) -> int:
    """The leaves per treelet as an int in :data:`TREELET_SIZES`, or a ValueError naming it."""
    if isinstance(leaves, bool) or not isinstance(leaves, (int, np.integer)) \
            or leaves not in TREELET_SIZES:
        raise ValueError(f"treelet_leaves: {leaves!r}; expected an integer from "
                         f"{TREELET_SIZES[0]} to {TREELET_SIZES[-1]}")
    return int(leaves)


def check_min_leaves(min_leaves: object) -> int:
    """``treelet_min_leaves`` as an int >= 0, or a ValueError naming it."""
    if isinstance(min_leaves, bool) or not isinstance(min_leaves, (int, np.integer)) \
            or not 0 <= min_leaves <= 1 << 30:
        raise ValueError(f"treelet_min_leaves: {min_leaves!r}; expected an integer from 0 to 2**30")
    return int(min_leaves)


# -- pure Python twin ---------------------------------------------------------------

class _Treelets:
    """Serial restructuring of one tree held in host arrays (modified in place)."""

    def __init__(self, nodes: np.ndarray, parent: np.ndarray, root: int,
                 c_node: float, c_tri: float, leaves: int = TREELET_LEAVES) -> None:
        self.nodes, self.parent = nodes, parent
        self.leaves = check_treelet_leaves(leaves)
        self.lo, self.hi = nodes["lower"], nodes["upper"]
        self.scale = box_scale(self.lo[root], self.hi[root])[0]
        self.c_node = np.float32(c_node)
        self.cost = np.zeros(len(nodes), np.float32)
        leaves = np.flatnonzero(nodes["b"] < 0)
        with np.errstate(over="ignore", under="ignore"):
            for x in leaves:
                count = np.float32(-nodes["b"][x])
                self.cost[x] = np.float32(c_tri) * count * self.area(self.lo[x], self.hi[x])

    def area(self, lo: np.ndarray, hi: np.ndarray) -> np.float32:
        return scaled_half_area(lo, hi, self.scale)

    def is_internal(self, x: int) -> bool:
        return self.nodes["b"][x] >= 0

    def children(self, x: int) -> tuple[int, int]:
        return int(self.nodes["a"][x]), int(self.nodes["b"][x])

    def form(self, root: int) -> tuple[list[int], list[int]]:
        """Section 4.1: the treelet's leaves and internal nodes (root first)."""
        leaf = list(self.children(root))
        area = [self.area(self.lo[x], self.hi[x]) for x in leaf]
        inner = [root]
        while len(leaf) < self.leaves:
            grow = -1
            for i, x in enumerate(leaf):
                if self.is_internal(x) and (grow < 0 or area[i] > area[grow]):
                    grow = i
            if grow < 0:
                break
            x = leaf[grow]
            inner.append(x)
            left, right = self.children(x)
            leaf[grow], area[grow] = left, self.area(self.lo[left], self.hi[left])
            leaf.append(right)
            area.append(self.area(self.lo[right], self.hi[right]))
        return leaf, inner

    def restructure(self, root: int) -> None:
        leaf, inner = self.form(root)
        full = (1 << len(leaf)) - 1
        sub_lo, sub_hi = [None] * (full + 1), [None] * (full + 1)
        sub_cost = [np.float32(0)] * (full + 1)
        split = [0] * (full + 1)
        for s in range(1, full + 1):
            low = s & -s
            rest = s ^ low
            if rest == 0:
                x = leaf[low.bit_length() - 1]
                sub_lo[s], sub_hi[s], sub_cost[s] = self.lo[x], self.hi[x], self.cost[x]
                continue
            sub_lo[s] = np.minimum(sub_lo[rest], sub_lo[low])
            sub_hi[s] = np.maximum(sub_hi[rest], sub_hi[low])
            best, best_p, p = np.float32(np.inf), rest, 0
            while True:
                p = (p - rest) & rest
                c = sub_cost[s ^ p] + sub_cost[p]
                if c < best:
                    best, best_p = c, p
                if p == rest:
                    break
            split[s] = best_p
            sub_cost[s] = self.c_node * self.area(sub_lo[s], sub_hi[s]) + best
        stack, next_inner = [(full, root)], 1
        while stack:
            s, node = stack.pop()
            kids = []
            for part in (s ^ split[s], split[s]):
                if part & (part - 1) == 0:
                    kid = leaf[part.bit_length() - 1]
                else:
                    kid = inner[next_inner]
                    next_inner += 1
                    stack.append((part, kid))
                self.parent[kid] = node
                kids.append(kid)
            self.lo[node], self.hi[node] = sub_lo[s], sub_hi[s]
            self.nodes["a"][node], self.nodes["b"][node] = kids
            self.cost[node] = sub_cost[s]

    def cost_only(self, x: int) -> None:
        """Kernel cost_only: x's cost from its children's, as a two-leaf treelet's."""
        a, b = self.children(x)
        below = self.cost[a] + self.cost[b]
        self.cost[x] = self.c_node * self.area(self.lo[x], self.hi[x]) + below

    def run(self, root: int, min_leaves: int = 0) -> None:
        """One round: every internal node after both of its subtrees (post order);
        those with fewer than ``min_leaves`` leaves below only get their cost."""
        order, stack = [], [(root, False)]
        while stack:
            x, children_done = stack.pop()
            if not self.is_internal(x):
                continue
            if children_done:
                order.append(x)
                continue
            stack.append((x, True))
            left, right = self.children(x)
            stack += [(right, False), (left, False)]
        size = {}
        with np.errstate(over="ignore", under="ignore"):
            for x in order:
                a, b = self.children(x)
                size[x] = size.get(a, 1) + size.get(b, 1)
                if size[x] >= min_leaves:
                    self.restructure(x)
                else:
                    self.cost_only(x)


def restructure_python(nodes: np.ndarray, parent: np.ndarray, root: int, rounds: int = 1,
                       c_node: float = C_NODE, c_tri: float = C_TRI,
                       leaves: int = TREELET_LEAVES,
                       min_leaves: int = TREELET_MIN_LEAVES) -> tuple[np.ndarray, np.ndarray]:
    """Serial twin of :func:`restructure_treelets` on host copies of a tree with final boxes,
    treelets of ``leaves`` leaves, rounds as :func:`round_min_leaves` says.

    Returns new ``nodes`` (:data:`NODE_DTYPE`) and ``parent`` (``int32``); the
    inputs are not modified.
    """
    nodes = np.array(nodes, dtype=NODE_DTYPE, copy=True)
    parent = np.array(parent, dtype=np.int32, copy=True)
    work = _Treelets(nodes, parent, root, c_node, c_tri, leaves)
    for r in range(rounds):
        work.run(root, round_min_leaves(r, min_leaves))
    return work.nodes, work.parent
