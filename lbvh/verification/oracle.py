"""Brute-force ray/triangle intersection in numpy: the exact oracle of the ray queries.

Every ray is tested against every triangle with the watertight test of Woop,
Benthin and Wald (JCGT 2013), written once for two precisions. The shear is
taken times ``d_kz`` as in the kernel (``x = ez p_kx - ex p_kz`` instead of
``p_kx - Sx p_kz``, see :class:`_Rays`): the same test in exact arithmetic,
and in either precision a vertex exactly on the ray's line lands exactly on
it (a ray along an edge is then in the triangle's plane: ``det = 0``, a miss).

``dtype=np.float64`` (the oracle)
    Coordinates are the caller's float32 values, the arithmetic is float64:
    ``p - o`` is exact, each later step rounds to 53 bits, so ``t`` and the
    barycentrics carry a relative error of a few 1e-16 times the conditioning
    of the hit (``1 / cos`` of the angle between ray and triangle plane); hit
    or miss can differ from exact arithmetic only for rays within about 1e-15
    (relative to the coordinates) of a triangle's edge.

``dtype=np.float32`` (the kernel's twin)
    The kernel's default watertight test on a device with doubles
    (kernels/ray_triangle.h): each edge function's sign and the sign of ``t``
    exact (double with an error bound, exact integers where the bound does
    not settle it: :mod:`lbvh.queries.exact`), ``t, u, v`` from the same
    double formula, the direction scaled by ``2^-texp``, and accept_hit's
    rule: a hit counts only where the ray enters the triangle's own box by
    the slab test, its ``t`` raised to that box's entry. For the triangle the
    kernel reports, its ``t, u, v`` equal the twin's bit for bit.

Zero-area triangles are never hit, in both precisions and in the kernel: a
triangle is degenerate when its corners are exactly collinear (see
:func:`degenerate_triangles`); the float64 Woop test alone would let rays
through the line of a collinear triangle hit it after rounding.

By default (``cull=True``) ray-triangle pairs whose triangle lies in a block
of 16 triangles whose box (padded by ``1e-6`` of the scene's scale) the ray
cannot reach are skipped before the exact test; the padding is a million
times the float64 rounding of that box test, so culling never changes a
result (``cull=False`` tests every pair, to check exactly that). Pairs are
processed in chunks of :data:`MAX_PAIRS` to bound memory.

Both return :class:`lbvh.queries.traverse.Hits`; among triangles hit at exactly the
same ``t`` the lowest triangle index wins.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..mesh import as_faces, as_vertices
from ..queries.all_hits import AllHits
# the kernel's degenerate test and its twin live with the walks that read it
from ..queries import exact
from ..queries.traverse import Hits, check_rays, degenerate_triangles
#: Triangles per culling block, and the blocks' padding relative to the scene's scale.
BLOCK_SIZE = 16
BLOCK_PADDING = 1e-6


def woop_axes(directions: np.ndarray) -> np.ndarray:
    """``int64 (N, 3)`` axis permutation (kx, ky, kz) of each ray, as the kernel picks it.

    ``kz`` is the axis of the largest ``|d|`` (ties resolved in the kernel's
    comparison order); ``kx, ky`` follow cyclically and are swapped when
    ``d[kz] < 0`` so that the triangle's winding is kept.
    """
    ad = np.abs(directions)
    kz = np.where(ad[:, 0] >= ad[:, 1], np.where(ad[:, 0] >= ad[:, 2], 0, 2),
                  np.where(ad[:, 1] >= ad[:, 2], 1, 2))
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    swap = directions[np.arange(len(directions)), kz] < 0
    kx, ky = np.where(swap, ky, kx), np.where(swap, kx, ky)
    return np.stack([kx, ky, kz], axis=1).astype(np.int64)


#: make_ray's range of directions (kernels/traverse.cl): a direction whose largest
#: component lies outside [2^-60, 2^60] is traced as ``d * 2^-texp``.
_TEXP_RANGE = 60


def _texp(directions: np.ndarray) -> np.ndarray:
    """``int64 (N,)``: the power of two the kernel divides each direction by (make_ray)."""
    dmax = np.abs(directions).max(axis=1).astype(np.float64)
    _, e = np.frexp(dmax)
    e = e.astype(np.int64)
    out = np.where(e > 0, e - _TEXP_RANGE, e + _TEXP_RANGE - 1)
    inside = (dmax >= 2.0 ** -_TEXP_RANGE) & (dmax <= 2.0 ** _TEXP_RANGE)
    return np.where(inside, 0, out)


def _exact_under(c: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``bool``: whether ``c * 2^-e`` is exact in ``c``'s precision."""
    return np.ldexp(np.ldexp(c, -e), e) == c


