"""Named generators of numerically hard scenes (issue 5), shared by the tests and the bench.

Each generator returns a :class:`Case`: ``float32 (V, 3)`` vertices, ``uint32
(F, 3)`` faces, a one-line statement of what makes it hard, and the rays that
probe it (``float32 (R, 3)`` origins and directions, aimed at the geometry so
that most of them hit). Sizes are small enough for a float64 brute-force oracle
unless a case says otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass
class Case:
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    why: str
    origins: np.ndarray = field(default=None)
    directions: np.ndarray = field(default=None)
    oracle: bool = True  # small enough for the float64 brute force


def _soup(n: int, rng: np.random.Generator, size: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    centres = rng.random((n, 1, 3))
    v = (centres + rng.normal(0, size, (n, 3, 3))).reshape(-1, 3)
    return v.astype(np.float32), np.arange(3 * n, dtype=np.uint32).reshape(n, 3)


def rays_at(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0,
            spread: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Rays from points around the scene's box towards random points on random triangles."""
    rng = np.random.default_rng(seed)
    v64 = vertices.astype(np.float64)
    lo, hi = v64.min(axis=0), v64.max(axis=0)
    centre, extent = (lo + hi) / 2, np.maximum(hi - lo, np.abs(lo + hi) * 1e-6 + 1e-30)
    tri = v64[faces[rng.integers(0, len(faces), count)]]
    w = rng.dirichlet(np.ones(3), count)
    targets = np.einsum("rk,rkc->rc", w, tri)
    dirs = rng.normal(size=(count, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = targets - dirs * (np.linalg.norm(extent) * spread + np.abs(centre).max() * 0)
    directions = targets - origins
    return origins.astype(np.float32), directions.astype(np.float32)


def identical_triangles(count: int = 20000) -> Case:
    v = np.tile(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), (count, 1))
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    o, d = rays_at(v, f[:1], 256)
    return Case("identical_triangles", v, f, f"{count} copies of one triangle: all Morton codes equal",
                o, d, oracle=False)


def one_point(count: int = 3000) -> Case:
    v = np.full((3 * count, 3), 1.5, np.float32)
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    o = np.float32([[0, 0, 0], [1.5, 1.5, 0]])
    d = np.float32([[1, 1, 1], [0, 0, 1]])
    return Case("one_point", v, f, "all vertices at one point: zero-extent scene, nothing can be hit", o, d)


def flat_plane(count: int = 4000, seed: int = 1) -> Case:
    v, f = _soup(count, np.random.default_rng(seed), 0.02)
    v[:, 2] = 0
    o, d = rays_at(v, f, 512, seed)
    return Case("flat_plane", v, f, "every triangle in the plane z = 0: one axis of zero extent", o, d)


def line_of_triangles(count: int = 2000) -> Case:
    x = np.arange(count, dtype=np.float32)
    v = np.stack([np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1),
                  np.stack([x + 0.5, np.full_like(x, 1), np.zeros_like(x)], 1),
                  np.stack([x + 1, np.zeros_like(x), np.zeros_like(x)], 1)], 1).reshape(-1, 3)
    # every triangle in the plane z = 0 with y in [0, 1]: two axes nearly degenerate
    v[:, 1] *= np.float32(1e-3)
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    rng = np.random.default_rng(2)
    o = np.stack([rng.random(512) * count, rng.random(512) * 5e-4, np.ones(512)], 1).astype(np.float32)
    d = np.tile(np.float32([0, 0, -1]), (512, 1))
    return Case("line_of_triangles", v, f, "a line of triangles: y extent 1e-3, z extent 0", o, d)


def zero_area_mix(count: int = 4000, seed: int = 3) -> Case:
    rng = np.random.default_rng(seed)
    v, f = _soup(count, rng, 0.03)
    tri = v.reshape(-1, 3, 3)
    third = count // 3
    tri[:third, 2] = tri[:third, 0] * 0.5 + tri[:third, 1] * 0.5          # collinear
    tri[third:2 * third, 1] = tri[third:2 * third, 0]                   # repeated vertex
    o, d = rays_at(v, f, 512, seed)
    return Case("zero_area_mix", tri.reshape(-1, 3), f,
                "two thirds zero-area triangles (collinear or repeated vertices) among good ones", o, d)


