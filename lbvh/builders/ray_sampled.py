"""Ray-sampled split probabilities for the SAH reference (``SAHOptions(rays=...)``).

The SAH weighs a child ``X`` of a node ``N`` by ``A(X) / A(N)``, the probability
that a uniformly distributed ray through ``N`` enters ``X`` (MacDonald & Booth
1990). Camera rays are not uniform and a closest-hit ray ends at its hit, so
Nabata, Iwasaki, Dobashi & Nishita 2013 ("Efficient divide-and-conquer ray
tracing using ray sampling", HPG 2013) estimate the probability from a sample
of the rays that will be traced instead. This module does the simple form of
that idea inside the SAH reference's sweep (:mod:`lbvh.builders.sah`):

* each sampled ray is a segment ``[0, tmax]`` (``tmax`` its closest hit; ``inf``
  where it misses); a node keeps the sample rays whose segment enters its box;
* for a split candidate with side ``X`` of a node entered by ``r`` sample rays,
  ``h`` of which enter ``X``, the probability is the ray fraction smoothed
  towards the area ratio by ``w = ray_prior`` pseudo-rays::

      P(X | N) = (h + w * A(X) / A(N)) / (r + w)

  so a node seen by many rays is split by where the rays go, one seen by few
  by its area, and the split cost ``C_node + C_tri (P(L)|L| + P(R)|R|)`` stays
  in the SAH's units (``P(N | N) = 1``);
* a node that no sample ray enters is split by the full-sweep SAH, exactly as
  without rays; in a node that some enter, counting every candidate would cost
  ``n * r`` slab tests, so ``ray_candidates`` of each axis order are costed:
  half evenly spaced (every ``ceil(n / (ray_candidates / 2))``-th), half the
  cheapest by the SAH's area cost (ties: the smaller left side), so the SAH's own
  choice is always among them; with the prefix and suffix boxes of the full
  sweep (exact, not binned). Evenly spaced alone missed the splits that cut a
  few large triangles off (Conference's SAH cost went from 34 to 50).

:class:`RaySample` holds the rays; :class:`RayLists` the sample rays of the
open nodes of a level of the build and the probabilities of their candidates.
The slab test is float32 over numpy, ``nan`` (a zero direction component on
a box's face) ignored; it only weighs candidates, it decides no hit.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: Pairs (candidate box, ray) tested at once: bounds the memory of a level's tests.
PAIRS_PER_CHUNK = 1 << 20
#: Each segment's end is moved out by this fraction of ``tmax``, so the hit
#: triangle's own leaf is entered despite float32 rounding of the hit point.
TMAX_SLACK = 1e-6


def _as_rays(name: str, value: Any, count: int | None) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in "fiu" or a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"rays: {name} must be a numeric (R, 3) array, got dtype {a.dtype} "
                         f"shape {a.shape}")
    if count is not None and len(a) != count:
        raise ValueError(f"rays: {name} has {len(a)} rows, origins {count}")
    a = a.astype(np.float32)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"rays: {name}[{i}] = {a[i].tolist()} is not finite (in float32)")
    return a


@dataclass(frozen=True, eq=False)
class RaySample:
    """A sample of the rays a tree will trace: ``origins``, ``directions``
    (``float32 (R, 3)``, finite, directions non-zero) and ``tmax`` (``float32
    (R,)``: where each ray's segment ends, its closest hit, ``inf`` for a miss;
    ``None``: not yet traced, :func:`lbvh.build` traces them through the default
    LBVH of the mesh first). A ``(origins, directions)`` pair given to
    ``SAHOptions(rays=...)`` becomes one."""
    origins: np.ndarray
    directions: np.ndarray
    tmax: np.ndarray | None = None

    def __post_init__(self) -> None:
        o = _as_rays("origins", self.origins, None)
        if len(o) == 0:
            raise ValueError("rays: an empty sample; give at least one ray")
        d = _as_rays("directions", self.directions, len(o))
        zero = ~(d != 0).any(axis=1)
        if zero.any():
            raise ValueError(f"rays: directions[{int(np.flatnonzero(zero)[0])}] is zero")
        object.__setattr__(self, "origins", o)
        object.__setattr__(self, "directions", d)
        if self.tmax is not None:
            t = np.asarray(self.tmax)
            if t.dtype.kind not in "fiu" or t.shape != (len(o),):
                raise ValueError(f"rays: tmax must be a numeric ({len(o)},) array, got dtype "
                                 f"{t.dtype} shape {t.shape}")
            t = t.astype(np.float32)
            bad = np.isnan(t) | (t < 0)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(f"rays: tmax[{i}] = {t[i]}; expected a number >= 0 or inf")
            object.__setattr__(self, "tmax", t)

    def __len__(self) -> int:
        return len(self.origins)

    def ended_at(self, t: Any) -> "RaySample":
        """The same rays, their segments ending at ``t`` (``(R,)``; ``inf``: no end)."""
        return RaySample(self.origins, self.directions, t)

    def __repr__(self) -> str:
        traced = "traced" if self.tmax is not None else "not traced"
        return f"RaySample({len(self)} rays, {traced})"


def as_ray_sample(value: Any) -> RaySample | None:
    """``SAHOptions.rays`` as given (a :class:`RaySample`, an ``(origins,
    directions)`` pair or ``None``) -> a :class:`RaySample` or ``None``."""
    if value is None or isinstance(value, RaySample):
        return value
    if isinstance(value, (tuple, list)) and len(value) in (2, 3):
        return RaySample(*value)
    raise ValueError(f"rays: {type(value).__name__} given; expected a RaySample, an "
                     "(origins, directions) pair or None")


def segments_enter(o: np.ndarray, inv: np.ndarray, tmax: np.ndarray, lo: np.ndarray,
                   hi: np.ndarray) -> np.ndarray:
    """``bool (P,)``: whether each segment ``o + t d``, ``t`` in ``[0, tmax]`` (``inv`` =
    ``1 / d``), meets the box ``[lo, hi]`` (all ``float32 (P, 3)``, ``tmax (P,)``)."""
    with np.errstate(invalid="ignore", over="ignore"):
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
        near = np.fmax.reduce(np.fmin(t0, t1), axis=1)
        far = np.fmin.reduce(np.fmax(t0, t1), axis=1)
    return (near <= far) & (far >= 0) & (near <= tmax)


class RayLists:
    """The sample rays of each open node of a level of the SAH build (a flat list of
    ray indices, node by node), and the ray-sampled probabilities of its candidates."""

    def __init__(self, sample: RaySample, prior: float, candidates: int) -> None:
        if sample.tmax is None:
            raise ValueError("rays: the sample is not traced (tmax is None); lbvh.build "
                             "traces it, or give RaySample(..., tmax=closest hits)")
        self.o = sample.origins
        with np.errstate(divide="ignore", over="ignore"):   # 1/0 and 1/denormal: +-inf
            self.inv = (np.float32(1) / sample.directions).astype(np.float32)
        self.tmax = (sample.tmax * np.float32(1 + TMAX_SLACK)).astype(np.float32)
        self.prior = float(prior)
        self.candidates = int(candidates)
        self.ids = np.arange(len(sample), dtype=np.int64)    # the root gets every ray
        self.count = np.array([len(sample)], np.int64)
        self.filtered = False

    # -- the lists, kept aligned with the build's open nodes -----------------------
    def keep(self, mask: np.ndarray) -> None:
        """Keep the lists of the nodes where ``mask``."""
        self.ids = self.ids[np.repeat(mask, self.count)]
        self.count = self.count[mask]

    def split(self, mask: np.ndarray) -> None:
        """Nodes where ``mask`` are split: each child starts with its parent's list
        (filtered by the child's own box when its level is swept); the others end."""
        self.keep(mask)
        starts = np.cumsum(self.count) - self.count
        twice = np.repeat(self.count, 2)
        first = np.repeat(np.repeat(starts, 2), twice)
        local = np.arange(int(twice.sum())) - np.repeat(np.cumsum(twice) - twice, twice)
        self.ids = self.ids[first + local]
        self.count = twice
        self.filtered = False

    def _filter(self, box_lo: np.ndarray, box_hi: np.ndarray) -> None:
        """Keep in each node's list the rays whose segment enters the node's box."""
        seg = np.repeat(np.arange(len(self.count)), self.count)
        enter = np.empty(len(self.ids), bool)
        for s in range(0, len(self.ids), PAIRS_PER_CHUNK):
            r, g = self.ids[s:s + PAIRS_PER_CHUNK], seg[s:s + PAIRS_PER_CHUNK]
            enter[s:s + len(r)] = segments_enter(self.o[r], self.inv[r], self.tmax[r],
                                                 box_lo[g], box_hi[g])
        self.ids = self.ids[enter]
        self.count = np.bincount(seg[enter], minlength=len(self.count)).astype(np.int64)
        self.filtered = True

    # -- the probabilities -----------------------------------------------------------
    def weigh(self, box_lo: np.ndarray, box_hi: np.ndarray, area: np.ndarray,
              seg_of: np.ndarray, local: np.ndarray, seg_count: np.ndarray,
              pre: tuple[np.ndarray, np.ndarray, np.ndarray],
              right: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The areas the sweep costs one axis's candidates by, ray-sampled.

        Args:
            box_lo, box_hi, area: each node's box (``float32 (S, 3)``) and area.
            seg_of, local, seg_count: each candidate's node, its place in the node
                (the split after primitive ``local``), and each node's primitives.
            pre, right: ``(lo, hi, area)`` of each candidate's left side and right side.

        Returns:
            ``(left, right)`` effective areas ``A(N) P(X | N)`` (``float64 (M,)``;
            ``inf`` for a candidate not costed), the candidates' areas themselves
            in nodes that no ray enters.
        """
        if not self.filtered:
            self._filter(box_lo, box_hi)
        rays = self.count[seg_of]
        inside = local + 1 < seg_count[seg_of]          # the right side is not empty
        spaced = -(-self.candidates // 2)
        step = np.maximum(1, -(-seg_count // spaced))[seg_of]
        costed = (rays > 0) & ((local + 1) % step == 0) & inside
        # and the node's cheapest candidates by area (the SAH's own choice among them)
        open_ = np.flatnonzero((rays > 0) & inside)      # in order of node, then place
        sub = seg_of[open_]
        area_cost = pre[2][open_] * (local[open_] + 1) + right[2][open_] * (
            seg_count[sub] - local[open_] - 1)
        order = np.lexsort((area_cost, sub))            # by node, then cost, then place
        sizes = np.bincount(sub, minlength=len(seg_count))
        first = (np.cumsum(sizes) - sizes)[sub[order]]
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order)) - first
        costed[open_[rank < self.candidates // 2]] = True
        left, right_area = pre[2].copy(), right[2].copy()
        left[(rays > 0) & inside] = np.inf
        right_area[(rays > 0) & inside] = np.inf
        cand = np.flatnonzero(costed)
        if not len(cand):
            return left, right_area
        hits_l, hits_r = self._count_hits(cand, seg_of, pre, right)
        a_n = area[seg_of[cand]]
        r = rays[cand].astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio_l = np.where(a_n > 0, pre[2][cand] / a_n, 0.0)
            ratio_r = np.where(a_n > 0, right[2][cand] / a_n, 0.0)
        w = self.prior
        left[cand] = a_n * (hits_l + w * ratio_l) / (r + w)
        right_area[cand] = a_n * (hits_r + w * ratio_r) / (r + w)
        return left, right_area

    def _count_hits(self, cand: np.ndarray, seg_of: np.ndarray,
                    pre: tuple[np.ndarray, ...], right: tuple[np.ndarray, ...]
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Sample rays of each candidate's node entering its left and its right side."""
        starts = np.cumsum(self.count) - self.count
        hits_l = np.zeros(len(cand))
        hits_r = np.zeros(len(cand))
        per = self.count[seg_of[cand]]
        ends = np.cumsum(per)
        begin = 0
        while begin < len(cand):   # chunks of whole candidates, about PAIRS_PER_CHUNK pairs
            stop = int(np.searchsorted(ends, (ends[begin - 1] if begin else 0) + PAIRS_PER_CHUNK,
                                       side="right"))
            stop = max(stop, begin + 1)
            c = np.arange(begin, stop)
            n = per[c]
            which = np.repeat(c, n)
            offset = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
            r = self.ids[starts[seg_of[cand[which]]] + offset]
            k = cand[which]
            o, inv, t = self.o[r], self.inv[r], self.tmax[r]
            hits_l[begin:stop] = np.bincount(which - begin, segments_enter(o, inv, t, pre[0][k],
                                             pre[1][k]), minlength=stop - begin)
            hits_r[begin:stop] = np.bincount(which - begin, segments_enter(o, inv, t, right[0][k],
                                             right[1][k]), minlength=stop - begin)
            begin = stop
        return hits_l, hits_r
