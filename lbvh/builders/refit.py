"""Stage 6: bottom-up refit of the boxes on the device (kernels/refit.cl).

Used by the build and by :meth:`lbvh.BVH.refit` after vertices moved. Works on
any tree in the project's layout: Karras trees have their leaves in one block,
other builders pass the list of their leaf nodes.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from .bounds import triangle_bounds, triangle_boxes_numpy
from ..device import Context, MemoryTracker, run
from ..tree import Mesh, Tree
from ..layout import children_of, is_leaf, node_depths, prim_range_of

KERNEL_FILE = "refit.cl"


def clear_arrivals(ctx: Context, arrivals: cl.Buffer, count: int) -> cl.Event:
    """Zero ``count`` int32 arrival counters of a bottom-up walk (a kernel: PoCL's fill is slow)."""
    clear = ctx.launch(count, min_per_item=4096)
    return run(ctx, KERNEL_FILE, "clear_arrivals", clear, arrivals, count, clear.per_item)


def refit_from_boxes(tree: Tree, boxes: cl.Buffer, arrivals: cl.Buffer | None, *,
                     karras_ranges: bool = False, per_item: int | None = None) -> list[cl.Event]:
    """Recompute every node box of ``tree`` in place from the triangle boxes (``2 *
    num_prims`` float4).

    A tree without a leaf list (:meth:`lbvh.tree.Tree.leaf_walks`) has its leaves at
    nodes ``num_prims - 1 ..`` (Karras numbering); ``arrivals`` is scratch of ``4 *
    num_nodes`` bytes.
    ``karras_ranges``: the tree comes straight from emit.cl, whose internal
    nodes still hold the far end of their range where lower.x goes and a zero
    where lower.y goes; the walks then skip the atomics of nodes whose range
    lies in one work-item's chunk, count the arrivals at the others in that
    zero (``arrivals`` is not used and may be None), and write the leaf records
    whole (leaf ``k`` holds slot ``k``), so emission may leave them out
    (``emit_hierarchy(write_leaves=False)``).
    ``per_item`` forces the chunk length (tests); by default the launch picks it.
    """
    ctx, nodes, parent, prim_order = tree.ctx, tree.nodes, tree.parent, tree.prim_order
    leaf_nodes, _, num_leaves = tree.leaf_walks()
    num_prims, num_nodes = tree.num_prims, tree.num_nodes
    if karras_ranges and leaf_nodes is not None:
        raise ValueError("karras_ranges needs the Karras numbering of the leaves, not a leaf list")
    events = []
    if karras_ranges:
        arrivals = nodes   # an argument the kernel does not read
    else:
        events.append(clear_arrivals(ctx, arrivals, num_nodes))
    launch = (ctx.walk_launch(num_leaves, min_per_item=256) if per_item is None
              else ctx.launch_chunks(num_leaves, per_item))
    use_list = leaf_nodes is not None
    leaf_arg = leaf_nodes if use_list else arrivals  # not read by the kernel in that case
    defines = {"KARRAS_RANGES": int(karras_ranges), "CLANG_PREFETCH": int(ctx.compiler_is_clang)}
    events.append(run(ctx, KERNEL_FILE, "refit", launch, boxes, prim_order, nodes, parent,
                      arrivals, leaf_arg, use_list, num_prims - 1, num_leaves, launch.per_item,
                      defines=defines))
    return events


def refit_boxes(mesh: Mesh, tree: Tree) -> list[cl.Event]:
    """Refit ``tree`` after the vertices moved to ``mesh``'s: triangle boxes (stage 1),
    then the bottom-up pass."""
    ctx = tree.ctx
    mem = MemoryTracker(ctx)
    boxes, centroid_box, events = triangle_bounds(ctx, mem, mesh.vertices_buf, mesh.faces_buf,
                                                  tree.num_prims)
    arrivals = mem.alloc(4 * tree.num_nodes, scratch=True)
    events += refit_from_boxes(tree, boxes, arrivals)
    ctx.queue.finish()
    mem.free(boxes, centroid_box, arrivals)
    mem.close()
    return events


def refit_numpy(nodes: np.ndarray, parent: np.ndarray, root: int, prim_order: np.ndarray,
                vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Serial twin: boxes of every node over the same topology, deepest level first.

    Returns ``lower, upper`` ``float32 (num_nodes, 3)``. min/max are exact and
    the leaf boxes hold +0.0 for -0.0, so the device refit must match this bit
    for bit, the sign of zero included.
    """
    tlo, thi = triangle_boxes_numpy(vertices, faces)
    tlo, thi = tlo[prim_order], thi[prim_order]
    num_nodes = len(nodes)
    lower = np.zeros((num_nodes, 3), np.float32)
    upper = np.zeros((num_nodes, 3), np.float32)
    leaf = is_leaf(nodes)
    ranges = prim_range_of(nodes)
    leaves = np.flatnonzero(leaf)
    by_first = leaves[np.argsort(ranges[leaves, 0], kind="stable")]
    starts = ranges[by_first, 0]
    # + 0: -0.0 becomes +0.0, as in refit.cl's leaf_box
    lower[by_first] = np.minimum.reduceat(tlo, starts, axis=0) + np.float32(0)
    upper[by_first] = np.maximum.reduceat(thi, starts, axis=0) + np.float32(0)
    children = children_of(nodes)
    depth = node_depths(parent, root)
    internal = np.flatnonzero(~leaf)
    for level in range(int(depth.max()), -1, -1):
        at = internal[depth[internal] == level]
        left, right = children[at, 0], children[at, 1]
        lower[at] = np.minimum(lower[left], lower[right])
        upper[at] = np.maximum(upper[left], upper[right])
    return lower, upper
