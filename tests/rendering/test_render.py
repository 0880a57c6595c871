"""Rendering: camera rays and framing, image files, shading, and rendered images
against references made by the float64 oracle (never by the kernel itself)."""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

import lbvh
from lbvh.camera import Camera, frame_bounds
from lbvh.rendering.image import heat_colours, image_kind, read_image, to_8bit, write_image
from lbvh.verification.oracle import brute_force
from lbvh.rendering.render import (MODES, ambient_occlusion, cosine_directions, display, hammersley,
                         orthonormal_basis, render, render_reference, shade_primary,
                         triangle_normals)
from lbvh.files import load_scene
from lbvh.queries.traverse import intersect

REPO = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parent / "data"


def _make_references_module():
    spec = importlib.util.spec_from_file_location("make_references", DATA / "make_references.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


REFS = _make_references_module()


@pytest.fixture(scope="module")
def scenes():
    out = {}
    for name in ("teapot", "cornell"):
        scene = load_scene(REPO / "scenes" / f"{name}.json")
        out[name] = (scene, lbvh.build(scene.vertices, scene.faces))
    return out


# -- camera -----------------------------------------------------------------------
def test_rays_go_through_pixel_centres_row_zero_at_the_top():
    cam = Camera([1.0, 2.0, 3.0], [1.0, 2.0, -7.0], [0, 1, 0], 60.0, 5, 3)
    origins, dirs = cam.rays()
    assert origins.dtype == dirs.dtype == np.float32
    assert origins.shape == dirs.shape == (15, 3)
    assert np.all(origins == np.float32([1, 2, 3]))
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, rtol=1e-6)
    # The centre pixel of an odd-sized image looks straight at the target.
    np.testing.assert_allclose(dirs[7], [0, 0, -1], atol=1e-7)
    # Top row looks up, left column looks left (right is +x for this view).
    assert (dirs[:5, 1] > 0).all() and (dirs[10:, 1] < 0).all()
    assert (dirs[0::5, 0] < 0).all() and (dirs[4::5, 0] > 0).all()
    # The top-row centre pixel is 1/3 of the half-height below the top edge.
    expected = math.atan(math.tan(math.radians(30.0)) * (1 - 1 / 3))
    assert math.isclose(math.atan2(dirs[2, 1], -dirs[2, 2]), expected, rel_tol=1e-6)
    # Square pixels: horizontal spacing equals vertical spacing at the centre.
    assert math.isclose(dirs[8, 0] / -dirs[8, 2], dirs[2, 1] / -dirs[2, 2], rel_tol=1e-6)


def test_frame_bounds_sees_every_corner_and_fills_the_image():
    lower, upper = np.array([-3.0, 0.0, -2.0]), np.array([3.4, 3.2, 2.0])
    for width, height, direction in [(64, 48, (0.45, 0.35, 1.0)), (30, 90, (0, 0, -1)),
                                     (50, 50, (0, 1, 0))]:
        cam = frame_bounds(lower, upper, width, height, fov=40, direction=direction)
        right, up, forward = cam.basis()
        corners = np.array([[x, y, z] for x in (lower[0], upper[0]) for y in (lower[1], upper[1])
                            for z in (lower[2], upper[2])]) - cam.position
        depth = corners @ forward
        assert (depth > 0).all()
        tan_v = math.tan(math.radians(20))
        sx = corners @ right / depth / (tan_v * width / height)
        sy = corners @ up / depth / tan_v
        extent = np.maximum(np.abs(sx), np.abs(sy)).max()
        # Inside with the 5% margin, and tight: the widest corner touches the margin.
        assert extent <= 1 / 1.05 + 1e-9
        assert extent >= 1 / 1.05 - 1e-6


def test_frame_bounds_of_a_flat_or_point_scene_still_makes_a_camera():
    flat = frame_bounds([0, 0, 0], [1, 1, 0], 8, 8)
    assert np.isfinite(flat.position).all()
    point = frame_bounds([2, 2, 2], [2, 2, 2], 8, 8)
    assert np.linalg.norm(point.position - point.target) > 0


