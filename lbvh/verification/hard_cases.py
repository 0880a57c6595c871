"""Named generators of numerically hard scenes and rays (issue 5).

Used by ``lbvh check`` (:mod:`lbvh.verification.check`), the test suite
(tests/verification/test_hard_cases.py) and the bench; the meshes come from
:mod:`lbvh.verification.meshes`. Each generator returns a
:class:`Case`: a mesh (``float32 (V, 3)`` vertices, ``uint32 (F, 3)`` faces),
the rays that probe it (``float32 (R, 3)`` origins and directions, ``float32
(R,)`` tmin and tmax) and a one-line statement of what makes it hard. Unless a
case says otherwise its answers come from the float64 brute-force oracle
(:func:`lbvh.verification.oracle.brute_force`); the case over 2^24 triangles is too big for
it and carries its exact answers instead (``expected_prim``, ``expected_t``).

Every scene case also gets axis-aligned rays (:func:`axis_rays_at`) whose zero
direction components are ``+0.0`` or ``-0.0``: the traversal's slab test meets
``0 * inf`` there, on flat boxes too.

The numbers in :data:`ISSUE_CASE` are those of issue 5's list (1-12).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

# cube_mesh and grid_mesh are also taken from here (tests/test_bad_input.py)
from .meshes import cube_mesh, cube_sphere, grid_mesh, soup


@dataclass
class Case:
    """A hard scene with its rays.

    Attributes:
        name: short identifier (``lbvh check --cases`` takes these).
        vertices, faces: ``float32 (V, 3)`` and ``uint32 (F, 3)``.
        why: one line on what makes it hard.
        origins, directions: ``float32 (R, 3)``.
        tmin, tmax: ``float32 (R,)``.
        stack_size: force this traversal stack (entries) instead of the tree's
            own (:func:`lbvh.queries.traverse.stack_size_for`); overflows are then expected
            and must be reported.
        expected_prim, expected_t: exact answers (``int32 (R,)``, ``float32 (R,)``)
            where the oracle is too slow; ``None`` otherwise.
        must_hit: ``bool (R,)`` rays that must hit something whatever the
            oracle says (rays from inside a closed mesh: a miss is a leak); or ``None``.
        slow: the case takes minutes (``lbvh check`` runs it only with ``--large``).
    """
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    why: str
    origins: np.ndarray
    directions: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    stack_size: int | None = None
    expected_prim: np.ndarray | None = None
    expected_t: np.ndarray | None = None
    must_hit: np.ndarray | None = None
    slow: bool = False

    @property
    def num_rays(self) -> int:
        return len(self.origins)


def make_case(name: str, vertices: np.ndarray, faces: np.ndarray, why: str, rays: tuple, *,
              axis_rays: int = 0, seed: int = 0, **extra) -> Case:
    """A :class:`Case` with ``rays`` (``(origins, directions)`` or ``(origins,
    directions, tmin, tmax)``) as float32 arrays, plus ``axis_rays`` axis-aligned rays
    (drawn with ``seed``); ``extra``: the other fields of :class:`Case`."""
    origins, directions, tmin, tmax = (*rays, 0.0, np.inf) if len(rays) == 2 else rays
    o = np.asarray(origins, np.float32).reshape(-1, 3)
    d = np.asarray(directions, np.float32).reshape(-1, 3)
    lo = np.broadcast_to(np.asarray(tmin, np.float32), (len(o),))
    hi = np.broadcast_to(np.asarray(tmax, np.float32), (len(o),))
    if axis_rays:
        ao, ad = axis_rays_at(vertices, faces, axis_rays, seed)
        o, d = np.concatenate([o, ao]), np.concatenate([d, ad])
        lo = np.concatenate([lo, np.zeros(len(ao), np.float32)])
        hi = np.concatenate([hi, np.full(len(ao), np.inf, np.float32)])
        if extra.get("must_hit") is not None:
            extra["must_hit"] = np.concatenate([extra["must_hit"], np.zeros(len(ao), bool)])
    return Case(name, np.ascontiguousarray(vertices, np.float32),
                np.ascontiguousarray(faces, np.uint32), why, o, d,
                np.ascontiguousarray(lo), np.ascontiguousarray(hi), **extra)


# -- rays -------------------------------------------------------------------------

def _scale(v64: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Box centre, box extent, and a positive length of the scene's own size."""
    lo, hi = v64.min(axis=0), v64.max(axis=0)
    extent = hi - lo
    size = float(extent.max())
    if size == 0.0:  # a zero-extent scene: fall back to the size of its coordinates
        size = float(np.abs(lo).max()) or 1.0
    return (lo + hi) / 2, extent, size


