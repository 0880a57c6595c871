"""Leaf collapse on the device (kernels/collapse.cl): merge subtrees into leaves by the SAH.

The device LBVH has one triangle per leaf; testing a few triangles is often
cheaper than visiting the nodes above them. A bottom-up pass computes, for
every node, the cheaper of keeping its subtree and turning it into one leaf
(cost model in kernels/collapse.cl, the same SAH convention as
:mod:`lbvh.quality`), then a compaction drops the nodes below the new leaves.
Only a few scalars (the new node and leaf counts) and the new leaf list come
back to the host.

Works on any tree in the project's layout: a subtree becomes a leaf only when
its slots of ``prim_order`` are contiguous (always true for Karras trees and
for the SAH builder's trees) and it holds at most ``max_leaf_size`` triangles.
Kept nodes keep their relative order, so the root stays node 0 and the
Karras numbering's internal-nodes-first order survives (docs/pages/layout.md).

:func:`collapse_numpy` is the numpy twin of the decision and of the compacted
tree; with correctly rounded float32 division on the device (PoCL) both agree
bit for bit.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..tree import Tree
from ..layout import NODE_DTYPE, children_of, is_leaf, node_depths
from ..metrics.cost import C_NODE, C_TRI, MAX_LEAF_SIZE, box_scale, scaled_half_area
from .options import CollapseOptions
from .refit import clear_arrivals
from ..report import BuildReport

KERNEL_FILE = "collapse.cl"
_STATS_DTYPE = np.dtype([("first", "<i4"), ("end", "<i4"), ("count", "<i4"), ("cost", "<f4")])


def _decide(tree: Tree, options: CollapseOptions, scope: dev.Scope | None = None
            ) -> tuple[cl.Buffer, cl.Buffer, list[cl.Event]]:
    """Run collapse_costs: per-node stats (``_STATS_DTYPE``) and becomes_leaf (int32),
    scratch of ``scope`` (see :func:`collapse`)."""
    ctx, n, mem = tree.ctx, tree.num_nodes, tree.ctx.memory
    leaf_list, leaf_first, num_leaves = tree.leaf_walks()
    arrivals = mem.alloc(4 * n, scratch=True, scope=scope)
    stats = mem.alloc(_STATS_DTYPE.itemsize * n, scratch=True, scope=scope)
    becomes_leaf = mem.alloc(4 * n, scratch=True, scope=scope)
    fill = clear_arrivals(ctx, arrivals, n)
    launch = ctx.walk_launch(num_leaves, min_per_item=256)
    ev = dev.run(ctx, KERNEL_FILE, "collapse_costs", launch, tree.nodes, tree.parent, arrivals,
                 leaf_list if leaf_list is not None else arrivals, leaf_list is not None,
                 leaf_first, num_leaves, launch.per_item, float(options.c_node),
                 float(options.c_tri), int(options.max_leaf_size), stats, becomes_leaf)
    mem.free(arrivals)  # OpenCL frees it once the kernel is done
    return stats, becomes_leaf, [fill, ev]


def collapse_decisions(tree: Tree, options: CollapseOptions = CollapseOptions()
                       ) -> dict[str, np.ndarray]:
    """The device's per-node decision, read back (for checks and inspection).

    Returns ``first``, ``end``, ``count`` (``int32 (num_nodes,)``: the subtree's
    slot span and triangle count), ``cost`` (``float32``: C(n) per ray reaching
    the node) and ``becomes_leaf`` (``bool``: leaf in the collapsed tree if no
    ancestor is).
    """
    with tree.ctx.lock:
        stats, becomes_leaf, _ = _decide(tree, options)
        s = dev.from_device(tree.ctx, stats, _STATS_DTYPE, (tree.num_nodes,))
        flags = dev.from_device(tree.ctx, becomes_leaf, np.int32, (tree.num_nodes,))
        tree.ctx.memory.free(stats, becomes_leaf)
    return {"first": s["first"], "end": s["end"], "count": s["count"], "cost": s["cost"],
            "becomes_leaf": flags != 0}


def collapse(tree: Tree, options: CollapseOptions = CollapseOptions(),
             mem: dev.Scope | None = None) -> Tree:
    """The optimiser: a new tree whose leaves are the subtrees of ``tree`` that the SAH
    prefers as leaves; ``tree`` is not modified. The caller holds ``ctx.lock``.

    Returns a :class:`~lbvh.tree.Tree` over the same mesh, root 0, builder
    ``"<builder>+collapse"``; its report (the input's, or a new one) adds a
    ``collapse`` phase. ``mem``: the scope of the build it is part of; its
    peak becomes the report's ``peak_device_bytes``.

    Its scratch comes from and goes back to the memory's pool (kept there for the
    next build when ``mem`` is given: :meth:`lbvh.device.Scope.close`), and the new
    tree's buffers are pooled ones where the pool has them (a dropped tree's): a
    rebuild touches no fresh pages, whose faults took a tenth of the collapse's time.
    """
    ctx, n, memory = tree.ctx, tree.num_nodes, tree.ctx.memory
    t0 = time.perf_counter()
    stats, becomes_leaf, events = _decide(tree, options, mem)
    launch = ctx.launch(n, min_per_item=1024, gpu_per_item=max(1, -(-n // 4096)))
    chunks = launch.global_size
    flags = memory.alloc(8 * n, scratch=True, scope=mem)
    chunk_counts = memory.alloc(8 * (chunks + 1), scratch=True, scope=mem)
    events.append(dev.run(ctx, KERNEL_FILE, "mark_kept", launch, tree.parent, becomes_leaf, stats,
                          int(options.max_leaf_size), n, launch.per_item, flags, chunk_counts))
    events.append(dev.run(ctx, KERNEL_FILE, "scan_chunks", dev.Launch(1, 1, 1, None),
                          chunk_counts, chunks))
    totals = np.empty(2, np.int32)
    cl.enqueue_copy(ctx.queue, totals, chunk_counts, src_offset=8 * chunks, is_blocking=True)
    new_count, leaf_count = int(totals[0]), int(totals[1])
    new_index = memory.alloc(4 * n, scratch=True, scope=mem)
    leaf_list = memory.alloc(4 * leaf_count, pooled=True, scope=mem)
    events.append(dev.run(ctx, KERNEL_FILE, "assign_indices", launch, flags, chunk_counts, n,
                          launch.per_item, new_index, leaf_list))
    out_nodes = memory.alloc(NODE_DTYPE.itemsize * new_count, pooled=True, scope=mem)
    out_parent = memory.alloc(4 * new_count, pooled=True, scope=mem)
    events.append(dev.run(ctx, KERNEL_FILE, "emit_compacted", launch, tree.nodes, tree.parent,
                          flags, stats, new_index, n, launch.per_item, out_nodes, out_parent))
    prim_order = memory.alloc(4 * tree.num_prims, pooled=True, scope=mem)
    events.append(cl.enqueue_copy(ctx.queue, prim_order, tree.prim_order,
                                  byte_count=4 * tree.num_prims))
    root = np.empty(1, np.int32)
    cl.enqueue_copy(ctx.queue, root, new_index, src_offset=4 * tree.root, is_blocking=True)
    leaves = dev.from_device(ctx, leaf_list, np.int32, (leaf_count,))
    wall = time.perf_counter() - t0
    memory.free(stats, becomes_leaf, flags, chunk_counts, new_index)
    builder = f"{tree.builder}+collapse"
    report = _collapse_report(tree, builder, dev.event_seconds(events), wall, mem)
    return Tree(ctx, out_nodes, out_parent, prim_order, int(root[0]), new_count, tree.num_prims,
                builder, leaves, leaf_list, report)


def _collapse_report(tree: Tree, builder: str, device_seconds: float, wall: float,
                     mem: dev.Scope | None) -> BuildReport:
    """The input tree's report with the collapse added as one more phase."""
    old = tree.report or BuildReport(device=tree.ctx.name, builder=tree.builder,
                                     num_triangles=tree.num_prims)
    peak = max(old.peak_device_bytes, mem.peak) if mem is not None else old.peak_device_bytes
    return dataclasses.replace(old, builder=builder,
                               phase_seconds={**old.phase_seconds, "collapse": device_seconds},
                               device_seconds=old.device_seconds + device_seconds,
                               wall_seconds=old.wall_seconds + wall,
                               peak_device_bytes=peak, leaf_size_histogram={})


