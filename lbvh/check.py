"""``lbvh check``: the hard-case suite (:mod:`lbvh.hard_cases`) run by every builder.

For each case and builder it builds the tree, runs the validator, looks for
NaN or infinite boxes, compares the stack the traversal needs with the one it
gets, traces the
case's rays (closest hit and any hit) and compares them with the reference
answers: the float64 brute-force oracle (:func:`lbvh.oracle.brute_force`), or
the exact answers a case carries when it is too big for the oracle.

What must hold (a case passes when all do):

* the build succeeds and ``bvh.validate()`` passes; no box has a NaN or an infinity;
* the stack the traversal can need (:func:`lbvh.traverse.stack_need`, at least
  the depth) <= the stack it gets (:func:`lbvh.traverse.stack_size_for`),
  and then no ray overflows; a case that forces a smaller stack may overflow,
  but only on rays flagged ``overflow``;
* every ray not flagged ``overflow`` agrees with the reference: same hit or
  miss, ``t`` within the bound below, the same triangle unless the reference
  hits the kernel's triangle at the same ``t`` within the bound (a tie); the
  any-hit query gives the same hit or miss;
* rays a case marks ``must_hit`` (from inside a closed mesh) all hit: no leak.

The bound on ``t``, with ``u = 2^-24``::

    |t - t_ref| * |cos a| <= 16 u (t_ref + s) kappa

``a`` is the angle between the ray and the triangle's normal, ``s`` the distance
from the ray's origin to the triangle's farthest vertex over ``|d|`` (the size
of the numbers the float32 test subtracts), ``kappa >= 1`` the conditioning of
the triangle seen along the ray (the sum of the magnitudes of the products in
its edge functions over their sum: about 1 for a fat triangle, its aspect ratio
for a sliver). It is tests/test_traverse.py's bound times ``kappa``. Whatever
the conditioning, the kernel's ``t`` must also lie in the range of the
triangle's vertex depths (along the ray, over ``|d|``), widened by
``16 u`` of the largest: the kernel's ``t`` is a convex combination of them
(:class:`PairGeometry`), so a bound that ``kappa / |cos a|`` makes meaningless
(1e70 and more for slivers seen edge-on) does not let any ``t`` pass.

The oracle computes in float64, the kernel in float32: where they disagree,
:class:`Judge` decides with the kernel's own rounding errors (a hit that
exact arithmetic gives for some input within those errors is right; a miss
is wrong only if a triangle is hit for every such input). Rays through shared
edges and vertices, grazing and near-edge hits, ties between triangles at the
same ``t`` and triangles at the degeneracy threshold land there. So do rays in
a triangle's plane (``det = 0`` in float64): the kernel's rounded coordinates
leave the plane, and it may hit such a triangle; a hit there is right where
the origin lies on the segment the triangle projects to (within rounding) and
``t`` within the vertices' depths (:class:`PairGeometry`).

In the table, ``wrong`` counts rays with a wrong answer (closest hit, any hit,
and leaks), ``ambig`` rays whose answer differs from the oracle's but is right
within float32 rounding (ties on shared edges and vertices, grazing hits, thin
triangles: :class:`Judge`); ``worst rel dt`` is the largest ``|t - t_ref| / t_ref``
over rays that hit the reference's triangle at least 1/1000 of the scene's
extent from their origin; ``dt/bound`` the largest ratio of the error to the bound.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from typing import Any, Iterable

import numpy as np

from . import hard_cases
from .hard_cases import Case

U = 2.0 ** -24
T_BOUND = 16 * U
#: Absolute error floor of float32 results that underflow (2^9 of the smallest denormal).
UNDERFLOW = 2.0 ** -140

#: Builders by the names ``--builders`` takes: the options given to :func:`lbvh.build`.
BUILDERS: dict[str, dict[str, Any]] = {
    "lbvh30": {"builder": "lbvh", "key_bits": 30},
    "lbvh63": {"builder": "lbvh", "key_bits": 63},
    "lbvh-auto": {"builder": "lbvh", "key_bits": "auto"},
    "lbvh30-collapse": {"builder": "lbvh", "key_bits": 30, "collapse": True},
    "lbvh63-collapse": {"builder": "lbvh", "key_bits": 63, "collapse": True},
    "lbvh-auto-collapse": {"builder": "lbvh", "key_bits": "auto", "collapse": True},
    "lbvh-auto-treelets": {"builder": "lbvh", "key_bits": "auto", "treelet_rounds": 2},
    "sah": {"builder": "sah"},
}

#: Builders that cannot run a case in reasonable time, with the reason (reported, not run).
SKIPS: dict[tuple[str, str], str] = {
    ("over_2_24_triangles", "sah"): "the serial SAH would need an estimated 20+ minutes and "
                                    "10+ GB for 2^24 triangles (it takes 149 s and 1.4 GB "
                                    "for 2^21)",
}

#: Cases ``--quick`` leaves out (the slowest oracle comparisons); slow cases need ``--large``.
QUICK_SKIPS = ("identical_triangles", "closed_cube_vertices_edges", "closed_sphere_stack2")


@dataclass
class Reference:
    """The answers a case's rays must get: ``prim int32 (R,)``, ``t float64 (R,)``
    (``inf`` on a miss); ``exact``: given by the case rather than by the oracle."""
    prim: np.ndarray
    t: np.ndarray
    exact: bool

    @property
    def hit(self) -> np.ndarray:
        return self.prim >= 0


def reference(case: Case) -> Reference:
    """The float64 oracle's answers for the case's rays, or the case's exact answers."""
    if case.expected_prim is not None:
        return Reference(np.asarray(case.expected_prim, np.int32),
                         np.asarray(case.expected_t, np.float64), exact=True)
    from .oracle import brute_force

    hits = brute_force(case.vertices, case.faces, case.origins, case.directions,
                       case.tmin, case.tmax)
    return Reference(hits.prim, hits.t.astype(np.float64), exact=False)


