"""The moments of the winding numbers' far-node expansion (kernels/winding_moments.cl).

kernels/winding.cl replaces a node of the tree that lies far from a point by
the expansion of its triangles' solid angles about their area-weighted
centroid (Barill et al. 2018, sections 3.1-3.2): per node, the centroid ``p``,
the radius ``R`` of the node about it, the sum ``N`` of the vector areas, the
first moment ``M`` and, to the second order, the contracted ``H_ijk``
(:func:`node_moments` says which floats, in which order). A tree makes them
once, at its first inside query, and :class:`lbvh.BVH` keeps them with the
wide records they follow (:func:`wide_moments`: the lanes' moments in rows,
then the corners of each leaf lane's first triangle, :func:`lane_corners`).

:func:`make_moments` makes them on the device where it has doubles
(cl_khr_fp64; PoCL has): a bottom-up walk per leaf sums each node's
triangle terms in double about the centre of the mesh's box and writes the
node's float32 rows as soon as its sums are known, in its own row or in the
lane of the wide record that holds it. Its twins are
:func:`node_moments` and :func:`wide_moments`, the same float64 operations in
the same order: the device's floats are theirs bit for bit (tested). The
time is in bench/README.md (bench_queries.py's scene table: the device and
the twins, the same tree in the same run). A device without doubles, or
whose largest buffer would not hold the nodes' sums, gets the twins'
numbers, computed on the host and uploaded.

Lengths are scaled by :func:`winding_scale`, a power of two that brings a
mesh of any size to unit size, where kernels/winding.cl walks it.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..builders.refit import clear_arrivals
from ..layout import NODE_DTYPE, children_of, is_leaf, node_depths, prim_range_of
from ..tree import Mesh, Tree
from .wide import Wide

KERNEL_FILE = "winding_moments.cl"

__all__ = ["DEFAULT_ORDER", "ROWS_ORDER1", "ROWS_ORDER2", "CORNER_ROWS", "CUBIC_MONOMIALS",
           "NODE_ERROR", "node_moments", "wide_moments", "lane_corners", "read_lanes", "make_moments",
           "device_can_make", "kernel_defines", "winding_scale", "scale_of_box", "least_first"]

#: Floats per node of the first-order moments (:func:`node_moments` with ``order=1``).
ROWS_ORDER1 = 15
#: Floats per node with the second-order terms (``order=2``, the default).
ROWS_ORDER2 = 28
#: Rows a wide record holds after its lanes' moments: the corners of each leaf lane's
#: first triangle (:func:`lane_corners`).
CORNER_ROWS = 9
#: The error allowed per far node, estimated as ``A / (4 pi r^2) * (R / r)^3`` (``A``
#: the node's triangle area, ``r`` the point's distance to ``p``): its solid angle's
#: bound times the relative error of the second-order expansion, ``(R / r)^3`` (Barill
#: et al. 2018). The last row of each node holds ``A R^3 / (4 pi NODE_ERROR)``, and
#: kernels/winding.cl expands a node only where ``r^5`` is at least that as well as
#: ``r > beta R``: a node of much area for its radius (a tube, seen along its axis from
#: beyond an open end, 1.3 radii from its centre, was off by 0.06 alone: Sponza's beams)
#: is opened instead. On a smooth patch (a node's area about twice its radius squared)
#: the floor is about ``1.3 R``, where ``beta`` is already. Measured on 1M points per
#: bench scene (bench/README.md): the largest error 0.062 -> 0.048 on Sponza, 0.042 ->
#: 0.037 on terrain-1m, for about 6% more time on Sponza and none measurable elsewhere;
#: 0.03 gave 0.051 on Sponza and 1.2x the time on terrain-1m.
NODE_ERROR = 0.04
#: The floor's divisor, ``4 pi NODE_ERROR`` (one float64 for the kernel and the twin).
FAR_DIVISOR = 4.0 * np.pi * NODE_ERROR
#: The order of the expansion of far nodes (Barill et al. 2018 use 2).
DEFAULT_ORDER = 2

# the six pairs (j, k), j <= k, of the symmetric second moments, in the kernel's order
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: The ten monomials ``r_a r_b r_c`` (axes a <= b <= c) of the second order's cubic, in
#: the order of their coefficients' rows (:func:`node_moments`): xxx, yyy, zzz, xxy,
#: xxz, xyy, yyz, xzz, yzz, xyz.
CUBIC_MONOMIALS = ((0, 0, 0), (1, 1, 1), (2, 2, 2), (0, 0, 1), (0, 0, 2), (0, 1, 1),
                   (1, 1, 2), (0, 2, 2), (1, 2, 2), (0, 1, 2))


def least_first(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each face's corners from its least on (ascending x, then y, then z, of the
    float32 ``vertices``), in the face's cyclic order, ``int64 (F, 3)``, and
    ``bool (F,)``: the faces two of whose corners are one point (kept as they are).
    The twin of kernels/common.h ``least_corner``: the winding walk and its moments
    read a triangle so, whatever corner the mesh lists first (a face flipped then
    differs only by its last two corners)."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    p = [v[f[:, k]] for k in range(3)]

    def before(a, b):
        return (a[:, 0] < b[:, 0]) | ((a[:, 0] == b[:, 0]) & (
            (a[:, 1] < b[:, 1]) | ((a[:, 1] == b[:, 1]) & (a[:, 2] < b[:, 2]))))

    def same(a, b):
        return (a == b).all(axis=1)
    one_point = same(p[0], p[1]) | same(p[1], p[2]) | same(p[0], p[2])
    first = np.where(before(p[1], p[0]) & before(p[1], p[2]), 1,
                     np.where(before(p[2], p[0]) & before(p[2], p[1]), 2, 0))
    first[one_point] = 0
    rotated = np.take_along_axis(f, (first[:, None] + np.arange(3)) % 3, axis=1)
    return rotated, one_point


def _triangle_terms(vertices: np.ndarray, faces: np.ndarray, order: int = 1) -> np.ndarray:
    """``float64 (F, 16)`` per triangle (``(F, 34)`` with ``order=2``): area, area *
    centroid (3), vector area ``a`` (3), the 3x3 outer product ``a c^T`` row by row (9);
    with ``order=2`` also ``a_i Q_jk`` for ``i`` = x, y, z and the six pairs ``jk`` of
    :data:`_PAIRS` (18), ``Q`` the mean of ``x x^T`` over the triangle,
    ``(sum_v v v^T + 9 c c^T) / 12``, the sums over the corners grouped symmetric in
    the last two (``faces`` as :func:`least_first` gives them: the same terms for any
    first corner, those of ``a`` negated exactly for a face flipped). The array is the
    transpose of a C-ordered ``(columns, F)`` one: each term is contiguous."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    # corner k's coordinate j: x[k][j], contiguous (F,) arrays
    x = [[v[f[:, k], j] for j in range(3)] for k in range(3)]
    e1 = [x[1][j] - x[0][j] for j in range(3)]
    e2 = [x[2][j] - x[0][j] for j in range(3)]
    a = [0.5 * (e1[1] * e2[2] - e1[2] * e2[1]), 0.5 * (e1[2] * e2[0] - e1[0] * e2[2]),
         0.5 * (e1[0] * e2[1] - e1[1] * e2[0])]
    area = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    c = [(x[0][j] + (x[1][j] + x[2][j])) / 3.0 for j in range(3)]
    out = np.empty((16 if order == 1 else 34, len(f)))
    out[0] = area
    for j in range(3):
        out[1 + j] = area * c[j]
        out[4 + j] = a[j]
        for k in range(3):
            out[7 + 3 * j + k] = a[j] * c[k]
    if order == 2:
        for m, (j, k) in enumerate(_PAIRS):
            q = ((x[0][j] * x[0][k] + (x[1][j] * x[1][k] + x[2][j] * x[2][k]))
                 + 9.0 * c[j] * c[k]) / 12.0
            for i in range(3):
                out[16 + 3 * m + i] = a[i] * q
    return out.T


