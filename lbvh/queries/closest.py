"""Closest points on the mesh (kernels/closest.cl): distance, point, triangle, barycentrics.

``bvh.closest_points(points, max_distance=inf)`` answers, for each query
point, the nearest point of the mesh within ``max_distance``: a best-first
branch-and-bound traversal of the tree with the point-box distance as the
bound, and Ericson's point-triangle test (Real-Time Collision Detection,
5.1.5) in float32 at the leaves. Its twin is :func:`closest_points_numpy`, a
float64 brute force over every triangle; the two agree on the distance within
:func:`lbvh.metrics.error_bound.closest_distance_bound` (the triangle may
differ where two are equally near).

Points are ``(N, 3)`` real arrays (converted to float32); a NaN, infinite or
beyond-float32 point is refused with a ``ValueError`` naming it, as is a NaN
or negative ``max_distance``. A point with no triangle within ``max_distance``
gets distance ``inf``, point NaN and triangle ``-1``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..mesh import real_array
from .ray_order import MIN_POINTS, ordered_points
from .target import QueryTarget, query_target
from .wide import lane_defines
from .traverse import stack_bucket, stack_need

KERNEL_FILE = "closest.cl"

#: Bit of the per-point flag word: the stack was full and a subtree was skipped.
FLAG_OVERFLOW = 1

_WORK_GROUP = 64


@dataclass
class Closest:
    """Closest points, one entry per query point (numpy arrays).

    Attributes:
        distance: ``float32 (N,)``, ``inf`` where nothing is within ``max_distance``.
        points: ``float32 (N, 3)``, the closest point of the mesh (NaN where none).
        prim: ``int32 (N,)`` triangle in the caller's numbering, ``-1`` where none.
        u, v: ``float32 (N,)`` barycentrics of the point on its triangle:
            ``(1-u-v)*p0 + u*p1 + v*p2`` with ``p0, p1, p2 = vertices[faces[prim]]``.
        overflow: ``bool (N,)`` the traversal's stack overflowed (the answer may
            have missed a subtree); ``overflow_count`` how many.
    """
    distance: np.ndarray
    points: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    overflow: np.ndarray
    overflow_count: int

    @property
    def found(self) -> np.ndarray:
        """``bool (N,)``: a triangle was within ``max_distance``."""
        return self.prim >= 0

    def __len__(self) -> int:
        return len(self.distance)


@dataclass(frozen=True)
class CheckedPoints:
    """Query points checked once at the public boundary (:func:`checked_points`):
    ``array`` ``float32 (N, 3)`` C-contiguous, finite; ``least`` and ``largest``
    coordinate. The point queries take it as it is, without checking again."""
    array: np.ndarray
    least: float
    largest: float


def checked_points(points: Any) -> CheckedPoints:
    """``points`` checked (:func:`check_points_range`) into a :class:`CheckedPoints`."""
    return CheckedPoints(*check_points_range(points))


def check_points_range(points: Any) -> tuple[np.ndarray, float, float]:
    """:func:`check_points`, with the least and the largest coordinate of any point
    (over every axis; 0, 0 for no point), which its check computes anyway."""
    if isinstance(points, CheckedPoints):
        return points.array, points.least, points.largest
    given = real_array("points", points)
    if given.ndim != 2 or given.shape[1] != 3:
        raise ValueError(f"points: shape {given.shape}, expected (N, 3)")
    with np.errstate(over="ignore", invalid="ignore"):
        p = np.ascontiguousarray(given, dtype=np.float32)
    if not p.size:
        return p, 0.0, 0.0
    least, largest = p.min(), p.max()
    if not (np.isfinite(least) and np.isfinite(largest)):
        i = int(np.flatnonzero(~np.isfinite(p).all(axis=1))[0])
        raise ValueError(f"points: point {i} has a NaN, infinite or beyond-float32 component "
                         f"{given[i].tolist()}")
    return p, float(least), float(largest)


def check_points(points: Any) -> np.ndarray:
    """``float32 (N, 3)`` C-contiguous query points, or a ``ValueError`` naming the first bad one."""
    return check_points_range(points)[0]


def _max_distance(max_distance: Any) -> np.float32:
    """The search radius as float32 (beyond float32's range: ``inf``, no bound)."""
    try:
        d = float(max_distance)
    except (TypeError, ValueError):
        raise ValueError(f"max_distance: {max_distance!r}; expected a number >= 0 or inf") from None
    if not d >= 0:
        raise ValueError(f"max_distance: {max_distance!r}; expected a number >= 0 or inf")
    with np.errstate(over="ignore"):
        return np.float32(d)


def stack_size_for(target: QueryTarget) -> int:
    """Stack entries for this tree: one push per level at most, rounded up to a bucket."""
    target = query_target(target)   # a BVH gives its query data
    return stack_bucket(target.traversal_depth() + 1)


def walk_of(target: QueryTarget) -> tuple[tuple[cl.Buffer, int, int], dict[str, int]]:
    """What a depth-first walk of kernels/closest.cl or kernels/overlap.cl is given: the
    records and the root's reference in them ``(buffer, root_x, root_y)``, and the
    defines ``STACK_SIZE`` (and ``WIDE``, ``WIDTH`` and the lanes' :func:`lane_defines`
    of :mod:`lbvh.queries.wide`). Through the wide records where
    they fit (a record pushes all its lanes entered but one: the records' own stack
    need), else through the binary nodes (one push per level)."""
    target = query_target(target)   # a BVH gives its query data
    wide = target.wide_records()
    if wide.packed:
        return ((wide.buffer, wide.root_x, wide.root_y),
                {"STACK_SIZE": stack_bucket(stack_need(target)), "WIDE": 1, "WIDTH": wide.width,
                 **lane_defines(target.ctx)})
    return (target.tree.nodes, target.tree.root, 0), {"STACK_SIZE": stack_size_for(target)}


@dev.serialised
def closest_points(target: QueryTarget, points: Any, max_distance: float = np.inf, *,
                   batch_size: int = 1 << 20,
                   extra_defines: dict[str, int] | None = None) -> Closest:
    """The closest point of the mesh to each query point within ``max_distance``.

    Args:
        target: an :class:`lbvh.BVH`.
        points: ``(N, 3)`` real array (converted to float32).
        max_distance: search radius (default ``inf``: every point finds a triangle).
        batch_size: points per kernel launch (about 60 bytes of device memory each).
        extra_defines: -D defines added to kernels/closest.cl's (tests: ``NO_FP64``).

    Returns:
        :class:`Closest`.

    Raises:
        ValueError: a bad point (named), a bad ``max_distance`` or ``batch_size``.
    """
    target = query_target(target)   # a BVH gives its query data
    p = check_points(points)
    limit = _max_distance(max_distance)
    if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ValueError(f"batch_size: {batch_size!r}; expected a positive integer")
    n = len(p)
    out = {"distance": np.empty(n, np.float32), "points": np.empty((n, 3), np.float32),
           "prim": np.empty(n, np.int32), "bary": np.empty((n, 2), np.float32),
           "flags": np.empty(n, np.int32)}
    ctx, tree = target.ctx, target.tree
    records, walk = walk_of(target)
    batch = int(min(batch_size, max(n, 1)))
    mem = ctx.memory
    bufs = {"points": mem.alloc(12 * batch, flags=cl.mem_flags.READ_ONLY),
            "distance": mem.alloc(4 * batch), "points_out": mem.alloc(12 * batch),
            "prim": mem.alloc(4 * batch), "bary": mem.alloc(8 * batch), "flags": mem.alloc(4 * batch)}
    base = {**walk, **(extra_defines or {})}
    slot_faces = target.slot_faces()
    order = sorted_points = None
    try:
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            m = stop - start
            ups = [cl.enqueue_copy(ctx.queue, bufs["points"], p[start:stop], is_blocking=False)]
            order = sorted_points = None
            if m >= MIN_POINTS:
                # nearby points one after another (1.8x on the bunny), read as one run
                # (bench/README.md)
                order, sorted_points, ups = ordered_points(ctx, bufs["points"], m,
                                                           *tree.root_box())
            launch = dev.Launch(m, 1, -(-m // _WORK_GROUP) * _WORK_GROUP, _WORK_GROUP)
            ev = dev.run(ctx, KERNEL_FILE, "closest_points", launch, tree.nodes, records[0],
                         tree.prim_order, target.mesh.vertices_buf, slot_faces, tree.root,
                         records[1], records[2], tree.num_nodes,
                         bufs["points"] if order is None else sorted_points,
                         order if order is not None else bufs["flags"], limit, m,
                         bufs["distance"], bufs["points_out"], bufs["prim"], bufs["bary"],
                         bufs["flags"], defines={**base, "POINT_ORDER": int(order is not None)},
                         wait_for=ups)
            for name, buf in (("distance", "distance"), ("points", "points_out"), ("prim", "prim"),
                              ("bary", "bary"), ("flags", "flags")):
                cl.enqueue_copy(ctx.queue, out[name][start:stop], bufs[buf], wait_for=[ev],
                                is_blocking=False)
            ctx.queue.finish()
            mem.free(order, sorted_points)
            order = sorted_points = None
    finally:
        mem.free(*bufs.values(), order, sorted_points)
    overflow = (out["flags"] & FLAG_OVERFLOW) != 0
    return Closest(out["distance"], out["points"], out["prim"], out["bary"][:, 0].copy(),
                   out["bary"][:, 1].copy(), overflow, int(overflow.sum()))


# -- numpy twin ---------------------------------------------------------------------

def _segment_points(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    len2 = (ab * ab).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(len2 > 0, ((p - a) * ab).sum(-1) / np.where(len2 > 0, len2, 1), 0.0)
    return a + np.clip(t, 0.0, 1.0)[..., None] * ab


def point_triangle_numpy(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points of triangles ``(a, b, c)`` to points ``p`` (broadcast ``(..., 3)``),
    in float64: the projection on the plane where it falls inside the triangle
    (all three edge functions of one sign), else the nearest point of the three
    edges. Another formulation than the kernel's (Ericson's regions), so that
    the two check each other."""
    p, a, b, c = (np.asarray(x, np.float64) for x in (p, a, b, c))
    n = np.cross(b - a, c - a)
    nn = (n * n).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = p - (((p - a) * n).sum(-1) / np.where(nn > 0, nn, 1))[..., None] * n
    inside = nn > 0
    for u, w in ((a, b), (b, c), (c, a)):
        inside = inside & ((np.cross(w - u, proj - u) * n).sum(-1) >= 0)
    edges = [_segment_points(p, u, w) for u, w in ((a, b), (b, c), (c, a))]
    d2 = np.stack([((p - q) ** 2).sum(-1) for q in edges])
    nearest = np.take_along_axis(np.stack(edges), d2.argmin(0)[None, ..., None], 0)[0]
    return np.where(inside[..., None], proj, nearest)


def closest_points_numpy(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                         chunk: int = 1 << 22) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The float64 brute force: ``(distance (N,), closest point (N, 3), triangle (N,))``
    over every triangle for every point (``N * F`` pairs, ``chunk`` at a time)."""
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces, np.int64)]
    pts = np.asarray(points, np.float64)
    best_d2 = np.full(len(pts), np.inf)
    best_q = np.full((len(pts), 3), np.nan)
    best_t = np.full(len(pts), -1, np.int64)
    per = max(1, chunk // max(len(tri), 1))
    for s in range(0, len(pts), per):
        p = pts[s:s + per, None, :]
        q = point_triangle_numpy(p, tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
        d2 = ((p - q) ** 2).sum(-1)
        k = d2.argmin(1)
        rows = np.arange(len(k))
        best_d2[s:s + per], best_q[s:s + per], best_t[s:s + per] = d2[rows, k], q[rows, k], k
    return np.sqrt(best_d2), best_q, best_t
