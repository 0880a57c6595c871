"""What a right answer is: the rules of ``lbvh check`` and of the tests that use them.

For each case and builder the runner (:mod:`lbvh.verification.runner`) builds
the tree, runs the validator, looks for NaN or infinite boxes, compares the
stack the traversal needs with the one it gets, traces the case's rays
(closest hit and any hit) and compares them with the reference answers
(:func:`reference`): the float64 brute-force oracle
(:func:`lbvh.verification.oracle.brute_force`), or the exact answers a case
carries when it is too big for the oracle.

What must hold (a case passes when all do: :meth:`Outcome.failures`):

* the build succeeds and ``bvh.validate()`` passes; no box has a NaN or an infinity;
* the stack the traversal can need (:func:`lbvh.queries.traverse.stack_need`, at least
  the depth) <= the stack it gets (:func:`lbvh.queries.traverse.stack_size_for`),
  and then no ray overflows; a case that forces a smaller stack may overflow,
  but only on rays flagged ``overflow``;
* every ray not flagged ``overflow`` agrees with the reference: same hit or
  miss, ``t`` within the bound ``|t - t_ref| |cos a| <= 16 u (t_ref + s) kappa``
  and within the triangle's vertex depths (:mod:`lbvh.verification.error_analysis`),
  the same triangle unless the reference hits the kernel's triangle at the
  same ``t`` within the bound (a tie); the any-hit query gives the same hit or miss;
* rays a case marks ``must_hit`` (from inside a closed mesh) all hit: no leak.

The oracle computes in float64, the kernel in float32: where they disagree,
:class:`Judge` decides with the kernel's own rounding errors (a hit that
exact arithmetic gives for some input within those errors is right; a miss
is wrong only if a triangle is hit for every such input). Rays through shared
edges and vertices, grazing and near-edge hits, ties between triangles at the
same ``t`` and triangles at the degeneracy threshold land there. So do rays in
a triangle's plane (``det = 0`` in float64): the kernel's rounded coordinates
leave the plane, and it may hit such a triangle; a hit there is right where
the origin lies on the segment the triangle projects to (within rounding) and
``t`` within the vertices' depths
(:class:`~lbvh.verification.error_analysis.PairGeometry`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .error_analysis import PairGeometry, pair_geometry, t_agrees
from .hard_cases import Case
from .oracle import brute_force, degenerate_triangles


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
