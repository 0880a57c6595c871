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
than ``beta`` times its radius from the point is replaced by the expansion of
its triangles' solid angles about their area-weighted centroid up to the
second order, where it is also far enough for its area
(:data:`lbvh.queries.winding_moments.NODE_ERROR`) (Barill et al. 2018; :mod:`lbvh.queries.winding_moments` makes the
moments once per tree, in float64 on the device, and the :class:`lbvh.BVH` keeps
them; :func:`expansion_numpy` is the twin of the far-node term). ``beta = 1.4`` (the
default) keeps ``|w - w_exact|`` within
:data:`lbvh.metrics.error_bound.WINDING_BOUND` on the tests' meshes and
the bench's scenes, far below the 1/2 that would flip ``contains``; a larger
``beta`` is slower and closer. (It was 1.3 until a point of the bench's Sponza
set came out 0.058 from the exact sum, past the bound: a cluster of small nodes
just past 1.3 radii whose errors all had one sign. At 1.35 the largest error
over the bench's 1M points per scene was 0.042 on Sponza, for 4-7% more time;
through the restructured copy of the tree that the walk now takes
(:data:`WINDING_TREELET_ROUNDS`) it was 0.049, and 0.043 at 1.4.) The
LBVH tree is walked through a copy of it restructured with treelets,
made at the first inside query (:meth:`lbvh.BVH.winding_target`): 1.4x the
points per second on Sponza. The second-order term is what lets ``beta`` be
that small: against the first-order expansion at ``beta = 2`` (what came
before) it gives 1.7x, 1.7x and 1.9x the points per second on the bunny, Sponza
and a 1M-triangle terrain, with a largest error on the tests' meshes of 0.023
instead of 0.059 and about the same on those scenes (0.023 against 0.021;
bench/README.md). The walk goes through the tree's wide records where they
are packed (the moments then per record), a record's
lanes tested and expanded in one vector computation: on the 2-core Zen 3
machine 3.8x, 1.6x and 4.0x as many points per second as the binary walk on
the bunny, Sponza and a 1M-triangle terrain (bench/README.md). On a CPU the
points go through the records 16 at a time (:func:`use_packets`: nearby points,
each with its own tests, the arithmetic 16 points wide), about 2x the points per
second on Sponza, whose points sum many near triangles and expansions each. The
twin is :func:`winding_numbers_numpy`, the exact float64 sum over every triangle.

``contains`` and the sign of ``signed_distance`` need only the side of 1/2: they
walk every point at :data:`SIGN_BETA` and :data:`SIGN_NODE_ERROR` (cheaper, within
:data:`SIGN_FILTER_BOUND`), and again by the default walk only the points whose
first ``w`` lies within that bound of 1/2 (:func:`inside`). Where both walks are
within their bounds that is the default walk's answer for every point (tested, on an
open terrain and Sponza), for 1.3x the points per second on Sponza and the bunny,
0.92x on a 1M-triangle terrain (open: 18% of its points within the bound of 1/2;
bench/README.md).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from .closest import check_points_range, checked_points, closest_points, walk_of
from .ray_order import MIN_POINTS, ordered_points
from .target import QueryTarget, query_target
from .winding_moments import (CUBIC_MONOMIALS, DEFAULT_ORDER, NODE_ERROR, ROWS_ORDER2,
                              scale_of_box)

KERNEL_FILE = "winding.cl"

__all__ = ["DEFAULT_BETA", "DEFAULT_ORDER", "NODE_ERROR", "PACKET", "SIGN_BETA", "SIGN_NODE_ERROR",
           "SIGN_FILTER_BOUND", "WINDING_TREELET_ROUNDS", "WINDING_TREELET_LEAVES",
           "expansion_numpy", "use_packets", "walks_a_copy", "winding_numbers", "inside",
           "contains", "signed_distance", "winding_numbers_numpy"]

#: The accuracy parameter of Barill et al. 2018: a node is expanded only where the point
#: lies farther than beta times its radius (with the second-order expansion; the
#: first-order one needs about 2 for the same error).
DEFAULT_BETA = 1.4