@pytest.mark.parametrize("kwargs, message", [
    (dict(fov=0.0), "fov"), (dict(fov=180.0), "fov"), (dict(fov="wide"), "fov"),
    (dict(width=0), "width"), (dict(height=2.5), "height"), (dict(width=True), "width"),
    (dict(position=[0, 0, float("nan")]), "position"), (dict(target=[0, 0]), "target"),
    (dict(target=[0, 0, 5]), "same point"), (dict(up=[0, 0, 1]), "parallel"),
    (dict(up=[0, 0, 0]), "up"),
])
def test_bad_camera_values_are_named(kwargs, message):
    args = dict(position=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0], fov=45.0, width=4, height=3)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Camera(**args)


def test_camera_dict_round_trip():
    cam = Camera([1, 2, 3], [0, 0, 0], [0, 1, 0], 33.0, 20, 10)
    again = Camera.from_dict(cam.as_dict())
    assert again.as_dict() == cam.as_dict()
    assert Camera.from_dict(cam.as_dict(), size=(7, 5)).width == 7


# -- image files --------------------------------------------------------------------
def test_png_round_trip_is_exact_8_bit(tmp_path):
    rng = np.random.default_rng(1)
    for channels in (1, 3):
        pixels = rng.integers(0, 256, (5, 7, channels), dtype=np.uint8)
        write_image(tmp_path / f"x{channels}.png", pixels)
        back = read_image(tmp_path / f"x{channels}.png")
        assert back.dtype == np.uint8 and np.array_equal(back, pixels)


def test_exr_and_tiff_round_trip_floats_exactly_including_infinity(tmp_path):
    rng = np.random.default_rng(2)
    pixels = rng.normal(0, 1e3, (6, 9, 1)).astype(np.float32)
    pixels[0, 0, 0], pixels[1, 2, 0] = np.inf, 1e-30
    for suffix in (".exr", ".tif"):
        write_image(tmp_path / f"x{suffix}", pixels[:, :, 0])
        back = read_image(tmp_path / f"x{suffix}")
        assert back.dtype == np.float32 and back.shape == (6, 9, 1)
        assert np.array_equal(back, pixels)


def test_float_pixels_to_an_8_bit_file_are_clipped_and_rounded(tmp_path):
    pixels = np.array([[-0.5, 0.0, 0.4 / 255, 0.2, 1.0, 7.0, np.nan]], np.float32)
    write_image(tmp_path / "c.png", pixels)
    assert read_image(tmp_path / "c.png")[0, :, 0].tolist() == [0, 0, 0, 51, 255, 255, 0]
    assert to_8bit(np.float32([1.5 / 255]))[0] == 2  # round half to even, as numpy rint


def test_unknown_extension_and_unwritable_paths_are_value_errors(tmp_path):
    pixels = np.zeros((2, 2), np.uint8)
    with pytest.raises(ValueError, match=r"unknown image format '\.bmp'"):
        write_image(tmp_path / "x.bmp", pixels)
    with pytest.raises(ValueError, match="no extension"):
        image_kind(tmp_path / "noext")
    with pytest.raises(ValueError, match="cannot write"):
        write_image(tmp_path / "missing" / "x.png", pixels)
    (tmp_path / "folder.exr").mkdir()
    with pytest.raises(ValueError, match="folder.exr"):
        write_image(tmp_path / "folder.exr", pixels)
    for channels in (2, 4):   # no alpha: OpenImageIO would premultiply it
        with pytest.raises(ValueError, match="shape"):
            write_image(tmp_path / "x.png", np.zeros((2, 2, channels), np.uint8))
    with pytest.raises(ValueError, match="cannot read"):
        read_image(tmp_path / "absent.png")


def test_heat_colours_run_from_dark_to_bright():
    colours = heat_colours(np.array([0.0, 5.0, 10.0, 20.0, np.nan]), vmax=10.0)
    brightness = colours.sum(axis=1)
    assert brightness[0] < brightness[1] < brightness[2] == brightness[3]
    assert np.array_equal(colours[4], colours[0])
    assert colours.dtype == np.float32 and (colours >= 0).all() and (colours <= 1).all()


