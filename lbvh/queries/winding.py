"""Inside tests and signed distance by generalised winding numbers (kernels/winding.cl).

``bvh.winding_numbers(points)`` answers the generalised winding number of each
point (Jacobson, Kavan & Sorkine-Hornung 2013): the sum of the solid angles
the triangles subtend at the point, over 4 pi. ``bvh.contains(points)`` is
``winding > 0.5``; ``bvh.signed_distance(points)`` is the distance of
:func:`lbvh.queries.closest.closest_points`, negative inside (the sign
convention of Open3D and warp; trimesh's ``signed_distance`` is the opposite).

Why winding numbers and not ray parity: on a closed, consistently oriented
mesh both give the same answer (1 inside, 0 outside, exactly in exact
arithmetic), but on a mesh that is not quite closed (a scan with holes, a
model missing a face, duplicated or flipped pieces) parity flips wherever a
ray escapes through a hole, while the winding number changes smoothly: a
point well inside a bunny with holes in its base still has ``w`` close to 1.
What it answers on an open mesh: ``w`` near 1/2 on either side of a lone
sheet (a terrain has ``w`` about +-1/2 just below and above), so ``contains``
there is a coin toss by design, and a mesh whose faces point inwards has
``w = -1`` inside (``contains`` False: fix the winding with trimesh's
``fix_normals``). Points on the surface get ``w`` about 1/2 either way.

How it is computed: near a point the triangles' solid angles are summed
exactly (Van Oosterom & Strackee 1983) in float32; a node of the tree farther
than ``beta`` times its radius from the point is replaced by the first-order
expansion of its triangles' solid angles about their area-weighted centroid
(Barill et al. 2018; :func:`node_moments` computes the moments once per tree,
in float64, and the :class:`lbvh.BVH` keeps them). ``beta = 2`` (the default)
keeps ``|w - w_exact|`` within :data:`lbvh.verification.error_bound.WINDING_BOUND`
on the tests' meshes, far below the 1/2 that would flip ``contains``; a larger
``beta`` is slower and closer. The walk goes through the tree's wide records
where they are packed (the moments then per record, :func:`wide_moments`), a
record's lanes tested and expanded in one vector computation: on the 2-core
Zen 3 machine 3.8x, 1.6x and 4.0x as many points per second as the binary walk
on the bunny, Sponza and a 1M-triangle terrain (bench/README.md). The twin is
:func:`winding_numbers_numpy`, the exact float64 sum over every triangle.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..layout import children_of, is_leaf, node_depths, prim_range_of
from .closest import check_points, closest_points, walk_of
from .target import QueryTarget
from .wide import Wide

KERNEL_FILE = "winding.cl"

__all__ = ["DEFAULT_BETA", "node_moments", "wide_moments", "winding_numbers", "contains", "signed_distance",
           "winding_numbers_numpy"]

#: The accuracy parameter of Barill et al. 2018: a node is expanded only where the point
#: lies farther than beta times its radius.
DEFAULT_BETA = 2.0

#: Bit of the per-point flag word: the stack was full and a subtree was skipped.
FLAG_OVERFLOW = 1

_WORK_GROUP = 64


def _triangle_terms(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``float64 (F, 16)`` per triangle: area, area * centroid (3), vector area (3),
    vector area times centroid, the 3x3 outer product ``a c^T`` row by row (9)."""
    p = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    a = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(a, axis=1)
    c = p.mean(axis=1)
    out = np.empty((len(p), 16))
    out[:, 0] = area
    out[:, 1:4] = area[:, None] * c
    out[:, 4:7] = a
    out[:, 7:16] = (a[:, :, None] * c[:, None, :]).reshape(-1, 9)
    return out


