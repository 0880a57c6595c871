"""Procedural triangle meshes for benchmarks and tests (numpy only).

Every generator returns ``(vertices, faces)``: ``float32 (V, 3)`` and
``uint32 (F, 3)``, C-contiguous, with about the number of triangles asked for
(the exact count depends on the grid that fits it). All are vectorised, so a
4M-triangle mesh takes well under a second or two.

    sphere(n_tris)          UV sphere, shared vertices, pole fans (no degenerate triangles)
    terrain(n_tris, seed)   height field over a square grid, shared vertices
    soup(n_tris, seed)      random small triangles in the unit cube, 3 own vertices each
    copies(mesh, k)         k copies of a mesh side by side on a grid
    copies_to(mesh, n_tris) as many copies as make about n_tris triangles
"""
from __future__ import annotations

import math

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def _mesh(vertices: np.ndarray, faces: np.ndarray) -> Mesh:
    return (np.ascontiguousarray(vertices, dtype=np.float32),
            np.ascontiguousarray(faces, dtype=np.uint32))


def _check_count(n_tris: int) -> int:
    n = int(n_tris)
    if n < 1:
        raise ValueError(f"n_tris: {n_tris!r}; expected a positive number of triangles")
    return n


def _grid_quads(rows: int, cols: int, row_stride: int, first: int = 0,
                wrap: bool = False) -> np.ndarray:
    """Two triangles per cell of a vertex grid: ``uint32 (2 * rows * cols, 3)``.

    Vertex (r, c) has index ``first + r * row_stride + c``; with ``wrap`` the
    last column joins column 0 (a band around a sphere).
    """
    r = np.arange(rows, dtype=np.int64)[:, None]
    c = np.arange(cols, dtype=np.int64)[None, :]
    c1 = (c + 1) % row_stride if wrap else c + 1
    a = first + r * row_stride + c
    b = first + (r + 1) * row_stride + c
    d = first + r * row_stride + c1
    e = first + (r + 1) * row_stride + c1
    lower = np.stack([a, b, e], axis=-1).reshape(-1, 3)
    upper = np.stack([a, e, d], axis=-1).reshape(-1, 3)
    return np.concatenate([lower, upper]).astype(np.uint32)


def sphere(n_tris: int, radius: float = 1.0) -> Mesh:
    """UV sphere of about ``n_tris`` triangles (``4 m^2`` for ``m`` latitude circles).

    Shared vertices (V is about F / 2); the poles are triangle fans, so no
    triangle has zero area.
    """
    n = _check_count(n_tris)
    m = max(1, round(math.sqrt(n / 4)))           # latitude circles between the poles
    s = max(3, 2 * m)                             # segments around each circle
    theta = np.pi * np.arange(1, m + 1) / (m + 1)
    phi = 2 * np.pi * np.arange(s) / s
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(ct, (m, s))], axis=-1)
    north, south = 0, 1 + m * s
    vertices = np.concatenate([[[0.0, 0.0, 1.0]], ring.reshape(-1, 3), [[0.0, 0.0, -1.0]]]) * radius
    j = np.arange(s, dtype=np.int64)
    top = np.stack([np.full(s, north), 1 + j, 1 + (j + 1) % s], axis=1)
    last = 1 + (m - 1) * s
    bottom = np.stack([np.full(s, south), last + (j + 1) % s, last + j], axis=1)
    bands = _grid_quads(m - 1, s, s, first=1, wrap=True)
    return _mesh(vertices, np.concatenate([top, bands, bottom]))


def terrain(n_tris: int, seed: int = 0) -> Mesh:
    """Height field over the unit square with about ``n_tris`` triangles (``2 k^2``).

    Heights are a few random sine waves plus small noise: a surface with
    relief but no overhangs, the kind of input where most boxes are flat-ish.
    """
    n = _check_count(n_tris)
    k = max(1, round(math.sqrt(n / 2)))          # cells per side
    rng = np.random.default_rng(seed)
    u = np.linspace(0.0, 1.0, k + 1, dtype=np.float32)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = np.zeros_like(x)
    for _ in range(4):
        fx, fy = rng.uniform(1.0, 8.0, 2)
        px, py = rng.uniform(0.0, 2 * np.pi, 2)
        z += np.float32(rng.uniform(0.02, 0.08)) * (np.sin(fx * 2 * np.pi * x + px)
                                                      * np.cos(fy * 2 * np.pi * y + py))
    z += rng.normal(0.0, 0.002, z.shape).astype(np.float32)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    return _mesh(vertices, _grid_quads(k, k, k + 1))


def soup(n_tris: int, seed: int = 0) -> Mesh:
    """``n_tris`` random small triangles in the unit cube, each with its own 3 vertices.

    Edges are about twice the mean spacing of the centres, so neighbours
    overlap a little (as in a dense scene). Faces are in generation order,
    i.e. spatially random: no locality for the build to exploit.
    """
    n = _check_count(n_tris)
    rng = np.random.default_rng(seed)
    edge = np.float32(2.0 / n ** (1.0 / 3.0))
    centres = rng.random((n, 1, 3), dtype=np.float32)
    offsets = rng.random((n, 3, 3), dtype=np.float32) - np.float32(0.5)
    vertices = (centres + offsets * edge).reshape(-1, 3)
    faces = np.arange(3 * n, dtype=np.uint32).reshape(n, 3)
    return _mesh(vertices, faces)


def copies(mesh: Mesh, k: int, gap: float = 0.1) -> Mesh:
    """``k`` copies of ``mesh`` side by side on a square grid in the x-y plane.

    Copies are ``(1 + gap)`` box extents apart, so they do not overlap;
    copy ``i`` has faces ``i * F .. (i + 1) * F - 1``.
    """
    vertices, faces = _mesh(*mesh)
    k = int(k)
    if k < 1:
        raise ValueError(f"k: {k}; expected at least one copy")
    if k * len(vertices) >= 2 ** 32:
        raise ValueError(f"k: {k} copies of {len(vertices):,} vertices overflow uint32 indices")
    extent = vertices.max(axis=0) - vertices.min(axis=0)
    step = np.where(extent > 0, extent, 1.0).astype(np.float64) * (1.0 + gap)
    cols = math.ceil(math.sqrt(k))
    i = np.arange(k)
    offsets = np.zeros((k, 3))
    offsets[:, 0] = (i % cols) * step[0]
    offsets[:, 1] = (i // cols) * step[1]
    out_v = vertices[None, :, :] + offsets[:, None, :].astype(np.float32)
    shift = (np.arange(k, dtype=np.uint64) * len(vertices))[:, None, None]
    out_f = faces[None, :, :].astype(np.uint64) + shift
    return _mesh(out_v.reshape(-1, 3), out_f.reshape(-1, 3))


def copies_to(mesh: Mesh, n_tris: int, gap: float = 0.1) -> Mesh:
    """As many copies of ``mesh`` as give about ``n_tris`` triangles (at least one)."""
    n = _check_count(n_tris)
    return copies(mesh, max(1, round(n / len(mesh[1]))), gap)


#: Generators of a mesh from a triangle count and a seed, by name.
GENERATORS = {
    "sphere": lambda n, seed=0: sphere(n),
    "terrain": terrain,
    "soup": soup,
}