def _targets(vertices: np.ndarray, faces: np.ndarray, count: int,
             rng: np.random.Generator) -> np.ndarray:
    """``float64 (count, 3)`` random points on random triangles."""
    tri = vertices.astype(np.float64)[faces[rng.integers(0, len(faces), count)]]
    w = rng.dirichlet(np.ones(3), count)
    return np.einsum("rk,rkc->rc", w, tri)


def rays_at(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0,
            spread: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Rays from points around the scene towards random points on random triangles.

    Origins are ``spread`` scene sizes away from their target; a direction is
    the float32 difference target - origin, so ``t`` is about 1 at the target.
    """
    rng = np.random.default_rng(seed)
    targets = _targets(vertices, faces, count, rng)
    dirs = rng.normal(size=(count, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    size = _scale(vertices.astype(np.float64))[2]
    origins = _to_float32(targets - dirs * size * spread)
    return origins, (targets - origins).astype(np.float32)


def axis_rays_at(vertices: np.ndarray, faces: np.ndarray, count: int,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned rays through random points on random triangles.

    Directions cycle through +x, -x, +y, -y, +z, -z; their zero components are
    ``+0.0`` for even rays and ``-0.0`` for odd ones, so both signs of zero meet
    every axis. Origins lie one scene size before the target along the ray.
    """
    rng = np.random.default_rng(seed + 1)
    targets = _targets(vertices, faces, count, rng)
    size = _scale(vertices.astype(np.float64))[2]
    k = np.arange(count)
    axis, sign = (k // 2) % 3, np.where(k % 2 == 0, 1.0, -1.0)
    zero = np.where(k % 2 == 0, 0.0, -0.0)
    d = np.repeat(zero[:, None], 3, axis=1)
    d[k, axis] = sign
    o = targets.copy()
    # no further than 2^125 (4e37): t must stay a float32 in scenes near its limit
    o[k, axis] -= sign * min(size, 2.0 ** 125)
    return _to_float32(o), d.astype(np.float32)


def _to_float32(points: np.ndarray) -> np.ndarray:
    """float32 points, clamped into the finite float32 range (scenes near float32's limit)."""
    big = float(np.finfo(np.float32).max)
    return np.clip(points, -big, big).astype(np.float32)


def _soup(count: int, seed: int, size: float) -> tuple[np.ndarray, np.ndarray]:
    """The hard cases' soup: :func:`lbvh.verification.meshes.soup` with normal offsets of
    standard deviation ``size``, drawn in float64."""
    return soup(count, seed, size, spread="normal", dtype=np.float64)


def _scene_case(name: str, v: np.ndarray, f: np.ndarray, why: str, rays: int = 512,
                seed: int = 0, spread: float = 1.0, aim_faces: np.ndarray | None = None) -> Case:
    """A scene case with aimed rays and axis-aligned rays (a quarter as many)."""
    o, d = rays_at(v, f if aim_faces is None else aim_faces, rays, seed, spread)
    return make_case(name, v, f, why, (o, d), axis_rays=max(rays // 4, 6), seed=seed)


# -- 1-9: scenes ----------------------------------------------------------------------

def identical_triangles(count: int = 20000) -> Case:
    v = np.tile(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), (count, 1))
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    return _scene_case("identical_triangles", v, f,
                       f"{count} copies of one triangle: all Morton codes equal, every hit a tie",
                       rays=128, aim_faces=f[:1])


def one_point(count: int = 3000) -> Case:
    v = np.full((3 * count, 3), 1.5, np.float32)
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    o = np.float32([[0, 0, 0], [1.5, 1.5, 0], [1.5, 1.5, 1.5], [1.5, 1.5, 1.5]])
    d = np.float32([[1, 1, 1], [0, 0, 1], [1, 0, 0], [-0.0, -0.0, -1]])
    return make_case("one_point", v, f, "all vertices at one point: zero-extent scene, "
                     "nothing can be hit", (o, d), axis_rays=12)


def flat_plane(count: int = 4000, seed: int = 1) -> Case:
    v, f = _soup(count, seed, 0.02)
    v[:, 2] = 0
    return _scene_case("flat_plane", v, f, "every triangle in the plane z = 0: one axis of "
                       "zero extent, every box flat", seed=seed)


def line_of_triangles(count: int = 2000) -> Case:
    x = np.arange(count, dtype=np.float32)
    zero = np.zeros_like(x)
    v = np.stack([np.stack([x, zero, zero], 1), np.stack([x + 0.5, zero + 1, zero], 1),
                  np.stack([x + 1, zero, zero], 1)], 1).reshape(-1, 3)
    v[:, 1] *= np.float32(1e-3)  # y extent 1e-3, z extent 0
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    rng = np.random.default_rng(2)
    o = np.stack([rng.random(384) * count, rng.random(384) * 5e-4, np.ones(384)], 1)
    d = np.tile([0.0, -0.0, -1.0], (384, 1))
    case = make_case("line_of_triangles", v, f, "a line of triangles: y extent 1e-3, z extent 0",
                     (o, d), axis_rays=96, seed=2)
    return case


def zero_area_mix(count: int = 4000, seed: int = 3) -> Case:
    v, f = _soup(count, seed, 0.03)
    tri = v.reshape(-1, 3, 3)
    third = count // 3
    tri[:third, 2] = tri[:third, 0] * 0.5 + tri[:third, 1] * 0.5          # (nearly) collinear
    tri[third:2 * third, 1] = tri[third:2 * third, 0]                   # repeated vertex
    # and faces that repeat an index (the Conference kind)
    f = f.copy()
    f[2 * third:2 * third + 50, 2] = f[2 * third:2 * third + 50, 0]
    return _scene_case("zero_area_mix", tri.reshape(-1, 3), f, "two thirds zero-area triangles "
                       "(collinear, repeated vertices, repeated indices) among good ones", seed=seed)


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
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    return _scene_case("slivers", v.astype(np.float32), f,
                       "slivers 10^4 times longer than wide, needles across the scene", seed=seed)


def huge_coordinates(count: int = 3000, seed: int = 5) -> Case:
    v, f = _soup(count, seed, 0.02)
    v = (v.astype(np.float64) * 2e30 - 1e30).astype(np.float32)
    return _scene_case("huge_coordinates", v, f, "coordinates around 1e30: box areas overflow "
                       "float32", seed=seed)


def near_float_max(count: int = 1000, seed: int = 11) -> Case:
    v, f = _soup(count, seed, 0.02)
    big = np.finfo(np.float32).max
    v = np.clip((v.astype(np.float64) * 2 - 1) * big, -big, big).astype(np.float32)
    return _scene_case("near_float_max", v, f, "coordinates up to +-3.4e38: extents and "
                       "centres overflow unless halved first", seed=seed, rays=256, spread=0.25)


def tiny_coordinates(count: int = 3000, seed: int = 6, scale: float = 1e-30,
                     name: str = "tiny_coordinates") -> Case:
    v, f = _soup(count, seed, 0.02)
    v = (v.astype(np.float64) * scale).astype(np.float32)
    return _scene_case(name, v, f, f"coordinates around {scale:g}: areas underflow", seed=seed)


def denormal_coordinates(count: int = 1000, seed: int = 7) -> Case:
    case = tiny_coordinates(count, seed, scale=1e-38, name="denormal_coordinates")
    case.why = "coordinates near 1e-38: denormal differences"
    return case


def far_from_origin(count: int = 3000, seed: int = 8, offset: float = 5e6) -> Case:
    v, f = _soup(count, seed, 0.02)
    v = (v.astype(np.float64) * 10 + offset).astype(np.float32)
    return _scene_case("far_from_origin", v, f, f"a small mesh offset by {offset:g}: float32 "
                       "spacing 0.5 at the mesh", seed=seed)


def mixed_scales(count: int = 3000, seed: int = 9, grid: int = 20) -> Case:
    small, f_small = _soup(count, seed, 0.002)
    small[:, :2] = small[:, :2] * 10 - 5
    # a tessellated ground 10^4 times larger: its centroids set the Morton grid,
    # so every small object falls into a handful of cells
    ground, f_ground = grid_mesh(grid, grid, -5e4, 1e5 / grid)
    v = np.concatenate([small, ground]).astype(np.float32)
    f = np.concatenate([f_small, f_ground + len(small)]).astype(np.uint32)
    return _scene_case("mixed_scales", v, f, "a ground plane 10^4 times larger than the objects "
                       "on it", seed=seed, spread=0.1, aim_faces=f_small)


def few_triangles(count: int) -> Case:
    v, f = _soup(count, count, 0.2)
    name = "1_triangle" if count == 1 else f"{count}_triangles"
    return _scene_case(name, v, f, f"{count} triangle(s)", rays=64, seed=count)


# -- 10: rays -------------------------------------------------------------------------

def _edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(E, 2)`` of a mesh."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    return np.unique(np.sort(e, axis=1), axis=0)


def _through_points(points: np.ndarray, centre: np.ndarray, far: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays from ``centre`` out through ``points`` and from outside in through them.

    Returns origins, directions and a ``must_hit`` mask (the rays from inside).
    """
    out_dir = points - centre
    inner_o = np.repeat(centre[None], len(points), axis=0)
    outer_o = centre + out_dir * far
    o = np.concatenate([inner_o, outer_o])
    d = np.concatenate([out_dir, points - outer_o])
    must = np.concatenate([np.ones(len(points), bool), np.zeros(len(points), bool)])
    return o, d, must


def closed_cube_vertices_edges(n: int = 8) -> Case:
    """Rays exactly through every vertex and edge midpoint of a closed cube."""
    v, f = cube_mesh(n, half=n / 2)  # cell size 1: vertices and midpoints exact
    e = _edges(f)
    v64 = v.astype(np.float64)
    points = np.concatenate([v64, (v64[e[:, 0]] + v64[e[:, 1]]) / 2])
    o, d, must = _through_points(points, np.float64([0.0, 0.0, 0.0]), 3.0)
    # and off-centre origins, so that rays cross edges at other angles
    o2, d2, must2 = _through_points(points, np.float64([0.75, -0.5, 0.25]), 3.0)
    return make_case("closed_cube_vertices_edges", v, f,
                     "rays exactly through the shared vertices and edges of a closed cube; "
                     "from inside every ray must hit (no leak)",
                     (np.concatenate([o, o2]), np.concatenate([d, d2])),
                     must_hit=np.concatenate([must, must2]))


def closed_sphere_vertices_edges(n: int = 8) -> Case:
    """A cube projected onto a sphere: shared vertices in general position."""
    v, f = cube_sphere(n)
    v64 = v.astype(np.float64)
    e = _edges(f)
    points = np.concatenate([v64, (v64[e[:, 0]] + v64[e[:, 1]]) / 2])
    o, d, must = _through_points(points, np.float64([0.0, 0.0, 0.0]), 3.0)
    o2, d2, must2 = _through_points(points, np.float64([0.1, 0.2, -0.3]), 3.0)
    return make_case("closed_sphere_vertices_edges", v, f,
                     "rays through the vertices and edge midpoints of a closed sphere mesh "
                     "(general position); from inside every ray must hit",
                     (np.concatenate([o, o2]), np.concatenate([d, d2])),
                     must_hit=np.concatenate([must, must2]))


def _signed_zero_axes() -> np.ndarray:
    """All 6 axis directions, each with every +0.0/-0.0 choice of its zero components."""
    dirs = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            for zeros in ((0.0, 0.0), (0.0, -0.0), (-0.0, 0.0), (-0.0, -0.0)):
                d = list(zeros)
                d.insert(axis, sign)
                dirs.append(d)
    return np.array(dirs, np.float64)


def axis_rays_signed_zeros(n: int = 4) -> Case:
    """Axis-aligned rays with every sign of zero, from the cube's centre and from
    origins on the planes of its faces and of the boxes inside it."""
    v, f = cube_mesh(n, half=n / 2)
    dirs = _signed_zero_axes()
    grid = np.arange(-n / 2, n / 2 + 1, 1.0)
    starts = [np.zeros(3), [0.5, 0.25, 0.0], [0.0, 0.0, 0.0]]
    # origins on box planes (x = a grid line) with x components of the direction zero
    starts += [[x, 0.25, 0.5] for x in grid] + [[0.25, y, 0.5] for y in grid]
    starts += [[-n / 2, -n / 2, 0.5], [n / 2, 0.5, n / 2]]  # on cube edges
    o = np.repeat(np.array(starts, np.float64), len(dirs), axis=0)
    d = np.tile(dirs, (len(starts), 1))
    return make_case("axis_rays_signed_zeros", v, f,
                     "axis-aligned rays, zero components +0.0 and -0.0, origins on box and "
                     "face planes (0 * inf in the slab test)", (o, d))


def rays_on_surface(n: int = 4) -> Case:
    """Rays starting exactly on a triangle (t = 0 hits), tmax = 0, tmin = tmax."""
    v, f = cube_mesh(n, half=n / 2)
    h = n / 2
    rng = np.random.default_rng(10)
    m = 64
    on_top = np.stack([rng.uniform(-h, h, m), rng.uniform(-h, h, m), np.full(m, h)], 1)
    # leaving the surface outwards, entering inwards, grazing along it, any direction
    dirs = np.concatenate([np.tile([0.0, 0.0, 1.0], (16, 1)), np.tile([0.0, 0.0, -1.0], (16, 1)),
                           rng.normal(size=(32, 3))])
    o = [on_top, on_top]
    d = [dirs, -dirs]
    tmin = [np.zeros(m), np.zeros(m)]
    tmax = [np.full(m, np.inf), np.zeros(m)]  # tmax = 0: only the hit at t = 0 counts
    # off the surface with tmax = 0: nothing
    o.append(on_top + [0.0, 0.0, 0.5])
    d.append(np.tile([0.0, 0.0, -1.0], (m, 1)))
    tmin.append(np.zeros(m))
    tmax.append(np.zeros(m))
    # tmin = tmax = the exact distance to a face: hit; one float before it: miss
    o.append(on_top + [0.0, 0.0, 2.0])
    d.append(np.tile([0.0, -0.0, -1.0], (m, 1)))
    short = float(np.nextafter(np.float32(2.0), np.float32(0.0)))
    ends = np.concatenate([np.full(m // 2, 2.0), np.full(m - m // 2, short)])
    tmin.append(ends)
    tmax.append(ends)
    # from a vertex and from an edge of the closed mesh, both directions
    corner = np.float64([[h, h, h], [h, 0.0, h], [-h, h, 0.0]])
    cd = rng.normal(size=(12, 3))
    o.append(np.repeat(corner, 12, axis=0))
    d.append(np.tile(cd, (3, 1)))
    tmin.append(np.zeros(36))
    tmax.append(np.full(36, np.inf))
    return make_case("rays_on_surface", v, f,
                     "origins exactly on triangles, vertices and edges (t = 0); tmax = 0; "
                     "tmin = tmax at the exact hit distance",
                     (np.concatenate(o), np.concatenate(d), np.concatenate(tmin),
                      np.concatenate(tmax)))


def rays_in_face_planes(n: int = 4) -> Case:
    """Rays lying in the plane of a face (parallel to it), inside and on its edges."""
    v, f = cube_mesh(n, half=n / 2)
    h = n / 2
    rng = np.random.default_rng(12)
    m = 96
    # in the plane z = h (the top face): inside the face, along its edges, outside it
    x = np.concatenate([rng.uniform(-h, h, m // 3), np.full(m // 3, h), rng.uniform(-h, h, m // 3)])
    y = np.concatenate([rng.uniform(-h, h, m // 3), rng.uniform(-h, h, m // 3), np.full(m // 3, h)])
    start = np.stack([x, y, np.full(m, h)], 1)
    ang = rng.uniform(0, 2 * np.pi, m)
    d = np.stack([np.cos(ang), np.sin(ang), np.where(np.arange(m) % 2, 0.0, -0.0)], 1)
    axis_d = np.tile([[1.0, 0.0, 0.0], [0.0, -1.0, -0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                     (m // 4, 1))
    o = np.concatenate([start, start - 3 * h * axis_d])
    return make_case("rays_in_face_planes", v, f,
                     "rays parallel to a face and lying in its plane (inside it, along its "
                     "edges, and from outside the cube)", (o, np.concatenate([d, axis_d])))


def scaled_directions(count: int = 1025, scale: float = 1e-35, size: float = 1000.0) -> Case:
    """The scene and rays of :func:`few_triangles` grown ``size`` times, with the
    directions scaled by ``scale`` and by ``1 / scale``: the same hits at ``t / scale``
    and ``t * scale`` (``t`` times a triangle's area passes float32's range)."""
    base = few_triangles(count)
    v = base.vertices * np.float32(size)
    o = np.concatenate([base.origins, base.origins]) * np.float32(size)
    d = np.concatenate([base.directions.astype(np.float64) * scale,
                        base.directions.astype(np.float64) / scale]) * size
    return make_case("scaled_directions", v, base.faces,
                     f"directions of length {scale:g} and {1 / scale:g}: hits at t near "
                     f"{1 / scale:g} and {scale:g}", (o, d))


# -- 11: deep trees -----------------------------------------------------------------

def _tiny_triangles_at(centres: np.ndarray, half: float) -> np.ndarray:
    """``float32 (3 n, 3)`` triangles whose boxes are ``centre +- half`` exactly."""
    c = np.asarray(centres, np.float64)
    offsets = np.float64([[-1, -1, -1], [1, -1, 1], [0, 1, 0]]) * half
    return (c[:, None, :] + offsets[None]).reshape(-1, 3).astype(np.float32)


def deep_morton_chain(axis_bits: int = 10, run: int = 4096) -> Case:
    """The deepest Karras tree for ``3 axis_bits``-bit codes: one triangle per code bit.

    Centres on each axis at ``2^i`` for ``i = -1 .. axis_bits - 1`` (the others 0)
    quantise to single-bit cells ``2^(i + 1)`` (the largest to all ones), so every
    code bit splits off one triangle: a chain ``3 axis_bits`` long. ``run`` copies
    at the origin (code 0) add ``log2(run)`` levels of index-split ties below it.
    """
    pts = [np.zeros(3)]
    for axis in range(3):
        for i in range(-1, axis_bits):
            p = np.zeros(3)
            p[axis] = 2.0 ** i
            pts.append(p)
    centres = np.concatenate([np.array(pts), np.zeros((run, 3))])
    v = _tiny_triangles_at(centres, 2.0 ** -4)
    f = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
    chain = centres[: len(pts)]
    # rays along each axis through every chain triangle, and through the run
    o = np.concatenate([chain + [0.0, 0.0, -1.0], chain + [-0.5, 0.0, 0.0], [[-1.0, 0.0, 0.0]]])
    d = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(chain), 1)),
                        np.tile([1.0, -0.0, 0.0], (len(chain), 1)), [[1.0, 1e-3, 2e-3]]])
    key = 3 * axis_bits
    return make_case(f"deep_morton_chain_{key}", v, f,
                     f"one triangle per bit of {key}-bit Morton codes plus {run} copies: "
                     f"a Karras chain about {key} + log2({run}) deep", (o, d), axis_rays=64)


def deep_sah_chain(step: float = 3.5, size: float = 2.0 ** -10, top: int = 127, bottom: int = -150,
                   name: str = "deep_sah_chain") -> Case:
    """Triangles at ``+-2^(127 - step k)`` down to the denormals: the deepest SAH tree found.

    Triangle k lies in the plane ``x = +-2^e`` with half-size ``size * 2^e``; with
    ``2^step`` between neighbours, the box of all nearer triangles is so much
    smaller that the SAH peels off about one triangle per level. A search over
    steps, sizes and staircases along 3 axes found no deeper SAH tree (96
    levels); float32's exponent range is the limit. Rays along x from the
    origin push one far child per level.
    """
    e = np.arange(top, bottom, -step, dtype=np.float64)
    x = np.concatenate([2.0 ** e, -(2.0 ** e)])
    s = np.maximum(np.abs(x) * size, 2.0 ** -149)
    zero = np.zeros_like(x)
    tri = np.stack([np.stack([x, -s, -s], 1), np.stack([x, s, -s], 1),
                    np.stack([x, zero, s], 1)], 1)
    v = tri.reshape(-1, 3).astype(np.float32)
    f = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
    o = [[0.0, 0.0, 0.0]] * 4 + [[2.0 ** -140, 0.0, 0.0], [-3e38, 0.0, 0.0], [3e38, 0.0, 0.0]]
    d = [[1.0, 0.0, 0.0], [-1.0, -0.0, -0.0], [1.0, 1e-30, 0.0], [-1.0, 0.0, 1e-30],
         [1.0, -0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]
    # and one ray per triangle from just in front of it, outwards
    sign = np.sign(x)
    o = np.concatenate([o, np.stack([x - sign * s, zero, zero], 1)])
    d = np.concatenate([d, np.stack([sign, np.where(sign > 0, 0.0, -0.0), zero], 1)])
    return make_case(name, v, f,
                     f"{len(x)} triangles at +-2^k, k from {top} down by {step:g} to "
                     f"{int(e[-1])}: SAH splits peel about one per level", (o, d))


def exponential_spacing(count: int = 120) -> Case:
    # centres at 2^-k: each Morton split peels off one triangle until the grid runs out
    x = np.float64(2.0) ** -np.arange(count)
    base = np.stack([x, np.zeros(count), np.zeros(count)], 1)
    tri = np.stack([base, base + [0, 1e-3, 0], base + [0, 0, 1e-3]], 1)
    v = tri.reshape(-1, 3).astype(np.float32)
    f = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    o = np.stack([x, np.full(count, 2e-4), np.full(count, -1.0)], 1)
    d = np.tile([0.0, 0.0, 1.0], (count, 1))
    return make_case("exponential_spacing", v, f, "primitives spaced 2^-k apart along x", (o, d),
                     axis_rays=32)


def small_stack(case: Case, stack_size: int = 4, name: str | None = None) -> Case:
    """The same scene and rays traversed with a tiny stack: overflows must be reported."""
    return Case(name or f"{case.name}_stack{stack_size}", case.vertices, case.faces,
                f"{case.why}; traversed with a {stack_size}-entry stack", case.origins,
                case.directions, case.tmin, case.tmax, stack_size=stack_size,
                must_hit=case.must_hit)


# -- 12: more than 2^24 triangles -------------------------------------------------------

def over_2_24_triangles(width: int = 4097, height: int = 2048) -> Case:
    """A flat grid of ``2 width height`` triangles (default 16,781,312 > 2^24 = 16,777,216).

    Rays straight down onto chosen cells, their answers known exactly: the
    triangle numbers above 2^24 are not float32 numbers, so an index that passed
    through a float on the way would come back wrong.
    """
    v, f = grid_mesh(width, height)
    n = len(f)
    prims = np.unique(np.concatenate([np.arange(n - 64, n), np.arange(0, 16),
                                      2 ** 24 + np.arange(-16, 17), [n // 2, n // 3]]))
    prims = prims[(prims >= 0) & (prims < n)]
    cell, upper = prims // 2, prims % 2
    i, j = cell // height, cell % height
    # a point inside the triangle: below the diagonal (fx > fy) or above it
    fx = np.where(upper == 0, 0.75, 0.25)
    fy = np.where(upper == 0, 0.25, 0.75)
    o = np.stack([i + fx, j + fy, np.full(len(prims), 1.0)], 1)
    d = np.tile([0.0, 0.0, -1.0], (len(prims), 1))
    case = make_case("over_2_24_triangles", v, f,
                     f"{n:,} triangles (> 2^24): indices beyond float32's integers", (o, d),
                     expected_prim=prims.astype(np.int32),
                     expected_t=np.ones(len(prims), np.float32), slow=True)
    return case


# -- the catalogue -------------------------------------------------------------------

#: every generator by name, with its default size
CASES: dict[str, Callable[[], Case]] = {
    "identical_triangles": identical_triangles,
    "one_point": one_point,
    "flat_plane": flat_plane,
    "line_of_triangles": line_of_triangles,
    "zero_area_mix": zero_area_mix,
    "slivers": slivers,
    "huge_coordinates": huge_coordinates,
    "near_float_max": near_float_max,
    "tiny_coordinates": tiny_coordinates,
    "denormal_coordinates": denormal_coordinates,
    "far_from_origin": far_from_origin,
    "far_from_origin_1e7": lambda: _renamed(far_from_origin(offset=1e7), "far_from_origin_1e7"),
    "mixed_scales": mixed_scales,
    "1_triangle": lambda: few_triangles(1),
    "2_triangles": lambda: few_triangles(2),
    "1025_triangles": lambda: few_triangles(1025),
    "axis_rays_signed_zeros": axis_rays_signed_zeros,
    "rays_on_surface": rays_on_surface,
    "rays_in_face_planes": rays_in_face_planes,
    "scaled_directions": scaled_directions,
    "closed_cube_vertices_edges": closed_cube_vertices_edges,
    "closed_sphere_vertices_edges": closed_sphere_vertices_edges,
    "exponential_spacing": exponential_spacing,
    "deep_morton_chain_30": lambda: deep_morton_chain(10),
    "deep_morton_chain_63": lambda: deep_morton_chain(21),
    "deep_sah_chain": deep_sah_chain,
    "deep_sah_chain_mid": lambda: deep_sah_chain(top=50, bottom=-31, name="deep_sah_chain_mid"),
    "deep_morton_chain_63_stack4": lambda: small_stack(deep_morton_chain(21)),
    "closed_sphere_stack2": lambda: small_stack(closed_sphere_vertices_edges(), 2,
                                                "closed_sphere_stack2"),
    "over_2_24_triangles": over_2_24_triangles,
}

#: the issue-5 item (1-12) each case belongs to
ISSUE_CASE: dict[str, int] = {
    "identical_triangles": 1, "one_point": 2, "flat_plane": 3, "line_of_triangles": 3,
    "zero_area_mix": 4, "slivers": 5, "huge_coordinates": 6, "near_float_max": 6,
    "tiny_coordinates": 6, "denormal_coordinates": 6, "far_from_origin": 7,
    "far_from_origin_1e7": 7, "mixed_scales": 8, "1_triangle": 9, "2_triangles": 9,
    "1025_triangles": 9, "axis_rays_signed_zeros": 10, "rays_on_surface": 10,
    "rays_in_face_planes": 10, "scaled_directions": 10, "closed_cube_vertices_edges": 10,
    "closed_sphere_vertices_edges": 10, "exponential_spacing": 11, "deep_morton_chain_30": 11,
    "deep_morton_chain_63": 11, "deep_sah_chain": 11, "deep_sah_chain_mid": 11,
    "deep_morton_chain_63_stack4": 11,
    "closed_sphere_stack2": 11, "over_2_24_triangles": 12,
}


def _renamed(case: Case, name: str) -> Case:
    case.name = name
    return case


def make(name: str) -> Case:
    """The case called ``name`` (``ValueError`` listing the names otherwise)."""
    try:
        return CASES[name]()
    except KeyError:
        raise ValueError(f"unknown hard case {name!r}; known: {', '.join(CASES)}") from None