def slivers(count: int = 3000, seed: int = 4) -> Case:
    rng = np.random.default_rng(seed)
    a = rng.random((count, 3)) * 10
    along = rng.normal(size=(count, 3))
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    b = a + along * 10
    side = np.cross(along, rng.normal(size=(count, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    c = a + along * 5 + side * 1e-3  # 10,000 times longer than wide
    v = np.stack([a, b, c], 1).reshape(-1, 3)
    # and needles crossing the whole scene
    v[:30] = np.repeat(np.float64([[-1, -1, -1], [11, 11, 11], [11, 11, 11.001]]), 10, axis=0)
    v = v.astype(np.float32)
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    o, d = rays_at(v, f, 512, seed)
    return Case("slivers", v, f, "slivers 10^4 times longer than wide, needles across the scene", o, d)


def huge_coordinates(count: int = 3000, seed: int = 5) -> Case:
    v, f = _soup(count, np.random.default_rng(seed), 0.02)
    v = (v.astype(np.float64) * 2e30 - 1e30).astype(np.float32)
    o, d = rays_at(v, f, 512, seed)
    return Case("huge_coordinates", v, f, "coordinates around 1e30: box areas overflow float32", o, d)


def tiny_coordinates(count: int = 3000, seed: int = 6, scale: float = 1e-30) -> Case:
    v, f = _soup(count, np.random.default_rng(seed), 0.02)
    v = (v.astype(np.float64) * scale).astype(np.float32)
    o, d = rays_at(v, f, 512, seed)
    return Case("tiny_coordinates", v, f, f"coordinates around {scale:g}: areas underflow", o, d)


def denormal_coordinates(count: int = 1000, seed: int = 7) -> Case:
    case = tiny_coordinates(count, seed, scale=1e-38)
    case.name, case.why = "denormal_coordinates", "coordinates near 1e-38: denormal differences"
    return case


def far_from_origin(count: int = 3000, seed: int = 8, offset: float = 5e6) -> Case:
    v, f = _soup(count, np.random.default_rng(seed), 0.02)
    v = (v.astype(np.float64) * 10 + offset).astype(np.float32)
    o, d = rays_at(v, f, 512, seed)
    return Case("far_from_origin", v, f, f"a small mesh offset by {offset:g}: coarse float32 spacing", o, d)


def mixed_scales(count: int = 3000, seed: int = 9, grid: int = 20) -> Case:
    rng = np.random.default_rng(seed)
    small, f_small = _soup(count, rng, 0.002)
    small[:, :2] = small[:, :2] * 10 - 5
    # a tessellated ground 10^4 times larger: its centroids set the Morton grid,
    # so every small object falls into a handful of cells
    g = np.linspace(-5e4, 5e4, grid + 1)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1).astype(np.float32)
    idx = np.arange((grid + 1) ** 2).reshape(grid + 1, grid + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f_ground = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]) + len(small)
    v = np.concatenate([small, ground]).astype(np.float32)
    f = np.concatenate([f_small, f_ground.astype(np.uint32)])
    o, d = rays_at(v, f_small, 512, seed, spread=0.1)
    return Case("mixed_scales", v, f, "a ground plane 10^4 times larger than the objects on it", o, d)


def few_triangles(count: int) -> Case:
    v, f = _soup(count, np.random.default_rng(count), 0.2)
    o, d = rays_at(v, f, 64, count)
    return Case(f"{count}_triangles", v, f, f"{count} triangle(s)", o, d)


def exponential_spacing(count: int = 120) -> Case:
    # centres at 2^-k: each Morton split peels off one triangle, the deepest trees
    x = np.float64(2.0) ** -np.arange(count)
    base = np.stack([x, np.zeros(count), np.zeros(count)], 1)
    tri = np.stack([base, base + [0, 1e-3, 0], base + [0, 0, 1e-3]], 1) * [1, 1, 1]
    v = tri.reshape(-1, 3).astype(np.float32)
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    o = np.stack([x, np.full(count, 2e-4), np.full(count, -1.0)], 1).astype(np.float32)
    d = np.tile(np.float32([0, 0, 1]), (count, 1))
    return Case("exponential_spacing", v, f, "primitives spaced 2^-k apart: as deep as a tree gets", o, d)


#: every generator by name, with its default size
CASES: dict[str, Callable[[], Case]] = {
    "identical_triangles": identical_triangles,
    "one_point": one_point,
    "flat_plane": flat_plane,
    "line_of_triangles": line_of_triangles,
    "zero_area_mix": zero_area_mix,
    "slivers": slivers,
    "huge_coordinates": huge_coordinates,
    "tiny_coordinates": tiny_coordinates,
    "denormal_coordinates": denormal_coordinates,
    "far_from_origin": far_from_origin,
    "mixed_scales": mixed_scales,
    "1_triangle": lambda: few_triangles(1),
    "2_triangles": lambda: few_triangles(2),
    "1025_triangles": lambda: few_triangles(1025),
    "exponential_spacing": exponential_spacing,
}