class _Rays:
    """Validated rays with the per-ray constants of the watertight test.

    The shear of Woop et al. 2013 (``Sx = d_kx / d_kz``, ``Sy = d_ky / d_kz``) is
    taken times ``d_kz`` as the kernel does (make_ray): the sheared coordinates
    are ``x = ez p_kx - ex p_kz``, ``y = ez p_ky - ey p_kz`` with ``(ex, ey, ez)``
    ``= (d_kx, d_ky, d_kz) 2^-e``, ``|ez|`` in ``[0.5, 1)``. In float32 a ray whose
    ``d_kx`` or ``d_ky`` would lose bits in that scaling is ``hard``: the kernel
    tests its triangles in double with ``e = 0``. The float32 twin also traces
    ``d * 2^-texp`` (make_ray) and scales ``t`` back, as the kernel does.
    """

    def __init__(self, origins: Any, directions: Any, tmin: Any, tmax: Any, dtype) -> None:
        rays = check_rays(origins, directions, tmin, tmax)
        self.count = len(rays)
        self.origin = rays.origins
        self.direction = rays.directions
        self.tmin, self.tmax = rays.intervals()
        rows = np.arange(self.count)[:, None]
        if dtype == np.float32:
            self.texp = _texp(self.direction)
            traced = np.ldexp(self.direction, -self.texp[:, None]).astype(np.float32)
        else:
            self.texp = np.zeros(self.count, np.int64)
            traced = self.direction
        self.axes = woop_axes(traced)
        d = traced[rows, self.axes].astype(dtype)
        self.o_perm = self.origin[rows, self.axes].astype(dtype)
        _, e = np.frexp(d[:, 2])
        e = e.astype(np.int64)
        if dtype == np.float32:
            self.hard = (e > 0) & ~(_exact_under(d[:, 0], e) & _exact_under(d[:, 1], e))
            e = np.where(self.hard, 0, e)
        else:
            self.hard = np.zeros(self.count, bool)   # float64 holds every scaled float32 exactly
        # (ex, ey, ez) and sz = 1 / d_kz, as the kernel computes them, in the chosen precision
        self.shear = np.ldexp(d, -e[:, None]).astype(dtype)
        with np.errstate(divide="ignore"):
            self.sz = dtype(1) / d[:, 2]
        if dtype == np.float32:
            # the slab test of accept_hit (kernels/traverse.cl) on d * 2^-texp
            self.traced = traced
            self.tmin_traced = np.ldexp(self.tmin.astype(np.float32), self.texp).astype(np.float32)
            with np.errstate(divide="ignore", over="ignore"):
                self.inv = (np.float32(1) / traced).astype(np.float32)
            big = np.float32(np.finfo(np.float32).max)
            self.inv_near = np.where((traced != 0) & np.isinf(self.inv),
                                     np.copysign(big, traced), self.inv).astype(np.float32)
            self.negative = np.signbit(traced)


def _edge_sign(F: np.ndarray, px: np.ndarray, py: np.ndarray, qx: np.ndarray,
               qy: np.ndarray) -> np.ndarray:
    """EDGE_SIGN of kernels/ray_triangle.h: the sign of ``F``, and where ``F == 0`` the sign
    at the ray moved by ``(eps, eps^2)``: of ``py - qy``, then of ``qx - px``."""
    tie = np.where(py > qy, 1, np.where(py < qy, -1, np.where(qx > px, 1,
                                                              np.where(qx < px, -1, 0))))
    return np.where(F > 0, 1, np.where(F < 0, -1, tie))


