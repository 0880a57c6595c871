"""Bad input to lbvh.build: a ValueError that names the problem, and nothing built."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import random_soup

GOOD_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
GOOD_F = np.array([[0, 1, 2], [0, 2, 3]], np.int32)


@pytest.mark.parametrize("vertices, faces, message", [
    (np.array([[0, 0, 0], [1, np.nan, 0], [0, 1, 0]], np.float32), [[0, 1, 2]], "vertex 1 has a NaN"),
    (np.array([[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], np.float64), [[0, 1, 2]], "vertex 2 has a NaN or infinite"),
    (np.array([[0, 0, 0], [1e39, 0, 0], [0, 1, 0]], np.float64), [[0, 1, 2]], "vertex 1 .* overflows float32"),
    (GOOD_V, [[0, 1, 2], [0, 1, 4]], r"face 1 \[0, 1, 4\] indexes a vertex outside \[0, 4\)"),
    (GOOD_V, [[0, 1, 2], [0, -1, 3]], "face 1 .* negative vertex index"),
    (GOOD_V, [[0, 1, 2, 3]], "faces have 4 vertices, only triangles"),
    (GOOD_V, [[0, 1, 2], [0, 1]], "ragged|every face must be a triangle"),
    (GOOD_V, np.zeros((0, 3), np.int32), "no triangles"),
    (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), "no vertices"),
    (GOOD_V, np.array([[0, 1, 2]], np.float32), "indices must be integers"),
    (GOOD_V[:, :2], GOOD_F, r"shape \(4, 2\), expected \(V, 3\)"),
    (GOOD_V.astype(str), GOOD_F, "not a real number type"),
    (GOOD_V, GOOD_F.ravel(), r"shape \(6,\), expected \(F, 3\)"),
])
def test_bad_mesh_raises_named_error(vertices, faces, message):
    with pytest.raises(ValueError, match=message):
        lbvh.build(vertices, faces)


def test_faces_missing():
    with pytest.raises(ValueError, match="faces: missing"):
        lbvh.build(GOOD_V)


@pytest.mark.parametrize("kwargs, message", [
    ({"key_bits": 31}, "key_bits"),
    ({"builder": "octree"}, "builder"),
    ({"bogus": 1}, "unknown option"),
    ({"collapse": True, "bogus": 1}, "unknown option.*collapse: bogus"),
    ({"collapse": True, "max_leaf_size": 0}, "max_leaf_size"),
    ({"builder": "sah", "collapse": True}, "collapse: only for builder='lbvh'"),
])
def test_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        lbvh.build(GOOD_V, GOOD_F, **kwargs)


def test_convertible_dtypes_are_accepted():
    bvh = lbvh.build(GOOD_V.astype(np.float64), GOOD_F.astype(np.uint64))
    bvh.validate()
    assert bvh.vertices.dtype == np.float32 and bvh.faces.dtype == np.uint32


def test_bad_refit_leaves_tree_usable():
    bvh = lbvh.build(GOOD_V, GOOD_F)
    before = bvh.nodes.copy()
    bad = GOOD_V.copy()
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="vertex 3"):
        bvh.refit(bad)
    with pytest.raises(ValueError, match="shape"):
        bvh.refit(GOOD_V[:3])
    assert np.array_equal(bvh.nodes, before)
    bvh.validate()


def test_unknown_device_names_the_choices():
    with pytest.raises(lbvh.DeviceError, match="no OpenCL device matches"):
        lbvh.build(GOOD_V, GOOD_F, device="no-such-device-xyz")


def test_a_mesh_too_large_for_the_device_is_refused_before_upload(ctx):
    from lbvh.builders.pipeline import check_fits
    too_many = int(ctx.device.max_mem_alloc_size) // 64 + 1  # 32 B x (2F - 1) nodes
    with pytest.raises(lbvh.DeviceError, match="node buffer, more than .* largest allocation"):
        check_fits(ctx, too_many)
    check_fits(ctx, 1000)  # small meshes pass


# -- what a new user passes (issue 19, item 1) ---------------------------------------

def test_a_path_is_loaded(tmp_path):
    import trimesh
    path = tmp_path / "tet.obj"
    trimesh.Trimesh(GOOD_V, GOOD_F, process=False).export(path)
    for given in (str(path), path):
        bvh = lbvh.build(given)
        bvh.validate()
        assert bvh.mesh.num_prims == len(GOOD_F)
    with pytest.raises(ValueError, match="a path .* together with faces"):
        lbvh.build(str(path), GOOD_F)


def test_a_missing_or_empty_file_names_itself(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.obj: no such file"):
        lbvh.build(str(tmp_path / "absent.obj"))
    with pytest.raises(ValueError, match="absent.obj: no such file"):   # also a ValueError
        lbvh.build(tmp_path / "absent.obj")
    (tmp_path / "empty.obj").write_text("")
    with pytest.raises(ValueError, match="empty.obj: the file is empty"):
        lbvh.build(tmp_path / "empty.obj")


@pytest.mark.parametrize("make, message", [
    (lambda t: t.PointCloud(GOOD_V), "a trimesh.PointCloud has vertices but no faces"),
    (lambda t: 42, "got a int alone; pass vertices and faces"),
    (lambda t: GOOD_V, "got a numpy.ndarray alone; pass vertices and faces"),
])
def test_what_was_passed_is_named_with_what_to_pass(make, message):
    import trimesh
    with pytest.raises(ValueError, match=message):
        lbvh.build(make(trimesh))


def test_a_trimesh_scene_becomes_a_scene_of_instances_and_as_mesh_says_how():
    import trimesh
    source = trimesh.Scene([trimesh.creation.box(), trimesh.creation.icosphere()])
    assert isinstance(lbvh.build(source), lbvh.Scene)
    from lbvh.mesh import as_mesh
    with pytest.raises(ValueError, match=r"a trimesh.Scene of 2 geometries .* scene.to_mesh\(\)"):
        as_mesh(source)


def test_a_mesh_with_its_faces_again_says_pass_it_alone():
    import trimesh
    mesh = trimesh.Trimesh(GOOD_V, GOOD_F, process=False)
    with pytest.raises(ValueError, match=r"trimesh.Trimesh was passed together with faces; "
                                         r"pass the mesh alone"):
        lbvh.build(mesh, mesh.faces)


# -- one name, one meaning (item 2) ----------------------------------------------------

@pytest.mark.parametrize("asked", ["auto", 30, 63])
def test_the_reported_key_bits_build_the_same_tree_again(asked):
    v, f = random_soup(2000, seed=3)
    first = lbvh.build(v, f, key_bits=asked)
    report = first.report()
    assert report.key_bits in (30, 63)
    assert f"morton keys: {report.key_bits}-bit" in str(report)
    again = lbvh.build(v, f, key_bits=report.key_bits)
    assert again.report().key_bits == report.key_bits
    assert np.array_equal(again.nodes, first.nodes)


def test_lbvh_info_json_and_text_say_the_same_key_bits(tmp_path, capsys):
    import json

    import trimesh
    from lbvh.cli import main
    path = tmp_path / "tet.obj"
    trimesh.Trimesh(GOOD_V, GOOD_F, process=False).export(path)
    assert main(["info", str(path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert main(["info", str(path)]) == 0
    assert report["key_bits"] == 30 and "morton keys: 30-bit" in capsys.readouterr().out
