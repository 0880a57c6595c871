"""Scene loading: mesh formats through trimesh, multi-mesh flattening, and the JSON
scene description with its camera and transforms (good and bad inputs)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from lbvh.files import apply_transform, load_mesh, load_scene, transform_matrix

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "scenes"


def _write(path: Path, data) -> Path:
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


def _tetrahedron() -> trimesh.Trimesh:
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    return trimesh.Trimesh(v, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False)


@pytest.mark.parametrize("name", ["teapot", "cornell", "suzanne"])
def test_shipped_scene_descriptions_load_with_their_cameras(name):
    scene = load_scene(SCENES / f"{name}.json")
    assert scene.name == name and scene.camera is not None
    assert scene.vertices.dtype == np.float32 and scene.faces.dtype == np.uint32
    mesh_v, mesh_f = load_mesh(scene.extras["mesh_path"])
    assert np.array_equal(scene.vertices, mesh_v) and np.array_equal(scene.faces, mesh_f)
    # The saved camera looks at the mesh: its target is inside the mesh's box.
    assert (scene.camera.target >= mesh_v.min(0) - 1e-6).all()
    assert (scene.camera.target <= mesh_v.max(0) + 1e-6).all()
    assert "credit" in scene.extras


def test_bare_mesh_has_no_camera():
    scene = load_scene(SCENES / "cornell_box_gkit.obj")
    assert scene.camera is None and len(scene.faces) == 32


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".off", ".obj", ".glb"])
def test_mesh_formats_load_through_trimesh(tmp_path, suffix):
    mesh = _tetrahedron()
    path = tmp_path / f"tet{suffix}"
    mesh.export(path)
    v, f = load_mesh(path)
    assert len(f) == 4
    # Same triangles whatever the format did to the vertex order.
    expected = sorted(map(tuple, np.sort(mesh.vertices[mesh.faces].reshape(4, -1), axis=1)))
    got = sorted(map(tuple, np.sort(v[f].reshape(4, -1).astype(np.float64), axis=1)))
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_multi_mesh_glb_is_flattened_with_node_transforms(tmp_path):
    scene = trimesh.Scene()
    shift = trimesh.transformations.translation_matrix([10.0, 0.0, 0.0])
    turn = trimesh.transformations.rotation_matrix(math.pi / 2, [0, 0, 1])
    scene.add_geometry(_tetrahedron(), node_name="a", geom_name="a", transform=shift)
    scene.add_geometry(trimesh.creation.box(extents=[1, 2, 3]), node_name="b", geom_name="b",
                       transform=turn)
    path = tmp_path / "two.glb"
    scene.export(path)
    loaded = load_scene(path)
    assert len(loaded.faces) == 4 + 12
    # The tetrahedron moved by +10 in x; the box turned 90 degrees about z (x and y swapped).
    lo, hi = loaded.vertices.min(0), loaded.vertices.max(0)
    np.testing.assert_allclose(lo, [-1.0, -0.5, -1.5], atol=1e-6)
    np.testing.assert_allclose(hi, [11.0, 1.0, 1.5], atol=1e-6)


def test_transforms_apply_first_to_last(tmp_path):
    _tetrahedron().export(tmp_path / "tet.obj")
    transforms = [{"scale": 2.0}, {"rotate": {"axis": [0, 0, 1], "degrees": 90}},
                  {"translate": [1, 2, 3]}, {"scale": [1, 1, -1]}]
    scene = load_scene(_write(tmp_path / "s.json", {"mesh": "tet.obj", "transforms": transforms}))
    v, _ = load_mesh(tmp_path / "tet.obj")
    # By hand: scale 2, then (x, y) -> (-y, x), then translate, then mirror z.
    p = 2.0 * v.astype(np.float64)
    p = np.stack([-p[:, 1], p[:, 0], p[:, 2]], axis=1) + [1, 2, 3]
    p[:, 2] *= -1
    np.testing.assert_allclose(scene.vertices, p, atol=1e-6)
    matrix = [[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    moved = load_scene(_write(tmp_path / "m.json", {"mesh": "tet.obj", "transforms": [matrix]}))
    np.testing.assert_allclose(moved.vertices, v + [5, 0, 0])
    assert np.array_equal(apply_transform(transform_matrix([]), v), v)


def test_camera_in_a_scene_file(tmp_path):
    _tetrahedron().export(tmp_path / "tet.obj")
    camera = {"position": [0, 0, 5], "target": [0, 0, 0], "fov": 30, "width": 20, "height": 10}
    scene = load_scene(_write(tmp_path / "s.json", {"mesh": "tet.obj", "camera": camera}))
    assert (scene.camera.width, scene.camera.height, scene.camera.fov) == (20, 10, 30.0)
    assert scene.camera.up.tolist() == [0, 1, 0]
    no_camera = load_scene(_write(tmp_path / "n.json", {"mesh": "tet.obj", "camera": None}))
    assert no_camera.camera is None


GOOD_CAMERA = {"position": [0, 0, 5], "target": [0, 0, 0]}


@pytest.mark.parametrize("data, message", [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "JSON object"),
    ({}, 'missing "mesh"'),
    ({"mesh": 3}, "mesh: 3"),
    ({"mesh": "absent.obj"}, "absent.obj: no such file"),
    ({"mesh": "tet.obj", "lights": []}, "unknown key 'lights'"),
    ({"mesh": "tet.obj", "camera": [0, 0, 5]}, "camera: expected an object"),
    ({"mesh": "tet.obj", "camera": {"target": [0, 0, 0]}}, "camera: missing 'position'"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "fov": 0}}, "camera fov"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "fov": "45"}}, "camera fov"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "width": -3}}, "camera width"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "height": 2.5}}, "camera height"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "position": [0, 0]}}, "camera position"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "position": [0, 0, "x"]}}, "camera position"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "target": [0, 0, 5]}}, "same point"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "up": [0, 0, 2]}}, "parallel"),
    ({"mesh": "tet.obj", "camera": {**GOOD_CAMERA, "zoom": 2}}, "unknown key 'zoom'"),
    ({"mesh": "tet.obj", "transforms": {"scale": 2}}, "transforms: expected a list"),
    ({"mesh": "tet.obj", "transforms": [{"shear": 1}]}, r"transforms\[0\]: unknown transform 'shear'"),
    ({"mesh": "tet.obj", "transforms": [{"scale": 1}, {"scale": 0}]}, r"transforms\[1\] scale.*zero"),
    ({"mesh": "tet.obj", "transforms": [{"translate": [1, 2]}]}, r"transforms\[0\] translate"),
    ({"mesh": "tet.obj", "transforms": [{"rotate": {"axis": [0, 0, 0], "degrees": 9}}]}, "zero vector"),
    ({"mesh": "tet.obj", "transforms": [{"rotate": [0, 1, 0, 90]}]}, r"transforms\[0\] rotate"),
    ({"mesh": "tet.obj", "transforms": [[[1, 0, 0], [0, 1, 0], [0, 0, 1]]]}, r"transforms\[0\]"),
    ({"mesh": "tet.obj", "transforms": [[[0] * 4] * 3 + [[0, 0, 0, 1]]]}, "singular"),
    ({"mesh": "tet.obj", "transforms": [{"scale": 1e39}]}, "overflows float32"),
])
def test_bad_scene_descriptions_name_the_problem(tmp_path, data, message):
    _tetrahedron().export(tmp_path / "tet.obj")
    path = _write(tmp_path / "bad.json", data)
    with pytest.raises(ValueError, match=message) as info:
        load_scene(path)
    assert str(path) in str(info.value)


def test_missing_scene_file_and_nested_scene(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load_scene(tmp_path / "absent.json")
    _write(tmp_path / "inner.json", {"mesh": "x.obj"})
    with pytest.raises(ValueError, match="scene description, not a mesh"):
        load_scene(_write(tmp_path / "outer.json", {"mesh": "inner.json"}))


# -- what ships in the package: lbvh.data, shipped names, the views file --------------------

def test_the_shipped_teapot_is_the_scenes_teapot():
    import lbvh.data

    v, f = lbvh.data.teapot()
    assert v.dtype == np.float32 and f.dtype == np.uint32 and v.shape == (3644, 3) and f.shape == (6320, 3)
    ref_v, ref_f = load_mesh(SCENES / "teapot.obj")        # through trimesh
    assert np.array_equal(v, ref_v) and np.array_equal(f, ref_f)
    assert lbvh.data.path("teapot").read_bytes() == (SCENES / "teapot.obj").read_bytes()
    assert lbvh.data.MESHES == ("teapot",)
    v[0] = 99.0                                             # every call gives new arrays
    assert not np.array_equal(lbvh.data.mesh("teapot")[0], v)
    with pytest.raises(ValueError, match=r"'cow' is not a mesh that ships with lbvh \(shipped: teapot\)"):
        lbvh.data.path("cow")
    notes = lbvh.data.path("teapot").parent / "licenses" / "common-3d-test-models_README.md"
    assert notes.read_bytes() == (SCENES / "licenses" / "common-3d-test-models_README.md").read_bytes()


def test_load_scene_takes_a_shipped_name_and_a_file_of_that_name_wins(tmp_path, monkeypatch):
    import lbvh.data
    from lbvh.files import find_scene

    monkeypatch.chdir(tmp_path)
    scene = load_scene("teapot")
    assert scene.name == "teapot" and len(scene.faces) == 6320 and scene.camera is None
    assert find_scene("teapot") == lbvh.data.path("teapot")
    _tetrahedron().export(tmp_path / "tet.obj")
    (tmp_path / "teapot").symlink_to(tmp_path / "tet.obj")    # a file named teapot, here
    assert find_scene("teapot") == Path("teapot")
    with pytest.raises(ValueError, match="teapot: unknown mesh format"):
        load_scene("teapot")
    with pytest.raises(ValueError, match="teapt: no such file, nor a mesh that ships with lbvh"):
        load_scene("teapt")
    with pytest.raises(ValueError, match="^absent.obj: no such file$"):   # a path: no hint
        load_scene("absent.obj")


def test_the_shipped_views_are_the_bench_cameras():
    from lbvh.camera import load_views, view_camera

    assert not (REPO / "bench" / "cameras.json").exists()   # one set of views: the shipped one
    views = load_views()
    assert "_comment" not in views and {"teapot", "sponza", "sponza-atrium"} <= set(views)
    for name in views:
        camera = view_camera(name, size=(8, 6))
        assert (camera.width, camera.height) == (8, 6)
    atrium = view_camera("sponza-atrium")
    assert atrium.position.tolist() == [75, 25, -3] and atrium.fov == 55
    assert (atrium.width, atrium.height) == (640, 480)


@pytest.mark.parametrize("text, message", [
    (None, "no such views file"),
    ("{oops", "not valid JSON"),
    ("[]", "a views file is a JSON object of named cameras"),
    ('{"a": [1, 2, 3]}', "view 'a': expected a camera object"),
])
def test_bad_views_files_name_the_file(tmp_path, text, message):
    from lbvh.camera import load_views

    path = tmp_path / "views.json"
    if text is not None:
        path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        load_views(path)
    assert str(path) in str(info.value)


def test_a_bad_or_unknown_view_names_the_file_and_the_view(tmp_path):
    from lbvh.camera import view_camera

    path = _write(tmp_path / "views.json", {"good": GOOD_CAMERA, "wide": {**GOOD_CAMERA, "fov": 190}})
    assert view_camera("good", path).fov == 45.0
    with pytest.raises(ValueError, match=r"views.json: view 'wide': camera fov: 190"):
        view_camera("wide", path)
    with pytest.raises(ValueError, match=r"views.json: no view 'bad' \(views: good, wide\)"):
        view_camera("bad", path)
