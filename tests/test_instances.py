"""Two-level scenes of instances (lbvh.Scene, kernels/instances.cl) against a flattened copy: the float64
oracle of the one mesh the scene stands for gives the same hits, ties and rounding aside."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import lbvh
from conftest import shipped_mesh
from lbvh.verification import meshes
from lbvh.metrics.error_bound import t_bound
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
    starts = np.concatenate([[0], np.cumsum([scene.meshes[m].mesh.num_prims for m in scene.mesh_of])])
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
    mesh_nodes = scene._chunks
    v, f, _ = scene.flattened()
    o, d = rays_at(v, f, 2000, 5)
    scene.set_transforms([103, 107], t[[7, 3]] * [[1.1], [1.0], [0.9]])
    assert scene._chunks is mesh_nodes   # the meshes' trees are not touched
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
    # the scene's node buffers obey the same limit: two parts' trees to a buffer
    monkeypatch.setattr(lbvh.scene, "chunk_nodes", lambda ctx: 4000)
    scene = lbvh.build(v, f)
    assert isinstance(scene, lbvh.Scene) and scene.num_instances == -(-len(f) // 1000)
    assert len(scene._chunks) == 4 and max(c.size for c in scene._chunks) <= 4000 * 32
    o, d = rays_at(v, f, 1000, 11)
    monkeypatch.undo()
    whole = lbvh.build(v, f)
    assert np.array_equal(scene.intersect(o, d).t, whole.intersect(o, d).t)
    assert np.array_equal(scene.occluded(o, d), whole.occluded(o, d))
    assert np.array_equal(scene.count_hits(o, d), whole.count_hits(o, d))
    got, want = scene.all_hits(o, d), whole.all_hits(o, d)
    assert np.array_equal(got.offsets, want.offsets) and np.array_equal(got.t, want.t)
    p = o[:300]
    assert np.allclose(scene.closest_points(p)[0], whole.closest_points(p).distance, rtol=1e-6,
                       atol=0)


def test_trees_beyond_the_scenes_node_buffers_are_refused(monkeypatch):
    v, f = shipped_mesh("teapot.obj")
    monkeypatch.setattr(lbvh.scene, "chunk_nodes", lambda ctx: 2000)   # a part's tree each
    with pytest.raises(lbvh.DeviceError, match="need more than 4 node buffers"):
        lbvh.build_parts(v, f, part_triangles=1000)


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
    from lbvh.metrics.error_bound import WINDING_BOUND
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
    # a shear keeps no distances in proportion, yet answers in world space (the kernel
    # bounds world boxes and moves triangles: tests/test_instance_closest.py)
    sheared = lbvh.Scene([ball], [0], np.array([[[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]]))
    sv, sf, _ = sheared.flattened()
    assert np.allclose(sheared.closest_points(p[:50])[0], closest_points_numpy(sv, sf, p[:50])[0],
                       rtol=1e-5, atol=1e-5 * np.abs(sv).max())


def test_winding_numbers_of_open_meshes_under_shears_are_the_world_triangles():
    from lbvh.queries.winding import winding_numbers_numpy
    from lbvh.metrics.error_bound import WINDING_BOUND
    bv, bf = meshes.cube_sphere(6)
    ball = lbvh.build(bv, bf)                                  # closed: moved points exact
    cap_f = bf[bv[bf].mean(axis=1)[:, 2] > 0.2]                # a bowl: very open
    bowl = lbvh.build(bv, cap_f)
    squash = np.eye(3, 4)[None].copy()
    squash[0, :, :3] = [[3, 0, 0], [0, 1, 0], [0, 0, 0.3]]
    one = lbvh.Scene([bowl], [0], squash)
    v, f, _ = one.flattened()
    rng = np.random.default_rng(21)
    lo, hi = v.min(0), v.max(0)
    p = (lo + (hi - lo) * rng.uniform(0, 1, (800, 3))).astype(np.float32)
    exact = winding_numbers_numpy(v, f, p)
    assert np.abs(one.winding_numbers(p) - exact).max() <= WINDING_BOUND
    # the bowl's own winding number at the moved point is another number (0.27 off here)
    local = (p.astype(np.float64) @ np.linalg.inv(squash[0, :, :3]).T).astype(np.float32)
    assert np.abs(winding_numbers_numpy(bv, cap_f, local) - exact).max() > 3 * WINDING_BOUND
    # several instances: shears, a reflection, closed and open meshes, then a move
    t = np.tile(np.eye(3, 4), (3, 1, 1))
    t[0, :, :3] = [[1, 0.9, 0], [0, 1, 0], [0, 0, 0.4]]
    t[1, :, :3], t[1, :, 3] = [[2.5, 0, 0], [0, 0.5, 0.3], [0, 0, 1]], [4, 0, 0]
    t[2, :, :3], t[2, :, 3] = [[1, 0, 0.7], [0, -1, 0], [0, 0, 1]], [0, 0, 5]
    scene = lbvh.Scene([ball, bowl], [1, 0, 1], t)
    bound = scene.num_instances * WINDING_BOUND
    for move in (None, [0, 3, 0]):
        if move is not None:                # moving the sheared bowl moves its copy
            t[0, :, 3] = move
            scene.set_transforms([0], t[:1])
        v, f, _ = scene.flattened()
        lo, hi = v.min(0), v.max(0)
        p = (lo + (hi - lo) * rng.uniform(-0.1, 1.1, (800, 3))).astype(np.float32)
        assert np.abs(scene.winding_numbers(p) - winding_numbers_numpy(v, f, p)).max() <= bound


# -- every hit and the hit counts through a scene (kernels/instance_hits.cl) -----------------

def placed_oddly(count: int, seed: int) -> np.ndarray:
    """random_transforms, with instance 0 a reflection and instance 1 a non-uniform scale
    with no rotation (the others: rotations, some with reflections, times non-uniform
    scales)."""
    t = random_transforms(count, seed, spread=4.0)
    t[0, :, :3] = np.diag([-1.0, 1.0, 1.0]) @ t[0, :, :3]   # flips the sign of det
    t[1, :, :3] = np.diag([2.0, 0.5, 1.3])
    return t


def hit_pairs(scene: lbvh.Scene, got) -> np.ndarray:
    """``(ray, face of the flattened copy)`` of every hit, ``int64 (M, 2)``."""
    return np.stack([got.ray, scene.flat_faces(got.instance, got.prim)], axis=1)


def test_every_hit_through_a_scene_is_a_flattened_copys(parts):
    from lbvh.verification.oracle import all_hits_brute
    rng = np.random.default_rng(20)
    scene = lbvh.Scene(parts, rng.integers(0, 3, 12), placed_oddly(12, 21))
    v, f, _ = scene.flattened()
    o, d = rays_at(v, f, 1500, 22)
    got = scene.all_hits(o, d)
    assert isinstance(got, lbvh.AllHits) and got.overflow_count == 0
    assert got.instance.dtype == np.int32 and got.id.dtype == np.int64
    assert got.counts.max() >= 4 and (got.counts == 0).any()          # deep rays and misses
    assert np.array_equal(scene.count_hits(o, d), got.total)
    assert np.array_equal(got.id, scene.ids[got.instance])
    assert np.array_equal(got.mesh, scene.mesh_of[got.instance])
    # nearest first within each ray
    same_ray = got.ray[1:] == got.ray[:-1]
    assert (got.t[1:][same_ray] >= got.t[:-1][same_ray]).all()
    # the float64 oracle of the flattened copy: the same hits but for rays within
    # rounding of an edge (the kernel moves the ray, the copy the vertices)
    ref = all_hits_brute(v, f, o, d, dtype=np.float64)
    assert (got.total == ref.total).mean() >= 0.995
    mine = hit_pairs(scene, got)
    theirs = np.stack([ref.ray, ref.prim.astype(np.int64)], axis=1)
    agree = np.isin(got.ray, np.flatnonzero(got.total == ref.total))
    assert np.array_equal(np.unique(mine[agree], axis=0),
                          np.unique(theirs[np.isin(ref.ray, got.ray[agree])], axis=0))
    # t within the float32 bound of the flattened mesh's oracle, hit by hit
    key = lambda p: p[:, 0] * len(f) + p[:, 1]   # noqa: E731
    t_ref = dict(zip(key(theirs).tolist(), ref.t.tolist()))
    want = np.array([t_ref[k] for k in key(mine[agree]).tolist()])
    slack = t_bound(v, f, o[got.ray[agree]], d[got.ray[agree]], want, mine[agree, 1])
    assert (np.abs(got.t[agree] - want) <= slack).all()
    # the barycentrics are on the hit triangle of its instance's mesh: the point they
    # give, moved to world space, is the hit's location
    a, b = scene.transforms[got.instance, :, :3], scene.transforms[got.instance, :, 3]
    tri = np.stack([scene.meshes[m].vertices[scene.meshes[m].faces[p]] for m, p in
                    zip(got.mesh, got.prim)]).astype(np.float64)
    local = (1 - got.u - got.v)[:, None] * tri[:, 0] + got.u[:, None] * tri[:, 1] \
        + got.v[:, None] * tri[:, 2]
    world = np.einsum("ijk,ik->ij", a, local) + b
    assert np.abs(world - got.locations(o, d)).max() < 1e-4 * np.abs(v).max()


def test_identity_instances_and_spatial_splits_answer_as_one_tree():
    """The parts of one mesh (identity instances) move no ray: every hit is the one
    tree's, t, u, v bit for bit; a mesh of spatial splits gives each hit once, the same
    as the same mesh's LBVH placed the same way."""
    v, f = shipped_mesh("teapot.obj")
    whole, parts = lbvh.build(v, f), lbvh.build_parts(v, f, part_triangles=400)
    o, d = rays_at(v, f, 1500, 23)
    got, want = parts.all_hits(o, d), whole.all_hits(o, d)
    assert got.counts.max() >= 4
    assert np.array_equal(got.offsets, want.offsets) and np.array_equal(got.total, want.total)
    order = np.lexsort((got.prim, got.t, got.ray))   # the one tree's tie order: by triangle
    for name in ("t", "prim", "u", "v"):
        assert np.array_equal(getattr(got, name)[order], getattr(want, name)), name
    assert np.array_equal(parts.count_hits(o, d), whole.count_hits(o, d))
    moves = placed_oddly(3, 24)
    split = lbvh.Scene([lbvh.build(v, f, builder="sbvh")], [0, 0, 0], moves)
    plain = lbvh.Scene([whole], [0, 0, 0], moves)
    vv, ff, _ = plain.flattened()
    o, d = rays_at(vv, ff, 1500, 25)
    a, b = split.all_hits(o, d), plain.all_hits(o, d)
    assert split.meshes[0].tree.clipped_leaves and a.counts.max() >= 4
    for name in ("offsets", "total", "t", "prim", "u", "v", "instance"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(split.count_hits(o, d), b.total)
    near = split.all_hits(o, d, max_hits=1)   # max_hits after the duplicates are dropped
    assert np.array_equal(near.counts, np.minimum(b.counts, 1))


def test_crossings_through_shared_vertices_and_edges_count_once():
    """A closed ball placed by a reflection, a non-uniform scale and a rotation with a
    shear: rays through each world-space vertex and edge midpoint of each instance, from
    its centre (one crossing of that instance) and from outside through the centre (two):
    without the edge rule such a ray would hit every triangle around the vertex."""
    bv, bf = meshes.cube_sphere(5)
    t = np.zeros((3, 3, 4))
    t[0, :, :3] = np.diag([-1.5, 1.0, 1.0])
    t[1, :, :3] = np.diag([2.0, 0.5, 1.25])
    t[2, :, :3] = np.array([[1, 0.4, 0], [0, 1, 0], [0.2, 0, 0.8]]) @ np.linalg.qr(
        np.random.default_rng(26).normal(size=(3, 3)))[0]
    t[:, :, 3] = [[-5, 0, 0], [0, 5, 0], [5, 0, 1]]
    scene = lbvh.Scene([lbvh.build(bv, bf)], [0, 0, 0], t)
    v, f, owner = scene.flattened()
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    for k in range(3):
        mine = np.unique(f[owner == k])
        own_edges = edges[np.isin(edges[:, 0], mine)]
        points = np.concatenate([v[mine], (v[own_edges[:, 0]] + v[own_edges[:, 1]]) * 0.5])
        centre = t[k, :, 3].astype(np.float32)
        d = (points - centre).astype(np.float32)
        o = np.broadcast_to(centre, d.shape).astype(np.float32)
        for origin, direction, crossings in ((o, d, 1), ((o + 3 * d).astype(np.float32), -d, 2)):
            got = scene.all_hits(origin, direction)
            of_k = np.bincount(got.ray[got.instance == k], minlength=len(d))
            assert (of_k == crossings).all(), (k, crossings, np.bincount(of_k))


def test_intervals_max_hits_and_bad_rays_through_a_scene(parts):
    scene = lbvh.Scene(parts, [0, 1, 2, 0, 1], placed_oddly(5, 27))
    v, f, _ = scene.flattened()
    o, d = rays_at(v, f, 800, 28)
    full = scene.all_hits(o, d)
    # per-ray intervals keep exactly the hits of the whole ray inside them (t is the same
    # number whatever the interval), in batches of any size
    rng = np.random.default_rng(29)
    tmin = rng.uniform(0, 0.6, len(o)).astype(np.float32)
    tmax = (tmin + rng.uniform(0, 0.6, len(o))).astype(np.float32)
    window = scene.all_hits(o, d, tmin, tmax, batch_size=37)
    inside = (full.t >= tmin[full.ray]) & (full.t <= tmax[full.ray])
    assert 0 < inside.sum() < len(full.t)
    for name in ("ray", "t", "prim", "instance", "u", "v"):
        assert np.array_equal(getattr(window, name), getattr(full, name)[inside]), name
    assert np.array_equal(scene.count_hits(o, d, tmin, tmax, batch_size=64), window.total)
    # max_hits keeps the nearest (ties: the lower instance, then triangle)
    for k in (0, 1, 3):
        got = scene.all_hits(o, d, max_hits=k)
        assert np.array_equal(got.total, full.total)
        assert np.array_equal(got.counts, np.minimum(full.counts, k))
        assert np.array_equal(got.truncated, full.counts > k) and got.truncated.any()
        first = np.arange(len(full.t)) - full.offsets[full.ray] < k
        for name in ("t", "prim", "instance"):
            assert np.array_equal(getattr(got, name), getattr(full, name)[first]), name
    # the nearest hit is the closest hit query's
    near, hits = scene.all_hits(o, d, max_hits=1), scene.intersect(o, d)
    assert np.array_equal(near.ray, np.flatnonzero(hits.mask))
    assert np.array_equal(near.t, hits.t[hits.mask])
    assert np.array_equal(near.instance, hits.instance[hits.mask])
    # no rays; a bad ray refused by name, or counted as no hits with invalid_rays="miss"
    assert len(scene.all_hits(o[:0], d[:0])) == 0 and scene.count_hits(o[:0], d[:0]).shape == (0,)
    bad = d.copy()
    bad[3] = np.nan
    for call in (scene.count_hits, scene.all_hits):
        with pytest.raises(ValueError, match="ray 3"):
            call(o, bad)
    counts = scene.count_hits(o, bad, invalid_rays="miss")
    assert counts[3] == 0 and np.array_equal(np.delete(counts, 3), np.delete(full.total, 3))
    miss = scene.all_hits(o, bad, invalid_rays="miss")
    assert miss.invalid[3] and miss.counts[3] == 0 and miss.counts.sum() == full.counts.sum() \
        - full.counts[3]
    with pytest.raises(ValueError, match="max_hits: -1"):
        scene.all_hits(o, d, max_hits=-1)
    with pytest.raises(ValueError, match="batch_size: 0"):
        scene.count_hits(o, d, batch_size=0)
    with pytest.raises(ValueError, match="ray 0 has tmin 1.0 > tmax 0.5"):
        scene.all_hits(o, d, tmin=1.0, tmax=0.5)


def deep_chain(depth: int) -> lbvh.BVH:
    """Triangles in the planes x = 0..depth in a chain deeper than the kernels' largest
    stack: internal node i has node i+1 on the left and the leaf of triangle i on the
    right, so a ray along the chain pushes a leaf at every level."""
    from lbvh.layout import make_nodes
    k = np.arange(depth + 1, dtype=np.float32)
    m1, p3 = np.full_like(k, -1), np.full_like(k, 3)
    v = np.stack([np.stack([k, m1, m1], 1), np.stack([k, p3, m1], 1),
                  np.stack([k, m1, p3], 1)], 1).reshape(-1, 3)
    f = np.arange(3 * (depth + 1), dtype=np.uint32).reshape(-1, 3)
    lower = [[i, -1, -1] for i in range(depth)] + [[j, -1, -1] for j in range(depth + 1)]
    upper = [[depth, 3, 3]] * depth + [[j, 3, 3] for j in range(depth + 1)]
    children = [[i + 1 if i + 1 < depth else 2 * depth, depth + i] for i in range(depth)] \
        + [[-1, -1]] * (depth + 1)
    ranges = [[0, 0]] * depth + [[j, 1] for j in range(depth + 1)]
    nodes = make_nodes(np.float32(lower), np.float32(upper), np.array(children), np.array(ranges))
    return lbvh.BVH.from_arrays(nodes, np.arange(depth + 1, dtype=np.int32), 0, v, f,
                                builder="chain")


def test_a_stack_overflow_is_raised_or_flagged_never_silent():
    chain = deep_chain(800)
    moves = np.tile(np.eye(3, 4), (2, 1, 1))
    moves[1, 1, 3] = 10.0
    scene = lbvh.Scene([chain], [0, 0], moves)
    # along the chain (through both instances, 10 apart in y) and beside it
    o = np.float32([[801, 0, 0.5], [801, 10, 0.5], [801, 50, 0.5]])
    d = np.float32([[-1, 0, 0]] * 3)
    with pytest.raises(RuntimeError, match="overflowed for 2 rays .first: ray 0"):
        scene.count_hits(o, d)
    got = scene.all_hits(o, d)
    assert got.overflow.tolist() == [True, True, False] and got.overflow_count == 2
    assert (got.total[:2] < 801).all() and got.total[2] == 0   # hits were skipped: flagged
