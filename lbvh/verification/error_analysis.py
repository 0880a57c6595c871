"""Float32 error analysis of ray/triangle pairs: how far the traversal kernel's
answer may lie from exact arithmetic, pair by pair (:class:`PairGeometry`); the
:class:`~lbvh.verification.rules.Judge` decides with it.

The bound on ``t``, with ``u = 2^-24``::

    |t - t_ref| * |cos a| <= 16 u (t_ref + s) kappa

``a`` is the angle between the ray and the triangle's normal, ``s`` the distance
from the ray's origin to the triangle's farthest vertex over ``|d|`` (the size
of the numbers the float32 test subtracts), ``kappa >= 1`` the conditioning of
the triangle seen along the ray (the sum of the magnitudes of the products in
its edge functions over their sum: about 1 for a fat triangle, its aspect ratio
for a sliver). Whatever the conditioning, the kernel's ``t`` must also lie in
the range of the triangle's vertex depths (along the ray, over ``|d|``),
widened by ``16 u`` of the largest: the kernel's ``t`` is a convex combination
of them (:class:`PairGeometry`), so a bound that ``kappa / |cos a|`` makes
meaningless (1e70 and more for slivers seen edge-on) does not let any ``t`` pass.

How it relates to :func:`lbvh.metrics.error_bound.t_bound` (the bound the
tests and the benches use, and the one home of :data:`U`, :data:`T_BOUND` and
:data:`UNDERFLOW`, which this analysis takes from there): the same ``T_BOUND =
16 u`` on the same quantities, made finer per pair. ``t_bound`` takes one
scene-wide ``s = (extent + largest origin component) / |d|``, no ``kappa``
(enough for well-shaped triangles, such as the tests' scenes) and floors ``|cos a|``;
here ``s`` is the pair's own, ``kappa`` the pair's conditioning, and where the
quotient is meaningless the interval of the vertex depths decides. Beyond the
bound on ``t``, the analysis bounds each edge function's rounding, which says
whether a hit is robust (every rounding hits), possible (some rounding hits)
or impossible, and decides rays in a triangle's plane (``det = 0``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..metrics.error_bound import T_BOUND, U, UNDERFLOW
from .hard_cases import Case
from .oracle import woop_axes


@dataclass
class PairGeometry:
    """Ray/triangle pairs analysed in float64 in the kernel's own frame (Woop 2013:
    origin at the ray's, permuted and sheared so that the ray is +z), with bounds
    on the float32 kernel's rounding. One entry per pair:

    * ``t``: distance of the hit on the triangle's plane (NaN or inf where ``det = 0``:
      the ray lies in the plane or parallel to it; the kernel's rounding can still
      make a hit of a triangle in the ray's plane, which ``lo, hi`` then bound);
    * ``bound``: how far the kernel's ``t`` may be from it (the module docstring's bound);
    * ``robust``: every rounding the kernel can do still gives a hit in
      ``[tmin, tmax]`` (all edge functions clear of zero by their error bound,
      ``t`` clear of the interval's ends, the triangle not degenerate);
    * ``possible``: some rounding gives a hit (no edge function is clearly on the
      wrong side, and ``[lo, hi]`` meets ``[tmin, tmax]``); the kernel may return
      it, or not;
    * ``lo``, ``hi``: where the kernel's ``t`` of a hit on the triangle must lie
      whatever the conditioning: the kernel returns only hits whose three edge
      functions share a sign, so its ``t = (U z_a + V z_b + W z_c) / (U + V + W)``
      is a convex combination of the vertices' depths ``z / d_kz``, up to its
      rounding: ``[min z, max z] / d_kz`` widened by ``16 u max |z / d_kz|`` (the
      kernel's is below ``10 u``: ``v - o``, ``1 / d_kz``, the products, the two
      sums, the quotient) and by ``UNDERFLOW``. Where ``bound`` is meaningless (a
      sliver or a triangle seen edge-on: ``kappa / |cos a|`` of 1e70 and more,
      bounds far beyond float32's range) this interval still decides.
    """
    t: np.ndarray
    bound: np.ndarray
    robust: np.ndarray | None
    possible: np.ndarray | None
    lo: np.ndarray
    hi: np.ndarray


def _edge_function(p: tuple, q: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``q.x p.y - q.y p.x`` in float64, its float32 error bound, and the sum of the
    magnitudes of its two products (for the conditioning of the determinant).

    ``p`` and ``q`` are ``(x, y, mx, my)``: sheared coordinates and the sizes of the
    numbers the kernel computed them from (``|v - o| + |shear * z|`` per axis):
    each coordinate carries at most about ``5 u`` of those; the bound allows 16 u.
    Below float32's normal range rounding is absolute: ``UNDERFLOW`` is added to
    the sizes (through ``mx, my``, for a shear constant that underflows, times the
    depth) and to the products.
    """
    px, py, pmx, pmy = p
    qx, qy, qmx, qmy = q
    value = qx * py - qy * px
    size = np.abs(qx * py) + np.abs(qy * px)
    error = 16 * U * (np.abs(qx) * pmy + np.abs(py) * qmx + np.abs(qy) * pmx
                      + np.abs(px) * qmy + size) + UNDERFLOW
    return value, error, size


def pair_geometry(case: Case, ray: np.ndarray, tri: np.ndarray, degenerate32: np.ndarray,
                  degenerate64: np.ndarray) -> PairGeometry:
    """:class:`PairGeometry` of the pairs (``ray[k]``, ``tri[k]``).

    ``degenerate32/64`` (one per pair) say whether
    :func:`lbvh.queries.traverse.degenerate_triangles` calls ``tri[k]`` degenerate in
    float32 (the kernel never hits those) and in float64 (the oracle's decision);
    triangles degenerate in one precision only may be hit or not.
    """

    with np.errstate(all="ignore"):  # parallel rays and infinite bounds make NaN on purpose
        return _pair_geometry(case, ray, tri, degenerate32, degenerate64, woop_axes)


def _pair_geometry(case: Case, ray: np.ndarray, tri: np.ndarray, degenerate32: np.ndarray,
                   degenerate64: np.ndarray, woop_axes) -> PairGeometry:
    d32 = case.directions[ray]
    axes = woop_axes(d32)
    rows = np.arange(len(ray))[:, None]
    o = case.origins[ray].astype(np.float64)[rows, axes]
    d = d32.astype(np.float64)[rows, axes]
    sx, sy, sz = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2], 1.0 / d[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    corners, depth = [], []
    reach = np.zeros(len(ray))  # farthest vertex from the origin
    for corner in range(3):
        r = case.vertices[case.faces[tri, corner]].astype(np.float64)[rows, axes] - o
        reach = np.maximum(reach, np.linalg.norm(r, axis=1))
        # the sizes carry the absolute floor of underflowing differences and shears
        floor = UNDERFLOW / (16 * U) * (1.0 + np.abs(r[:, 2]))
        # r_x - Sx r_z as the kernel forms it (times d_kz, no quotient before the
        # difference): exactly 0 for a vertex on the ray's line
        corners.append(((r[:, 0] * dz - r[:, 2] * dx) / dz, (r[:, 1] * dz - r[:, 2] * dy) / dz,
                        np.abs(r[:, 0]) + np.abs(sx * r[:, 2]) + floor,
                        np.abs(r[:, 1]) + np.abs(sy * r[:, 2]) + floor))
        depth.append(r[:, 2] * sz)
    a, b, c = corners
    (u_, eu, su), (v_, ev, sv), (w_, ew, sw) = _edge_function(b, c), _edge_function(c, a), \
        _edge_function(a, b)
    det = u_ + v_ + w_
    t = (u_ * depth[0] + v_ * depth[1] + w_ * depth[2]) / det
    kappa = np.maximum((su + sv + sw) / np.abs(det), 1.0)
    tri64 = case.vertices[case.faces[tri]].astype(np.float64)
    normal = np.cross(tri64[:, 1] - tri64[:, 0], tri64[:, 2] - tri64[:, 0])
    dn = np.linalg.norm(d, axis=1)
    cos = np.abs((normal * case.directions[ray].astype(np.float64)).sum(axis=1)) / (
        np.linalg.norm(normal, axis=1) * dn)
    s = reach / dn
    bound = T_BOUND * (np.abs(np.nan_to_num(t)) + s) * kappa / cos
    bound = np.where(np.isfinite(bound), bound, np.inf)
    outside = (((u_ < -eu) | (v_ < -ev) | (w_ < -ew)) & ((u_ > eu) | (v_ > ev) | (w_ > ew)))
    inside = (((u_ > eu) & (v_ > ev) & (w_ > ew)) | ((u_ < -eu) & (v_ < -ev) & (w_ < -ew)))
    tmin, tmax = case.tmin[ray].astype(np.float64), case.tmax[ray].astype(np.float64)
    depths = np.stack(depth, axis=1)
    margin = T_BOUND * np.abs(depths).max(axis=1) + UNDERFLOW
    lo, hi = depths.min(axis=1) - margin, depths.max(axis=1) + margin
    # The kernel's projected triangle holds the origin only if the box of its three
    # projected vertices does: the origin lies in the exact vertices' box widened by
    # their rounding. (Implied by ~outside for a triangle seen at an angle; for one
    # seen edge-on, which projects onto a segment, it says whether the origin lies
    # on that segment or beside it.)
    in_box = np.ones(len(ray), bool)
    for k in (0, 1):
        ends = np.stack([p[k] for p in corners], axis=1)
        slack = 16 * U * np.stack([p[k + 2] for p in corners], axis=1)
        in_box &= ((ends - slack).min(axis=1) <= 0) & ((ends + slack).max(axis=1) >= 0)
    # det = 0 (a ray in the triangle's plane, or parallel to it): no t on the plane;
    # a hit the kernel's rounding makes has its t in [lo, hi]
    plane = np.isfinite(t)
    t_fits = np.where(plane, (t >= tmin - bound) & (t <= tmax + bound), True)
    kernel_may = ~degenerate32
    robust = (kernel_may & ~degenerate64 & inside & (np.abs(det) > eu + ev + ew)
              & (t >= tmin + bound) & (t <= tmax - bound))
    possible = (kernel_may & ~outside & in_box & t_fits & (hi >= tmin) & (lo <= tmax))
    return PairGeometry(t, bound, robust, possible | robust, lo, hi)


def t_agrees(g: PairGeometry, t: np.ndarray) -> np.ndarray:
    """Whether the kernel's ``t`` is the pairs' ``t`` within the bound and within
    ``[lo, hi]``. The kernel reports a ``t`` past float32's range as ``inf`` (its
    primitive kept): that agrees where the values it may have (``t`` within the
    bound, in ``[lo, hi]``) reach past float32's range."""
    big = float(np.finfo(np.float32).max) * (1 - T_BOUND)
    with np.errstate(invalid="ignore"):
        plane = np.isfinite(g.t)
        beyond = (t == np.inf) & (g.hi >= big) & (~plane | (g.t + g.bound >= big))
        near = np.where(plane, np.abs(g.t - t) <= g.bound, True)  # det = 0: [lo, hi]
        return (near & (t >= g.lo) & (t <= g.hi)) | beyond
