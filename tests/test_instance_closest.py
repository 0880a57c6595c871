"""Closest points through a scene of placed meshes (lbvh.Scene.closest_points,
kernels/instance_closest.cl) against the float64 brute force over the flattened scene's
triangles, for placements that keep no distances in proportion (shears, non-uniform
scales, reflections) and overlapping instances."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import shipped_mesh
from lbvh.queries import instance_closest
from lbvh.queries.closest import closest_points_numpy, point_triangle_numpy
from lbvh.verification import meshes
from lbvh.metrics.error_bound import scene_closest_distance_bound


def odd_placements() -> np.ndarray:
    """Six placements: a shear, a non-uniform scale, a reflection, a rotation times a
    non-uniform scale with a shear, and two that overlap instance 0 (one of them a
    shear of it in place, one a near copy)."""
    t = np.zeros((6, 3, 4))
    t[0, :, :3] = [[1, 0.8, 0], [0, 1, 0], [0.3, 0, 1]]             # shear
    t[1, :, :3], t[1, :, 3] = np.diag([3.0, 0.4, 1.2]), [4, 0, 0]     # non-uniform scale
    t[2, :, :3], t[2, :, 3] = np.diag([-1.0, 1, 1]) * 1.5, [0, 4, 0]  # reflection
    q, _ = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))
    t[3, :, :3], t[3, :, 3] = q @ np.diag([0.5, 2, 1]) @ [[1, 0, 0.6], [0, 1, 0], [0, 0, 1]], \
        [-4, -2, 1]
    t[4, :, :3], t[4, :, 3] = [[1, -0.5, 0], [0, 1, 0.2], [0, 0, 1]], [0.3, 0, 0]   # overlaps 0
    t[5, :, :3], t[5, :, 3] = np.eye(3) * 1.01, [0.01, 0, 0]                     # overlaps 0
    return t


@pytest.fixture(scope="module")
def scene():
    ball = lbvh.build(*meshes.cube_sphere(6))          # closed
    teapot = lbvh.build(*shipped_mesh("teapot.obj"))   # open
    return lbvh.Scene([ball, teapot], [0, 1, 0, 1, 0, 1], odd_placements())


def points_around(v: np.ndarray, n: int, seed: int, spread: float = 0.2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    return (lo + (hi - lo) * rng.uniform(-spread, 1 + spread, (n, 3))).astype(np.float32)


def check_against_brute_force(scene: lbvh.Scene, p: np.ndarray, got) -> np.ndarray:
    """The answers are the flattened scene's: distance within the bound, the named
    triangle that near, the point on it from the barycentrics. Returns the reference
    distances."""
    v, f, owner = scene.flattened()
    want_d, want_q, want_f = closest_points_numpy(v, f, p)
    distance, where, inst, prim = got
    bound = scene_closest_distance_bound(v, p)
    assert (inst >= 0).all() and (prim >= 0).all()
    assert (np.abs(distance - want_d) <= bound).all(), np.abs(distance - want_d).max()
    # the named triangle of the flattened copy is that near (another only on a tie)
    face = scene.flat_faces(inst, prim)
    tri = v[f[face]].astype(np.float64)
    q = point_triangle_numpy(p, tri[:, 0], tri[:, 1], tri[:, 2])
    assert (np.abs(np.linalg.norm(q - p, axis=1) - want_d) <= 2 * bound).all()
    # the point, and its barycentrics on the triangle (an affine map keeps them)
    extent = float(np.abs(v).max())
    assert np.abs(where - q).max() <= 1e-5 * extent
    u, w = got.u.astype(np.float64)[:, None], got.v.astype(np.float64)[:, None]
    assert np.abs((1 - u - w) * tri[:, 0] + u * tri[:, 1] + w * tri[:, 2] - where).max() \
        <= 1e-5 * extent
    assert np.array_equal(got.id, scene.ids[inst]) and np.array_equal(got.mesh, scene.mesh_of[inst])
    return want_d


def test_closest_points_through_shears_scales_reflections_and_overlaps(scene):
    v, f, owner = scene.flattened()
    p = points_around(v, 1500, 1)
    got = scene.closest_points(p)
    want_d = check_against_brute_force(scene, p, got)
    # every instance answers some point: none is left out by the top level
    assert set(np.unique(got.instance)) == set(range(scene.num_instances))
    assert (want_d > 0.05).any() and (want_d < 0.01).any()
    # the old host loop could not have answered: the shear is not a similarity
    a = scene.transforms[0, :, :3]
    assert np.abs(a.T @ a - np.eye(3) * np.trace(a.T @ a) / 3).max() > 0.1


def test_closest_points_within_a_radius(scene):
    v, f, _ = scene.flattened()
    p = points_around(v, 1200, 2, spread=0.5)
    full = scene.closest_points(p)
    for radius in (0.0, *np.quantile(full.distance, (0.1, 0.5, 0.9)).tolist()):
        near = scene.closest_points(p, max_distance=radius)
        clear = np.abs(full.distance - radius) > 1e-5 * np.abs(v).max()   # not on the rim
        found = near.instance >= 0
        assert np.array_equal(found[clear], (full.distance <= radius)[clear])
        assert np.isinf(near.distance[~found]).all() and np.isnan(near.points[~found]).all()
        assert (near.prim[~found] == -1).all() and (near.u[~found] == 0).all()
        assert np.array_equal(near.distance[found], full.distance[found])
        if radius > 0:
            assert found.any() and not found.all()


def test_points_far_away_and_on_the_surfaces(scene):
    v, f, _ = scene.flattened()
    rng = np.random.default_rng(3)
    far = rng.normal(size=(200, 3))
    far = (far / np.linalg.norm(far, axis=1, keepdims=True) * rng.uniform(1e2, 1e5, (200, 1)))
    far = far.astype(np.float32)
    check_against_brute_force(scene, far, scene.closest_points(far))
    # on the surfaces: the flattened copy's vertices and the centres of its triangles
    on = np.concatenate([v[rng.integers(0, len(v), 300)],
                         v[f[rng.integers(0, len(f), 300)]].mean(axis=1)]).astype(np.float32)
    got = scene.closest_points(on)
    want_d = check_against_brute_force(scene, on, got)
    assert (want_d < 1e-6).all()
    assert (got.distance <= scene_closest_distance_bound(v, on)).all()


def test_set_transforms_moves_the_closest_points(scene):
    moved = lbvh.Scene(scene.meshes, scene.mesh_of, scene.transforms)
    v, _, _ = moved.flattened()
    p = points_around(v, 600, 4)
    before = moved.closest_points(p)
    shear = np.eye(3, 4)
    shear[0, 2], shear[1, 3] = 1.5, 2.0
    moved.set_transforms([1], shear[None])
    after = moved.closest_points(p)
    check_against_brute_force(moved, p, after)
    assert not np.array_equal(before.distance, after.distance)


def test_batches_and_the_point_order_give_the_same_answers(scene, monkeypatch):
    """Points in Morton order (as kernels/closest.cl's, from MIN_POINTS points on: lowered
    to 256 here) and in batches answer as one launch in the given order."""
    v, _, _ = scene.flattened()
    p = points_around(v, 1000, 5)
    plain = scene.closest_points(p)
    monkeypatch.setattr(instance_closest, "MIN_POINTS", 256)
    for batch in (1 << 20, 300):
        got = scene.closest_points(p, batch_size=batch)
        for a, b in zip((*got, got.u, got.v), (*plain, plain.u, plain.v)):
            assert np.array_equal(a, b, equal_nan=True)


def test_float32_arithmetic_stays_near(scene):
    """NO_FP64 (float32 arithmetic, the kernel of devices without doubles) on these
    well-conditioned coordinates: within a few hundred units of float32 rounding."""
    v, _, _ = scene.flattened()
    p = points_around(v, 500, 6)
    with scene.ctx.lock:
        got = instance_closest.closest_scene_points(scene.ctx, scene._buffers(), scene.ids,
                                                    scene.mesh_of, p,
                                                    extra_defines={"NO_FP64": 1})
    want = scene.closest_points(p)
    assert np.abs(got.distance - want.distance).max() <= 1e-4 * np.abs(v).max()


def test_parts_of_one_mesh_answer_as_the_mesh():
    """The identity placements of lbvh.build_parts: the mesh's own distances and
    triangle numbers (face_ids)."""
    v, f = shipped_mesh("teapot.obj")
    whole = lbvh.build(v, f)
    parts = lbvh.build_parts(v, f, part_triangles=500)
    p = points_around(v, 2000, 7)
    got, want = parts.closest_points(p), whole.closest_points(p)
    assert np.array_equal(got.distance, want.distance)
    # another triangle only on a tie (a shared vertex or edge is often the nearest)
    tri = v[f[got.prim]].astype(np.float64)
    q = point_triangle_numpy(p, tri[:, 0], tri[:, 1], tri[:, 2])
    assert np.allclose(np.linalg.norm(q - p, axis=1), want.distance, rtol=1e-6, atol=1e-7)
    same = got.prim == want.prim
    assert same.mean() > 0.5
    assert np.array_equal(got.u[same], want.u[same]) and np.array_equal(got.v[same], want.v[same])


def test_empty_and_bad_input(scene):
    got = scene.closest_points(np.zeros((0, 3)))
    assert [x.shape for x in got] == [(0,), (0, 3), (0,), (0,)]
    assert [x.dtype for x in got] == [np.float32, np.float32, np.int32, np.int32]
    assert got.u.shape == (0,) and got.id.dtype == np.int64
    p = np.zeros((4, 3), np.float32)
    p[2, 1] = np.nan
    with pytest.raises(ValueError, match="point 2 has a NaN"):
        scene.closest_points(p)
    with pytest.raises(ValueError, match=r"shape \(4, 2\)"):
        scene.closest_points(p[:, :2])
    for bad in (-1, float("nan"), "far"):
        with pytest.raises(ValueError, match="max_distance"):
            scene.closest_points(p[:2], max_distance=bad)
    with pytest.raises(ValueError, match="batch_size"):
        scene.closest_points(p[:2], batch_size=0)


def test_a_stack_overflow_is_raised_never_silent():
    """The chain tree of tests/test_instances.py (a leaf pushed at every level, deeper than
    the largest stack): a point the chain's walk reaches raises, naming how many; one
    beyond max_distance of every instance does not."""
    from test_instances import deep_chain
    chain = deep_chain(800)
    moves = np.tile(np.eye(3, 4), (2, 1, 1))
    moves[1, 1, 3] = 10.0
    moves[1, 0, 1] = 0.3            # a shear: the kernel's own path, not a similarity
    scene = lbvh.Scene([chain], [0, 0], moves)
    # best first, nothing found yet: beyond the chain's end every level pushes its leaf;
    # before its start the first leaf answers and the rest is cut
    p = np.float32([[801, 0, 0.5], [801, 10, 0.5], [-1, 0, 0.5]])
    with pytest.raises(RuntimeError, match="overflowed for 2 points .first: point 0"):
        scene.closest_points(p)
    with pytest.raises(RuntimeError, match="overflowed for 1 points .first: point 0"):
        scene.closest_points(p[1:])
    got = scene.closest_points(p[2:])
    assert got.instance.tolist() == [0] and got.prim.tolist() == [0] and got.distance[0] == 1
    # within max_distance only the leaves that near are pushed: no overflow
    got = scene.closest_points(p[:2], max_distance=5)
    assert got.instance.tolist() == [0, 1] and got.prim.tolist() == [800, 800]