def _inside(U, V, W, ax, ay, bx, by, cx, cy, edge_rule: bool) -> np.ndarray:
    """RAY_INSIDE of kernels/ray_triangle.h (``det != 0`` is checked apart)."""
    if edge_rule:
        su, sv, sw = (_edge_sign(U, cx, cy, bx, by), _edge_sign(V, ax, ay, cx, cy),
                      _edge_sign(W, bx, by, ax, ay))
        return (su == sv) & (sv == sw) & (su != 0)
    return ~(((U < 0) | (V < 0) | (W < 0)) & ((U > 0) | (V > 0) | (W > 0)))


def _pair_hits(v: np.ndarray, f: np.ndarray, rays: _Rays, ray: np.ndarray, tri: np.ndarray,
               skip: np.ndarray, dtype, edge_rule: bool = False
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Woop 2013 for the pairs (``ray[k]``, ``tri[k]``): ``t, u, v`` per pair, ``t`` NaN on a
    miss (a hit's ``t`` may be inf: float32's, undone from d * 2^-texp, can overflow).

    tmin/tmax are not applied here. Operation order follows kernels/ray_triangle.h;
    ``edge_rule``: its EDGE_RULE (a ray through a shared edge or vertex hits one triangle);
    the fourth value is the sign of each pair's det (hit_triangle's return: +1 where the
    ray enters the front), from the arithmetic the test took.
    """
    axes = rays.axes[ray]
    o = rays.o_perm[ray]
    ex, ey, ez = (rays.shear[ray, k] for k in range(3))
    sz = rays.sz[ray]
    if dtype == np.float32:
        t, bu, bv, sign, inside = _exact_pairs(v, f, rays, ray, tri, axes, o, edge_rule)
    else:
        x, y, z = [], [], []
        for corner in range(3):
            vid = f[tri, corner]
            rel = [v[vid, axes[:, k]].astype(dtype) - o[:, k] for k in range(3)]
            z.append(rel[2])
            x.append(rel[0] * ez - rel[2] * ex)
            y.append(rel[1] * ez - rel[2] * ey)
        (ax, bx, cx), (ay, by, cy) = x, y
        with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
            U = cx * by - cy * bx
            V = ax * cy - ay * cx
            W = bx * ay - by * ax
            det = U + V + W
            T = U * (sz * z[0]) + V * (sz * z[1]) + W * (sz * z[2])
            inside = _inside(U, V, W, ax, ay, bx, by, cx, cy, edge_rule) & (det != 0)
            t = T / det
            bu = V / det
            bv = W / det
            sign = np.sign(det)
            if dtype == np.float64:
                # where a sign is within float64's rounding (a ray through an edge or a
                # vertex, an origin on the plane), decide it in exact rational arithmetic
                finite = np.isfinite(np.stack([*x, *y, *z], axis=1)).all(axis=1)
                Q = np.abs(np.stack([v[f[tri, c], axes[:, k]].astype(np.float64) - o[:, k]
                                     for c in range(3) for k in range(3)], axis=1)).max(axis=1)
                ez2 = ez.astype(np.float64) ** 2
                edge = 2.0 ** -40 * ez2 * Q * Q
                near = ((np.minimum(np.minimum(np.abs(U), np.abs(V)), np.abs(W)) <= edge)
                        | (np.abs(U * z[0] + V * z[1] + W * z[2]) <= 2.0 ** -38 * ez2 * Q ** 3))
                # two edge functions of opposite signs beyond their rounding: a miss
                # whatever the others' exact signs (most pairs far from the origin,
                # where every rounding is large: 905K exact pairs of 1.9M on the
                # far_from_origin case, 334 s)
                sure_miss = (((U > edge) | (V > edge) | (W > edge))
                             & ((U < -edge) | (V < -edge) | (W < -edge)))
                near &= finite & ~sure_miss
                for k in np.flatnonzero(near):
                    hit, tk, sk = exact_pair(v[f[tri[k]]], rays.origin[ray[k]],
                                             rays.direction[ray[k]],
                                             *((axes[k], rays.shear[ray[k]]) if edge_rule
                                               else ()))
                    inside[k], sign[k] = hit, sk
                    if hit:
                        t[k] = float(tk)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        if dtype == np.float32:
            # accept_hit takes a t below its best, INFINITY at most: a t that
            # overflows along d * 2^-texp is no hit
            inside &= _own_box(v, f, rays, ray, tri, t) & (t < np.inf)
            # accept_hit decides tmin on t along d * 2^-texp: a t of the wrong side that
            # rounds to -0 once scaled back is still no hit
            inside &= t >= rays.tmin_traced[ray]
            # t was measured along d * 2^-texp; undone it may overflow to inf, as the
            # kernel's does (keep_hit), and stays a hit, as the float64 oracle's
            with np.errstate(over="ignore"):
                t = np.ldexp(t, -rays.texp[ray]).astype(np.float32)
    inside &= ~skip[tri]
    # a miss is NaN: no comparison takes it, where inf may be a hit's t
    return np.where(inside, t, np.nan), bu, bv, sign


def exact_pair(corners: np.ndarray, origin: np.ndarray, direction: np.ndarray,
               axes: np.ndarray | None = None, shear: np.ndarray | None = None):
    """One ray against one triangle in exact rational arithmetic on the float32 inputs:
    ``(inside, t, sign)``: whether the ray's line crosses the triangle (edge functions
    ``d . ((p - o) x (r - o))`` with no two of opposite signs, not all zero), its
    exact ``t`` (a ``Fraction``, of any sign) and the sign of det (+1 where the ray
    enters the front). The reference of :mod:`tests.queries.test_invariance`.

    With ``axes`` (kx, ky, kz) and ``shear`` (ex, ey, ez), EDGE_RULE: an edge function
    that is exactly 0 takes the sign of ``y_p - y_r``, then of ``x_r - x_p``, of the
    exactly sheared corners (kernels/ray_triangle.h), and the ray is inside where
    the three signs are one."""
    from fractions import Fraction
    # Every float32 is an integer times 2^-149: the values times 2^149 are integers, and
    # Python's integers do the products and sums exactly without the gcd a Fraction
    # takes at every step (7x faster on the far_from_origin case); every sign below
    # is that of a product of as many scaled factors on each side, and t a ratio of two.
    a, b, c = (_scaled_ints(p) for p in corners)
    o = _scaled_ints(origin)
    d = _scaled_ints(direction)
    q = [[p[i] - o[i] for i in range(3)] for p in (a, b, c)]

    def cross(x, y):
        return [x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]]

    def dot(x, y):
        return sum(i * j for i, j in zip(x, y))
    e = [dot(d, cross(q[2], q[1])), dot(d, cross(q[0], q[2])), dot(d, cross(q[1], q[0]))]
    n = cross([b[i] - a[i] for i in range(3)], [c[i] - a[i] for i in range(3)])
    nd = dot(n, d)
    if all(x == 0 for x in e) or nd == 0:
        return False, Fraction(0), 0
    if axes is None:
        if min(e) < 0 < max(e):
            return False, Fraction(0), 0
    else:
        kx, ky, kz = (int(k) for k in axes)
        ex, ey, ez = _scaled_ints(shear)

        def ruled(f, p, r):
            if f != 0:
                return (f > 0) - (f < 0)
            y = ez * (p[ky] - r[ky]) - ey * (p[kz] - r[kz])
            if y != 0:
                return (y > 0) - (y < 0)
            x = ez * (r[kx] - p[kx]) - ex * (r[kz] - p[kz])
            return (x > 0) - (x < 0)
        signs = {ruled(e[0], c, b), ruled(e[1], a, c), ruled(e[2], b, a)}
        if len(signs) != 1 or 0 in signs:
            return False, Fraction(0), 0
    return True, Fraction(dot(n, q[0]), nd), (1 if nd < 0 else -1)


#: float32 values are integers times 2^-FLOAT32_SCALE (the denormals' unit).
FLOAT32_SCALE = 149


def _scaled_ints(values) -> list[int]:
    """Finite float32 values times 2^149, as exact Python integers."""
    out = []
    for x in np.asarray(values, np.float32).ravel():
        num, den = float(x).as_integer_ratio()   # den: a power of two, 2^149 at most
        out.append(num * ((1 << FLOAT32_SCALE) // den))
    return out


def _exact_pairs(v: np.ndarray, f: np.ndarray, rays: _Rays, ray: np.ndarray, tri: np.ndarray,
                 axes: np.ndarray, o: np.ndarray, edge_rule: bool):
    """hit_triangle of kernels/ray_triangle.h on a device with doubles, for the pairs
    (``ray[k]``, ``tri[k]``): ``t`` (float32, along d * 2^-texp), ``u``, ``v``, the sign
    of det and whether the ray is inside (before accept_hit). Double stage and
    exact signs as :mod:`lbvh.queries.exact` says; the same operations in the same
    order as the kernel, so the same bits."""
    e32 = rays.shear[ray].astype(np.float32)
    ex, ey, ez = (e32[:, k].astype(np.float64) for k in range(3))
    o64 = o.astype(np.float64)
    corners = [np.stack([v[f[tri, c], axes[:, k]] for k in range(3)], axis=1).astype(np.float32)
               for c in range(3)]
    q = [p.astype(np.float64) - o64 for p in corners]
    X = [qq[:, 0] * ez - qq[:, 2] * ex for qq in q]
    Y = [qq[:, 1] * ez - qq[:, 2] * ey for qq in q]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        U = X[2] * Y[1] - Y[2] * X[1]
        V = X[0] * Y[2] - Y[0] * X[2]
        W = X[1] * Y[0] - Y[1] * X[0]
        Q = np.abs(np.stack(q, axis=1)).reshape(len(ray), 9).max(axis=1)
        ez2 = ez * ez
        bound = ((ez2 * exact.BOUND_EDGE) * Q) * Q
        F = np.stack([U, V, W], axis=1)
        pos, neg = F > bound[:, None], F < -bound[:, None]
        sign = np.where(pos, 1, np.where(neg, -1, 0)).astype(np.int64)
        undecided = ~(pos | neg)
        alive = ~(pos.any(axis=1) & neg.any(axis=1))
        edges = ((2, 1), (0, 2), (1, 0))   # U: c x b, V: a x c, W: b x a
        for j, (p_, r_) in enumerate(edges):
            k = np.flatnonzero(undecided[:, j] & alive)
            if len(k):
                sign[k, j] = exact.edge_signs_exact(e32[k], o[k], corners[p_][k], corners[r_][k])
        su, sv, sw = sign[:, 0], sign[:, 1], sign[:, 2]
        if edge_rule:
            ruled = [exact.ruled_signs_exact(sign[:, j], e32, corners[p_], corners[r_])
                     if (sign[:, j] == 0).any() else sign[:, j]
                     for j, (p_, r_) in enumerate(edges)]
            inside = (ruled[0] == ruled[1]) & (ruled[1] == ruled[2]) & (ruled[0] != 0)
        else:
            inside = ~(((su < 0) | (sv < 0) | (sw < 0)) & ((su > 0) | (sv > 0) | (sw > 0)))
        inside &= alive & ~((su == 0) & (sv == 0) & (sw == 0))
        s = np.where(su + sv + sw > 0, 1, -1)
        # an unsettled edge function whose double value is 0 or of the wrong sign counts 0
        settled = ~undecided.any(axis=1)
        U, V, W = (np.where(settled | ((F > 0) == (sg > 0)) & ((F < 0) == (sg < 0)), F, 0.0)
                   for F, sg in ((U, su), (V, sv), (W, sw)))
        det = exact.sum3(U, V, W)
        T = exact.sum3(U * q[0][:, 2], V * q[1][:, 2], W * q[2][:, 2])
        tbound = (((ez2 * exact.BOUND_NUMERATOR) * Q) * Q) * Q
        sT = np.where(T > tbound, 1, np.where(T < -tbound, -1, 0)).astype(np.int64)
        k = np.flatnonzero(inside & (np.abs(T) <= tbound))
        if len(k):
            sT[k] = exact.numerator_signs_exact(o[k], corners[0][k], corners[1][k],
                                                corners[2][k])
        dkz = rays.traced[ray, axes[:, 2]].astype(np.float32)
        st = np.where(dkz < 0, -(sT * s), sT * s)
        t = np.where(det != 0, np.abs(T / (det * dkz.astype(np.float64))), 0.0).astype(np.float32)
        t = np.where((st != 0) & (t == 0), np.float32(2.0 ** -149), t)
        t = np.where(st == 0, np.float32(0), np.where(st < 0, -t, t)).astype(np.float32)
        bu = np.where(det != 0, V / det, 0.0).astype(np.float32)
        bv = np.where(det != 0, W / det, 0.0).astype(np.float32)
    return t, bu, bv, s, inside


#: The slab test's factor on the far distance (SLAB_PAD in kernels/traverse.cl).
SLAB_PAD = np.float32(1 + 2.0 ** -21)


def _keep_max(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """max_keep of the kernel: ``x > m ? x : m`` (NaN in x keeps m)."""
    return np.where(x > m, x, m)


def _own_box(v: np.ndarray, f: np.ndarray, rays: _Rays, ray: np.ndarray, tri: np.ndarray,
             t: np.ndarray) -> np.ndarray:
    """accept_hit of kernels/traverse.cl in float32, for the float32 twin: whether the
    ray enters triangle ``tri``'s own box by the slab test (``bool`` per pair), and
    ``t`` (along d * 2^-texp, updated in place) raised to that box's entry where
    ``tmin <= t < t0``."""
    p = v[f[tri]]                      # (pairs, 3 corners, 3 axes) float32
    lower, upper = p.min(axis=1), p.max(axis=1)
    neg = rays.negative[ray]
    near, far = np.where(neg, upper, lower), np.where(neg, lower, upper)
    o = rays.origin[ray]
    with np.errstate(over="ignore", invalid="ignore"):
        t0 = rays.tmin_traced[ray]
        t1 = np.full(len(ray), np.inf, np.float32)
        for k in range(3):
            t0 = _keep_max((near[:, k] - o[:, k]) * rays.inv_near[ray, k], t0)
            t1 = np.where((far[:, k] - o[:, k]) * rays.inv[ray, k] < t1,
                          (far[:, k] - o[:, k]) * rays.inv[ray, k], t1)
        enters = t0 <= t1 * SLAB_PAD
        raise_ = t >= rays.tmin_traced[ray]
        t[raise_] = _keep_max(t0, t)[raise_]
    return enters


def _blocks(v: np.ndarray, f: np.ndarray, pad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles in spatially coherent blocks: (order, block lower, block upper), float64 boxes."""
    p = v.astype(np.float64)[f]
    lo, hi = p.min(axis=1), p.max(axis=1)
    centre = 0.5 * (lo + hi)
    c_lo, c_hi = centre.min(axis=0), centre.max(axis=0)
    extent = np.where(c_hi > c_lo, c_hi - c_lo, 1.0)
    cell = np.minimum(((centre - c_lo) / extent * 1024).astype(np.int64), 1023)
    order = np.argsort(_interleave(cell), kind="stable")
    starts = np.arange(0, len(f), BLOCK_SIZE)
    return (order, np.minimum.reduceat(lo[order], starts) - pad,
            np.maximum.reduceat(hi[order], starts) + pad)