@dataclass
class Outcome:
    """What one builder did on one case (see the module docstring for the rules)."""
    case: str
    builder: str
    issue_case: int
    triangles: int
    rays: int
    build_seconds: float = float("nan")
    depth: int = -1
    stack_need: int = -1
    stack: int = -1
    tree_stack: int = -1
    forced_stack: bool = False
    nonfinite_boxes: int = 0
    validate_error: str | None = None
    overflow: int = 0
    any_hit_overflow: int = 0
    mismatches: int = 0
    any_hit_mismatches: int = 0
    leaks: int = 0
    ambiguous: int = 0
    worst_rel_t: float = 0.0
    worst_t_over_bound: float = 0.0
    first_mismatch: str | None = None
    error: str | None = None
    skipped: str | None = None

    def failures(self) -> list[str]:
        """Each rule the outcome breaks, in words (empty when it passed)."""
        if self.skipped:
            return []
        if self.error:
            return [f"error: {self.error}"]
        out = []
        if self.validate_error:
            out.append(f"validator: {self.validate_error}")
        if self.nonfinite_boxes:
            out.append(f"{self.nonfinite_boxes} boxes with NaN or infinity")
        if max(self.depth, self.stack_need) > self.tree_stack:
            out.append(f"the traversal can need {max(self.depth, self.stack_need)} stack entries "
                       f"(depth {self.depth}), it gets {self.tree_stack}")
        if not self.forced_stack and (self.overflow or self.any_hit_overflow):
            out.append(f"{self.overflow + self.any_hit_overflow} overflows with a stack that "
                       "holds the tree")
        if self.mismatches:
            out.append(f"{self.mismatches} closest-hit mismatches ({self.first_mismatch})")
        if self.any_hit_mismatches:
            out.append(f"{self.any_hit_mismatches} any-hit mismatches")
        if self.leaks:
            out.append(f"{self.leaks} rays from inside a closed mesh missed (leaks)")
        return out

    @property
    def passed(self) -> bool:
        return not self.skipped and not self.failures()


