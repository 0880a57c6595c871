"""Generated test meshes, one generator per kind (numpy only): the tests, the
hard cases (:mod:`lbvh.verification.hard_cases`) and the benches (bench/meshes.py)
all draw their meshes here.

Every generator returns ``(vertices, faces)``: ``float32 (V, 3)`` and
``uint32 (F, 3)``, C-contiguous. They are vectorised (a 4M-triangle mesh takes
about a second) and deterministic: the same arguments give the same bits, which
tests and bench tables rely on.

    soup(n_tris, seed, size)        random small triangles, 3 own vertices each
    sphere(n_tris)                  UV sphere, shared vertices, pole fans
    cube_sphere(n)                  closed cube mesh projected onto the unit sphere
    cube_mesh(n, half)              closed cube, each face an n x n grid, welded vertices
    grid_mesh(width, height)        flat grid in z = 0, shared vertices
    terrain(n_tris, seed)           smooth height field (sine waves) over the unit square
    height_field(n, seed)           rough height field (random heights), both diagonals
    copies(mesh, k), copies_to(mesh, n_tris)   a mesh tiled side by side

All grids (:func:`grid_mesh`, :func:`terrain`, :func:`height_field`, the bands of
:func:`sphere`) are triangulated by :func:`grid_faces`.
"""
from __future__ import annotations

import math

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def as_mesh(vertices: np.ndarray, faces: np.ndarray) -> Mesh:
    """``(float32 (V, 3), uint32 (F, 3))``, C-contiguous (no copy where they already are)."""
    return (np.ascontiguousarray(vertices, dtype=np.float32),
            np.ascontiguousarray(faces, dtype=np.uint32))


def _check_count(n_tris: int) -> int:
    n = int(n_tris)
    if n < 1:
        raise ValueError(f"n_tris: {n_tris!r}; expected a positive number of triangles")
    return n


# -- triangle soups ---------------------------------------------------------------------

def soup(n_tris: int, seed: int | np.random.Generator = 0, size: float | None = None, *,
         scale: float = 1.0, spread: str = "uniform", dtype: type = np.float32) -> Mesh:
    """``n_tris`` random small triangles, each with its own 3 vertices (faces
    ``0 1 2, 3 4 5, ...``) around a centre uniform in ``[0, scale)^3``; faces in
    generation order, i.e. spatially random: no locality for a build to exploit.

    Each vertex is its centre plus an offset per coordinate:

    * ``spread="uniform"`` (the benches): uniform in ``[-size/2, size/2)``; ``size``
      defaults to ``2 n^(-1/3) scale``, about twice the mean spacing of the
      centres, so neighbours overlap a little (as in a dense scene);
    * ``spread="normal"``: normal with standard deviation ``size`` (default
      ``0.01 scale``): the tests' well-behaved soup (``size`` 0.01) and the hard
      cases' (0.002 to 0.2, then reshaped).

    ``dtype`` is the precision the numbers are drawn and summed in before the
    vertices are rounded to float32: ``np.float32`` (the tests, the benches) or
    ``np.float64`` (the hard cases); the two draw different streams from the
    generator. ``seed`` is a seed or a ``np.random.Generator`` (drawn from, and
    left where the soup ends).
    """
    n = _check_count(n_tris)
    if spread not in ("uniform", "normal"):
        raise ValueError(f"spread: {spread!r}; expected 'uniform' or 'normal'")
    rng = np.random.default_rng(seed)  # a Generator passes through unchanged
    centres = rng.random((n, 1, 3), dtype=dtype) * scale
    if spread == "uniform":
        edge = dtype(2.0 / n ** (1.0 / 3.0) * scale if size is None else size)
        offsets = (rng.random((n, 3, 3), dtype=dtype) - dtype(0.5)) * edge
    else:
        sd = 0.01 * scale if size is None else size
        offsets = rng.normal(0, sd, (n, 3, 3)).astype(dtype)
    vertices = (centres + offsets).reshape(-1, 3).astype(np.float32)
    return as_mesh(vertices, np.arange(3 * n, dtype=np.uint32).reshape(n, 3))