#: The first pass of :func:`inside` (``contains``, the sign of ``signed_distance``): a
#: walk at this ``beta`` and :data:`SIGN_NODE_ERROR` answers every point whose ``w``
#: lies farther than :data:`SIGN_FILTER_BOUND` from 1/2 (nearly all of them), the
#: default walk the rest.
SIGN_BETA = 1.1
#: The first pass's error target per far node (four times the default's
#: :data:`~lbvh.queries.winding_moments.NODE_ERROR`: Sponza's first pass 1.16x, the
#: terrain's 1.3x, for a largest error of 0.136 instead of 0.122 on Sponza).
SIGN_NODE_ERROR = 0.16
#: The walk at :data:`SIGN_BETA` and :data:`SIGN_NODE_ERROR` keeps ``|w - w_exact|``
#: within this. Measured as :data:`lbvh.metrics.error_bound.WINDING_BOUND` is,
#: over 1,048,576 points in the box grown by a fifth of each of the bench's scenes
#: against the walk at ``beta = 4``: at most 0.087 on the bunny, 0.187 on Sponza and
#: 0.073 on a 1M-triangle terrain through the restructured copy the walk takes
#: (:data:`WINDING_TREELET_ROUNDS`); 0.075, 0.136 and 0.094 through the Morton trees
#: (0.041, 0.122 and 0.065 there at the default node error).
SIGN_FILTER_BOUND = 0.25

#: The winding walk's own tree (:func:`walks_a_copy`, :meth:`lbvh.BVH.winding_target`):
#: an LBVH tree is walked through a copy of it after this many rounds of treelet
#: restructuring (:func:`lbvh.builders.restructure.restructured`, Karras & Aila 2013) of
#: :data:`WINDING_TREELET_LEAVES` leaves, made at the first inside query. The walk opens
#: the nodes whose balls hold a point, and the Morton tree's nodes, split where the codes
#: split, are larger than they need be. On the bench's 1M points (bench/README.md):
#: Sponza's ``contains`` 1.41x (252 -> 179 ms), its ``winding_numbers`` 1.38x, terrain-1m's
#: 1.07x and 1.04x, the bunny's the same, for 35 ms (Sponza) to 150 ms (terrain-1m) more
#: at the first inside query and a second tree's nodes and slots on the device. The
#: closest points keep the BVH's own tree (on Sponza 10% slower through a restructured
#: one).
WINDING_TREELET_ROUNDS = 6
#: Leaves per treelet of the winding walk's copy: 5 (not the builder's 7), a third of
#: the work a round for most of its gain.
WINDING_TREELET_LEAVES = 5


def walks_a_copy(builder: str) -> bool:
    """Whether the winding walk goes through a restructured copy of a tree made by
    ``builder`` (:data:`WINDING_TREELET_ROUNDS`): an LBVH without treelet rounds,
    collapsed or not (``"lbvh"``, ``"lbvh+collapse"``: on Sponza the collapsed one's
    ``contains`` 245 -> 171 ms through its copy); a tree built with treelet rounds or by
    another builder is walked as it is, as its maker chose."""
    return builder in ("lbvh", "lbvh+collapse")


#: Bit of the per-point flag word: the stack was full and a subtree was skipped.
FLAG_OVERFLOW = 1

_WORK_GROUP = 64


#: How far from the mesh's box, in its unit-size lengths (``2^40`` times its extent),
#: :func:`unit_points` moves a point to: there the far terms of a unit-size node
#: (distance^3 times size^4) are 0 in float32 and its ``r^2`` stays finite, where a
#: point 1e13 sizes away overflowed them to NaN.
FAR_LIMIT = 2.0 ** 40