def _shift(vertices: np.ndarray) -> np.ndarray:
    """The centre of the mesh's box in float64: what the sums are taken about."""
    v = np.asarray(vertices)
    if not len(v):
        return np.zeros(3)
    return _centre(v.min(axis=0), v.max(axis=0))


def _centre(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The centre of a box, in float64 (the float32 corners convert exactly)."""
    return 0.5 * (np.asarray(lower, np.float64) + np.asarray(upper, np.float64))


def winding_scale(vertices: np.ndarray) -> float:
    """The power of two that brings a mesh to unit size: ``2^-e`` with the largest
    extent of the mesh's box in ``[2^(e-1), 2^e)``, ``e`` within [-126, 126] (a
    normal float32). kernels/winding.cl walks every mesh at that size: the points
    (:func:`lbvh.queries.winding.unit_points`), the nodes' centres and rows
    (:func:`node_moments`) and the corner rows (:func:`lane_corners`) are scaled by
    it, and the vertices it reads from the mesh are, there. So no float32 product of
    the walk overflows or underflows on a mesh of any size (unscaled, the walk
    answered NaN for an icosphere of radius 1e6 or 1e-8: tests/queries/test_winding.py),
    and the same mesh and points at any power-of-two scale are walked with the same
    floats: the same winding numbers, bit for bit (tests/queries/test_invariance.py).
    Scaling the points once, on the host, costs nothing measurable; scaling every
    difference in the walk cost 4-7% on Sponza and a 1M terrain (bench/README.md)."""
    v = np.asarray(vertices)
    if not len(v):
        return 1.0
    return scale_of_box(v.min(axis=0), v.max(axis=0))


def scale_of_box(lower: np.ndarray, upper: np.ndarray) -> float:
    """:func:`winding_scale` of a mesh whose vertices' box is ``lower, upper``."""
    extent = float((np.asarray(upper, np.float64) - np.asarray(lower, np.float64)).max())
    if not extent > 0 or not np.isfinite(extent):
        return 1.0
    e = int(np.frexp(extent)[1])
    return float(2.0 ** -min(max(e, -126), 126))


