"""Box queries (kernels/overlap.cl): the triangles whose boxes overlap each query box.

``bvh.overlapping(lower, upper)`` answers, for each query box ``[lower[i],
upper[i]]`` (closed: touching counts), the triangles whose own boxes (the min
and max of their three vertices) overlap it, as flat arrays with offsets: the
triangles of box ``i`` are ``prims[offsets[i]:offsets[i + 1]]``, ascending.
The kernel compares float32 values and does no arithmetic, so the answer is
exact; its twin is :func:`overlapping_numpy`, a brute force over every
triangle, and the two agree element for element.

Boxes are ``(N, 3)`` real arrays (converted to float32): a NaN, infinite or
beyond-float32 corner, or a box with ``lower > upper`` on an axis, is refused
with a ``ValueError`` naming the first such box.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..builders.bounds import triangle_boxes_numpy
from ..mesh import real_array
from .closest import walk_of
from .target import QueryTarget, query_target

KERNEL_FILE = "overlap.cl"

#: Bit of the per-box flag word: the stack was full and a subtree was skipped.
FLAG_OVERFLOW = 1

_WORK_GROUP = 64


@dataclass
class Overlaps:
    """Triangles overlapping each query box, as flat arrays.

    Attributes:
        offsets: ``int64 (N + 1,)``; the triangles of box ``i`` are
            ``prims[offsets[i]:offsets[i + 1]]``.
        prims: ``int32 (M,)`` triangle indices in the caller's numbering, ascending per box.
        overflow: ``bool (N,)`` the traversal's stack overflowed for that box (its
            answer may miss triangles); ``overflow_count`` how many.
    """
    offsets: np.ndarray
    prims: np.ndarray
    overflow: np.ndarray
    overflow_count: int

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def counts(self) -> np.ndarray:
        """``int64 (N,)``: how many triangles each box overlaps."""
        return np.diff(self.offsets)

    def of(self, i: int) -> np.ndarray:
        """The triangles of box ``i``."""
        return self.prims[self.offsets[i]:self.offsets[i + 1]]


def check_boxes(lower: Any, upper: Any) -> tuple[np.ndarray, np.ndarray]:
    """``float32 (N, 3)`` C-contiguous corners, or a ``ValueError`` naming the first bad box."""
    given = []
    for name, value in (("lower", lower), ("upper", upper)):
        arr = real_array(name, value)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"{name}: shape {arr.shape}, expected (N, 3)")
        given.append(arr)
    if len(given[0]) != len(given[1]):
        raise ValueError(f"upper: {len(given[1])} boxes, but lower has {len(given[0])}")
    with np.errstate(over="ignore", invalid="ignore"):
        lo, hi = (np.ascontiguousarray(a, dtype=np.float32) for a in given)
    for name, arr, raw in (("lower", lo, given[0]), ("upper", hi, given[1])):
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{name}: box {i} has a NaN, infinite or beyond-float32 corner "
                             f"{raw[i].tolist()}")
    inverted = (lo > hi).any(axis=1)
    if inverted.any():
        i = int(np.flatnonzero(inverted)[0])
        raise ValueError(f"lower/upper: box {i} has lower {lo[i].tolist()} > upper "
                         f"{hi[i].tolist()} on an axis")
    return lo, hi


@dev.serialised
def overlapping(target: QueryTarget, lower: Any, upper: Any) -> Overlaps:
    """The triangles whose boxes overlap each query box ``[lower[i], upper[i]]``.

    Args:
        target: an :class:`lbvh.BVH`.
        lower, upper: ``(N, 3)`` real arrays (converted to float32), ``lower <= upper``.

    Returns:
        :class:`Overlaps`.

    Raises:
        ValueError: a bad box (named).
        lbvh.DeviceError: the answer would not fit the device's largest buffer.
    """
    target = query_target(target)   # a BVH gives its query data
    if target.tree.clipped_leaves:
        raise ValueError("overlapping: this tree has spatial splits (builder='sbvh'): its leaves "
                         "hold parts of triangles, not their boxes; build another tree for box "
                         "queries")
    lo, hi = check_boxes(lower, upper)
    n = len(lo)
    ctx, tree, mem = target.ctx, target.tree, target.ctx.memory
    if n == 0:
        return Overlaps(np.zeros(1, np.int64), np.zeros(0, np.int32), np.zeros(0, bool), 0)
    launch = dev.Launch(n, 1, -(-n // _WORK_GROUP) * _WORK_GROUP, _WORK_GROUP)
    bufs = {"lower": mem.upload(lo), "upper": mem.upload(hi), "counts": mem.alloc(4 * n),
            "flags": mem.alloc(4 * n), "offsets": mem.alloc(8 * (n + 1))}
    records, walk = walk_of(target)
    args = (tree.nodes, records[0], tree.prim_order, target.mesh.vertices_buf,
            target.slot_faces(), tree.root, records[1], records[2], tree.num_nodes,
            bufs["lower"], bufs["upper"], n)
    prims_buf = None
    try:
        dev.run(ctx, KERNEL_FILE, "overlapping", launch, *args, bufs["offsets"], bufs["counts"],
                bufs["flags"], defines={**walk, "COUNT": 1})
        counts = dev.from_device(ctx, bufs["counts"], np.int32, (n,))
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        total = int(offsets[-1])
        prims = np.empty(total, np.int32)
        if total:
            prims_buf = mem.alloc(4 * total)
            cl.enqueue_copy(ctx.queue, bufs["offsets"], offsets)
            dev.run(ctx, KERNEL_FILE, "overlapping", launch, *args, bufs["offsets"], prims_buf,
                    bufs["flags"], defines={**walk, "COUNT": 0})
            cl.enqueue_copy(ctx.queue, prims, prims_buf, is_blocking=True)
        flags = dev.from_device(ctx, bufs["flags"], np.int32, (n,))
    finally:
        mem.free(prims_buf, *bufs.values())
    # ascending per box: the kernel sorts each box's triangles (sort_prims)
    overflow = (flags & FLAG_OVERFLOW) != 0
    return Overlaps(offsets, prims, overflow, int(overflow.sum()))


def overlapping_numpy(vertices: np.ndarray, faces: np.ndarray, lower: np.ndarray,
                      upper: np.ndarray) -> Overlaps:
    """The brute force over every triangle (the twin of kernels/overlap.cl)."""
    tlo, thi = triangle_boxes_numpy(vertices, faces)
    lo, hi = np.asarray(lower, np.float32), np.asarray(upper, np.float32)
    per_box = [np.flatnonzero(((tlo <= hi[i]) & (thi >= lo[i])).all(axis=1)).astype(np.int32)
               for i in range(len(lo))]
    counts = np.array([len(p) for p in per_box], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    prims = np.concatenate(per_box) if per_box else np.zeros(0, np.int32)
    return Overlaps(offsets, prims.astype(np.int32), np.zeros(len(lo), bool), 0)
