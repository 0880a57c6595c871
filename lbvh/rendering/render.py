"""Rendering a BVH: primary rays from a pinhole camera, shaded on the host.

Modes (:data:`MODES`); each gives a float image ``(H, W, C)`` of the raw
quantity (what a float file stores) and an 8-bit picture for display:

- ``normals``: the geometric normal of the hit triangle (unit, as wound),
  ``(H, W, 3)`` in [-1, 1]; shown as ``(n + 1) / 2``.
- ``depth``: the hit distance ``t`` along unit rays, ``(H, W, 1)``, ``inf`` on a
  miss; shown bright near, dark far.
- ``diffuse``: headlight shading ``|cos|`` between ray and normal, ``(H, W, 1)``.
- ``ao``: ambient occlusion, the fraction of cosine-weighted hemisphere rays
  that escape within a fraction of the scene diagonal, ``(H, W, 1)``.
- ``heatmap``: traversal cost, nodes visited plus triangles tested by each
  primary ray, ``(H, W, 1)``; shown with a heat ramp topped at the 99th percentile.

Misses are 0 in every mode but depth. The shading is plain numpy on the hits
(t, primitive, barycentrics), so the same functions shade the kernel's hits and
the float64 oracle's (:func:`render_reference`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..bvh import BVH
from ..scene import Scene
from ..queries.traverse import kernel_defines
from ..verification.oracle import brute_force
from ..camera import Camera
from .image import heat_colours, image_kind, to_8bit, write_image

MODES = ("normals", "depth", "diffuse", "ao", "heatmap")
#: Modes that need only the closest hit of the primary rays.
PRIMARY_ONLY_MODES = ("normals", "depth", "diffuse")
#: Ambient occlusion defaults: samples per pixel, reach as a fraction of the
#: scene diagonal, and the offset of secondary-ray origins along the normal
#: (also a fraction of the diagonal) that keeps them off their own triangle.
AO_SAMPLES = 16
AO_DISTANCE = 0.1
AO_OFFSET = 1e-4


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise ValueError(f"mode: {mode!r}; expected one of {', '.join(MODES)}")
    return mode


# -- geometry of the hits ------------------------------------------------------
def triangle_normals(vertices: np.ndarray, faces: np.ndarray, prim: np.ndarray) -> np.ndarray:
    """Unit geometric normals ``float64 (N, 3)`` of triangles ``faces[prim]``, as wound
    (``(p1 - p0) x (p2 - p0)``); zero rows where ``prim < 0`` or the triangle has no area."""
    prim = np.asarray(prim)
    normals = np.zeros((len(prim), 3))
    hit = prim >= 0
    tri = vertices[faces[prim[hit]]].astype(np.float64)  # (n, 3 corners, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    normals[hit] = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    return normals


def hit_points(vertices: np.ndarray, faces: np.ndarray, prim: np.ndarray,
               u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Hit points ``float64 (n, 3)`` from barycentrics, for rays with ``prim >= 0`` only.

    Interpolating the triangle is more accurate than ``origin + t * direction``,
    which is what keeps ambient occlusion rays off their own triangle.
    """
    tri = vertices[faces[prim]].astype(np.float64)
    u = np.asarray(u, np.float64)[:, None]
    v = np.asarray(v, np.float64)[:, None]
    return (1.0 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents ``(n, 3)`` completing unit normals ``n`` to a right-handed basis,
    without a branch on the normal's direction (Duff et al., JCGT 2017, listing 3)."""
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t2 = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t1, t2


def cosine_directions(normals: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions ``float64 (n, 3)`` around unit ``normals`` from uniform
    ``xi (n, 2)`` in [0, 1): a uniform point of the unit disk lifted to the hemisphere
    (Malley's method, as in Pharr, Jakob, Humphreys, PBRT 3rd ed. 13.6.3)."""
    r = np.sqrt(xi[:, 0:1])
    phi = 2.0 * np.pi * xi[:, 1:2]
    z = np.sqrt(np.maximum(0.0, 1.0 - xi[:, 0:1]))
    t1, t2 = orthonormal_basis(normals)
    return r * np.cos(phi) * t1 + r * np.sin(phi) * t2 + z * normals


def hammersley(count: int) -> np.ndarray:
    """``float64 (count, 2)``: the Hammersley point set ``(i / count, radical inverse of i
    in base 2)``, evenly spread over the unit square."""
    i = np.arange(count, dtype=np.uint64)
    bits = np.zeros(count, np.float64)
    scale = 0.5
    while (i > 0).any():
        bits += (i & np.uint64(1)).astype(np.float64) * scale
        i >>= np.uint64(1)
        scale *= 0.5
    return np.stack([np.arange(count) / count, bits], axis=1)


# -- shading --------------------------------------------------------------------
def shade_primary(mode: str, t: np.ndarray, prim: np.ndarray, directions: np.ndarray,
                  vertices: np.ndarray, faces: np.ndarray, width: int, height: int) -> np.ndarray:
    """The image ``float32 (H, W, C)`` of a primary-hit mode (normals, depth, diffuse)."""
    prim = np.asarray(prim)
    if mode == "depth":
        depth = np.where(prim >= 0, np.asarray(t, np.float32), np.float32(np.inf))
        return depth.reshape(height, width, 1).astype(np.float32)
    normals = triangle_normals(vertices, faces, prim)
    if mode == "normals":
        return normals.reshape(height, width, 3).astype(np.float32)
    if mode == "diffuse":
        d = np.asarray(directions, np.float64)
        cos = np.abs(np.einsum("ij,ij->i", normals, d)) / np.linalg.norm(d, axis=1)
        return cos.reshape(height, width, 1).astype(np.float32)
    raise ValueError(f"mode: {mode!r} is not a primary-hit mode ({', '.join(PRIMARY_ONLY_MODES)})")


def display(mode: str, image: np.ndarray) -> np.ndarray:
    """The 8-bit picture ``uint8 (H, W, C)`` of a mode's float image."""
    check_mode(mode)
    if mode == "normals":
        hit = np.any(image != 0.0, axis=2, keepdims=True)
        return to_8bit(np.where(hit, 0.5 * (image + 1.0), 0.0))
    if mode == "depth":
        finite = np.isfinite(image)
        if not finite.any():
            return np.zeros(image.shape, np.uint8)
        near, far = float(image[finite].min()), float(image[finite].max())
        # Nearest at white, farthest at 20% grey: the background stays distinct.
        scaled = 1.0 - 0.8 * (image - near) / (far - near if far > near else 1.0)
        return to_8bit(np.where(finite, scaled, 0.0))
    if mode == "heatmap":
        # The top of the ramp at the 99th percentile: a few very expensive rays
        # would otherwise leave the rest of the picture dark.
        return to_8bit(heat_colours(image[:, :, 0], max(float(np.percentile(image, 99)), 1.0)))
    return to_8bit(image)


# -- the render -------------------------------------------------------------------
@dataclass
class RenderResult:
    """A rendered image and what it cost.

    Attributes:
        mode, camera: what was rendered.
        image: ``float32 (H, W, C)``, the raw quantity of the mode (see module doc).
        primary_hits: the closest hits of the primary rays (``lbvh.queries.traverse.Hits``).
        rays: number of rays traced (primary plus ambient occlusion rays).
        trace_seconds: wall time of the ray queries (kernel compile excluded).
        warmup_seconds: wall time of the first, one-ray queries (kernel compile).
        total_seconds: wall time of the whole render, shading included.
        overflow_count: rays whose traversal stack overflowed.
    """
    mode: str
    camera: Camera
    image: np.ndarray
    primary_hits: Any
    rays: int = 0
    trace_seconds: float = 0.0
    warmup_seconds: float = 0.0
    total_seconds: float = 0.0
    overflow_count: int = 0
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def rays_per_second(self) -> float:
        return self.rays / self.trace_seconds if self.trace_seconds > 0 else float("nan")

    def display(self) -> np.ndarray:
        """``uint8 (H, W, C)`` picture for an 8-bit file."""
        return display(self.mode, self.image)

    def save(self, path: Any) -> None:
        """Write the picture (8-bit formats) or the raw float image (float formats)."""
        write_image(path, self.display() if image_kind(path) == "8bit" else self.image)


class _Tracer:
    """Times the ray queries of one render and compiles each variant on one ray first."""
    def __init__(self, bvh: Any, triangle_test: str, order: str = "ordered") -> None:
        self.bvh, self.triangle_test, self.order = bvh, triangle_test, order
        self.rays = 0
        self.seconds = 0.0
        self.warmup_seconds = 0.0
        self.overflow_count = 0
        self._warm: set[tuple[str, bool]] = set()

    def _timed(self, query: Callable, key: tuple[str, bool], origins: np.ndarray,
               directions: np.ndarray, tmax: float, **options: Any) -> Any:
        if key not in self._warm:
            start = time.perf_counter()
            query(origins[:1], directions[:1], 0.0, tmax,
                  triangle_test=self.triangle_test, **options)
            self.warmup_seconds += time.perf_counter() - start
            self._warm.add(key)
        start = time.perf_counter()
        result = query(origins, directions, 0.0, tmax,
                       triangle_test=self.triangle_test, **options)
        self.seconds += time.perf_counter() - start
        self.rays += len(origins)
        return result

    def closest(self, origins: np.ndarray, directions: np.ndarray, counters: bool = False) -> Any:
        hits = self._timed(self.bvh.intersect, ("closest", counters), origins, directions,
                           np.inf, counters=counters, order=self.order)
        self.overflow_count += int(hits.overflow_count)
        return hits

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: float) -> np.ndarray:
        hits = self._timed(self.bvh.occluded, ("any", False), origins, directions, tmax,
                           return_hits=True)
        self.overflow_count += int(hits.overflow_count)
        return hits.hit


def scene_diagonal(vertices: np.ndarray) -> float:
    return float(np.linalg.norm(vertices.max(axis=0).astype(np.float64) - vertices.min(axis=0)))


def ambient_occlusion(occluded: Callable[[np.ndarray, np.ndarray, float], np.ndarray],
                      vertices: np.ndarray, faces: np.ndarray, hits: tuple, directions: np.ndarray,
                      samples: int, *, distance: float = AO_DISTANCE, seed: int = 0) -> np.ndarray:
    """Ambient occlusion ``float32 (N,)`` of N primary hits ``hits = (prim, u, v)`` (the
    triangle of each, -1 for a miss, and the barycentrics; 0 where ``prim < 0``).

    ``occluded(origins, directions, tmax)`` answers any-hit queries (float32 rays).
    Each sample pass casts one cosine-weighted ray per hit pixel from the hit point
    moved off the surface along the normal facing the camera, with reach
    ``distance`` times the scene diagonal; a fixed ``seed`` makes it repeatable.
    Host memory is a few hundred bytes per hit pixel whatever ``samples`` is.
    """
    prim, u, v = hits
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ValueError(f"ao samples: {samples!r}, expected a whole number >= 1")
    if not (np.isfinite(distance) and distance > 0):
        raise ValueError(f"ao distance: {distance!r}, expected a positive fraction of the diagonal")
    prim = np.asarray(prim)
    hit = np.flatnonzero(prim >= 0)
    visible = np.zeros(len(prim), np.float64)
    if len(hit) == 0:
        return visible.astype(np.float32)
    diagonal = scene_diagonal(vertices)
    normals = triangle_normals(vertices, faces, prim[hit])
    # Face the normal towards the viewer: the hemisphere above the visible side.
    facing = np.einsum("ij,ij->i", normals, np.asarray(directions, np.float64)[hit]) > 0.0
    normals[facing] *= -1.0
    points = hit_points(vertices, faces, prim[hit], np.asarray(u)[hit], np.asarray(v)[hit])
    origins = (points + AO_OFFSET * diagonal * normals).astype(np.float32)
    reach = float(distance * diagonal)
    # Every pixel gets the same Hammersley set shifted by its own random offset
    # (Cranley-Patterson rotation): stratified samples, far less noise than
    # independent ones at the same count, and no pattern shared between pixels.
    points = hammersley(samples)
    shift = np.random.default_rng(seed).random((len(hit), 2))
    for point in points:
        dirs = cosine_directions(normals, (point + shift) % 1.0).astype(np.float32)
        visible[hit] += ~np.asarray(occluded(origins, dirs, reach), bool)
    return (visible / samples).astype(np.float32)


def render(bvh: Any, camera: Camera, mode: str = "normals", *, ao_samples: int = AO_SAMPLES,
           ao_distance: float = AO_DISTANCE, seed: int = 0,
           triangle_test: str = "watertight", order: str = "ordered") -> RenderResult:
    """Render ``bvh`` (an :class:`lbvh.BVH` or an :class:`lbvh.Scene` of instances) seen by
    ``camera`` with the traversal kernel.

    Args:
        mode: one of :data:`MODES`.
        ao_samples: rays per pixel of ambient occlusion (mode ``"ao"``), see
            :func:`ambient_occlusion`.
        ao_distance: their reach, a fraction of the scene's diagonal.
        seed: their random generator's seed.
        triangle_test: ``"watertight"`` or ``"moller"``, see :func:`lbvh.queries.traverse.intersect`.
        order: the closest-hit traversal's order, ``"ordered"`` or ``"global"`` (the same
            image), see :func:`lbvh.queries.traverse.intersect`.

    Returns:
        :class:`RenderResult` with the float image and the timings.
    """
    if not isinstance(bvh, (BVH, Scene)):
        raise ValueError(f"bvh: expected an lbvh.BVH or lbvh.Scene, got {type(bvh).__name__}")
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected an lbvh.Camera, got {type(camera).__name__}")
    check_mode(mode)
    start = time.perf_counter()
    kernel_defines(bvh.ctx, False, triangle_test, False, 1, order)   # the options, first
    tracer = _Tracer(bvh, triangle_test, order)
    origins, directions = camera.rays()
    hits = tracer.closest(origins, directions, counters=(mode == "heatmap"))
    w, h = camera.width, camera.height
    if isinstance(bvh, Scene):   # shaded on the one mesh it stands for
        vertices, faces, _ = bvh.flattened()
        prim = bvh.flat_prim(hits)
    else:
        vertices, faces, prim = bvh.vertices, bvh.faces, hits.prim
    if mode in PRIMARY_ONLY_MODES:
        image = shade_primary(mode, hits.t, prim, directions, vertices, faces, w, h)
    elif mode == "ao":
        ao = ambient_occlusion(tracer.occluded, vertices, faces, (prim, hits.u, hits.v),
                               directions, ao_samples, distance=ao_distance, seed=seed)
        image = ao.reshape(h, w, 1)
    else:
        cost = np.asarray(hits.nodes_visited, np.float32) + np.asarray(hits.tris_tested, np.float32)
        image = cost.reshape(h, w, 1)
    return RenderResult(mode, camera, image, hits, rays=tracer.rays, trace_seconds=tracer.seconds,
                        warmup_seconds=tracer.warmup_seconds,
                        total_seconds=time.perf_counter() - start,
                        overflow_count=tracer.overflow_count)


def render_reference(vertices: np.ndarray, faces: np.ndarray, camera: Camera, mode: str = "depth", *,
                     ao_samples: int = AO_SAMPLES, ao_distance: float = AO_DISTANCE,
                     seed: int = 0) -> np.ndarray:
    """The float image ``(H, W, C)`` of ``mode`` with the float64 brute-force oracle
    (:func:`lbvh.verification.oracle.brute_force`) in place of the kernel: the reference that
    rendered images are tested against. Not for ``heatmap`` (the oracle has no tree)."""

    check_mode(mode)
    if mode == "heatmap":
        raise ValueError("mode: 'heatmap' measures a tree; the oracle has none")
    origins, directions = camera.rays()
    hits = brute_force(vertices, faces, origins, directions)
    if mode in PRIMARY_ONLY_MODES:
        return shade_primary(mode, hits.t, hits.prim, directions, vertices, faces,
                             camera.width, camera.height)

    def occluded(o: np.ndarray, d: np.ndarray, tmax: float) -> np.ndarray:
        return brute_force(vertices, faces, o, d, 0.0, tmax).hit

    ao = ambient_occlusion(occluded, vertices, faces, (hits.prim, hits.u, hits.v), directions,
                           ao_samples, distance=ao_distance, seed=seed)
    return ao.reshape(camera.height, camera.width, 1)