# -- numpy twin ---------------------------------------------------------------------

@dataclass
class CollapseResult:
    """What :func:`collapse_numpy` computes: the decision per old node and the new tree."""
    first: np.ndarray         #: int32 (N,) first slot of each subtree
    end: np.ndarray           #: int32 (N,) one past its last slot
    count: np.ndarray         #: int32 (N,) its triangle count
    cost: np.ndarray          #: float32 (N,) C(n)
    becomes_leaf: np.ndarray  #: bool (N,)
    nodes: np.ndarray         #: NODE_DTYPE (M,) the compacted tree
    parent: np.ndarray        #: int32 (M,)
    leaf_nodes: np.ndarray    #: int32 leaves of the compacted tree, ascending
    root: int


def collapse_numpy(nodes: np.ndarray, parent: np.ndarray, root: int, c_node: float = C_NODE,
                   c_tri: float = C_TRI, max_leaf_size: int = MAX_LEAF_SIZE) -> CollapseResult:
    """Numpy twin of :func:`collapse_leaves`: same float32 operations, level by level."""
    num = len(nodes)
    c_node32, c_tri32 = np.float32(c_node), np.float32(c_tri)
    leaf = is_leaf(nodes)
    children = children_of(nodes)
    lo, hi = nodes["lower"], nodes["upper"]
    first = np.where(leaf, nodes["a"], 0).astype(np.int32)
    count = np.where(leaf, -nodes["b"], 0).astype(np.int32)
    end = first + count
    cost = c_tri32 * count.astype(np.float32)
    becomes = leaf.copy()
    depth = node_depths(parent, root)
    internal = np.flatnonzero(~leaf)
    levels = [internal[depth[internal] == d] for d in range(int(depth.max()) + 1)]
    for at in reversed(levels):
        left, right = children[at, 0], children[at, 1]
        s = box_scale(lo[at], hi[at])
        an = scaled_half_area(lo[at], hi[at], s)
        has_area = an > 0
        safe = np.where(has_area, an, np.float32(1))
        rl = np.where(has_area, scaled_half_area(lo[left], hi[left], s) / safe, np.float32(1))
        rr = np.where(has_area, scaled_half_area(lo[right], hi[right], s) / safe, np.float32(1))
        first[at] = np.minimum(first[left], first[right])
        end[at] = np.maximum(end[left], end[right])
        count[at] = count[left] + count[right]
        subtree_cost = c_node32 + (rl * cost[left] + rr * cost[right])
        leaf_cost = c_tri32 * count[at].astype(np.float32)
        collapse = (count[at] <= max_leaf_size) & (end[at] - first[at] == count[at]) \
            & (leaf_cost <= subtree_cost)
        becomes[at] = collapse
        cost[at] = np.where(collapse, leaf_cost, subtree_cost)
    dropped = np.zeros(num, bool)
    for at in levels:
        below = dropped[at] | becomes[at]
        dropped[children[at, 0]] = below
        dropped[children[at, 1]] = below
    kept = ~dropped
    out_leaf = kept & becomes
    new_index = np.where(kept, np.cumsum(kept) - 1, -1).astype(np.int32)
    old = np.flatnonzero(kept)
    out = np.zeros(len(old), NODE_DTYPE)
    out["lower"], out["upper"] = lo[old], hi[old]
    as_leaf = out_leaf[old]
    out["a"] = np.where(as_leaf, first[old], new_index[np.maximum(children[old, 0], 0)])
    out["b"] = np.where(as_leaf, -count[old], new_index[np.maximum(children[old, 1], 0)])
    old_parent = parent[old]
    out_parent = np.where(old_parent < 0, -1, new_index[np.maximum(old_parent, 0)]).astype(np.int32)
    return CollapseResult(first, end, count, cost, becomes, out, out_parent,
                          new_index[out_leaf].astype(np.int32), int(new_index[root]))