def node_moments(nodes: np.ndarray, prim_order: np.ndarray, root: int, vertices: np.ndarray,
                 faces: np.ndarray, order: int = DEFAULT_ORDER,
                 scale: float | None = None) -> np.ndarray:
    """``float32 (num_nodes, 28)`` (``order=2``) or ``(num_nodes, 15)`` (``order=1``):
    what kernels/winding.cl reads of each node, each coefficient of the expansion
    one float, ready to multiply (the kernel's far term adds no moments together).

    ``[0:3]`` the area-weighted centroid ``p`` of the node's triangles (the box's
    centre if their area is 0), ``[3]`` ``R^2``, ``R`` the distance from ``p`` to the
    farthest corner of the node's box, ``[4:7]`` ``N``, the sum of the triangles'
    vector areas; of ``M = sum a_t (c_t - p)^T``, ``[7]`` its trace and ``[8:14]``
    ``-3`` times the coefficients of ``r^T M r`` over the pairs xx, yy, zz, xy, xz, yz
    (``M_jj``, ``M_jk + M_kj``). With ``order=2`` the second-order terms of
    ``H_ijk = sum_t a_t,i S_t,jk``, ``S_t`` the mean of ``(x - p)(x - p)^T`` over
    triangle ``t``: ``[14:17]`` ``g = -3/2 (2 u + t)``, ``u_k = H_iik``,
    ``t_i = H_ijj``; ``[17:27]`` the coefficients of the cubic
    ``15/2 sum_ijk H_ijk r_i r_j r_k`` over its ten monomials
    (:data:`CUBIC_MONOMIALS`). The last row (``[14]``, or ``[27]`` with ``order=2``):
    the far floor ``A R^3 /`` :data:`FAR_DIVISOR`, ``A`` the sum of the triangles'
    areas. Sums in float64 about the centre of the mesh's box (so that meshes far from
    the origin lose no digits): leaves over their slots, internal nodes from their
    children level by level, then shifted to ``p``, combined into the coefficients
    and rounded once.

    Every length is multiplied by ``scale`` (default :func:`winding_scale` of the
    vertices, a power of two) before it is summed: ``p`` (``centre + shift * scale``),
    ``R^2``, ``N``, ``M`` and the second-order rows are those of the mesh at unit
    size, where kernels/winding.cl walks it.
    """
    if order not in (1, 2):
        raise ValueError(f"order: {order!r}; expected 1 or 2")
    n = len(nodes)
    v = np.asarray(vertices, np.float64)
    shift = _shift(v)
    scale = winding_scale(vertices) if scale is None else float(scale)
    slots, _ = least_first(vertices, np.asarray(faces)[np.asarray(prim_order)])
    terms = _triangle_terms((v - shift) * scale, slots, order).T
    cols = np.zeros((len(terms), n))            # (columns, nodes): each term contiguous
    leaf = is_leaf(nodes)
    first, count = prim_range_of(nodes).T
    lf = np.flatnonzero(leaf & (count > 0))
    # a sum over each leaf's own slots, term by term (not prefix differences, which
    # would lose a small leaf's digits to the sums of the whole mesh)
    at, k = lf, 0
    while len(at):
        part = terms[:, first[at] + k]
        if k == 0:
            cols[:, at] = part
        else:
            cols[:, at] += part
        k += 1
        at = at[count[at] > k]
    del terms
    kids = children_of(nodes)
    if n > 1:
        parent = np.full(n, -1, np.int64)
        inner = np.flatnonzero(~leaf)
        parent[kids[inner, 0]] = inner
        parent[kids[inner, 1]] = inner
        depth = node_depths(parent, root)
        for level in range(int(depth.max()) - 1, -1, -1):
            at = inner[depth[inner] == level]
            cols[:, at] = cols[:, kids[at, 0]] + cols[:, kids[at, 1]]
    lower = (nodes["lower"].astype(np.float64).T - shift[:, None]) * scale
    upper = (nodes["upper"].astype(np.float64).T - shift[:, None]) * scale
    area = cols[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        centre = np.where(area > 0, cols[1:4] / area, 0.5 * (lower + upper))
    out = np.empty((ROWS_ORDER1 if order == 1 else ROWS_ORDER2, n), np.float32)
    far = np.maximum(np.abs(upper - centre), np.abs(centre - lower))
    out[0:3] = centre + (shift * scale)[:, None]
    out[3] = r2 = (far * far).sum(axis=0)
    out[-1] = area * r2 * np.sqrt(r2) / FAR_DIVISOR
    big_n = cols[4:7]
    out[4:7] = big_n
    b = cols[7:16].reshape(3, 3, n)        # B_ij = sum a_i c_j
    # M = B - N p^T, read by the kernel as tr M and the pairs of its symmetric part
    m = [[b[i, j] - big_n[i] * centre[j] for j in range(3)] for i in range(3)]
    out[7] = (m[0][0] + m[1][1]) + m[2][2]
    for q, (j, k) in enumerate(_PAIRS):
        out[8 + q] = -3.0 * (m[j][j] if j == k else m[j][k] + m[k][j])
    if order == 2:
        # H_ijk = sum a_i Q_jk - B_ij p_k - B_ik p_j + N_i p_j p_k, B = sum a c^T
        h = {}
        for q, (j, k) in enumerate(_PAIRS):
            h[j, k] = h[k, j] = (cols[16 + 3 * q:19 + 3 * q] - b[:, j] * centre[k]
                                 - b[:, k] * centre[j] + big_n * (centre[j] * centre[k]))
        u = [sum(h[i, k][i] for i in range(3)) for k in range(3)]     # u_k = H_iik
        t = [sum(h[j, j][i] for j in range(3)) for i in range(3)]     # t_i = H_ijj
        for k in range(3):
            out[14 + k] = -1.5 * (2.0 * u[k] + t[k])
        # the cubic's coefficient of each monomial r_a r_b r_c: the sum over each
        # factor i of the monomial of 15/2 H_ijk (jk the other two), doubled where j != k
        for c, cube in enumerate(CUBIC_MONOMIALS):
            coefficient = 0.0
            for n_i, i in enumerate(cube):
                if i in cube[:n_i]:
                    continue           # each distinct factor once
                rest = list(cube)
                rest.remove(i)
                j, k = rest
                term = (7.5 if j == k else 15.0) * h[j, k][i]
                coefficient = term if n_i == 0 else coefficient + term
            out[17 + c] = coefficient
    return np.ascontiguousarray(out.T)


def lane_corners(lanes: np.ndarray, nodes: np.ndarray, prim_order: np.ndarray,
                 vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``float32 (records, CORNER_ROWS, width)``: the corners of the first triangle
    (slot) of each leaf lane of the wide records (``lanes``, as :func:`wide_moments`
    takes them; ``nodes`` and ``prim_order`` the binary tree's), rows x, y, z of its
    first corner, then of the second and the third, from its least corner on
    (:func:`least_first`; a triangle with two corners at one point: its first corner
    three times, whose solid angle is 0), the float32 vertices times their
    :func:`winding_scale`;
    zeros in a lane that is not a leaf or is empty. kernels/winding.cl sums the near
    leaves' first triangles from these rows, lane by lane, instead of one by one
    through the faces (kernels/winding_moments.cl ``store_corners``, its twin)."""
    lanes = np.asarray(lanes)
    node = np.maximum(lanes, 0)
    leaf = (lanes >= 0) & is_leaf(nodes)[node]
    first = prim_range_of(nodes)[node, 0]
    tri, one_point = least_first(vertices, np.asarray(faces, np.int64)[
        np.asarray(prim_order, np.int64)[np.where(leaf, first, 0)].ravel()])
    tri[one_point] = tri[one_point, :1]
    corners = np.asarray(vertices, np.float32)[tri].reshape(*lanes.shape, CORNER_ROWS) \
        * np.float32(winding_scale(vertices))
    corners[~leaf] = 0.0
    return np.ascontiguousarray(corners.transpose(0, 2, 1))


def wide_moments(moments: np.ndarray, lanes: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """``float32 (records, rows + CORNER_ROWS, width)``: what kernels/winding.cl reads of
    each wide record (WIDE=1), ``rows`` those of ``moments`` (28 or 15): row ``k`` holds
    ``moments[:, k]`` (:func:`node_moments`) of each lane's binary node (``lanes``,
    ``int32 (records, width)``, -1 for an empty lane, as :class:`lbvh.queries.wide.Wide`
    keeps them); an empty lane has zeros and ``R^2`` and the far floor ``-1``, so the
    kernel takes it for far and adds nothing. The last :data:`CORNER_ROWS` are
    ``corners`` (:func:`lane_corners`)."""
    lanes = np.asarray(lanes)
    out = np.asarray(moments, np.float32)[np.maximum(lanes, 0)].transpose(0, 2, 1).copy()
    empty = np.broadcast_to((lanes < 0)[:, None, :], out.shape)
    out[empty] = 0.0
    out[:, 3][lanes < 0] = -1.0
    out[:, -1][lanes < 0] = -1.0
    return np.concatenate([out, np.asarray(corners, np.float32)], axis=1)


def read_lanes(ctx: dev.Context, wide: Wide) -> np.ndarray:
    """``int32 (records, width)``: the binary node of each lane of the records."""
    lanes = np.empty((wide.count, wide.width), np.int32)
    if wide.count:
        cl.enqueue_copy(ctx.queue, lanes, wide.lanes, is_blocking=True)
    return lanes



#: Double sums a node keeps on the device while the moments are made (kernels/winding_moments.cl
#: ``TERMS``): the columns of :func:`_triangle_terms`.
TERMS = {1: 16, 2: 34}


def kernel_defines(order: int, width: int | None) -> dict[str, int]:
    """kernels/winding_moments.cl's defines: the ``ORDER`` and, for the rows of wide
    records of ``width`` lanes, ``WIDE_OUT`` and ``WIDTH`` (``None``: one row per node)."""
    if width is None:
        return {"ORDER": order, "WIDE_OUT": 0}
    return {"ORDER": order, "WIDE_OUT": 1, "WIDTH": width}


def device_can_make(ctx: dev.Context, num_nodes: int, order: int) -> bool:
    """Whether :func:`make_moments` runs on the device: it has doubles and its largest
    buffer holds every node's sums (read from the device)."""
    return bool(ctx.device.double_fp_config) and \
        8 * TERMS[order] * max(num_nodes, 1) <= ctx.memory.max_alloc


def make_moments(ctx: dev.Context, tree: Tree, mesh: Mesh, wide: Wide | None,
                 order: int = DEFAULT_ORDER) -> cl.Buffer:
    """The moments on the device: ``float32 (records, rows + CORNER_ROWS, width)`` in the
    rows of ``wide``'s records where they are packed (:func:`wide_moments`), else
    ``float32 (num_nodes, rows)`` (:func:`node_moments`); ``rows`` 28 (``order=2``) or 15.

    Made by kernels/winding_moments.cl where :func:`device_can_make`, else by the
    twins on the host. The caller holds ``ctx.lock`` and owns the buffer returned.
    """
    if order not in TERMS:
        raise ValueError(f"order: {order!r}; expected 1 or 2")
    rows = ROWS_ORDER1 if order == 1 else ROWS_ORDER2
    into_records = wide is not None and wide.packed and wide.count > 0
    mem = ctx.memory
    if not device_can_make(ctx, tree.num_nodes, order):
        nodes = np.empty(tree.num_nodes, NODE_DTYPE)
        prim_order = np.empty(tree.num_prims, np.int32)
        cl.enqueue_copy(ctx.queue, nodes, tree.nodes, is_blocking=True)
        cl.enqueue_copy(ctx.queue, prim_order, tree.prim_order, is_blocking=True)
        moments = node_moments(nodes, prim_order, tree.root, mesh.vertices, mesh.faces, order)
        if into_records:
            lanes = read_lanes(ctx, wide)
            moments = wide_moments(moments, lanes, lane_corners(lanes, nodes, prim_order,
                                                                mesh.vertices, mesh.faces))
        return mem.upload(moments)
    sx, sy, sz = (np.float64(s) for s in _centre(*mesh.bounds))
    scale = np.float64(scale_of_box(*mesh.bounds))
    width = wide.width if into_records else None
    defines = kernel_defines(order, width)
    out = mem.alloc(4 * (wide.count * wide.width * (rows + CORNER_ROWS) if into_records
                         else rows * tree.num_nodes))
    sums = mem.alloc(8 * TERMS[order] * tree.num_nodes)
    arrivals = mem.alloc(4 * tree.num_nodes)
    slot = mem.alloc(4 * tree.num_nodes) if into_records else None
    try:
        events = [clear_arrivals(ctx, arrivals, tree.num_nodes)]
        if into_records:
            lanes = wide.count * wide.width
            events.append(clear_arrivals(ctx, slot, tree.num_nodes))
            fill = ctx.launch(lanes, min_per_item=4096)
            events.append(dev.run(ctx, KERNEL_FILE, "lane_slots", fill, wide.lanes, slot, out,
                                  lanes, fill.per_item, defines=defines, wait_for=events))
        leaf_list, leaf_first, num_leaves = tree.leaf_walks()
        walks = ctx.walk_launch(num_leaves, min_per_item=256)
        dev.run(ctx, KERNEL_FILE, "moments", walks, mesh.vertices_buf, mesh.faces_buf,
                tree.prim_order, tree.nodes, tree.parent, arrivals,
                leaf_list if leaf_list is not None else arrivals, leaf_list is not None,
                leaf_first, num_leaves, sums, slot if into_records else arrivals, out, sx, sy,
                sz, scale, np.float64(FAR_DIVISOR), walks.per_item, defines=defines,
                wait_for=events)
        ctx.queue.finish()
    except BaseException:
        mem.free(out)
        raise
    finally:
        mem.free(sums, arrivals, slot)
    return out
