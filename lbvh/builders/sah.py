"""The serial SAH reference builder: top-down, full sweep, on the host.

MacDonald & Booth 1990 ("Heuristics for ray tracing using space subdivision")
give the cost model; Wald 2007 ("On fast construction of SAH-based bounding
volume hierarchies", section 3) the full-sweep build:

* the primitives are sorted once per axis by the centre of their box
  (``lo * 0.5 + hi * 0.5``, as the device LBVH does);
* at every node every split candidate on every axis is costed, the first ``k``
  primitives of the axis order on the left: the boxes of all prefixes are swept
  left to right and those of all suffixes right to left over the *primitive
  boxes* (not their centres: costing centroid bounds is a known bug that makes
  SAH trees worse than LBVH ones);
* the cheapest candidate wins and the node's primitives are partitioned in
  every axis order by a side mask, keeping each order (no re-sort per node).

Cost of a split of node N into L and R (Wald 2007, eq. 2)::

    C_split = C_node + C_tri * (A(L) * |L| + A(R) * |R|) / A(N)        C_leaf = C_tri * |N|

A node becomes a leaf when it holds one primitive, or at most
``max_leaf_size`` primitives and no split is cheaper than ``C_leaf``; above
``max_leaf_size`` it is always split. Areas and costs are float64. Equal
costs are broken towards the most balanced split (then axis x, y, z, then the
smaller left side), so identical primitives and boxes without area (all
costs 0) get median splits instead of a degenerate chain.

The recursion runs level by level over all open nodes at once (no Python
recursion, no per-node Python loop): every node of a level is a contiguous
segment of the three axis orders, the sweeps are segmented prefix scans with
numpy, and the partition is a segmented stable partition. Leaves take the
slots of their segment, so ``prim_order`` is the final x-axis order.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import device as dev
from ..layout import NODE_DTYPE, parents_of
from ..tree import Mesh, Tree, upload_tree
from .options import SAHOptions
from ..metrics.cost import box_area
from ..progress import bar as progress_bar
from ..report import BuildReport
from .bounds import triangle_boxes_numpy
from .ray_sampled import RayLists


#: Meshes from this size on show a progress bar by default (a few seconds of build).
PROGRESS_TRIANGLES = 200_000

_LOW32 = np.int64(0xFFFFFFFF)
_LITTLE_ENDIAN = sys.byteorder == "little"


# -- exact segmented min/max scans on float32 -----------------------------------
# A float32 maps to a uint32 with the same order; putting the segment number
# above it in an int64 makes one global accumulate act segment by segment,
# exactly (no float arithmetic is involved).

def _order_keys(x: np.ndarray) -> np.ndarray:
    """int64 keys in [0, 2**32) ordered like the float32 values ``x``."""
    u = np.ascontiguousarray(x, np.float32).view(np.uint32)
    return np.where(u >> 31 == 1, ~u, u | np.uint32(0x80000000)).astype(np.int64)


def _from_keys(k: np.ndarray) -> np.ndarray:
    """float32 values of keys made by :func:`_order_keys` (segment bits ignored)."""
    if _LITTLE_ENDIAN:  # the low 32 bits of each int64, read in place
        u = k.view(np.uint32)[..., 0::2]
    else:
        u = (k & _LOW32).astype(np.uint32)
    # keys of negative floats have the top bit clear: flip all bits; else flip the top bit
    sign = u.view(np.int32) >> 31
    return (u ^ (~sign | np.int32(-2**31)).view(np.uint32)).view(np.float32)


@dataclass
class _Sweep:
    """Result of sweeping a batch of segments (one per open node)."""
    box_lo: np.ndarray    # float32 (S, 3) box of each segment's primitives
    box_hi: np.ndarray
    area: np.ndarray      # float64 (S,) its surface area
    axis: np.ndarray      # int64 (S,) axis of the cheapest split
    num_left: np.ndarray  # int64 (S,) primitives on its left
    cost_sum: np.ndarray  # float64 (S,) A(L)|L| + A(R)|R| of that split
    pids: np.ndarray      # int32 (3, M) primitives of the segments in each axis order
    seg_of: np.ndarray    # int64 (M,) segment of each element
    local: np.ndarray     # int64 (M,) position inside the segment
    pos: np.ndarray       # int64 (M,) position in the axis orders


def _sweep(order: np.ndarray, lo_key: np.ndarray, hi_key: np.ndarray,
           seg_start: np.ndarray, seg_count: np.ndarray, rays: RayLists | None = None) -> _Sweep:
    """Cost every split candidate of every segment (all ``seg_count >= 2``), keep the best.

    With ``rays`` (the segments' sample rays), the sides' areas are replaced by their
    ray-sampled effective areas (:meth:`lbvh.builders.ray_sampled.RayLists.weigh`)."""
    nseg = len(seg_start)
    offsets = np.cumsum(seg_count) - seg_count
    m = int(seg_count.sum())
    seg_of = np.repeat(np.arange(nseg, dtype=np.int64), seg_count)
    local = np.arange(m, dtype=np.int64) - offsets[seg_of]
    pos = seg_start[seg_of] + local
    rising = (seg_of << 32)[:, None]          # later segments above earlier ones
    falling = ((nseg - seg_of) << 32)[:, None]  # later segments below earlier ones
    num_left = local + 1
    num_right = seg_count[seg_of] - num_left
    costs = np.empty((3, m))
    pids = np.empty((3, m), np.int32)
    for a in range(3):
        p = order[a][pos]
        pids[a] = p
        lk, hk = lo_key[p], hi_key[p]
        # prefix boxes [first, i] left to right, suffix boxes [i, last] right to left
        pre_lo = np.minimum.accumulate(lk | falling, axis=0)
        pre_hi = np.maximum.accumulate(hk | rising, axis=0)
        suf_lo = np.minimum.accumulate((lk | rising)[::-1], axis=0)[::-1]
        suf_hi = np.maximum.accumulate((hk | falling)[::-1], axis=0)[::-1]
        if a == 0:
            last = offsets + seg_count - 1
            box_lo, box_hi = _from_keys(pre_lo[last]), _from_keys(pre_hi[last])
        pre_box = _from_keys(pre_lo), _from_keys(pre_hi)
        suf_box = _from_keys(suf_lo), _from_keys(suf_hi)
        pre_area = box_area(*pre_box)
        suf_area = box_area(*suf_box)
        right_area = np.empty(m)
        right_area[:-1] = suf_area[1:]  # the right side of "split after i" starts at i + 1
        right_area[-1] = 0.0
        if rays is not None:
            right_box = [np.roll(b, -1, axis=0) for b in suf_box]   # the last is never costed
            pre_area, right_area = rays.weigh(box_lo, box_hi, box_area(box_lo, box_hi), seg_of,
                                              local, seg_count, (*pre_box, pre_area),
                                              (*right_box, right_area))
        costs[a] = np.where(num_right > 0, pre_area * num_left + right_area * num_right, np.inf)
    best = np.minimum.reduceat(costs.min(axis=0), offsets)
    # ties: most balanced, then lowest axis, then smallest left side
    width = int(seg_count.max())
    balance = np.abs(num_left - num_right)
    tie_key = (balance * 3 + np.arange(3)[:, None]) * width + local
    tie_key = np.where(costs == best[seg_of], tie_key, np.iinfo(np.int64).max)
    chosen = np.minimum.reduceat(tie_key.min(axis=0), offsets)
    return _Sweep(box_lo, box_hi, box_area(box_lo, box_hi), (chosen // width) % 3,
                  chosen % width + 1, best, pids, seg_of, local, pos)


def _axis_orders(lo: np.ndarray, hi: np.ndarray, centres: np.ndarray | None) -> np.ndarray:
    """``int32 (3, F)``: primitives sorted by centre along x, y and z (stable: ties by index)."""
    if centres is None:
        half = np.float32(0.5)
        centres = lo * half + hi * half
    return np.stack([np.argsort(centres[:, a], kind="stable") for a in range(3)]).astype(np.int32)


@dataclass(frozen=True)
class SplitDecision:
    """The cheapest split of a set of primitives (what the builder does at a node)."""
    axis: int           #: 0, 1 or 2
    num_left: int       #: the first ``num_left`` primitives of the axis order go left
    cost_sum: float     #: ``A(L) * |L| + A(R) * |R|`` in float64
    node_area: float    #: ``A(N)``, float64
    left: np.ndarray    #: int32 indices of the left primitives, in axis order


def best_split(lo: np.ndarray, hi: np.ndarray, centres: np.ndarray | None = None) -> SplitDecision:
    """The split the builder chooses at a node holding these primitives.

    Args:
        lo, hi: ``float32 (n, 3)`` primitive boxes, ``n >= 2``.
        centres: ``float32 (n, 3)`` sort keys; default the box centres.
    """
    lo = np.ascontiguousarray(lo, np.float32)
    hi = np.ascontiguousarray(hi, np.float32)
    if len(lo) < 2:
        raise ValueError(f"best_split: needs at least 2 primitives, got {len(lo)}")
    order = _axis_orders(lo, hi, None if centres is None else np.asarray(centres, np.float32))
    sweep = _sweep(order, _order_keys(lo), _order_keys(hi), np.array([0]), np.array([len(lo)]))
    axis, k = int(sweep.axis[0]), int(sweep.num_left[0])
    return SplitDecision(axis, k, float(sweep.cost_sum[0]), float(sweep.area[0]), order[axis][:k].copy())


def _stable_partition(order: np.ndarray, sweep: _Sweep, split_seg: np.ndarray,
                      is_left: np.ndarray) -> None:
    """Move each split segment's left primitives before its right ones, in every axis order.

    ``is_left`` is a scratch ``bool (F,)`` mask, all False on entry and on return.
    """
    seg_of, local = sweep.seg_of, sweep.local
    moving = split_seg[seg_of]
    chosen = sweep.axis[seg_of]
    own = sweep.pids[chosen, np.arange(len(seg_of))]
    left_prims = own[moving & (local < sweep.num_left[seg_of])]
    is_left[left_prims] = True
    offsets = np.flatnonzero(local == 0)
    for a in range(3):
        pids = sweep.pids[a][moving]
        flag = is_left[sweep.pids[a]]
        before = np.cumsum(flag) - flag  # left primitives before each element
        left_rank = before - before[offsets][seg_of]
        target = np.where(flag, left_rank, sweep.num_left[seg_of] + local - left_rank)
        order[a][(sweep.pos - local + target)[moving]] = pids
    is_left[left_prims] = False


def sah_tree(lo: np.ndarray, hi: np.ndarray, options: SAHOptions = SAHOptions(),
             progress: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Build the SAH tree over primitive boxes.

    Args:
        lo, hi: ``float32 (F, 3)`` primitive boxes, ``F >= 1``.
        options: the cost constants ``c_node``, ``c_tri``, ``max_leaf_size`` and, with
            ``rays`` (a traced :class:`~lbvh.builders.ray_sampled.RaySample`), split
            probabilities from those rays (:mod:`lbvh.builders.ray_sampled`, with
            ``ray_prior`` and ``ray_candidates``) instead of areas; no rays: the SAH.
        progress: a bar (:func:`lbvh.progress.bar`) advanced by the primitives
            placed in leaves, level by level; or None.

    Returns:
        ``nodes`` (``NODE_DTYPE``, root 0, numbered level by level) and
        ``prim_order`` (``int32 (F,)``); leaves hold contiguous slots.
    """
    c_node, c_tri = float(options.c_node), float(options.c_tri)
    max_leaf_size, rays = int(options.max_leaf_size), options.rays
    ray_prior, ray_candidates = float(options.ray_prior), int(options.ray_candidates)
    lo = np.ascontiguousarray(lo, np.float32)
    hi = np.ascontiguousarray(hi, np.float32)
    num_prims = len(lo)
    order = _axis_orders(lo, hi, None)
    lo_key, hi_key = _order_keys(lo), _order_keys(hi)
    nodes = np.zeros(2 * num_prims - 1, NODE_DTYPE)
    is_left = np.zeros(num_prims, bool)
    start, count, ids = np.array([0]), np.array([num_prims]), np.array([0])
    lists = None if rays is None else RayLists(rays, ray_prior, ray_candidates)
    next_id = 1
    while len(start):
        single = count == 1
        if single.any():  # one primitive: a leaf over its own box
            p = order[0][start[single]]
            _write_leaves(nodes, ids[single], lo[p], hi[p], start[single], count[single])
            if progress is not None:
                progress.update(int(single.sum()))
        start, count, ids = start[~single], count[~single], ids[~single]
        if lists is not None:
            lists.keep(~single)
        if not len(start):
            break
        sweep = _sweep(order, lo_key, hi_key, start, count, lists)
        split_cost = c_node * sweep.area + c_tri * sweep.cost_sum
        leaf_cost = c_tri * count * sweep.area
        leaf = (count <= max_leaf_size) & (split_cost >= leaf_cost)
        _write_leaves(nodes, ids[leaf], sweep.box_lo[leaf], sweep.box_hi[leaf], start[leaf], count[leaf])
        if progress is not None:
            progress.update(int(count[leaf].sum()))
        split = ~leaf
        num_split = int(split.sum())
        left_ids = next_id + 2 * np.arange(num_split)
        next_id += 2 * num_split
        at = ids[split]
        nodes["lower"][at], nodes["upper"][at] = sweep.box_lo[split], sweep.box_hi[split]
        nodes["a"][at], nodes["b"][at] = left_ids, left_ids + 1
        _stable_partition(order, sweep, split, is_left)
        if lists is not None:
            lists.split(split)
        k = sweep.num_left[split]
        start = np.stack([start[split], start[split] + k], axis=1).ravel()
        count = np.stack([k, count[split] - k], axis=1).ravel()
        ids = np.stack([left_ids, left_ids + 1], axis=1).ravel()
    return nodes[:next_id], order[0].copy()


def _write_leaves(nodes: np.ndarray, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  first: np.ndarray, count: np.ndarray) -> None:
    nodes["lower"][ids], nodes["upper"][ids] = lo, hi
    nodes["a"][ids], nodes["b"][ids] = first, -count


def build_tree(ctx: dev.Context, mesh: Mesh, options: SAHOptions = SAHOptions(),
               progress: bool | None = None) -> Tree:
    """Build the SAH reference tree on the host and upload it (``lbvh.build(builder="sah")``).

    ``mesh`` holds checked host arrays (``lbvh.build`` checks them). The
    report's ``wall_seconds`` is the host build time, ``upload_seconds`` the
    upload of the tree. ``progress``: a bar on stderr (:mod:`lbvh.progress`);
    ``None`` shows it for meshes of :data:`PROGRESS_TRIANGLES` or more when
    stderr is a terminal. The caller holds ``ctx.lock``.
    """
    t0 = time.perf_counter()
    lo, hi = triangle_boxes_numpy(mesh.vertices, mesh.faces)
    if progress is None and mesh.num_prims < PROGRESS_TRIANGLES:
        progress = False
    with progress_bar(mesh.num_prims, "SAH build", "tri", progress) as placed:
        nodes, prim_order = sah_tree(lo, hi, options, placed)
    wall = time.perf_counter() - t0
    report = BuildReport(device=ctx.name, builder="sah", num_triangles=mesh.num_prims,
                         wall_seconds=wall, input_bytes=mesh.vertices.nbytes + mesh.faces.nbytes)
    t1 = time.perf_counter()
    tree = upload_tree(ctx, nodes, parents_of(nodes, 0), prim_order, 0, "sah", report)
    ctx.queue.finish()
    report.upload_seconds = time.perf_counter() - t1
    return tree