# -- shading pieces (numpy) -----------------------------------------------------------
def test_orthonormal_basis_and_cosine_directions():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(2000, 3))
    n[:4] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1e-9, -1]]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = orthonormal_basis(n)
    basis = np.stack([t1, t2, n], axis=1)
    np.testing.assert_allclose(basis @ basis.transpose(0, 2, 1), np.broadcast_to(np.eye(3), basis.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(basis), 1.0, atol=1e-12)
    dirs = cosine_directions(n, rng.random((len(n), 2)))
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    cos = np.einsum("ij,ij->i", dirs, n)
    assert (cos >= 0).all()
    # Cosine-weighted: E[cos] = 2/3 (the uniform hemisphere would give 1/2).
    assert abs(cos.mean() - 2 / 3) < 0.02


def test_hammersley_points():
    h = hammersley(8)
    assert h[:, 0].tolist() == [i / 8 for i in range(8)]
    assert h[:, 1].tolist() == [0, 0.5, 0.25, 0.75, 0.125, 0.625, 0.375, 0.875]


def test_shade_primary_on_a_known_triangle():
    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    f = np.uint32([[0, 1, 2]])
    d = np.float32([[0, 0, -1], [0, 0.6, -0.8], [1, 0, 0]])
    t, prim = np.float32([2.0, 3.0, np.inf]), np.int32([0, 0, -1])
    normals = shade_primary("normals", t, prim, d, v, f, 3, 1)
    assert normals[0].tolist() == [[0, 0, 1], [0, 0, 1], [0, 0, 0]]
    diffuse = shade_primary("diffuse", t, prim, d, v, f, 3, 1)
    np.testing.assert_allclose(diffuse[0, :, 0], [1.0, 0.8, 0.0], rtol=1e-6)
    depth = shade_primary("depth", t, prim, d, v, f, 3, 1)
    assert depth[0, :, 0].tolist() == [2.0, 3.0, np.inf]
    shown = display("depth", depth)
    assert shown[0, :, 0].tolist() == [255, 51, 0]   # near white, far 20% grey, miss black
    assert display("normals", normals)[0].tolist() == [[128, 128, 255], [128, 128, 255], [0, 0, 0]]
    assert triangle_normals(v, np.uint32([[0, 1, 1]]), np.int32([0])).tolist() == [[0, 0, 0]]


# -- rendering with the kernel ----------------------------------------------------------
def _floor_and_ceiling(height: float):
    """A 2x2 floor at y=0 facing up, and a 40x40 ceiling at y=height above it."""
    v = np.float32([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1],
                    [-20, height, -20], [20, height, -20], [20, height, 20], [-20, height, 20]])
    f = np.uint32([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]])
    return v, f


def test_ambient_occlusion_of_a_floor_under_a_ceiling():
    v, f = _floor_and_ceiling(0.5)
    bvh = lbvh.build(v, f)
    cam = Camera([0, 0.3, 0], [0.05, 0, 0.02], [0, 0, -1], 20.0, 8, 8)
    _, dirs = cam.rays()
    hits = intersect(bvh, *cam.rays())
    assert (hits.prim <= 1).all() and (hits.prim >= 0).all()

    def occluded(o, d, tmax):
        return bvh.occluded(o, d, 0.0, tmax)
    diagonal = float(np.linalg.norm(v.max(0) - v.min(0)))
    # Reach below the ceiling: nothing occludes; far beyond it: almost everything does
    # (the ceiling covers all but directions within atan(0.5/20) of the horizon).
    short = ambient_occlusion(occluded, v, f, (hits.prim, hits.u, hits.v), dirs, 16,
                              distance=0.4 / diagonal)
    assert short.tolist() == [1.0] * 64
    long = ambient_occlusion(occluded, v, f, (hits.prim, hits.u, hits.v), dirs, 16, distance=1.0)
    assert (long <= 1 / 16).all()
    with pytest.raises(ValueError, match="ao samples"):
        ambient_occlusion(occluded, v, f, (hits.prim, hits.u, hits.v), dirs, 0)