# -- grids ------------------------------------------------------------------------------

def grid_faces(rows: int, cols: int, row_stride: int | None = None, first: int = 0, *,
               wrap: bool = False, interleaved: bool = False,
               alternate: bool = False) -> np.ndarray:
    """Two triangles per cell of a vertex grid: ``uint32 (2 * rows * cols, 3)``.

    Vertex ``(r, c)`` has index ``first + r * row_stride + c`` (``row_stride``
    defaults to ``cols + 1``); with ``wrap`` the last column joins column 0 (a
    band around a sphere). Cell ``(r, c)``, corners ``a = (r, c)``, ``b = (r+1, c)``,
    ``e = (r+1, c+1)``, ``d = (r, c+1)``, is split along ``a e`` into ``(a, b, e)``
    and ``(a, e, d)``; with ``alternate``, cells with ``r + c`` even are split along
    ``b d`` instead, into ``(a, b, d)`` and ``(b, e, d)`` (both diagonals in use).
    Faces come cell by cell (``r`` major), the two of a cell together with
    ``interleaved`` (triangles ``2 (r cols + c)`` and the next), else all first
    triangles and then all second ones.
    """
    stride = np.uint32(cols + 1 if row_stride is None else row_stride)
    if first + (rows + 1) * int(stride) > 2 ** 32:
        raise ValueError(f"a {rows} x {cols} grid from vertex {first} overflows uint32 indices")
    r = np.arange(rows, dtype=np.uint32)[:, None]
    c = np.arange(cols, dtype=np.uint32)[None, :]
    c1 = (c + np.uint32(1)) % stride if wrap else c + np.uint32(1)
    base, below = np.uint32(first) + r * stride, np.uint32(first) + (r + np.uint32(1)) * stride
    a, b, d, e = base + c, below + c, base + c1, below + c1   # each (rows, cols)
    first_tri, second_tri = np.stack([a, b, e], axis=-1), np.stack([a, e, d], axis=-1)
    if alternate:
        flip = ((r + c) % 2 == 0)[..., None]
        first_tri = np.where(flip, np.stack([a, b, d], axis=-1), first_tri)
        second_tri = np.where(flip, np.stack([b, e, d], axis=-1), second_tri)
    if interleaved:
        return np.stack([first_tri, second_tri], axis=2).reshape(-1, 3)
    return np.concatenate([first_tri.reshape(-1, 3), second_tri.reshape(-1, 3)])


def grid_mesh(width: int, height: int, origin: float = 0.0, cell: float = 1.0) -> Mesh:
    """A ``width x height`` grid of square cells in the plane z = 0, two triangles each.

    Vertices are shared (``(width+1)(height+1)`` of them, float32). Cell ``(i, j)``
    spans ``x in origin + cell*[i, i+1]``, ``y in origin + cell*[j, j+1]``; its
    triangles are ``2 (i height + j)`` (below the diagonal, ``fx >= fy``) and the
    next one (above it).
    """
    xs = origin + cell * np.arange(width + 1, dtype=np.float64)
    ys = origin + cell * np.arange(height + 1, dtype=np.float64)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    vertices = np.stack([gx, gy, np.zeros_like(gx)], axis=-1).reshape(-1, 3)
    return as_mesh(vertices, grid_faces(width, height, interleaved=True))


