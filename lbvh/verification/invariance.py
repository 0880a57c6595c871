"""Answers that do not depend on how a mesh is written: the ray sets and the
rewritings of :mod:`tests.queries.test_invariance` and ``bench/bench_invariance.py``.

A rewriting changes how a scene is written, not what it is:

``rotate``
    each face's corners rotated (``a b c -> b c a``);
``flip``
    each face's winding reversed (``a b c -> a c b``);
``permute``
    the faces in another order (answers compared through the permutation);
``scale k``
    vertices and ray origins times ``2^k`` (directions as they are), so that
    every exact ``t`` is times ``2^k``.

:func:`differences` counts, for one query, the rays whose answer changed: a hit
that became a miss or the other way, another triangle, or a ``t`` that is not
the first one exactly (times ``2^k``). The ray sets (:func:`ray_sets`) are
those of the issue that asked for this: views (a camera's grid), aimed (at
random interior points of random triangles), and surface (leaving the view
rays' hit points, at random and at grazing angles).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["Rewrite", "REWRITES", "rewrites", "ray_sets", "sliver_soup", "differences",
           "representable", "winding_points"]


@dataclass(frozen=True)
class Rewrite:
    """One rewriting: ``name``, the corner order applied to every face, whether the
    faces are put in another order (the ``order`` given to :meth:`faces`: ``order[i]``
    is the original face of new face ``i``), and ``scale`` (the exponent of a power
    of two)."""
    name: str
    corners: tuple[int, int, int] = (0, 1, 2)
    permute: bool = False
    scale: int = 0

    def faces(self, faces: np.ndarray, order: np.ndarray) -> np.ndarray:
        f = faces[:, list(self.corners)]
        return np.ascontiguousarray(f[order] if self.permute else f)

    def points(self, x: np.ndarray) -> np.ndarray:
        return np.ldexp(x, self.scale).astype(np.float32) if self.scale else x


def representable(vertices: np.ndarray, k: int) -> bool:
    """Whether ``vertices * 2^k`` is exact in float32 and inside its normal range
    (zeros aside): how far the scaling statement holds for a mesh."""
    v = np.asarray(vertices, np.float32)
    with np.errstate(over="ignore", under="ignore"):
        s = np.ldexp(v.astype(np.float64), k)
        s32 = s.astype(np.float32)
    nz = s != 0
    return bool(np.all(s32.astype(np.float64) == s) and np.all(np.isfinite(s32))
                and np.all(np.abs(s32[nz]) >= np.finfo(np.float32).tiny))


#: The rewritings of the tests and the bench.
REWRITES = (Rewrite("rotate", (1, 2, 0)), Rewrite("flip", (0, 2, 1)),
            Rewrite("permute", permute=True),
            Rewrite("scale -60", scale=-60), Rewrite("scale -40", scale=-40),
            Rewrite("scale -20", scale=-20), Rewrite("scale 20", scale=20),
            Rewrite("scale 40", scale=40), Rewrite("scale 60", scale=60))


def rewrites(vertices: np.ndarray, origins: np.ndarray) -> list[Rewrite]:
    """:data:`REWRITES` less the scales that float32 cannot hold for this mesh and
    these origins."""
    return [r for r in REWRITES
            if not r.scale or (representable(vertices, r.scale)
                               and representable(origins, r.scale))]


def sliver_soup(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random slivers, each 1 long and ``1e-7 .. 1e-2`` high (log-uniform),
    in random orientations inside the unit cube: ``(float32 (3 count, 3), uint32)``."""
    rng = np.random.default_rng(seed)
    centre = rng.random((count, 1, 3))
    along = rng.normal(size=(count, 3))
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    side = np.cross(along, rng.normal(size=(count, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    height = 10.0 ** rng.uniform(-7, -2, count)
    t = rng.random(count)[:, None]
    corners = np.stack([-0.5 * along, 0.5 * along, (t - 0.5) * along + height[:, None] * side],
                       axis=1) * 0.05
    v = (centre + corners).reshape(-1, 3).astype(np.float32)
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    return v, f


def winding_points(vertices: np.ndarray, faces: np.ndarray, count: int,
                   seed: int = 0) -> np.ndarray:
    """``float32 (count + 2 (count // 4), 3)``: points for the inside tests' rewritings:
    ``count`` uniform in the mesh's box grown by a fifth each side, then the centroids
    of ``count // 4`` random faces (on the surface), then as many points a thousandth
    of the mesh's extent beside them (Gaussian)."""
    v = np.asarray(vertices, np.float32)
    rng = np.random.default_rng(seed)
    lo, hi = v.min(axis=0), v.max(axis=0)
    box = (lo + (hi - lo) * rng.uniform(-0.2, 1.2, (count, 3))).astype(np.float32)
    f = np.asarray(faces, np.int64)
    centroids = v[f[rng.integers(0, len(f), count // 4)]].mean(axis=1, dtype=np.float64)
    beside = centroids + rng.normal(size=centroids.shape) * 1e-3 * float((hi - lo).max())
    return np.concatenate([box, centroids.astype(np.float32), beside.astype(np.float32)])


def _camera(vertices: np.ndarray, n: int, rng: np.random.Generator):
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    eye = centre + size * np.array([0.7, 0.5, 1.3])
    forward = centre - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    s = np.linspace(-0.45, 0.45, n)
    x, y = np.meshgrid(s, s)
    d = forward + x.reshape(-1, 1) * right + y.reshape(-1, 1) * up
    o = np.broadcast_to(eye, d.shape)
    return o.astype(np.float32), d.astype(np.float32)


def ray_sets(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0,
             trace: Callable | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{name: (origins, directions)}``, float32, about ``count`` rays each: ``views``,
    ``aimed`` and, where ``trace`` (``(o, d) -> Hits`` of the unchanged mesh) is given,
    ``surface`` (from the views' hit points, half at random, half grazing)."""
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.int64)
    n = max(int(np.sqrt(count)), 2)
    out = {"views": _camera(v, n, rng)}
    tri = rng.integers(0, len(f), count)
    b = rng.random((count, 3)) + 1e-3
    b /= b.sum(axis=1, keepdims=True)
    target = np.einsum("ij,ijk->ik", b, v[f[tri]].astype(np.float64))
    lo, hi = v.min(axis=0).astype(np.float64), v.max(axis=0).astype(np.float64)
    size = float(np.max(hi - lo)) or 1.0
    eye = (lo + hi) / 2 + size * rng.normal(size=(count, 3))
    out["aimed"] = (eye.astype(np.float32), (target - eye).astype(np.float32))
    if trace is not None:
        o, d = out["views"]
        hits = trace(o, d)
        keep = np.flatnonzero(hits.hit)
        if len(keep):
            origin = hits.locations(o, d)[keep].astype(np.float32)
            p = v[f[hits.prim[keep]]].astype(np.float64)
            normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            r = rng.normal(size=normal.shape)
            tangent = r - (r * normal).sum(axis=1, keepdims=True) * normal
            tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
            side = np.where(rng.random((len(keep), 1)) < 0.5, 1.0, -1.0)
            grazing = 10.0 ** rng.uniform(-9, -2, (len(keep), 1))
            half = rng.random(len(keep)) < 0.5
            d2 = np.where(half[:, None], r, tangent + side * grazing * normal)
            out["surface"] = (origin, d2.astype(np.float32))
    return out


def differences(base, other, rewrite: Rewrite, order: np.ndarray) -> dict[str, int]:
    """Rays whose closest hit changed between ``base`` (the mesh as written) and
    ``other`` (rewritten by ``rewrite``; faces in ``order`` where it permutes):
    ``{"hit": hit/miss changed, "prim": another triangle, "t": t not the base's
    t times 2^scale}`` (t compared where both hit and the scaled t is a normal float32)."""
    hit = base.hit != other.hit
    both = base.hit & other.hit
    prim_other = np.where(other.hit, other.prim, -1)
    if rewrite.permute:
        prim_other = np.where(other.hit, order[np.maximum(other.prim, 0)], -1)
    prim = both & (prim_other != base.prim)
    with np.errstate(over="ignore", under="ignore"):
        want = np.ldexp(base.t.astype(np.float64), rewrite.scale)
        finfo = np.finfo(np.float32)
        normal = (np.abs(want) >= finfo.tiny) & (np.abs(want) <= finfo.max)
        t = both & (normal | (want == 0)) & (other.t.astype(np.float64) != want)
    if rewrite.permute:
        # equal t ties are resolved by the lowest index, which a permutation moves
        prim &= other.t != base.t
    return {"hit": int(hit.sum()), "prim": int(prim.sum()), "t": int(t.sum())}