def test_depth_and_normals_match_the_oracle_reference_images(scenes):
    """Kernel renders of the teapot at 64x48 against the stored float64-oracle images.

    Tolerance: hit or miss agrees on every pixel but at most 0.1% (a ray grazing the
    silhouette may round differently in float32); ``t`` within 1e-5 relative (the
    kernel's float32 rounding is ~1e-7); a normal may differ only on a pixel whose
    depth agrees (a tie between two triangles at the same distance), at most 1%.
    """
    scene, bvh = scenes["teapot"]
    name, scene_file, _, width, height = REFS.REFERENCES[0]
    depth_ref = read_image(DATA / name)
    normals_ref = read_image(DATA / REFS.REFERENCES[1][0])
    camera = scene.camera.resized(width, height)
    depth = render(bvh, camera, "depth").image
    normals = render(bvh, camera, "normals").image
    assert depth.shape == depth_ref.shape == (height, width, 1)
    hit, hit_ref = np.isfinite(depth), np.isfinite(depth_ref)
    assert hit_ref.sum() > 0.2 * width * height          # the teapot fills the frame
    assert (hit != hit_ref).sum() <= 0.001 * width * height
    both = hit & hit_ref
    np.testing.assert_allclose(depth[both], depth_ref[both], rtol=1e-5)
    differ = np.any(np.abs(normals - normals_ref) > 1e-5, axis=2)
    assert (differ & ~both[:, :, 0] & (hit == hit_ref)[:, :, 0]).sum() == 0
    assert differ.sum() <= 0.01 * width * height + (hit != hit_ref).sum()


def test_stored_references_are_the_oracle_images():
    """The files under tests/rendering/data are what make_references.py writes (float64 oracle)."""
    for name, scene_file, mode, width, height in REFS.REFERENCES:
        fresh = REFS.reference_image(scene_file, mode, width, height)
        stored = read_image(DATA / name)
        np.testing.assert_allclose(stored, fresh, rtol=1e-6, atol=1e-6)


def test_ambient_occlusion_matches_the_oracle(scenes):
    """AO of the cornell box at 32x32, 8 samples, kernel vs oracle with the same seed.

    Tolerance: mean absolute difference below 0.01 and at most 2% of pixels differing
    (pixels on the floor/wall corner edge are ties; their rays start on a plane).
    """
    scene, bvh = scenes["cornell"]
    camera = scene.camera.resized(32, 32)
    kernel = render(bvh, camera, "ao", ao_samples=8).image
    oracle = render_reference(scene.vertices, scene.faces, camera, "ao", ao_samples=8)
    diff = np.abs(kernel - oracle)
    assert kernel.min() < 0.9 and kernel.max() == 1.0     # the box does occlude
    assert diff.mean() < 0.01
    assert (diff > 0).sum() <= 0.02 * camera.num_pixels


def test_heatmap_is_the_traversal_counters(scenes):
    scene, bvh = scenes["teapot"]
    camera = scene.camera.resized(24, 18)
    result = render(bvh, camera, "heatmap")
    hits = intersect(bvh, *camera.rays(), counters=True)
    expected = (hits.nodes_visited + hits.tris_tested).reshape(18, 24, 1)
    assert np.array_equal(result.image, expected.astype(np.float32))
    assert (result.image >= 1).all()
    assert result.display().shape == (18, 24, 3)


@pytest.mark.parametrize("mode", MODES)
def test_every_mode_renders_and_saves(scenes, mode, tmp_path):
    scene, bvh = scenes["cornell"]
    camera = scene.camera.resized(16, 12)
    result = render(bvh, camera, mode, ao_samples=2)
    assert result.image.dtype == np.float32 and result.image.shape[:2] == (12, 16)
    hits = int((result.primary_hits.prim >= 0).sum())
    assert result.rays == camera.num_pixels + (2 * hits if mode == "ao" else 0)
    assert result.overflow_count == 0 and result.trace_seconds > 0
    result.save(tmp_path / "x.png")
    result.save(tmp_path / "x.exr")
    assert read_image(tmp_path / "x.png").dtype == np.uint8
    assert np.array_equal(read_image(tmp_path / "x.exr"), result.image)


def test_bad_mode_is_a_value_error(scenes):
    scene, bvh = scenes["cornell"]
    with pytest.raises(ValueError, match="mode: 'fancy'"):
        render(bvh, scene.camera.resized(4, 4), "fancy")
    with pytest.raises(ValueError, match="heatmap"):
        render_reference(scene.vertices, scene.faces, scene.camera.resized(4, 4), "heatmap")


def test_brute_force_is_the_oracle_used():
    # Guard against the reference silently switching to the float32 twin.
    scene = load_scene(REPO / "scenes" / "cornell.json")
    camera = scene.camera.resized(6, 4)
    o, d = camera.rays()
    hits = brute_force(scene.vertices, scene.faces, o, d)
    depth = render_reference(scene.vertices, scene.faces, camera, "depth")
    assert np.array_equal(depth[:, :, 0].ravel(), np.where(hits.prim >= 0, hits.t, np.inf))