def node_moments(nodes: np.ndarray, prim_order: np.ndarray, root: int, vertices: np.ndarray,
                 faces: np.ndarray) -> np.ndarray:
    """``float32 (num_nodes, 16)``: what kernels/winding.cl reads of each node.

    ``[0:3]`` the area-weighted centroid ``p`` of the node's triangles (the box's
    centre if their area is 0), ``[3]`` ``R^2``, ``R`` the distance from ``p`` to the
    farthest corner of the node's box, ``[4:7]`` ``N``, the sum of the triangles'
    vector areas, ``[7:16]`` ``M = sum a_t (c_t - p)^T`` row by row. Sums in float64,
    leaves by prefix sums over the slots, internal nodes from their children level by
    level, then rounded once.
    """
    n = len(nodes)
    terms = _triangle_terms(vertices, np.asarray(faces)[np.asarray(prim_order)])
    sums = np.zeros((n, 16))
    leaf = is_leaf(nodes)
    first, count = prim_range_of(nodes).T
    prefix = np.zeros((len(terms) + 1, 16))
    np.cumsum(terms, axis=0, out=prefix[1:])
    lf = np.flatnonzero(leaf)
    sums[lf] = prefix[first[lf] + count[lf]] - prefix[first[lf]]
    kids = children_of(nodes)
    if n > 1:
        parent = np.full(n, -1, np.int64)
        inner = np.flatnonzero(~leaf)
        parent[kids[inner, 0]] = inner
        parent[kids[inner, 1]] = inner
        depth = node_depths(parent, root)
        for level in range(int(depth.max()) - 1, -1, -1):
            at = inner[depth[inner] == level]
            sums[at] = sums[kids[at, 0]] + sums[kids[at, 1]]
    lower = nodes["lower"].astype(np.float64)
    upper = nodes["upper"].astype(np.float64)
    area = sums[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        centre = np.where(area[:, None] > 0, sums[:, 1:4] / area[:, None], 0.5 * (lower + upper))
    far = np.maximum(np.abs(upper - centre), np.abs(centre - lower))
    out = np.empty((n, 16))
    out[:, 0:3] = centre
    out[:, 3] = (far * far).sum(axis=1)
    out[:, 4:7] = sums[:, 4:7]
    # M = sum a c^T - N p^T
    out[:, 7:16] = sums[:, 7:16] - (sums[:, 4:7, None] * centre[:, None, :]).reshape(-1, 9)
    with np.errstate(over="ignore"):
        return out.astype(np.float32)


def wide_moments(moments: np.ndarray, lanes: np.ndarray) -> np.ndarray:
    """``float32 (records, 16, width)``: what kernels/winding.cl reads of each wide
    record (WIDE=1): row ``k`` holds ``moments[:, k]`` (:func:`node_moments`) of each
    lane's binary node (``lanes``, ``int32 (records, width)``, -1 for an empty lane,
    as :class:`lbvh.queries.wide.Wide` keeps them); an empty lane has zeros and
    ``R^2 = -1``, so the kernel takes it for far and adds nothing."""
    lanes = np.asarray(lanes)
    out = np.asarray(moments, np.float32)[np.maximum(lanes, 0)].transpose(0, 2, 1).copy()
    empty = np.broadcast_to((lanes < 0)[:, None, :], out.shape)
    out[empty] = 0.0
    out[:, 3][lanes < 0] = -1.0
    return out


def read_lanes(ctx: dev.Context, wide: Wide) -> np.ndarray:
    """``int32 (records, width)``: the binary node of each lane of the records."""
    lanes = np.empty((wide.count, wide.width), np.int32)
    if wide.count:
        cl.enqueue_copy(ctx.queue, lanes, wide.lanes, is_blocking=True)
    return lanes


def kernel_defines(ctx: dev.Context) -> dict[str, int]:
    """kernels/winding.cl's device-wide choice: ``INLINE_SQRT`` where the compiler is
    clang's (kernels/common.h: its inline square root; 1.09x on Sponza's winding
    numbers, bench/README.md)."""
    return {"INLINE_SQRT": int(ctx.compiler_is_clang)}


def _check_beta(beta: Any) -> np.float32:
    try:
        b = float(beta)
    except (TypeError, ValueError):
        raise ValueError(f"beta: {beta!r}; expected a number >= 1") from None
    if not (b >= 1 and np.isfinite(b)):
        raise ValueError(f"beta: {beta!r}; expected a finite number >= 1")
    return np.float32(b * b)


@dev.serialised
def winding_numbers(target: QueryTarget, points: Any, *, beta: float = DEFAULT_BETA,
                    batch_size: int = 1 << 20) -> np.ndarray:
    """The generalised winding number of each point (see the module docstring).

    Args:
        target: an :class:`lbvh.BVH`.
        points: ``(N, 3)`` real array (converted to float32).
        beta: accuracy (>= 1): nodes farther than ``beta`` times their radius are
            expanded instead of summed.
        batch_size: points per kernel launch.

    Returns:
        ``float32 (N,)``.

    Raises:
        ValueError: a bad point (named), ``beta`` or ``batch_size``.
        RuntimeError: the traversal stack overflowed (a tree deeper than 768 levels).
    """
    if target.tree.clipped_leaves:
        raise ValueError("winding_numbers: this tree has spatial splits (builder='sbvh'), whose "
                         "nodes would count a split triangle more than once; build another tree "
                         "for inside tests and signed distance")
    p = check_points(points)
    beta2 = _check_beta(beta)
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
            or batch_size < 1:
        raise ValueError(f"batch_size: {batch_size!r}; expected a positive integer")
    n = len(p)
    out = np.empty(n, np.float32)
    flags = np.zeros(n, np.int32)
    if n == 0:
        return out
    ctx, tree, mem = target.ctx, target.tree, target.ctx.memory
    (records, root, root_y), defines = walk_of(target)
    defines = {**defines, **kernel_defines(ctx)}
    moments = target.winding_moments()
    slot_faces = target.slot_faces()
    batch = int(min(batch_size, n))
    bufs = {"points": mem.alloc(12 * batch, flags=cl.mem_flags.READ_ONLY),
            "w": mem.alloc(4 * batch), "flags": mem.alloc(4 * batch)}
    try:
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            m = stop - start
            up = cl.enqueue_copy(ctx.queue, bufs["points"], p[start:stop], is_blocking=False)
            launch = dev.Launch(m, 1, -(-m // _WORK_GROUP) * _WORK_GROUP, _WORK_GROUP)
            ev = dev.run(ctx, KERNEL_FILE, "winding_numbers", launch, records, moments,
                         target.mesh.vertices_buf, slot_faces, root, root_y, tree.num_nodes,
                         bufs["points"], m, beta2, bufs["w"], bufs["flags"], defines=defines,
                         wait_for=[up])
            cl.enqueue_copy(ctx.queue, out[start:stop], bufs["w"], wait_for=[ev], is_blocking=False)
            cl.enqueue_copy(ctx.queue, flags[start:stop], bufs["flags"], wait_for=[ev],
                            is_blocking=False)
            ctx.queue.finish()
    finally:
        mem.free(*bufs.values())
    if (flags & FLAG_OVERFLOW).any():
        bad = np.flatnonzero(flags & FLAG_OVERFLOW)
        raise RuntimeError(f"winding_numbers: the traversal stack overflowed for {len(bad)} "
                           f"points (first: point {int(bad[0])}); the tree is deeper than the "
                           "kernel's stack")
    return out


def contains(target: QueryTarget, points: Any, *, beta: float = DEFAULT_BETA) -> np.ndarray:
    """``bool (N,)``: whether each point is inside the mesh, ``winding > 0.5``
    (:func:`winding_numbers`)."""
    return winding_numbers(target, points, beta=beta) > 0.5


def signed_distance(target: QueryTarget, points: Any, *, beta: float = DEFAULT_BETA) -> np.ndarray:
    """``float32 (N,)``: the distance to the mesh (:func:`lbvh.queries.closest.closest_points`),
    negative inside (``winding > 0.5``)."""
    p = check_points(points)
    distance = closest_points(target, p).distance
    return np.where(winding_numbers(target, p, beta=beta) > 0.5, -distance, distance)


def winding_numbers_numpy(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                          chunk: int = 1 << 22) -> np.ndarray:
    """The exact float64 sum over every triangle (the twin of kernels/winding.cl),
    ``float64 (N,)``; ``N * F`` pairs, ``chunk`` at a time."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    pts = np.asarray(points, np.float64)
    out = np.zeros(len(pts))
    per = max(1, chunk // max(len(tri), 1))
    for s in range(0, len(pts), per):
        q = pts[s:s + per, None, :]
        a, b, c = tri[None, :, 0] - q, tri[None, :, 1] - q, tri[None, :, 2] - q
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = (a * np.cross(b, c)).sum(-1)
        den = (la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb
               + (b * c).sum(-1) * la)
        out[s:s + per] = (2 * np.arctan2(num, den)).sum(axis=1) / (4 * np.pi)
    return out