def unit_points(points: np.ndarray, scale: float, bounds: tuple[np.ndarray, np.ndarray],
                points_range: tuple[float, float] | None = None) -> np.ndarray:
    """``float32 (N, 3)``: checked ``points`` at the mesh's unit size, as
    kernels/winding.cl walks them: times ``scale`` (the mesh's
    :func:`~lbvh.queries.winding_moments.winding_scale`, a power of two: exact), each
    coordinate clamped to within :data:`FAR_LIMIT` of the mesh's box ``bounds``
    (lower, upper) at that size. The same points and mesh at another power-of-two scale
    give the same floats. ``points_range`` (the least and the largest coordinate, as
    :func:`~lbvh.queries.closest.check_points_range` gives them) lets the common case,
    every point within reach, go by one float32 product (exact) or none (scale 1); a
    point beyond goes through float64, so that nothing overflows."""
    lo, hi = (np.asarray(b, np.float64) * scale for b in bounds)
    p = np.asarray(points, np.float32)
    if points_range is None:
        points_range = (float(p.min()), float(p.max())) if p.size else (0.0, 0.0)
    least, largest = points_range[0] * scale, points_range[1] * scale
    if least >= float(lo.max()) - FAR_LIMIT and largest <= float(hi.min()) + FAR_LIMIT:
        return p if scale == 1.0 else p * np.float32(scale)
    q = np.clip(p.astype(np.float64) * scale, lo - FAR_LIMIT, hi + FAR_LIMIT)
    return np.ascontiguousarray(q, dtype=np.float32)


def kernel_defines(ctx: dev.Context) -> dict[str, int]:
    """kernels/winding.cl's choices: ``INLINE_SQRT`` where the compiler is clang's
    (kernels/common.h: its inline square root; 1.09x on Sponza's winding numbers,
    bench/README.md), and ``CLANG_PREFETCH`` (the packet walk's prefetch of the
    records it pushes; kernels/wide_rows.h); ``ORDER``, that of the moments the trees
    keep (:data:`DEFAULT_ORDER`)."""
    return {"INLINE_SQRT": int(ctx.compiler_is_clang), "ORDER": DEFAULT_ORDER,
            "CLANG_PREFETCH": int(ctx.compiler_is_clang)}


#: Points a work-item of kernels/winding.cl's packet walk (``winding_packets``) answers.
PACKET = 16
#: The alignment in bits that the packet walk's whole-vector reads of a point buffer
#: need (three ``float16``, 64 bytes, from a buffer's start plus ``192 k`` bytes).
PACKET_ALIGN_BITS = 512


def use_packets(ctx: dev.Context, defines: dict[str, int], packets: bool | None = None) -> bool:
    """Whether :func:`winding_numbers` walks its points in packets of :data:`PACKET`
    (kernels/winding.cl ``winding_packets``) rather than one a work-item: only through
    wide records (``WIDE`` in the walk's ``defines``) on a device whose buffers start
    :data:`PACKET_ALIGN_BITS`-aligned; then as ``packets`` says, by default (None) on
    a CPU. The packets' points are put in their Morton order first (any batch of more
    than one packet), so that a packet's points lie close together. On a CPU a
    work-item is a loop iteration, and a packet's arithmetic is 16 points wide, where
    the per-point walk's vectors are a record's lanes, many of them idle near the
    surface: about 2x the points per second on Sponza, about the same on the bunny
    and a 1M terrain (bench/README.md). A GPU gets one point a work-item. A point's
    winding number is the same in any packet (and so in any batch), but not the same
    float as the per-point walk's (within the same bound of the exact sum)."""
    if not defines.get("WIDE") or ctx.device.mem_base_addr_align < PACKET_ALIGN_BITS:
        return False
    return bool(ctx.is_cpu) if packets is None else bool(packets)


def _check_beta(beta: Any) -> np.float32:
    try:
        b = float(beta)
    except (TypeError, ValueError):
        raise ValueError(f"beta: {beta!r}; expected a number >= 1") from None
    if not (b >= 1 and np.isfinite(b)):
        raise ValueError(f"beta: {beta!r}; expected a finite number >= 1")
    return np.float32(b * b)


def _check_node_error(node_error: Any) -> np.float32:
    """The kernel's ``floor_scale`` for a far node's error target ``node_error``."""
    try:
        e = float(node_error)
    except (TypeError, ValueError):
        raise ValueError(f"node_error: {node_error!r}; expected a positive number") from None
    if not (e > 0 and np.isfinite(e)):
        raise ValueError(f"node_error: {node_error!r}; expected a finite number > 0")
    return np.float32(NODE_ERROR / e)


