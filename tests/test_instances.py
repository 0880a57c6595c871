"""Two-level scenes of instances (lbvh.Scene, kernels/instances.cl) against a flattened copy: the float64
oracle of the one mesh the scene stands for gives the same hits, ties and rounding aside."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import lbvh
from conftest import shipped_mesh
from lbvh.verification import meshes
from lbvh.verification.error_bound import t_bound
from lbvh.verification.oracle import brute_force


def random_transforms(count: int, seed: int, spread: float = 10.0) -> np.ndarray:
    """Rotations (with reflections), scales from 0.3 to 2 and translations."""
    rng = np.random.default_rng(seed)
    t = np.zeros((count, 3, 4))
    for i in range(count):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        t[i, :, :3] = q * rng.uniform(0.3, 2.0, 3)   # rotation times a non-uniform scale
        t[i, :, 3] = rng.uniform(-spread, spread, 3)
    return t


@pytest.fixture(scope="module")
def parts():
    return [lbvh.build(*meshes.cube_sphere(6)), lbvh.build(*shipped_mesh("teapot.obj"), builder="sah"),
            lbvh.build(*meshes.soup(300, 2, 0.2, spread="normal"), collapse=True)]


def rays_at(v: np.ndarray, f: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    o = lo + (hi - lo) * rng.uniform(-0.2, 1.2, (n, 3))
    aim = v[f[rng.integers(0, len(f), n)]].mean(axis=1)
    d = np.where(rng.random((n, 1)) < 0.8, aim - o, rng.normal(size=(n, 3)))
    return o.astype(np.float32), d.astype(np.float32)


def assert_like_flattened(scene: lbvh.Scene, o: np.ndarray, d: np.ndarray, tmin=0.0) -> None:
    v, f, owner = scene.flattened()
    ref = brute_force(v, f, o, d, tmin)
    got = scene.intersect(o, d, tmin)
    assert got.overflow_count == 0
    hit = ref.prim >= 0
    # hit or miss: the same but for rays within rounding of a silhouette edge
    assert (got.mask == hit).mean() >= 0.999
    both = np.flatnonzero(got.mask & hit)
    starts = np.concatenate([[0], np.cumsum([scene.meshes[m].num_prims for m in scene.mesh_of])])
    inst = owner[ref.prim[both]]
    local = ref.prim[both] - starts[inst]
    same = (got.instance[both] == inst) & (got.prim[both] == local)
    assert same.mean() >= 0.995
    # t within the float32 bound of the flattened mesh's oracle, on every ray both hit
    slack = t_bound(v, f, o[both], d[both], ref.t[both].astype(np.float64), ref.prim[both])
    assert (np.abs(got.t[both] - ref.t[both]) <= slack).all()
    assert (got.id[both] == scene.ids[got.instance[both]]).all()
    assert (got.mesh[both] == scene.mesh_of[got.instance[both]]).all()
    assert (got.prim[~got.mask] == -1).all() and (got.instance[~got.mask] == -1).all()
    assert np.array_equal(scene.occluded(o, d, tmin), got.mask)


def test_instances_hit_what_a_flattened_copy_hits(parts):
    rng = np.random.default_rng(0)
    scene = lbvh.Scene(parts, rng.integers(0, 3, 40), random_transforms(40, 1))
    assert scene.num_instances == 40 and len(scene.meshes) == 3
    v, f, _ = scene.flattened()
    assert len(f) == scene.num_triangles
    o, d = rays_at(v, f, 4000, 2)
    assert_like_flattened(scene, o, d)
    # per-ray intervals
    tmin = np.random.default_rng(3).uniform(0, 0.5, len(o)).astype(np.float32)
    assert_like_flattened(scene, o, d, tmin)


def test_moving_instances_rebuilds_the_top_only(parts):
    t = random_transforms(12, 4)
    scene = lbvh.Scene(parts, np.arange(12) % 3, t, ids=np.arange(100, 112))
    mesh_nodes = scene._nodes
    v, f, _ = scene.flattened()
    o, d = rays_at(v, f, 2000, 5)
    scene.set_transforms([103, 107], t[[7, 3]] * [[1.1], [1.0], [0.9]])
    assert scene._nodes is mesh_nodes   # the meshes' trees are not touched
    assert_like_flattened(scene, o, d)
    # a bad move changes nothing
    before = scene.transforms.copy()
    with pytest.raises(ValueError, match="no instance has id 5"):
        scene.set_transforms([5], t[:1])
    with pytest.raises(ValueError, match="singular"):
        scene.set_transforms([100], np.zeros((1, 3, 4)))
    assert np.array_equal(scene.transforms, before)


def test_counters_and_tiny_directions(parts):
    scene = lbvh.Scene(parts, [0, 1, 2], random_transforms(3, 6, spread=3.0))
    v, f, _ = scene.flattened()
    o, d = rays_at(v, f, 1000, 7)
    got = scene.intersect(o, d, counters=True)
    assert (got.nodes_visited >= 1).all() and (got.tris_tested[got.mask] >= 1).all()
    # directions 2^-100 long (exact): traced as d * 2^-texp in both levels, t back in the
    # caller's units: the same hits, t times 2^100 exactly
    small = scene.intersect(o, np.ldexp(d, -100))
    assert np.array_equal(small.mask, got.mask) and np.array_equal(small.prim, got.prim)
    assert np.array_equal(np.ldexp(small.t, -100), got.t)


def test_from_a_trimesh_scene_shared_geometry_is_built_once():
    box = trimesh.creation.box()
    ball = trimesh.creation.icosphere(subdivisions=2)
    source = trimesh.Scene()
    source.add_geometry(box, geom_name="box", node_name="left",
                        transform=trimesh.transformations.translation_matrix([-3, 0, 0]))
    source.graph.update(frame_to="right", geometry="box",
                        matrix=trimesh.transformations.rotation_matrix(0.7, [0, 1, 0], [3, 0, 0])
                        @ trimesh.transformations.translation_matrix([3, 0, 0]))
    source.add_geometry(ball, geom_name="ball", node_name="ball")
    scene = lbvh.build(source)
    assert isinstance(scene, lbvh.Scene)
    assert scene.num_instances == 3 and len(scene.meshes) == 2
    assert sorted(scene.names) == ["ball", "left", "right"]
    # the flattened scene is trimesh's own flattening (same triangles, any order)
    flat = source.to_mesh() if hasattr(source, "to_mesh") else source.dump(concatenate=True)
    v, f, _ = scene.flattened()
    assert np.allclose(np.sort(v[f].reshape(-1, 9), axis=0),
                       np.sort(np.asarray(flat.vertices)[flat.faces].reshape(-1, 9), axis=0),
                       atol=1e-5)
    o, d = rays_at(v, f, 1500, 8)
    assert_like_flattened(scene, o, d)
    hits = scene.intersect(o, d)
    named = {scene.names[i] for i in np.unique(hits.instance[hits.mask])}
    assert named == {"ball", "left", "right"}


def test_a_list_of_meshes():
    a, b = meshes.cube_sphere(4), shipped_mesh("teapot.obj")
    scene = lbvh.build([a, trimesh.Trimesh(*b, process=False)])
    assert scene.num_instances == 2 and np.array_equal(scene.transforms[0], np.eye(3, 4))
    v, f, _ = scene.flattened()
    o, d = rays_at(v, f, 1000, 9)
    assert_like_flattened(scene, o, d)


@pytest.mark.parametrize("make, fragment", [
    (lambda p: lbvh.Scene([], [0], np.eye(3, 4)[None]), "meshes: none given"),
    (lambda p: lbvh.Scene(p, [5], np.eye(3, 4)[None]), "names mesh 5"),
    (lambda p: lbvh.Scene(p, [0, 1], np.eye(3, 4)[None]), "1 of them for 2 instances"),
    (lambda p: lbvh.Scene(p, [0], np.zeros((1, 3, 4))), "instance 0 is singular"),
    (lambda p: lbvh.Scene(p, [0], np.ones((1, 4, 4))), "not affine"),
    (lambda p: lbvh.Scene(p, [0], np.full((1, 3, 4), np.nan)), "NaN"),
    (lambda p: lbvh.Scene(p, [0, 0], np.tile(np.eye(3, 4), (2, 1, 1)), ids=[1, 1]), "not unique"),
    (lambda p: lbvh.Scene([np.zeros(3)], [0], np.eye(3, 4)[None]), "expected an lbvh.BVH"),
    (lambda p: lbvh.build([np.zeros(3)]), "item 0"),
    (lambda p: lbvh.build(trimesh.Scene()), "without triangle meshes"),
])
def test_bad_scenes_are_named(parts, make, fragment):
    with pytest.raises(ValueError, match=fragment):
        make(parts)


def test_a_mesh_in_parts_answers_as_one_tree():
    v, f = shipped_mesh("teapot.obj")
    whole = lbvh.build(v, f)
    parts = lbvh.build_parts(v, f, part_triangles=500)
    assert parts.num_instances == -(-len(f) // 500) and parts.num_triangles == len(f)
    assert sorted(np.concatenate(parts.face_ids).tolist()) == list(range(len(f)))
    o, d = rays_at(v, f, 3000, 10)
    got, want = parts.intersect(o, d), whole.intersect(o, d)
    assert np.array_equal(got.t, want.t)             # the identity moves nothing
    tie = got.prim != want.prim                      # another triangle only at the same t
    assert tie.mean() < 0.01
    assert np.array_equal(parts.occluded(o, d), whole.occluded(o, d))
    # the barycentrics are of the mesh's own triangle
    same = ~tie & want.mask
    assert np.array_equal(got.u[same], want.u[same]) and np.array_equal(got.v[same], want.v[same])


def test_a_mesh_beyond_the_largest_buffer_is_built_in_parts(monkeypatch):
    """The device's largest allocation decides (read from the device; lowered here to
    1,000 triangles' worth so that the teapot passes it)."""
    from lbvh.builders import pipeline
    v, f = shipped_mesh("teapot.obj")
    monkeypatch.setattr(pipeline, "max_triangles", lambda ctx: 1000)
    scene = lbvh.build(v, f)
    assert isinstance(scene, lbvh.Scene) and scene.num_instances == -(-len(f) // 1000)
    o, d = rays_at(v, f, 1000, 11)
    monkeypatch.undo()
    assert np.array_equal(scene.intersect(o, d).t, lbvh.build(v, f).intersect(o, d).t)


def similarity_transforms(count: int, seed: int) -> np.ndarray:
    """Rotations and reflections times one scale each, and translations."""
    rng = np.random.default_rng(seed)
    t = np.zeros((count, 3, 4))
    for i in range(count):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        t[i, :, :3] = q * rng.uniform(0.3, 2.0)
        t[i, :, 3] = rng.uniform(-6, 6, 3)
    return t


def test_point_queries_through_a_scene_of_similarities():
    from lbvh.queries.closest import closest_points_numpy
    from lbvh.queries.winding import winding_numbers_numpy
    from lbvh.verification.error_bound import WINDING_BOUND
    ball = lbvh.build(*meshes.cube_sphere(6))          # closed
    teapot = lbvh.build(*shipped_mesh("teapot.obj"))   # open
    scene = lbvh.Scene([ball, teapot], [0, 1, 0, 0, 1], similarity_transforms(5, 12))
    v, f, owner = scene.flattened()
    rng = np.random.default_rng(13)
    lo, hi = v.min(0), v.max(0)
    p = (lo + (hi - lo) * rng.uniform(-0.1, 1.1, (600, 3))).astype(np.float32)
    distance, where, inst, prim = scene.closest_points(p)
    want_d, want_q, want_f = closest_points_numpy(v, f, p)
    assert np.allclose(distance, want_d, rtol=1e-5, atol=1e-5 * np.abs(v).max())
    assert np.allclose(where, want_q, atol=1e-4 * np.abs(v).max())
    assert (inst >= 0).all()
    # within a radius: nothing beyond it
    near = scene.closest_points(p, max_distance=0.3)[0]
    clear = np.abs(want_d - 0.3) > 1e-5                 # not within rounding of the radius
    assert np.array_equal(np.isfinite(near)[clear], (want_d < 0.3)[clear])
    assert (want_d < 0.3).any() and (want_d > 0.3).any()
    # winding numbers add up over the instances (a reflection flips one's sign): each
    # instance's within WINDING_BOUND of its exact sum
    w = scene.winding_numbers(p)
    exact = winding_numbers_numpy(v, f, p)
    bound = scene.num_instances * WINDING_BOUND
    assert np.abs(w - exact).max() <= bound
    sure = np.abs(exact - 0.5) > bound
    assert np.array_equal(scene.contains(p)[sure], (exact > 0.5)[sure]) and (exact[sure] > 0.5).any()
    sd = scene.signed_distance(p)
    assert np.array_equal(sd < 0, scene.contains(p) & (distance > 0))
    # a shear keeps no distances in proportion: refused, named
    sheared = lbvh.Scene([ball], [0], np.array([[[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]]))
    with pytest.raises(ValueError, match="instance 0 is not placed by a rotation"):
        sheared.closest_points(p[:3])
