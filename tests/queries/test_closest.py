"""Closest points (kernels/closest.cl) against the float64 brute force, on easy and hard meshes."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import random_soup, shipped_mesh
from lbvh.queries.closest import closest_points, closest_points_numpy, point_triangle_numpy
from lbvh.verification import hard_cases
from lbvh.metrics.error_bound import U, closest_distance_bound


def around(v: np.ndarray, n: int, seed: int, spread: float = 0.5) -> np.ndarray:
    """``n`` points in the mesh's box grown by ``spread`` on each side, and points on it."""
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
    ext = np.maximum(hi - lo, 1e-30)
    return np.clip(lo + ext * rng.uniform(-spread, 1 + spread, (n, 3)), -3e38, 3e38).astype(np.float32)


def check_against_twin(bvh: lbvh.BVH, p: np.ndarray, **kwargs) -> lbvh.queries.closest.Closest:
    v, f = bvh.vertices, bvh.faces
    got = closest_points(bvh.query_data, p, **kwargs)
    with np.errstate(all="ignore"):
        d, q, t = closest_points_numpy(v, f, p)
    bound = closest_distance_bound(v, p)
    assert got.overflow_count == 0
    assert (np.abs(got.distance.astype(np.float64) - d) <= bound).all(), \
        np.max(np.abs(got.distance - d) / bound)
    # the point is on the triangle named, at the distance given
    tri = v[f[got.prim]].astype(np.float64)
    u, w = got.u.astype(np.float64)[:, None], got.v.astype(np.float64)[:, None]
    assert (got.u >= 0).all() and (got.v >= 0).all() and (got.u + got.v <= 1 + 4 * U).all()
    on = (1 - u - w) * tri[:, 0] + u * tri[:, 1] + w * tri[:, 2]
    assert (np.abs(on - got.points).max(axis=1) <= bound).all()
    assert (np.abs(np.linalg.norm(p - got.points.astype(np.float64), axis=1) - d) <= 2 * bound).all()
    return got


def has_doubles(ctx) -> bool:
    return bool(ctx.device.double_fp_config)


def test_the_teapot_agrees_with_the_brute_force():
    v, f = shipped_mesh("teapot.obj")
    check_against_twin(lbvh.build(v, f), around(v, 300, 0))


@pytest.mark.parametrize("width", [8, 4])
def test_the_wide_walk_prunes_as_the_binary_walk(width):
    """Through wide records (either width) and through the binary nodes (records that
    would not fit): the same distances bit for bit, both within the twin's bound; the same
    triangle but where two are equally near."""
    v, f = shipped_mesh("teapot.obj")
    p = around(v, 400, 7)
    bvh = lbvh.build(v, f, collapse=True)
    assert bvh.query_data.wide_records(width=width).packed and bvh.query_data.wide_records().width == width
    wide = check_against_twin(bvh, p)
    binary = lbvh.BVH.from_arrays(bvh.nodes, bvh.prim_order, bvh.root, v, f, builder="x")
    assert not binary.query_data.wide_records(max_bytes=0).packed
    nodes = check_against_twin(binary, p)
    assert np.array_equal(wide.distance.view(np.uint32), nodes.distance.view(np.uint32))
    differ = wide.prim != nodes.prim
    q = p[differ].astype(np.float64)
    gap = [np.linalg.norm(q - point_triangle_numpy(q, *np.moveaxis(v[f[t]], 1, 0)), axis=1)
           for t in (wide.prim[differ], nodes.prim[differ])]
    assert (np.abs(gap[0] - gap[1]) <= closest_distance_bound(v, p[differ])).all()


@pytest.mark.parametrize("kind", ["lbvh+collapse", "sah", "treelets"])
def test_trees_with_leaf_lists_and_big_leaves(kind):
    v, f = random_soup(1500, seed=4)
    bvh = {"lbvh+collapse": lambda: lbvh.build(v, f, collapse=True),
           "sah": lambda: lbvh.build(v, f, builder="sah"),
           "treelets": lambda: lbvh.build(v, f, treelet_rounds=2)}[kind]()
    check_against_twin(bvh, around(v, 200, 1))


@pytest.mark.parametrize("name", ["slivers", "zero_area_mix", "identical_triangles", "flat_plane",
                                  "line_of_triangles", "huge_coordinates", "tiny_coordinates",
                                  "denormal_coordinates", "far_from_origin_1e7", "near_float_max"])
def test_hard_meshes_stay_within_the_bound(name, ctx):
    if not has_doubles(ctx):
        pytest.skip("the bound is for devices with doubles (cl_khr_fp64)")
    case = hard_cases.make(name)
    rng = np.random.default_rng(2)
    f = case.faces if len(case.faces) <= 2000 else case.faces[rng.choice(len(case.faces), 2000,
                                                                         replace=False)]
    bvh = lbvh.build(case.vertices, f)
    on_mesh = case.vertices[f[rng.integers(0, len(f), 40)]].astype(np.float64).mean(1)
    check_against_twin(bvh, np.vstack([around(case.vertices, 120, 3),
                                       on_mesh.astype(np.float32)]))


def test_without_doubles_well_shaped_meshes_hold_a_float32_bound():
    """The float32 path of devices without cl_khr_fp64 (forced with NO_FP64)."""
    v, f = shipped_mesh("teapot.obj")
    p = around(v, 200, 5)
    got = closest_points(lbvh.build(v, f), p, extra_defines={"NO_FP64": 1})
    d, _, _ = closest_points_numpy(v, f, p)
    assert (np.abs(got.distance - d) <= 4 * closest_distance_bound(v, p)).all()