def terrain(n_tris: int, seed: int = 0) -> Mesh:
    """Smooth height field over the unit square with about ``n_tris`` triangles (``2 k^2``).

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
    return as_mesh(vertices, grid_faces(k, k))


def height_field(n: int = 48, seed: int = 0) -> Mesh:
    """Rough height field: ``n x n`` cells over integer ``(x, y)``, independent random
    heights in ``[0, 2)`` at the vertices, the two diagonals alternating from cell
    to cell (shared vertices and edges meeting at every angle: the watertightness
    tests)."""
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    h = rng.random((n + 1, n + 1)) * 2
    vertices = np.stack([i, j, h], -1).reshape(-1, 3)
    return as_mesh(vertices, grid_faces(n, n, interleaved=True, alternate=True))


# -- closed surfaces ----------------------------------------------------------------------

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
    bands = grid_faces(m - 1, s, s, first=1, wrap=True)
    return as_mesh(vertices, np.concatenate([top, bands, bottom]))


def blob(n_tris: int, seed: int = 0) -> Mesh:
    """:func:`sphere` with relief: each vertex moved along its radius by a few random
    spherical waves (radius 1 +- about 0.25), so a closed surface with shared
    vertices, bumps and folds of every size, the kind of mesh an inside test or a
    signed distance is asked of most."""
    v, f = sphere(n_tris)
    p = v.astype(np.float64)
    rng = np.random.default_rng(seed)
    r = np.ones(len(p))
    for _ in range(6):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        r += rng.uniform(0.02, 0.06) * np.sin(rng.uniform(2.0, 9.0) * (p @ axis)
                                               + rng.uniform(0.0, 2 * np.pi))
    return as_mesh(p * r[:, None], f)


def cube_mesh(n: int = 4, half: float = 2.0) -> Mesh:
    """A closed cube ``[-half, half]^3``, each face an ``n x n`` grid: welded vertices,
    every edge shared by exactly two triangles, outward winding; exact coordinates
    when ``2 half / n`` is a power of two."""
    steps = np.linspace(-half, half, n + 1)
    keys: dict[tuple[float, float, float], int] = {}
    verts: list[tuple[float, float, float]] = []

    def vid(p) -> int:
        key = tuple(float(x) for x in p)
        if key not in keys:
            keys[key] = len(verts)
            verts.append(key)
        return keys[key]

    faces = []
    for axis in range(3):
        u, w = (axis + 1) % 3, (axis + 2) % 3
        for side in (-half, half):
            for i in range(n):
                for j in range(n):
                    corners = []
                    for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        p = [0.0, 0.0, 0.0]
                        p[axis], p[u], p[w] = side, steps[i + di], steps[j + dj]
                        corners.append(vid(p))
                    a, b, c, d = corners
                    # (u, w, axis) is right-handed: counter-clockwise seen from +axis
                    quad = [(a, b, c), (a, c, d)] if side > 0 else [(a, c, b), (a, d, c)]
                    faces.extend(quad)
    return np.array(verts, np.float32), np.array(faces, np.uint32)


def cube_sphere(n: int = 8) -> Mesh:
    """:func:`cube_mesh` ``(n, half=1)`` projected onto the unit sphere: a closed
    mesh with shared vertices in general position (not on any grid)."""
    v, f = cube_mesh(n, half=1.0)
    v64 = v.astype(np.float64)
    return (v64 / np.linalg.norm(v64, axis=1, keepdims=True)).astype(np.float32), f


# -- tiling ---------------------------------------------------------------------------------

def copies(mesh: Mesh, k: int, gap: float = 0.1) -> Mesh:
    """``k`` copies of ``mesh`` side by side on a square grid in the x-y plane.

    Copies are ``(1 + gap)`` box extents apart, so they do not overlap;
    copy ``i`` has faces ``i * F .. (i + 1) * F - 1``.
    """
    vertices, faces = as_mesh(*mesh)
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
    return as_mesh(out_v.reshape(-1, 3), out_f.reshape(-1, 3))


def copies_to(mesh: Mesh, n_tris: int, gap: float = 0.1) -> Mesh:
    """As many copies of ``mesh`` as give about ``n_tris`` triangles (at least one)."""
    n = _check_count(n_tris)
    return copies(mesh, max(1, round(n / len(mesh[1]))), gap)


#: Generators of a mesh from a triangle count and a seed, by name (the benches' ``--meshes``).
GENERATORS = {
    "sphere": lambda n, seed=0: sphere(n),
    "terrain": terrain,
    "soup": soup,
}