@dev.serialised
def winding_numbers(target: QueryTarget, points: Any, *, beta: float = DEFAULT_BETA,
                    node_error: float = NODE_ERROR, batch_size: int = 1 << 20,
                    packets: bool | None = None) -> np.ndarray:
    """The generalised winding number of each point (see the module docstring).

    Args:
        target: an :class:`lbvh.BVH`.
        points: ``(N, 3)`` real array (converted to float32).
        beta: accuracy (>= 1): nodes farther than ``beta`` times their radius are
            expanded instead of summed.
        node_error: accuracy (> 0): a node is expanded only where the estimate of its
            expansion's error, ``A / (4 pi r^2) (R / r)^3``, is at most this
            (:data:`lbvh.queries.winding_moments.NODE_ERROR` unless told).
        batch_size: points per kernel launch.
        packets: walk the points 16 at a time (:func:`use_packets`; None, the default:
            on a CPU). The sums differ from the per-point walk's within the walk's error
            bound.

    Returns:
        ``float32 (N,)``.

    Raises:
        ValueError: a bad point (named), ``beta``, ``node_error`` or ``batch_size``.
        RuntimeError: the traversal stack overflowed (a tree deeper than 768 levels).
    """
    target = query_target(target)   # a BVH gives its query data
    target = target.winding_target()
    if target.tree.clipped_leaves:
        raise ValueError("winding_numbers: this tree has spatial splits (builder='sbvh'), whose "
                         "nodes would count a split triangle more than once; build another tree "
                         "for inside tests and signed distance")
    if packets is not None and not isinstance(packets, (bool, np.bool_)):
        raise ValueError(f"packets: {packets!r}; expected None, True or False")
    p, least, largest = check_points_range(points)
    beta2 = _check_beta(beta)
    floor_scale = _check_node_error(node_error)
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
    bounds = target.mesh.bounds
    scale = scale_of_box(*bounds)
    p = unit_points(p, scale, bounds, (least, largest))
    defines = {**defines, **kernel_defines(ctx)}
    box = tuple(np.float32(b * np.float32(scale)) for b in tree.root_box())
    moments = target.winding_moments()
    slot_faces = target.slot_faces()
    packed = use_packets(ctx, defines, packets)
    batch = int(min(batch_size, n))
    bufs = {"points": mem.alloc(12 * batch, flags=cl.mem_flags.READ_ONLY),
            "w": mem.alloc(4 * batch), "flags": mem.alloc(4 * batch)}
    order = sorted_points = None
    try:
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            m = stop - start
            ups = [cl.enqueue_copy(ctx.queue, bufs["points"], p[start:stop], is_blocking=False)]
            if m >= MIN_POINTS or (packed and m > PACKET):
                # nearby points one after another, read as one run (bench/README.md)
                order, sorted_points, ups = ordered_points(ctx, bufs["points"], m, *box)
            items = -(-m // PACKET) if packed else m
            launch = dev.Launch(items, 1, -(-items // _WORK_GROUP) * _WORK_GROUP, _WORK_GROUP)
            ev = dev.run(ctx, KERNEL_FILE, "winding_packets" if packed else "winding_numbers",
                         launch, records, moments,
                         target.mesh.vertices_buf, slot_faces, root, root_y, tree.num_nodes,
                         bufs["points"] if order is None else sorted_points,
                         order if order is not None else bufs["flags"], m, beta2,
                         floor_scale, np.float32(scale), bufs["w"], bufs["flags"],
                         defines={**defines, "POINT_ORDER": int(order is not None)},
                         wait_for=ups)
            cl.enqueue_copy(ctx.queue, out[start:stop], bufs["w"], wait_for=[ev], is_blocking=False)
            cl.enqueue_copy(ctx.queue, flags[start:stop], bufs["flags"], wait_for=[ev],
                            is_blocking=False)
            ctx.queue.finish()
            mem.free(order, sorted_points)
            order = sorted_points = None
    finally:
        mem.free(*bufs.values(), order, sorted_points)
    if (flags & FLAG_OVERFLOW).any():
        bad = np.flatnonzero(flags & FLAG_OVERFLOW)
        raise RuntimeError(f"winding_numbers: the traversal stack overflowed for {len(bad)} "
                           f"points (first: point {int(bad[0])}); the tree is deeper than the "
                           "kernel's stack")
    return out


def inside(target: QueryTarget, points: np.ndarray, beta: float | None = None) -> np.ndarray:
    """``bool (N,)``: ``winding > 0.5`` for checked ``points`` (``float32 (N, 3)``), by
    :func:`winding_numbers` at ``beta``; with ``beta`` None, the answers of the default
    walk in two passes (a filter): every point at :data:`SIGN_BETA` and
    :data:`SIGN_NODE_ERROR`, then by the default walk only the points whose first ``w``
    lies within :data:`SIGN_FILTER_BOUND` of 1/2. A point past that has the sign of its
    exact ``w``, and so of the default's, wherever both walks are within their bounds."""
    target = query_target(target)   # a BVH gives its query data
    points = checked_points(points)   # checked once: the walks below take it as it is
    if beta is not None:
        return winding_numbers(target, points, beta=beta) > 0.5
    w = winding_numbers(target, points, beta=SIGN_BETA, node_error=SIGN_NODE_ERROR)
    near = np.flatnonzero(np.abs(w - np.float32(0.5)) <= SIGN_FILTER_BOUND)
    if len(near):
        w[near] = winding_numbers(target, points.array[near], beta=DEFAULT_BETA)
    return w > 0.5


def contains(target: QueryTarget, points: Any, *, beta: float | None = None) -> np.ndarray:
    """``bool (N,)``: whether each point is inside the mesh, ``winding > 0.5``
    (:func:`winding_numbers` at ``beta``; None, the default: :data:`DEFAULT_BETA`'s
    answers, by the filter of :func:`inside`)."""
    target = query_target(target)   # a BVH gives its query data
    return inside(target, checked_points(points), beta)


def signed_distance(target: QueryTarget, points: Any, *,
                    beta: float | None = None) -> np.ndarray:
    """``float32 (N,)``: the distance to the mesh (:func:`lbvh.queries.closest.closest_points`),
    negative inside (``winding > 0.5``, as :func:`contains` answers it)."""
    target = query_target(target)   # a BVH gives its query data
    p = checked_points(points)   # once, for both queries
    distance = closest_points(target, p).distance
    return np.where(inside(target, p, beta), -distance, distance)


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


def expansion_numpy(moments: np.ndarray, points: np.ndarray, scale: float) -> np.ndarray:
    """The twin of kernels/winding.cl's far-node term: ``float64 (K, N)``, the winding
    number that the expansion of each node of ``moments`` (``(K, 28)`` or ``(K, 15)``
    rows of :func:`lbvh.queries.winding_moments.node_moments`, its order read from the
    row length) gives at each point, ``(N, 3)``; in float64 from the float32 moments,
    which are those of the mesh times ``scale`` (its
    :func:`~lbvh.queries.winding_moments.winding_scale`), as the points are scaled."""
    m = np.asarray(moments, np.float64)
    r = m[:, None, 0:3] - np.asarray(points, np.float64)[None, :, :] * scale   # p - q
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    inv = 1.0 / np.sqrt(x * x + y * y + z * z)
    inv3 = inv ** 3
    col = [m[:, k, None] for k in range(m.shape[1])]
    pairs = (x * x, y * y, z * z, x * y, x * z, y * z)
    quad = sum(col[8 + q] * pairs[q] for q in range(6))          # -3 r^T M r
    w = (col[4] * x + col[5] * y + col[6] * z + col[7]) * inv3 + quad * inv3 * inv * inv
    if m.shape[1] == ROWS_ORDER2:
        axes = (x, y, z)
        cubic = sum(col[17 + c] * axes[a] * axes[b] * axes[d]
                    for c, (a, b, d) in enumerate(CUBIC_MONOMIALS))
        w = w + (col[14] * x + col[15] * y + col[16] * z) * inv3 * inv * inv \
            + cubic * inv3 * inv ** 4
    return w / (4.0 * np.pi)