def _interleave(cell: np.ndarray) -> np.ndarray:
    """Morton order key of 10-bit cell coordinates (only used to group nearby triangles)."""
    key = np.zeros(len(cell), np.int64)
    for bit in range(10):
        for axis in range(3):
            key |= ((cell[:, axis] >> bit) & 1) << (3 * bit + axis)
    return key


def _reachable_blocks(rays: _Rays, idx: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``bool (len(idx), B)``: whether each ray's [tmin, tmax] meets each padded block box.

    Slab test in float64 with the near plane picked by the sign bit (so -0.0 is
    negative) and fmax/fmin ignoring the NaN of an origin on a plane with a
    zero direction component.
    """
    o = rays.origin[idx].astype(np.float64)
    d = rays.direction[idx].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        neg = np.signbit(d)
        tn = np.full((len(idx), len(lo)), -np.inf)
        tf = np.full((len(idx), len(lo)), np.inf)
        for k in range(3):
            near = np.where(neg[:, k:k + 1], hi[None, :, k], lo[None, :, k])
            far = np.where(neg[:, k:k + 1], lo[None, :, k], hi[None, :, k])
            tn = np.fmax(tn, (near - o[:, k:k + 1]) * inv[:, k:k + 1])
            tf = np.fmin(tf, (far - o[:, k:k + 1]) * inv[:, k:k + 1])
    return (tn <= tf) & (tf >= rays.tmin[idx, None]) & (tn <= rays.tmax[idx, None])


#: Ray-triangle pairs per numpy step of the brute-force answers (about ``400 *
#: MAX_PAIRS`` bytes).
MAX_PAIRS = 1 << 18


def _candidate_pairs(rays: _Rays, num_tris: int, blocks, max_pairs: int):
    """Yield (ray, tri) index arrays of at most about ``max_pairs`` pairs covering every
    pair that is not culled."""
    if blocks is None:
        per = max(1, max_pairs // num_tris)
        for start in range(0, rays.count, per):
            r = np.arange(start, min(rays.count, start + per))
            yield np.repeat(r, num_tris), np.tile(np.arange(num_tris), len(r))
        return
    order, lo, hi = blocks
    per = max(1, max_pairs // max(len(lo), BLOCK_SIZE))
    for start in range(0, rays.count, per):
        idx = np.arange(start, min(rays.count, start + per))
        r, b = np.nonzero(_reachable_blocks(rays, idx, lo, hi))
        ray = np.repeat(idx[r], BLOCK_SIZE)
        slot = (b[:, None] * BLOCK_SIZE + np.arange(BLOCK_SIZE)).ravel()
        keep = slot < num_tris
        ray, slot = ray[keep], slot[keep]
        for s in range(0, len(ray), max_pairs):
            yield ray[s:s + max_pairs], order[slot[s:s + max_pairs]]


def _every_hit(vertices: Any, faces: Any, origins: Any, directions: Any, tmin: Any, tmax: Any,
               dtype, cull: bool, max_pairs: int, edge_rule: bool
               ) -> tuple[_Rays, list[tuple[np.ndarray, ...]]]:
    """Every (ray, triangle, t, u, v, sign of det) hit in ``[tmin, tmax]``, in chunks
    (:func:`_pair_hits`)."""
    dtype = np.dtype(dtype).type
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"dtype: {dtype}; expected float32 or float64")
    v = as_vertices(vertices)
    f = as_faces(faces, len(v)).astype(np.int64)
    rays = _Rays(origins, directions, tmin, tmax, dtype)
    skip = degenerate_triangles(v, f, dtype)
    blocks = None
    if cull:
        scale = max(float(np.abs(v).max()), float(np.abs(rays.origin).max(initial=0.0)), 1e-30)
        blocks = _blocks(v, f, BLOCK_PADDING * scale)
    found = []
    for ray, tri in _candidate_pairs(rays, len(f), blocks, max_pairs):
        t, bu, bv, sign = _pair_hits(v, f, rays, ray, tri, skip, dtype, edge_rule)
        ok = (t >= rays.tmin[ray]) & (t <= rays.tmax[ray])   # NaN: a miss
        found.append((ray[ok], tri[ok], t[ok], bu[ok], bv[ok], sign[ok]))
    return rays, found


def brute_force(vertices: Any, faces: Any, origins: Any, directions: Any, tmin: Any = 0.0,
                tmax: Any = np.inf, *, dtype=np.float64, cull: bool = True) -> Hits:
    """Closest hit of every ray against every triangle (see the module docstring).

    Args:
        vertices: ``(V, 3)``, faces: ``(F, 3)``: the mesh (validated like the builder's input).
        origins, directions, tmin, tmax: rays as for :func:`lbvh.queries.traverse.intersect`
            (same validation, same float32 conversion).
        dtype: ``np.float64`` for the oracle, ``np.float32`` for the kernel's twin.
        cull: skip pairs whose triangle's block the ray cannot reach (never changes results).

    Returns:
        :class:`lbvh.queries.traverse.Hits`, float32 fields (the oracle's float64 ``t, u, v``
        rounded to nearest), ``overflow`` all ``False``.
    """
    rays, found = _every_hit(vertices, faces, origins, directions, tmin, tmax, dtype, cull,
                             MAX_PAIRS, edge_rule=False)
    n = rays.count
    out = Hits(t=np.full(n, np.inf, np.float32), prim=np.full(n, -1, np.int32),
               u=np.zeros(n, np.float32), v=np.zeros(n, np.float32),
               overflow=np.zeros(n, bool), overflow_count=0)
    if found:
        ray, tri, t, bu, bv, _ = (np.concatenate(cols) for cols in zip(*found))
        order = np.lexsort((tri, t, ray))            # by ray, then t, then triangle index
        first = order[np.unique(ray[order], return_index=True)[1]]
        r = ray[first]
        # + 0 turns -0.0 into +0.0, as the kernel does. A float64 t beyond float32's
        # range becomes inf, as the kernel's t does (a hit that far is still a hit:
        # its primitive is kept); the cast's overflow warning says nothing more.
        with np.errstate(over="ignore"):
            out.t[r], out.prim[r], out.u[r], out.v[r] = (t[first] + 0, tri[first], bu[first],
                                                          bv[first])
    return out


def hits_on(vertices: Any, faces: Any, origins: Any, directions: Any, prims: Any,
            dtype=np.float64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``t, u, v`` of ray ``i`` against triangle ``prims[i]`` (tmin/tmax ignored).

    ``t`` is ``inf`` where the ray misses that triangle (or it is degenerate).
    Used to judge ties: two triangles hit at the same distance.
    """
    dtype = np.dtype(dtype).type
    v = as_vertices(vertices)
    f = as_faces(faces, len(v)).astype(np.int64)
    rays = _Rays(origins, directions, 0.0, np.inf, dtype)
    prims = np.asarray(prims, np.int64)
    skip = degenerate_triangles(v, f, dtype)
    t, bu, bv, _ = _pair_hits(v, f, rays, np.arange(rays.count), prims, skip, dtype)
    return np.where(np.isnan(t), np.inf, t), bu, bv


def all_hits_brute(vertices: Any, faces: Any, origins: Any, directions: Any, tmin: Any = 0.0,
                   tmax: Any = np.inf, *, dtype=np.float64, cull: bool = True) -> AllHits:
    """Every hit of every ray against every triangle, with the edge rule of
    kernels/all_hits.cl (a ray through a shared edge or vertex hits one of its
    triangles): the twin of :func:`lbvh.queries.all_hits.all_hits` (``dtype=np.float32``:
    the same hits, ``t, u, v`` bit for bit) and its oracle (``np.float64``).

    Returns :class:`lbvh.queries.all_hits.AllHits`, nearest first per ray (equal ``t``:
    lower triangle first), nothing truncated.
    """
    rays, found = _every_hit(vertices, faces, origins, directions, tmin, tmax, dtype, cull,
                             MAX_PAIRS, edge_rule=True)
    n = rays.count
    if found:
        ray, tri, t, bu, bv, _ = (np.concatenate(cols) for cols in zip(*found))
    else:
        ray, tri = np.zeros(0, np.int64), np.zeros(0, np.int64)
        t = bu = bv = np.zeros(0)
    with np.errstate(over="ignore"):
        t = (t + 0).astype(np.float32)
    order = np.lexsort((tri, t, ray))
    total = np.bincount(ray, minlength=n).astype(np.int64)
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(total, out=offsets[1:])
    return AllHits(offsets, t[order], tri[order].astype(np.int32),
                   bu[order].astype(np.float32), bv[order].astype(np.float32), total,
                   np.zeros(n, bool), 0, np.zeros(n, bool))



def signed_counts_brute(vertices: Any, faces: Any, origins: Any, directions: Any,
                        tmin: Any = 0.0, tmax: Any = np.inf, *, dtype=np.float32,
                        cull: bool = True) -> np.ndarray:
    """The twin of ``count_hits(..., signed=True)``: every hit of :func:`all_hits_brute`
    (``dtype``) counted -1 where its det is positive (the ray enters the triangle's
    front, ``n . d < 0``, ``n = (b - a) x (c - a)``) and +1 where it is negative, det
    as the test computed it (float32: from the corners moved to the ray's origin and
    rounded, as the kernel's; a sliver's can differ in sign from the exact ``n . d``,
    consistently for the triangles of a closed surface): ``int64 (N,)``."""
    rays, found = _every_hit(vertices, faces, origins, directions, tmin, tmax, dtype, cull,
                             MAX_PAIRS, edge_rule=True)
    if not found:
        return np.zeros(rays.count, np.int64)
    ray, *_, sign = (np.concatenate(cols) for cols in zip(*found))
    return np.bincount(ray, weights=-sign, minlength=rays.count).astype(np.int64)