# -- comparing hits -------------------------------------------------------------------

@dataclass
class PairGeometry:
    """Ray/triangle pairs analysed in float64 in the kernel's own frame (Woop 2013:
    origin at the ray's, permuted and sheared so that the ray is +z), with bounds
    on the float32 kernel's rounding. One entry per pair:

    * ``t``: distance of the hit on the triangle's plane (NaN or inf where ``det = 0``:
      the ray lies in the plane or parallel to it; the kernel's rounding can still
      make a hit of a triangle in the ray's plane, which ``lo, hi`` then bound);
    * ``bound``: how far the kernel's ``t`` may be from it (module docstring);
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

    ``degenerate32/64`` (one per pair) say whether :func:`lbvh.oracle.degenerate_triangles`
    calls ``tri[k]`` degenerate in float32 (the kernel never hits those) and in
    float64 (the oracle's decision); triangles degenerate in one precision only
    may be hit or not.
    """
    from .oracle import woop_axes

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


@dataclass
class Judge:
    """Decides whether kernel answers are right for one case (module docstring rules)."""
    case: Case
    ref: Reference

    def __post_init__(self) -> None:
        v = self.case.vertices
        self.extent = float(np.max(v.max(axis=0).astype(np.float64) - v.min(axis=0)))
        self._degenerate: tuple[np.ndarray, np.ndarray] | None = None

    def degenerate(self, tri: np.ndarray, whole: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Float32 and float64 degeneracy of triangles ``tri``; ``whole``: compute it
        once for the whole mesh (before searches over every triangle)."""
        from .oracle import degenerate_triangles

        v, f = self.case.vertices, self.case.faces
        with np.errstate(over="ignore", invalid="ignore"):  # edges past float32, as the kernel
            if whole and self._degenerate is None:
                self._degenerate = (degenerate_triangles(v, f, np.float32),
                                    degenerate_triangles(v, f, np.float64))
            if self._degenerate is not None:
                return self._degenerate[0][tri], self._degenerate[1][tri]
            return (degenerate_triangles(v, f[tri], np.float32),
                    degenerate_triangles(v, f[tri], np.float64))

    def geometry(self, ray: np.ndarray, tri: np.ndarray, whole: bool = False) -> PairGeometry:
        d32, d64 = self.degenerate(tri, whole)
        return pair_geometry(self.case, ray, tri, d32, d64)

    def agrees(self, prim: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``bool (R,)`` rays whose answer is the reference's (same triangle, ``t``
        within the bound, or both miss), and ``float64 (R,)`` the ``t`` bound (``inf``
        where the reference misses)."""
        ref = self.ref
        rays = np.flatnonzero(ref.hit)
        bound = np.full(len(prim), np.inf)
        lo, hi = np.full(len(prim), -np.inf), np.full(len(prim), np.inf)
        if len(rays):
            g = self.geometry(rays, ref.prim[rays])
            bound[rays], lo[rays], hi[rays] = g.bound, g.lo, g.hi
        with np.errstate(invalid="ignore"):  # inf - inf on rays both miss
            # t == ref.t also covers a hit beyond float32 that both report as inf
            near = (np.abs(t - ref.t) <= bound) & (t >= lo) & (t <= hi)
            same = (prim == ref.prim) & (~ref.hit | (t == ref.t) | near)
        return same, bound

    def right_answers(self, rays: np.ndarray, prim: np.ndarray, t: np.ndarray,
                      closest: bool) -> np.ndarray:
        """``bool (len(rays),)``: whether each answer (``prim[k]``, ``t[k]`` of ray
        ``rays[k]``; ``prim`` -1 is a miss) is right.

        A miss is right when no triangle is robustly hit; a hit when its triangle
        is a possible hit at that ``t`` (within the bound) and, for the closest
        hit, no triangle is robustly hit before it. The reference's own hit
        settles most rays (robust hits are exact hits, and the reference has the
        first exact hit); the rest are searched over every triangle.
        """
        ref = self.ref
        right = np.zeros(len(rays), bool)
        unsure = np.zeros(len(rays), bool)
        hit = prim >= 0
        genuine = np.zeros(len(rays), bool)
        if hit.any():
            g = self.geometry(rays[hit], prim[hit])
            genuine[hit] = g.possible & t_agrees(g, t[hit])
        ref_hit = ref.hit[rays]
        robust_ref = np.zeros(len(rays), bool)
        late = np.zeros(len(rays), bool)  # beyond the reference hit and its bound
        if ref_hit.any():
            g = self.geometry(rays[ref_hit], ref.prim[rays[ref_hit]])
            robust_ref[ref_hit] = g.robust
            late[ref_hit] = t[ref_hit] > ref.t[rays[ref_hit]] + g.bound
        # misses: wrong past a robust reference hit, right with no exact hit at all
        miss = ~hit
        right |= miss & ~ref_hit
        unsure |= miss & ref_hit & ~robust_ref
        # hits: must be genuine; a closest hit must not lie beyond a robust one
        if closest:
            right |= hit & genuine & ~(ref_hit & late)
            unsure |= hit & genuine & ref_hit & late & ~robust_ref
        else:
            right |= hit & genuine
        if unsure.any():
            idx = np.flatnonzero(unsure)
            right[idx] = self._search(rays[idx], prim[idx], t[idx], closest)
        return right

    def _search(self, rays: np.ndarray, prim: np.ndarray, t: np.ndarray, closest: bool,
                max_pairs: int = 1 << 20) -> np.ndarray:
        """:meth:`right_answers` by testing every triangle (rays the reference cannot settle)."""
        n_tris = len(self.case.faces)
        per = max(1, max_pairs // n_tris)
        out = np.zeros(len(rays), bool)
        for start in range(0, len(rays), per):
            chunk = slice(start, start + per)
            r = rays[chunk]
            g = self.geometry(np.repeat(r, n_tris), np.tile(np.arange(n_tris), len(r)), whole=True)
            robust = g.robust.reshape(len(r), n_tris)
            t_all, bound = g.t.reshape(robust.shape), g.bound.reshape(robust.shape)
            with np.errstate(invalid="ignore"):  # NaN t of parallel pairs, never robust
                first_robust = np.min(np.where(robust, t_all + bound, np.inf), axis=1)
            p, tk = prim[chunk], t[chunk]
            row, col = np.arange(len(r)), np.maximum(p, 0)
            lo, hi = g.lo.reshape(robust.shape), g.hi.reshape(robust.shape)
            genuine = (g.possible.reshape(robust.shape)[row, col]
                       & t_agrees(PairGeometry(t_all[row, col], bound[row, col], None, None,
                                               lo[row, col], hi[row, col]), tk))
            if closest:
                genuine &= tk <= first_robust
            out[chunk] = np.where(p >= 0, genuine, ~robust.any(axis=1))
        return out


@dataclass
class Agreement:
    """Verdicts of one query against the reference, per ray."""
    wrong: np.ndarray        # bool (R,): not a right answer, not flagged overflow
    ambiguous: int = 0       # right, but not the reference's (tie, edge, degenerate)
    worst_rel_t: float = 0.0
    worst_t_over_bound: float = 0.0
    first: str | None = None


def compare_closest(judge: Judge, prim: np.ndarray, t: np.ndarray,
                    flagged: np.ndarray) -> Agreement:
    """Closest hits of the kernel against the reference; rays that disagree are
    judged by :meth:`Judge.right_answers` (exact references: wrong outright)."""
    ref, case = judge.ref, judge.case
    t = np.asarray(t, np.float64)
    same, bound = judge.agrees(prim, t)
    wrong = ~same & ~flagged
    ambiguous = 0
    rest = np.flatnonzero(wrong)
    if not ref.exact and len(rest):
        right = judge.right_answers(rest, prim[rest], t[rest], closest=True)
        wrong[rest[right]] = False
        ambiguous = int(right.sum())
    agreement = Agreement(wrong, ambiguous)
    good = same & ref.hit & ~flagged
    if good.any():
        with np.errstate(invalid="ignore"):
            err = np.where(t == ref.t, 0.0, np.abs(t - np.where(ref.hit, ref.t, 0.0)))
        agreement.worst_t_over_bound = float(np.max(err[good] / bound[good]))
        # relative errors only of hits clear of the origin: a ray starting on a
        # surface has t_ref ~ 0 and a meaningless ratio (the bound covers it)
        reach = ref.t * np.linalg.norm(case.directions.astype(np.float64), axis=1)
        far = good & (reach > 1e-3 * judge.extent)
        if far.any():
            agreement.worst_rel_t = float(np.max(err[far] / ref.t[far]))
    if wrong.any():
        i = int(np.flatnonzero(wrong)[0])
        agreement.first = (f"ray {i}: o={case.origins[i].tolist()} d={case.directions[i].tolist()} "
                           f"tmin={float(case.tmin[i]):g} tmax={float(case.tmax[i]):g}: kernel "
                           f"prim {int(prim[i])} t {t[i]:.9g}, reference prim {int(ref.prim[i])} "
                           f"t {ref.t[i]:.9g}")
    return agreement


def compare_any(judge: Judge, prim: np.ndarray, t: np.ndarray, flagged: np.ndarray) -> np.ndarray:
    """``bool (R,)`` any-hit answers that are wrong (and not flagged overflow)."""
    ref = judge.ref
    wrong = ((prim >= 0) != ref.hit) & ~flagged
    rest = np.flatnonzero(wrong)
    if not ref.exact and len(rest):
        wrong[rest] = ~judge.right_answers(rest, prim[rest], np.asarray(t, np.float64)[rest],
                                           closest=False)
    return wrong


# -- running -----------------------------------------------------------------------------

def _nonfinite_boxes(bvh: Any) -> int:
    finite = np.isfinite(bvh.lower).all(axis=1) & np.isfinite(bvh.upper).all(axis=1)
    return int((~finite).sum())


def run_case(case: Case, builder: str, judge: Judge | None = None, device: Any = None,
             bvh_out: list | None = None) -> Outcome:
    """Build ``case`` with ``builder`` (a key of :data:`BUILDERS`) and check every rule.

    ``judge`` is ``Judge(case, reference(case))`` (made if not given). With
    ``bvh_out`` (a list) the tree is appended to it, for callers that test more.
    """
    import lbvh
    from .traverse import stack_need, stack_size_for

    if builder not in BUILDERS:
        raise ValueError(f"unknown builder {builder!r}; known: {', '.join(BUILDERS)}")
    out = Outcome(case.name, builder, hard_cases.ISSUE_CASE.get(case.name, 0),
                  len(case.faces), case.num_rays)
    if (case.name, builder) in SKIPS:
        out.skipped = SKIPS[(case.name, builder)]
        return out
    try:
        start = time.perf_counter()
        bvh = lbvh.build(case.vertices, case.faces, device=device, **BUILDERS[builder])
        out.build_seconds = time.perf_counter() - start
    except Exception as exc:  # a failed build is a result to report, not a crash
        out.error = f"build raised {type(exc).__name__}: {exc}"
        return out
    if bvh_out is not None:
        bvh_out.append(bvh)
    try:
        bvh.validate()
    except ValueError as exc:
        out.validate_error = str(exc)
    out.nonfinite_boxes = _nonfinite_boxes(bvh)
    out.forced_stack = case.stack_size is not None
    out.tree_stack = stack_size_for(bvh)
    out.stack = case.stack_size if out.forced_stack else out.tree_stack
    out.stack_need = stack_need(bvh)
    out.depth = int(bvh.depths().max()) if bvh.num_nodes > 1 else 0
    if out.validate_error:  # tracing a broken tree proves nothing more
        return out
    judge = Judge(case, reference(case)) if judge is None else judge
    try:
        _trace_and_compare(case, bvh, judge, out)
    except Exception as exc:
        out.error = f"query raised {type(exc).__name__}: {exc}"
    return out


def _trace_and_compare(case: Case, bvh: Any, judge: Judge, out: Outcome) -> None:
    options = {"stack_size": case.stack_size} if case.stack_size is not None else {}
    rays = (case.origins, case.directions, case.tmin, case.tmax)
    closest = bvh.intersect(*rays, **options)
    any_hit = bvh.occluded(*rays, return_hits=True, **options)
    out.overflow = int(closest.overflow_count)
    out.any_hit_overflow = int(any_hit.overflow_count)
    agreement = compare_closest(judge, closest.prim, closest.t, closest.overflow)
    out.mismatches = int(agreement.wrong.sum())
    out.ambiguous = agreement.ambiguous
    out.worst_rel_t = agreement.worst_rel_t
    out.worst_t_over_bound = agreement.worst_t_over_bound
    out.first_mismatch = agreement.first
    out.any_hit_mismatches = int(compare_any(judge, any_hit.prim, any_hit.t,
                                             any_hit.overflow).sum())
    if case.must_hit is not None:
        out.leaks = int((case.must_hit & ~closest.hit & ~closest.overflow).sum())


def run(case_names: Iterable[str], builders: Iterable[str], device: Any = None,
        progress=None) -> list[Outcome]:
    """Every case by every builder; ``progress(outcome)`` is called after each."""
    outcomes = []
    builders = list(builders)
    for name in case_names:
        case = hard_cases.make(name)
        judge = None
        for builder in builders:
            if judge is None and (case.name, builder) not in SKIPS:
                judge = Judge(case, reference(case))
            outcome = run_case(case, builder, judge, device)
            outcomes.append(outcome)
            if progress is not None:
                progress(outcome)
    return outcomes


# -- the report ----------------------------------------------------------------------------

COLUMNS = ("case", "builder", "result", "build ms", "depth", "stack", "overflow", "wrong",
           "ambig", "worst rel dt", "dt/bound")
WIDTHS = [28, 18, 7, 9, 5, 5, 8, 6, 6, 12, 8]


def _row(o: Outcome) -> tuple[str, ...]:
    if o.skipped:
        return (o.case, o.builder, "skipped") + ("",) * (len(COLUMNS) - 3)
    result = "passed" if o.passed else "FAILED"
    stack = f"{o.stack}{'*' if o.forced_stack else ''}" if o.stack >= 0 else ""
    return (o.case, o.builder, result, f"{o.build_seconds * 1e3:.1f}",
            str(o.depth) if o.depth >= 0 else "", stack,
            str(o.overflow + o.any_hit_overflow),
            str(o.mismatches + o.any_hit_mismatches + o.leaks), str(o.ambiguous),
            f"{o.worst_rel_t:.2e}", f"{o.worst_t_over_bound:.3f}")


def format_row(o: Outcome, widths: list[int] = WIDTHS) -> str:
    return "  ".join(cell.ljust(w) for cell, w in zip(_row(o), widths)).rstrip()


def totals(outcomes: list[Outcome]) -> dict[str, dict[str, int]]:
    """``{builder: {"passed": n, "failed": n, "skipped": n}}``."""
    out: dict[str, dict[str, int]] = {}
    for o in outcomes:
        t = out.setdefault(o.builder, {"passed": 0, "failed": 0, "skipped": 0})
        t["skipped" if o.skipped else "passed" if o.passed else "failed"] += 1
    return out


def format_totals(outcomes: list[Outcome]) -> str:
    lines = []
    for builder, t in totals(outcomes).items():
        skipped = f", {t['skipped']} skipped" if t["skipped"] else ""
        lines.append(f"{builder:18s} {t['passed']} passed, {t['failed']} failed{skipped}")
    return "\n".join(lines)


def select_cases(names: list[str] | None, quick: bool, large: bool) -> list[str]:
    """The case names to run: those asked for (all by default), less slow ones
    without ``large`` and the slowest oracle comparisons with ``quick``."""
    if names:
        for name in names:
            if name not in hard_cases.CASES:
                raise ValueError(f"--cases: unknown case {name!r}; known: "
                                 f"{', '.join(hard_cases.CASES)}")
        return list(names)
    chosen = []
    for name in hard_cases.CASES:
        if name == "over_2_24_triangles" and not large:
            continue
        if quick and name in QUICK_SKIPS:
            continue
        chosen.append(name)
    return chosen


def select_builders(names: list[str] | None) -> list[str]:
    if not names:
        return list(BUILDERS)
    for name in names:
        if name not in BUILDERS:
            raise ValueError(f"--builders: unknown builder {name!r}; known: {', '.join(BUILDERS)}")
    return list(names)


def _split(values: list[str] | None) -> list[str] | None:
    """``--x a,b --x c`` -> ``[a, b, c]``."""
    if not values:
        return None
    return [item for value in values for item in value.split(",") if item]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--builders", action="append", metavar="B[,B...]",
                   help=f"builders to run (default all: {', '.join(BUILDERS)})")
    p.add_argument("--cases", action="append", metavar="C[,C...]",
                   help="cases to run (default all but the large one)")
    p.add_argument("--quick", action="store_true",
                   help=f"leave out the slowest cases ({', '.join(QUICK_SKIPS)})")
    p.add_argument("--large", action="store_true",
                   help="also run the case over 2^24 triangles (a minute per LBVH builder, "
                        "7 GB of memory)")
    p.add_argument("--json", action="store_true", help="print the outcomes as JSON lines")
    p.add_argument("--device", default=None, help="OpenCL device name substring")


def warm_up(builders: list[str], device: Any = None) -> None:
    """Build and trace two triangles with each builder, so that the kernels are
    compiled before anything is timed."""
    import lbvh

    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.uint32([[0, 1, 2], [0, 1, 3]])
    for builder in builders:
        bvh = lbvh.build(v, f, device=device, **BUILDERS[builder])
        bvh.intersect(v[:1] - 1, np.float32([[1, 1, 1]]))
        bvh.occluded(v[:1] - 1, np.float32([[1, 1, 1]]))


def cmd_check(args: argparse.Namespace) -> int:
    """Run the suite and print one line per case and builder, then the totals;
    exit status 1 if anything failed."""
    builders = select_builders(_split(args.builders))
    cases = select_cases(_split(args.cases), args.quick, args.large)

    def show(o: Outcome) -> None:
        if args.json:
            print(json.dumps(asdict(o)), flush=True)
            return
        print(format_row(o, WIDTHS), flush=True)
        for failure in o.failures():
            print(f"    {failure}", flush=True)

    if not args.json:
        print(f"{len(cases)} cases x {len(builders)} builders "
              f"(rules: python -m pydoc lbvh.check)", flush=True)
        print("  ".join(c.ljust(w) for c, w in zip(COLUMNS, WIDTHS)).rstrip(), flush=True)
    warm_up(builders, args.device)
    start = time.perf_counter()
    outcomes = run(cases, builders, args.device, progress=show)
    if not args.json:
        print(f"\ntotals ({time.perf_counter() - start:.0f} s):")
        print(format_totals(outcomes))
        for o in outcomes:
            if o.skipped:
                print(f"skipped {o.case} / {o.builder}: {o.skipped}")
    return exit_status(outcomes)


def exit_status(outcomes: list[Outcome]) -> int:
    """1 if an outcome that ran failed, else 0 (skipped outcomes do not count)."""
    return 0 if all(o.passed or o.skipped for o in outcomes) else 1

