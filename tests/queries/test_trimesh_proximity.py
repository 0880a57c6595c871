"""lbvh.trimesh's proximity drop-in against trimesh.proximity and the float64 brute force.

Real kernels on PoCL. The closest point and distance are checked against the exact
float64 answer over every triangle (lbvh.queries.closest.closest_points_numpy), and
against trimesh's own calls: the same return types (float64, float64, int64), the
same distances to trimesh's rounding, trimesh's sign convention (positive inside,
positive on the surface) on closed meshes.
"""
from __future__ import annotations

import pickle
import threading

import numpy as np
import pytest

import lbvh.data
import lbvh.trimesh as lt
from lbvh.queries.closest import closest_points_numpy
from lbvh.metrics.error_bound import closest_distance_bound

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("rtree")   # trimesh's closest_point needs its r-tree


def meshes() -> dict[str, "trimesh.Trimesh"]:
    v, f = lbvh.data.teapot()
    return {"teapot": trimesh.Trimesh(v, f, process=False),
            "icosphere": trimesh.creation.icosphere(subdivisions=3),
            "box": trimesh.creation.box(extents=(2.0, 1.0, 0.5))}


def points_around(mesh, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds
    return lo + (hi - lo) * rng.uniform(-0.3, 1.3, (n, 3))


@pytest.mark.parametrize("name", ["teapot", "icosphere", "box"])
def test_closest_point_is_the_float64_answer_in_trimeshs_types(name):
    mesh = meshes()[name]
    p = points_around(mesh, 1500, 1)
    closest, distance, tri = lt.closest_point(mesh, p)
    assert closest.dtype == np.float64 and closest.shape == (len(p), 3)
    assert distance.dtype == np.float64 and tri.dtype == np.int64
    want_d, _, _ = closest_points_numpy(mesh.vertices, mesh.faces, p)
    scale = float(np.abs(mesh.vertices).max())
    # the float32 walk's triangle, refined in float64: never nearer than the exact
    # answer, and further only within the stated bound of the walk's choice
    assert (distance >= want_d - 1e-12 * scale).all()
    bound = closest_distance_bound(mesh.vertices - mesh.bounds.mean(axis=0),
                                   p - mesh.bounds.mean(axis=0))
    assert (distance - want_d <= bound).all()
    assert np.allclose(np.linalg.norm(p - closest, axis=1), distance, rtol=0, atol=1e-12 * scale)
    # the point lies on the reported triangle: its distance to that triangle is 0
    corners = mesh.vertices[mesh.faces[tri]]
    from lbvh.queries.closest import point_triangle_numpy
    on = point_triangle_numpy(closest, corners[:, 0], corners[:, 1], corners[:, 2])
    assert np.abs(on - closest).max() <= 1e-12 * scale
    # trimesh's own answers, to its rounding
    t_closest, t_distance, t_tri = trimesh.proximity.closest_point(mesh, p)
    assert np.abs(distance - t_distance).max() <= 1e-5 * scale
    assert lt.ProximityQuery(mesh).on_surface(p)[1].tobytes() == distance.tobytes()


@pytest.mark.parametrize("name", ["icosphere", "box"])
def test_signed_distance_has_trimeshs_sign(name):
    mesh = meshes()[name]
    assert mesh.is_watertight
    p = points_around(mesh, 1500, 2)
    ours = lt.signed_distance(mesh, p)
    theirs = trimesh.proximity.signed_distance(mesh, p)
    assert ours.dtype == np.float64 and ours.shape == (len(p),)
    clear = np.abs(theirs) > 1e-6
    assert np.array_equal(np.sign(ours[clear]), np.sign(theirs[clear]))
    assert np.abs(np.abs(ours) - np.abs(theirs)).max() <= 1e-5
    assert (ours[mesh.contains(p)] >= 0).all()
    # on the surface: positive (trimesh's tol.merge), whichever side rounding puts it
    surface, _ = trimesh.sample.sample_surface(mesh, 200, seed=3)
    on = lt.ProximityQuery(mesh).signed_distance(surface)
    assert (on >= 0).all() and on.max() <= 1e-8


def test_vertex_is_trimeshs_and_the_functions_keep_one_query_per_mesh():
    mesh = meshes()["box"]
    p = points_around(mesh, 50, 4)
    d, i = lt.ProximityQuery(mesh).vertex(p)
    want_d, want_i = mesh.nearest.vertex(p)
    assert np.array_equal(i, want_i) and np.allclose(d, want_d)
    lt.closest_point(mesh, p)
    first = lt._query_of(mesh)
    assert first._cache.state == "built"
    lt.signed_distance(mesh, p)
    assert lt._query_of(mesh) is first


def test_a_changed_mesh_is_queried_anew_and_copies_work():
    mesh = trimesh.creation.box()
    query = lt.ProximityQuery(mesh)
    p = np.array([[3.0, 0.0, 0.0]])
    assert np.allclose(query.on_surface(p)[1], [2.5])
    mesh.apply_translation([1.0, 0.0, 0.0])
    assert np.allclose(query.on_surface(p)[1], [1.5])
    other = pickle.loads(pickle.dumps(query))
    assert isinstance(other, lt.ProximityQuery) and np.allclose(other.on_surface(p)[1], [1.5])


def test_threads_sharing_one_query_get_their_own_answers():
    mesh = meshes()["teapot"]
    query = lt.ProximityQuery(mesh)
    sets = [points_around(mesh, 300, 10 + k) for k in range(4)]
    want = [closest_points_numpy(mesh.vertices, mesh.faces, s)[0] for s in sets]
    failures: list[str] = []

    def work(k):
        for _ in range(3):
            got = query.on_surface(sets[k])[1]
            if np.abs(got - want[k]).max() > 1e-5:
                failures.append(f"thread {k}")
    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures


def test_bad_input_and_a_mesh_without_faces():
    mesh = meshes()["box"]
    with pytest.raises(ValueError, match="points: point 1 has a NaN"):
        lt.closest_point(mesh, [[0, 0, 0], [np.nan, 0, 0]])
    with pytest.raises(ValueError, match=r"points: shape \(2, 2\)"):
        lt.signed_distance(mesh, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="Scene is not a mesh"):
        lt.ProximityQuery(trimesh.Scene([mesh]))
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    closest, distance, tri = lt.ProximityQuery(empty).on_surface(np.zeros((2, 3)))
    assert np.isnan(closest).all() and np.isinf(distance).all() and (tri == -1).all()
    got = lt.closest_point(mesh, np.zeros((0, 3)))
    assert [a.shape for a in got] == [(0, 3), (0,), (0,)]