def test_max_distance_keeps_only_what_is_within_it():
    v, f = shipped_mesh("teapot.obj")
    bvh = lbvh.build(v, f)
    p = around(v, 300, 6)
    d, _, _ = closest_points_numpy(v, f, p)
    radius = float(np.median(d))
    got = bvh.closest_points(p, max_distance=radius)
    bound = closest_distance_bound(v, p)
    clear = np.abs(d - radius) > bound            # points not on the sphere's edge
    assert np.array_equal(got.found[clear], (d <= radius)[clear])
    assert (got.distance[got.found] <= radius).all()
    missed = ~got.found
    assert np.isinf(got.distance[missed]).all() and (got.prim[missed] == -1).all()
    assert np.isnan(got.points[missed]).all()
    none = bvh.closest_points(p, max_distance=0.0)   # nothing lies on the mesh exactly
    assert none.found.sum() == (d == 0).sum()


def test_batches_give_the_same_answers():
    v, f = random_soup(800, seed=7)
    bvh = lbvh.build(v, f)
    p = around(v, 500, 8)
    one, many = bvh.closest_points(p), bvh.closest_points(p, batch_size=37)
    for name in ("distance", "prim", "u", "v"):
        assert np.array_equal(getattr(one, name), getattr(many, name)), name


@pytest.mark.parametrize("points, max_distance, message", [
    (np.float32([[0, 0, 0], [np.nan, 0, 0]]), np.inf, r"points: point 1 has a NaN"),
    (np.float64([[1e39, 0, 0]]), np.inf, r"points: point 0 .* beyond-float32"),
    (np.zeros((4, 2)), np.inf, r"points: shape \(4, 2\), expected \(N, 3\)"),
    (np.array([["a", "b", "c"]]), np.inf, "points: dtype"),
    (np.zeros((1, 3)), -1.0, "max_distance: -1.0"),
    (np.zeros((1, 3)), float("nan"), "max_distance: nan"),
    (np.zeros((1, 3)), "far", "max_distance: 'far'"),
])
def test_bad_input_is_named(points, max_distance, message):
    bvh = lbvh.build(*random_soup(50, seed=9))
    with pytest.raises(ValueError, match=message):
        bvh.closest_points(points, max_distance=max_distance)


def test_no_points_no_answers():
    bvh = lbvh.build(*random_soup(50, seed=9))
    got = bvh.closest_points(np.zeros((0, 3)))
    assert len(got) == 0 and got.points.shape == (0, 3)


def test_the_twin_is_right_on_hand_made_triangles():
    """The float64 brute force itself, where the answer is known."""
    a, b, c = np.float64([0, 0, 0]), np.float64([2, 0, 0]), np.float64([0, 2, 0])
    cases = [([0.5, 0.5, 3], [0.5, 0.5, 0]),     # over the face
             ([-1, -1, 0], [0, 0, 0]),           # beyond vertex a
             ([1, -5, 1], [1, 0, 0]),            # beyond edge ab
             ([3, 3, 0], [1, 1, 0]),             # beyond edge bc
             ([5, 0, 0], [2, 0, 0])]             # beyond vertex b
    for p, want in cases:
        assert np.allclose(point_triangle_numpy(np.float64(p), a, b, c), want)
    # a triangle of zero area (two equal vertices) is its segment
    assert np.allclose(point_triangle_numpy(np.float64([1, 1, 0]), a, a, b), [1, 0, 0])


def test_a_two_vertex_triangle_is_found(ctx):
    """Ericson's regions divide by zero on a triangle with two equal vertices: such
    a triangle must still be found through its edges (a bug found by the hard cases)."""
    v = np.float32([[0, 0, 0], [0, 0, 0], [1, 0, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]])
    f = np.uint32([[0, 1, 2], [3, 4, 5]])
    got = lbvh.build(v, f).closest_points(np.float32([[0.5, 0.1, 0]]))
    assert got.prim[0] == 0 and abs(got.distance[0] - 0.1) <= 1e-6


def test_points_in_morton_order_give_the_same_answers(monkeypatch):
    """Large batches are answered in the Morton order of the points' cells
    (kernels/ray_order.cl point_keys): every answer stays in its own slot."""
    import lbvh.queries.closest as closest_module
    from lbvh.queries.ray_order import point_keys_numpy, point_order
    v, f = shipped_mesh("teapot.obj")
    bvh = lbvh.build(v, f)
    p = around(v, 3000, 10)
    plain = bvh.closest_points(p)
    monkeypatch.setattr(closest_module, "MIN_POINTS", 1000)
    ordered = bvh.closest_points(p)
    for name in ("distance", "prim", "u", "v"):
        assert np.array_equal(getattr(ordered, name), getattr(plain, name)), name
    # the keys the order came from, against their numpy twin
    from lbvh import device as dev
    lower, upper = bvh.tree.root_box()
    ctx = bvh.ctx
    buf = dev.to_device(ctx, p)
    order, _ = point_order(ctx, buf, len(p), lower, upper)
    got = dev.from_device(ctx, order, np.int32, (len(p),))
    ctx.memory.free(order)
    want = np.argsort(point_keys_numpy(p, lower, upper), kind="stable")
    assert np.array_equal(got, want)
