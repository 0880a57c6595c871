"""lbvh.trimesh.RayMeshIntersector against trimesh's own ray_triangle intersector.

Real kernels on PoCL, the same rays given to both: the same (ray, triangle) pairs,
the same first hits, locations and answers of intersects_any, the same return
types; where they differ, the ray passes within rounding of a triangle's edge
(trimesh counts a ray through a shared edge on both triangles, lbvh on one).
Hit sets are compared as sets: trimesh promises no order.
"""
from __future__ import annotations

import copy
import pickle
import threading
from dataclasses import dataclass

import numpy as np
import pytest

import lbvh
import lbvh.data
from conftest import shared_mesh
from lbvh.trimesh import RayMeshIntersector

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("rtree")   # trimesh's ray_triangle needs its r-tree
from trimesh.ray.ray_triangle import RayMeshIntersector as TrimeshIntersector  # noqa: E402

#: rays per kind (from outside toward the mesh, from inside) and whether they run near
#: the axes (trimesh's r-tree then tests few candidates: the bunny stays fast)
RAYS = {"teapot": (400, False), "icosphere": (600, False), "box": (400, False),
        "bunny": (400, True), "teapot-far": (300, False)}
#: how close to an edge (times the scene's scale) a ray may be where the two disagree
EDGE_TOLERANCE = 1e-5
LOCATION_TOLERANCE = 1e-5


def make_mesh(name: str) -> "trimesh.Trimesh":
    if name == "icosphere":
        return trimesh.creation.icosphere(subdivisions=3)
    if name == "box":
        return trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    if name == "torus":
        return trimesh.creation.torus(1.0, 0.3)
    if name == "teapot-far":   # far from the origin: float32 is coarse there (lbvh centres it)
        mesh = make_mesh("teapot")
        mesh.apply_translation([3e5, -1e5, 2e5])
        return mesh
    v, f = lbvh.data.teapot() if name == "teapot" else shared_mesh("stanford-bunny.obj")
    return trimesh.Trimesh(np.asarray(v, np.float64), np.asarray(f, np.int64), process=False)


def unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def make_rays(mesh, n: int, seed: int, near_axes: bool) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rays from outside the mesh's box toward a point in it, then ``n`` from
    points in the box; directions of random lengths (0.1 to 10)."""
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds
    reach = np.linalg.norm(hi - lo)
    if near_axes:
        axes = np.eye(3)[rng.integers(0, 3, 2 * n)] * rng.choice([-1.0, 1.0], (2 * n, 1))
        d = unit(axes + 0.02 * rng.normal(size=(2 * n, 3)))
    else:
        d = unit(rng.normal(size=(2 * n, 3)))
    target = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    outside = target - d[:n] * reach
    inside = lo + (hi - lo) * rng.uniform(0.05, 0.95, (n, 3))
    return np.vstack([outside, inside]), d * rng.uniform(0.1, 10, (2 * n, 1))


def pairs(index_ray: np.ndarray, index_tri: np.ndarray) -> dict[int, set[int]]:
    out: dict[int, set[int]] = {}
    for r, t in zip(index_ray.tolist(), index_tri.tolist()):
        out.setdefault(r, set()).add(t)
    return out


def edge_distance(mesh, o: np.ndarray, d: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """``(k,)``: from where each ray ``o + s d`` meets its triangle's plane to the
    triangle's nearest edge (float64)."""
    corners = mesh.vertices[mesh.faces[tri]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    s = np.einsum("ij,ij->i", corners[:, 0] - o, normal) / np.einsum("ij,ij->i", d, normal)
    p = o + s[:, None] * d
    best = np.full(len(p), np.inf)
    for i in range(3):
        a, b = corners[:, i], corners[:, (i + 1) % 3]
        w = np.clip(np.einsum("ij,ij->i", p - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
        best = np.minimum(best, np.linalg.norm(p - (a + w[:, None] * (b - a)), axis=1))
    return best


@dataclass
class Case:
    """One scene, its rays, and both intersectors' every hit (computed once)."""
    name: str
    mesh: "trimesh.Trimesh"
    ours: RayMeshIntersector
    theirs: TrimeshIntersector
    origins: np.ndarray
    directions: np.ndarray
    our_hits: dict[int, set[int]]
    their_hits: dict[int, set[int]]
    ambiguous: np.ndarray   # bool (N,): the rays whose hit sets differ

    @property
    def scale(self) -> float:
        return float(self.mesh.scale)


@pytest.fixture(scope="module", params=sorted(RAYS))
def case(request) -> Case:
    name = request.param
    mesh = make_mesh(name)
    n, near_axes = RAYS[name]
    o, d = make_rays(mesh, n, seed=len(name), near_axes=near_axes)
    ours, theirs = RayMeshIntersector(mesh), TrimeshIntersector(mesh)
    our_tri, our_ray = ours.intersects_id(o, d)
    their_tri, their_ray = theirs.intersects_id(o, d)
    mine, other = pairs(our_ray, our_tri), pairs(their_ray, their_tri)
    ambiguous = np.array([mine.get(i, set()) != other.get(i, set()) for i in range(len(o))])
    return Case(name, mesh, ours, theirs, o, d, mine, other, ambiguous)


# -- every hit ---------------------------------------------------------------------
def test_every_hit_is_trimesh_s_but_near_edges(case):
    n = len(case.origins)
    agree = 1 - case.ambiguous.mean()
    hits = sum(len(s) for s in case.their_hits.values())
    print(f"{case.name}: {n} rays, {hits} trimesh hits, {agree:.2%} of rays agree "
          f"({int(case.ambiguous.sum())} differ)")
    assert hits > n // 4 and len(case.our_hits) > n // 4   # the rays do hit the mesh
    assert agree >= 0.99
    # where they differ, every triangle one has and the other lacks is crossed by the
    # ray within rounding of one of its edges (trimesh: both triangles of an edge)
    rays, tris = [], []
    for i in np.flatnonzero(case.ambiguous):
        for t in case.our_hits.get(i, set()) ^ case.their_hits.get(i, set()):
            rays.append(i)
            tris.append(t)
    if rays:
        gap = edge_distance(case.mesh, case.origins[rays], case.directions[rays], np.array(tris))
        assert (gap <= EDGE_TOLERANCE * case.scale).all(), gap.max() / case.scale


def test_hits_come_ray_by_ray_nearest_first(case):
    locations, index_ray, index_tri = case.ours.intersects_location(case.origins, case.directions)
    assert (np.diff(index_ray) >= 0).all()
    dist = np.linalg.norm(locations - case.origins[index_ray], axis=1)
    same_ray = np.diff(index_ray) == 0
    assert (np.diff(dist)[same_ray] >= -1e-6 * case.scale).all()
    # intersects_id gives the same hits, in the same order
    tri, ray, loc = case.ours.intersects_id(case.origins, case.directions, return_locations=True)
    assert np.array_equal(tri, index_tri) and np.array_equal(ray, index_ray)
    assert np.array_equal(loc, locations)


def test_locations_are_trimesh_s(case):
    ours = case.ours.intersects_location(case.origins, case.directions)
    theirs = case.theirs.intersects_location(case.origins, case.directions)
    mine = {(r, t): p for p, r, t in zip(ours[0], ours[1].tolist(), ours[2].tolist())}
    other = {(r, t): p for p, r, t in zip(theirs[0], theirs[1].tolist(), theirs[2].tolist())}
    common = sorted(set(mine) & set(other))
    assert len(common) >= 0.98 * len(other)
    gap = max(float(np.abs(mine[k] - other[k]).max()) for k in common)
    print(f"{case.name}: {len(common)} locations, largest difference {gap / case.scale:.2e} x scale")
    assert gap <= LOCATION_TOLERANCE * case.scale
    # on the ray, in front of its origin
    loc, ray = ours[0], ours[1]
    off = loc - case.origins[ray]
    along = np.einsum("ij,ij->i", off, unit(case.directions[ray]))
    assert (along >= -1e-6 * case.scale).all()
    assert np.abs(off - along[:, None] * unit(case.directions[ray])).max() <= 1e-9 * case.scale


def test_first_hit_is_trimesh_s(case):
    o, d = case.origins, case.directions
    tri, ray, loc = case.ours.intersects_id(o, d, multiple_hits=False, return_locations=True)
    t_tri, t_ray, t_loc = case.theirs.intersects_id(o, d, multiple_hits=False,
                                                    return_locations=True)
    clear = ~case.ambiguous
    assert (np.diff(ray) > 0).all()   # ray by ray, one hit each (trimesh: in no order)
    assert np.array_equal(ray[clear[ray]], np.sort(t_ray[clear[t_ray]]))
    mine = dict(zip(ray.tolist(), np.linalg.norm(loc - o[ray], axis=1)))
    other = dict(zip(t_ray.tolist(), np.linalg.norm(t_loc - o[t_ray], axis=1)))
    rel = max(abs(mine[r] - other[r]) / max(other[r], case.scale * 1e-3)
              for r in ray[clear[ray]].tolist())
    assert rel <= 1e-5
    # the triangle is trimesh's wherever the nearest hit is one triangle's alone
    first = case.ours.intersects_first(o, d)
    their_first = case.theirs.intersects_first(o, d)
    assert np.array_equal(first[ray], tri) and (np.delete(first, ray) == -1).all()
    unique = np.zeros(len(o), bool)
    their_loc, index_ray, _ = case.theirs.intersects_location(o, d)
    dist = np.linalg.norm(their_loc - o[index_ray], axis=1)
    for r in np.flatnonzero(clear & (their_first >= 0)):
        near = np.sort(dist[index_ray == r])
        unique[r] = len(near) == 1 or near[1] - near[0] > 1e-6 * case.scale
    assert unique.sum() >= 0.9 * (their_first >= 0).sum()
    assert np.array_equal(first[unique], their_first[unique])
    assert np.array_equal(first[clear] >= 0, their_first[clear] >= 0)


def test_any_hit_is_trimesh_s(case):
    got = case.ours.intersects_any(case.origins, case.directions)
    want = case.theirs.intersects_any(case.origins, case.directions)
    clear = ~case.ambiguous
    assert np.array_equal(got[clear], want[clear])
    assert np.array_equal(got, case.ours.intersects_first(case.origins, case.directions) >= 0)


def test_rays_aimed_at_centroids_hit_exactly_trimesh_s_triangles(case):
    """No ray passes near an edge: the same triangles exactly, and the same first."""
    rng = np.random.default_rng(7)
    mesh = case.mesh
    faces = rng.choice(len(mesh.faces), min(300, len(mesh.faces)), replace=False)
    faces = faces[mesh.area_faces[faces] > 1e-6 * case.scale ** 2]
    target = mesh.triangles_center[faces]
    d = unit(rng.normal(size=(len(faces), 3)))
    if case.name == "bunny":   # near the axes, for trimesh's r-tree
        d = unit(np.eye(3)[rng.integers(0, 3, len(faces))] + 0.02 * rng.normal(size=d.shape))
    o = target - d * 2 * case.scale
    d = d * rng.uniform(0.1, 10, (len(d), 1))
    ours, theirs = case.ours.intersects_id(o, d), case.theirs.intersects_id(o, d)
    mine, other = pairs(ours[1], ours[0]), pairs(theirs[1], theirs[0])
    assert mine == other
    assert all(int(f) in mine[i] for i, f in enumerate(faces))   # each hits its own
    assert np.array_equal(case.ours.intersects_first(o, d), case.theirs.intersects_first(o, d))


# -- return types ------------------------------------------------------------------
def describe(result) -> list[tuple[type, np.dtype, tuple[int, ...]]]:
    items = result if isinstance(result, tuple) else (result,)
    return [(type(a), a.dtype, a.shape) for a in items]


@pytest.mark.parametrize("which", ["hits", "misses", "empty"])
def test_return_types_are_trimesh_s(which):
    mesh = make_mesh("icosphere")
    ours, theirs = RayMeshIntersector(mesh), TrimeshIntersector(mesh)
    o, d = make_rays(mesh, 20, seed=3, near_axes=False)
    if which == "misses":
        o, d = o + 10.0, d * 0 + [1.0, 0.0, 0.0]
    elif which == "empty":
        o, d = np.zeros((0, 3)), np.zeros((0, 3))
    calls = {
        "intersects_id": lambda r: r.intersects_id(o, d),
        "intersects_id locations": lambda r: r.intersects_id(o, d, return_locations=True),
        "intersects_id first": lambda r: r.intersects_id(o, d, multiple_hits=False),
        "intersects_id first locations": lambda r: r.intersects_id(
            o, d, multiple_hits=False, return_locations=True),
        "intersects_location": lambda r: r.intersects_location(o, d),
        "intersects_location first": lambda r: r.intersects_location(o, d, multiple_hits=False),
        "intersects_first": lambda r: r.intersects_first(o, d),
        "intersects_any": lambda r: r.intersects_any(o, d),
        "contains_points": lambda r: r.contains_points(o),
    }
    if not hasattr(lbvh.BVH, "contains"):
        del calls["contains_points"]
    for name, call in calls.items():
        got, want = describe(call(ours)), describe(call(theirs))
        assert len(got) == len(want), name
        for (gt, gd, gs), (wt, wd, ws) in zip(got, want):
            assert gt is np.ndarray and gd == wd, (name, got, want)
            # no hit: trimesh's ray_triangle gives locations of shape (0,), lbvh (0, 3)
            assert gs == ws or (gs == (0, 3) and ws == (0,)), (name, got, want)


# -- edges and vertices ------------------------------------------------------------
def test_rays_through_vertices_cross_once():
    """A ray through a vertex of the closed icosphere (and its antipode) crosses the
    surface twice: lbvh reports two hits, trimesh's ray_triangle one per triangle
    around each vertex (its locations merge them to the same two points)."""
    mesh = make_mesh("icosphere")
    ours, theirs = RayMeshIntersector(mesh), TrimeshIntersector(mesh)
    v = mesh.vertices[::7]
    o, d = 3 * v, -v * np.linspace(0.5, 4, len(v))[:, None]
    _, index_ray = ours.intersects_id(o, d)
    assert np.array_equal(np.bincount(index_ray, minlength=len(o)), np.full(len(o), 2))
    _, their_ray = theirs.intersects_id(o, d)
    assert (np.bincount(their_ray, minlength=len(o)) >= 10).all()
    loc, ray, _ = ours.intersects_location(o, d)
    t_loc, t_ray, _ = theirs.intersects_location(o, d)
    for i in range(len(o)):
        mine = loc[ray == i]
        other = np.unique(np.round(t_loc[t_ray == i], 9), axis=0)   # the same point once
        other = other[np.argsort(np.linalg.norm(other - o[i], axis=1))]
        assert other.shape == mine.shape and np.abs(mine - other).max() <= 1e-9, i


def test_rays_through_edges_cross_once_and_differ_from_trimesh_only_there():
    """Rays through the midpoints of the icosphere's edges (and their antipodes):
    two hits each from lbvh, both triangles of each edge from trimesh; what differs
    is on an edge."""
    mesh = make_mesh("icosphere")
    ours, theirs = RayMeshIntersector(mesh), TrimeshIntersector(mesh)
    mid = mesh.vertices[mesh.edges_unique[::9]].mean(axis=1)
    o, d = 3 * mid, -mid * np.linspace(0.5, 4, len(mid))[:, None]
    tri, index_ray = ours.intersects_id(o, d)
    assert np.array_equal(np.bincount(index_ray, minlength=len(o)), np.full(len(o), 2))
    t_tri, t_ray = theirs.intersects_id(o, d)
    assert (np.bincount(t_ray, minlength=len(o)) == 4).all()
    mine, other = pairs(index_ray, tri), pairs(t_ray, t_tri)
    rays, tris = [], []
    for i in range(len(o)):
        assert mine[i] <= other[i]
        rays += [i] * len(other[i] - mine[i])
        tris += sorted(other[i] - mine[i])
    gap = edge_distance(mesh, o[rays], d[rays], np.array(tris))
    assert len(rays) == 2 * len(o) and (gap <= 1e-12 * mesh.scale).all()


# -- contains ----------------------------------------------------------------------
@pytest.mark.parametrize("name", ["icosphere", "box", "torus"])
def test_mesh_contains_uses_lbvh_and_agrees_with_trimesh(name):
    if not hasattr(lbvh.BVH, "contains"):
        pytest.skip("bvh.contains not there yet")
    mesh = make_mesh(name)
    reference = TrimeshIntersector(mesh)
    mesh.ray = RayMeshIntersector(mesh)
    rng = np.random.default_rng(11)
    lo, hi = mesh.bounds
    points = lo + (hi - lo) * rng.uniform(-0.2, 1.2, (2000, 3))
    bvh = mesh.ray.bvh
    clearance = bvh.closest_points(points - mesh.ray.center).distance
    points = points[clearance > 1e-3 * mesh.scale]
    got = mesh.contains(points)
    want = reference.contains_points(points)
    assert got.dtype == bool and got.shape == (len(points),)
    assert want.any() and (~want).any()
    assert np.array_equal(got, want)


# -- the cache ---------------------------------------------------------------------
def test_the_bvh_is_rebuilt_when_the_vertices_change():
    mesh = make_mesh("icosphere")
    ray = RayMeshIntersector(mesh)
    rng = np.random.default_rng(5)
    faces = rng.choice(len(mesh.faces), 50, replace=False)
    d = -mesh.face_normals[faces] * rng.uniform(0.1, 10, (50, 1))   # the sphere is convex

    def aimed() -> tuple[np.ndarray, ...]:
        """Rays aimed at the centres of ``faces`` from outside: their first hits."""
        o = mesh.triangles_center[faces] - 3 * unit(d)
        return ray.intersects_id(o, d, multiple_hits=False, return_locations=True)

    tri, index_ray, loc = aimed()
    first = ray.bvh
    assert ray.bvh is first   # kept while the mesh does not change
    assert np.array_equal(tri, faces) and np.array_equal(index_ray, np.arange(50))
    for step in range(2):
        before = mesh.triangles_center[faces].copy()
        if step == 0:
            mesh.vertices += 10.0
        else:
            mesh.apply_translation([-25.0, 20.0, 5.0])
        shift = mesh.triangles_center[faces] - before
        assert np.abs(shift).max() >= 10   # a stale BVH would miss the moved sphere
        tri, index_ray, new_loc = aimed()
        assert np.array_equal(tri, faces) and np.array_equal(index_ray, np.arange(50))
        assert np.abs(new_loc - (loc + shift)).max() <= 1e-9
        loc = new_loc
        assert ray.bvh is not first
        first = ray.bvh


def test_the_lazy_build_happens_once_across_threads():
    mesh = make_mesh("teapot")
    ray = RayMeshIntersector(mesh)
    o, d = make_rays(mesh, 50, seed=2, near_axes=False)
    results: list = [None] * 4
    start = threading.Barrier(4)

    def work(i: int) -> None:
        start.wait()
        results[i] = (ray.intersects_first(o, d), ray.bvh)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(r is not None for r in results)
    assert all(r[1] is results[0][1] for r in results)
    assert all(np.array_equal(r[0], results[0][0]) for r in results)


def test_copies_and_pickles_rebuild_over_their_mesh():
    mesh = make_mesh("box")
    ray = RayMeshIntersector(mesh)
    o, d = make_rays(mesh, 30, seed=4, near_axes=False)
    want = ray.intersects_first(o, d)
    for other in (copy.copy(ray), copy.deepcopy(ray), pickle.loads(pickle.dumps(ray))):
        assert isinstance(other, RayMeshIntersector)
        assert np.array_equal(other.intersects_first(o, d), want)


# -- options and bad input ---------------------------------------------------------
def test_the_constructor_takes_what_trimeshs_intersectors_take():
    """trimesh's ray_triangle takes ``(mesh)``, its embree one ``(geometry,
    scale_to_box=True)``: every spelling builds the same intersector, whose answers
    scale_to_box does not change (lbvh needs no rescaling)."""
    mesh = make_mesh("teapot")
    o, d = make_rays(mesh, 200, seed=9, near_axes=False)
    want = RayMeshIntersector(mesh).intersects_first(o, d)
    for ray in (RayMeshIntersector(mesh, True), RayMeshIntersector(geometry=mesh),
                RayMeshIntersector(mesh=mesh, scale_to_box=False),
                RayMeshIntersector(geometry=mesh, scale_to_box=False),   # embree's names
                pickle.loads(pickle.dumps(RayMeshIntersector(mesh, False)))):
        assert ray.mesh is mesh or ray.mesh.faces.shape == mesh.faces.shape
        assert np.array_equal(ray.intersects_first(o, d), want)


@pytest.mark.parametrize("make, match", [
    (lambda m: dict(geometry=trimesh.Scene([m])), r"a trimesh\.scene\.scene\.Scene is not a "
                                                  r"mesh .*scene\.to_mesh\(\).*lbvh\.build\(scene\)"),
    (lambda m: dict(geometry=trimesh.PointCloud(m.vertices)), "PointCloud is not a mesh"),
    (lambda m: dict(geometry=None), "pass the mesh once"),
    (lambda m: dict(geometry=m, mesh=m), "not both"),
    (lambda m: dict(geometry=m, scale_to_box="yes"), "scale_to_box: 'yes'"),
])
def test_the_constructor_refuses_what_is_not_a_mesh(make, match):
    with pytest.raises(ValueError, match=match):
        RayMeshIntersector(**make(make_mesh("box")))


def test_max_hits_keeps_the_nearest():
    mesh = make_mesh("teapot")
    ray = RayMeshIntersector(mesh)
    o, d = make_rays(mesh, 100, seed=6, near_axes=False)
    tri, index_ray = ray.intersects_id(o, d)
    tri1, ray1 = ray.intersects_id(o, d, max_hits=1)
    keep = np.r_[True, np.diff(index_ray) != 0]
    assert np.array_equal(ray1, index_ray[keep]) and np.array_equal(tri1, tri[keep])
    assert len(ray.intersects_id(o, d, max_hits=0)[0]) == 0
    with pytest.raises(ValueError, match="max_hits"):
        ray.intersects_id(o, d, max_hits=-1)


def test_a_mesh_without_faces_is_hit_by_nothing():
    mesh = trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int64))
    ray = RayMeshIntersector(mesh)
    o, d = np.zeros((3, 3)), np.eye(3)
    assert len(ray.intersects_id(o, d)[0]) == 0
    loc, index_ray, _ = ray.intersects_location(o, d)
    assert loc.shape == (0, 3) and index_ray.dtype == np.int64
    assert np.array_equal(ray.intersects_first(o, d), [-1, -1, -1])
    assert not ray.intersects_any(o, d).any() and not ray.contains_points(o).any()
    assert ray.bvh is None


@pytest.mark.parametrize("bad, match", [
    (("directions", 2, [np.nan, 0.0, 1.0]), r"ray_directions: ray 2 has a NaN"),
    (("directions", 1, [0.0, 0.0, 0.0]), r"ray_directions: ray 1 has a zero-length"),
    (("origins", 3, [np.inf, 0.0, 0.0]), r"ray_origins: ray 3 has a NaN or infinite"),
])
def test_bad_rays_are_refused_by_name(bad, match):
    mesh = make_mesh("box")
    ray = RayMeshIntersector(mesh)
    o, d = make_rays(mesh, 2, seed=1, near_axes=False)
    which, i, value = bad
    (d if which == "directions" else o)[i] = value
    for call in (lambda: ray.intersects_id(o, d), lambda: ray.intersects_location(o, d),
                 lambda: ray.intersects_first(o, d), lambda: ray.intersects_any(o, d),
                 lambda: ray.intersects_id(o, d, multiple_hits=False)):
        with pytest.raises(ValueError, match=match):
            call()


def test_bad_shapes_are_refused():
    ray = RayMeshIntersector(make_mesh("box"))
    with pytest.raises(ValueError, match="ray_directions: 2 rays, but ray_origins has 3"):
        ray.intersects_id(np.zeros((3, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"ray_origins: shape \(3, 2\)"):
        ray.intersects_first(np.zeros((3, 2)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="points: point 1 has a NaN"):
        ray.contains_points([[0.0, 0, 0], [np.nan, 0, 0]])
