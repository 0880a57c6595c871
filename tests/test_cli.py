"""The command line: `lbvh render`, `lbvh info`, `lbvh devices`; exit codes and one-line errors."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import lbvh.data
from lbvh.cli import main, parse_size, parse_vector
from lbvh.rendering.image import read_image
from lbvh.version import __version__

REPO = Path(__file__).resolve().parents[1]
CORNELL = str(REPO / "scenes" / "cornell.json")
TEAPOT = str(REPO / "scenes" / "teapot.json")
#: A camera in front of the teapot, as a scene file or views file holds it.
FRONT = {"position": [0.5, 2.0, 7.0], "target": [0.0, 1.2, 0.0], "up": [0, 1, 0], "fov": 35}


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _assert_one_line_error(code, err, fragment):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("lbvh: error:") and fragment in lines[0], err
    assert "Traceback" not in err


def test_render_writes_the_image_and_prints_timings(capsys, tmp_path):
    out_file = tmp_path / "cornell.png"
    code, out, err = _run(capsys, "render", CORNELL, "-o", str(out_file), "--size", "24x16")
    assert code == 0, err
    image = read_image(out_file)
    assert image.shape == (16, 24, 3) and image.dtype == np.uint8 and image.max() > 0
    for label in ("build:", "render:", "Mrays/s", "overflow:", "0 stack overflows", "wrote:"):
        assert label in out


@pytest.mark.parametrize("mode, suffix, channels", [
    ("depth", ".exr", 1), ("heatmap", ".exr", 1), ("diffuse", ".png", 1), ("ao", ".png", 1),
    ("heatmap", ".png", 3),
])
def test_render_modes_and_formats(capsys, tmp_path, mode, suffix, channels):
    out_file = tmp_path / f"x{suffix}"
    code, out, err = _run(capsys, "render", CORNELL, "-o", str(out_file), "--size", "12x10",
                          "--mode", mode, "--ao-samples", "2", "--builder", "sah")
    assert code == 0, err
    image = read_image(out_file)
    assert image.shape == (10, 12, channels)
    if mode == "depth":     # looking into the box: it fills most of the (wider) image
        assert np.isfinite(image).mean() > 0.75 and (image > 0).all()
    if mode == "heatmap" and suffix == ".exr":
        assert (image >= 1).all() and "cost:" in out


def test_render_frames_a_bare_mesh(capsys, tmp_path):
    code, out, err = _run(capsys, "render", str(REPO / "scenes" / "suzanne.obj"),
                          "-o", str(tmp_path / "s.exr"), "--mode", "depth", "--size", "16x12",
                          "--keys", "63", "--triangle-test", "moller")
    assert code == 0, err
    depth = read_image(tmp_path / "s.exr")
    hit = np.isfinite(depth)
    # Framed from the bounds: the mesh is in view and does not touch the border.
    assert hit.sum() > 10
    assert not hit[0].any() and not hit[-1].any() and not hit[:, 0].any() and not hit[:, -1].any()


@pytest.mark.parametrize("argv, fragment", [
    (["render", CORNELL, "-o", "{tmp}/x.png", "--size", "64by48"], "--size: '64by48'"),
    (["render", CORNELL, "-o", "{tmp}/x.png", "--size", "0x10"], "1 to 16384"),
    (["render", CORNELL, "-o", "{tmp}/x.png", "--mode", "fancy"], "invalid choice: 'fancy'"),
    (["render", CORNELL, "-o", "{tmp}/x.bmp"], "unknown image format '.bmp'"),
    (["render", CORNELL, "-o", "{tmp}/missing/x.png", "--size", "4x4"], "cannot write"),
    (["render", CORNELL, "-o", "{tmp}/x.png", "--ao-samples", "0"], "--ao-samples"),
    (["render", CORNELL, "-o", "{tmp}/x.png", "--ao-samples", "many"], "invalid int value"),
    (["render", "{tmp}/absent.obj", "-o", "{tmp}/x.png"], "absent.obj: no such file"),
    (["render", "{tmp}/bad.json", "-o", "{tmp}/x.png"], "not valid JSON"),
    (["render", CORNELL], "-o/--output"),
    (["info", "{tmp}/absent.obj"], "no such file"),
    (["paint", CORNELL], "invalid choice: 'paint'"),
    # the camera options
    (["render", "teapot", "-o", "{tmp}/x.png", "--eye", "1,2"], "--eye: '1,2' is not X,Y,Z"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--eye", "1,2,3,4"], "is not X,Y,Z"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--target", "a,b,c"], "--target: 'a,b,c' is not"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--eye", "1,nan,2"], "NaN or infinite"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--up", "0,inf,0"], "--up: '0,inf,0' has a NaN"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--up", "0,0,0"], "camera up: the zero vector"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--eye", "-1,2,3"], "write --eye=-1,2,3"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--eye", "0,1,0", "--target", "0,1,0"], "same point"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--fov", "nan"], "--fov: nan degrees"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--fov", "180"], "--fov: 180.0 degrees"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--fov", "wide"], "invalid float value: 'wide'"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--view", "nope"], "no view 'nope' (views: teapot"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--view", "a", "--views", "{tmp}/absent.json"],
     "absent.json: no such views file"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--view", "a", "--views", "{tmp}/bad.json"],
     "bad.json: not valid JSON"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--view", "a", "--views", "{tmp}/list.json"],
     "a views file is a JSON object"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--view", "flat", "--views", "{tmp}/views.json"],
     "view 'flat': camera fov: 0"),
    (["render", "teapot", "-o", "{tmp}/x.png", "--views", "{tmp}/views.json"], "give --view NAME"),
    (["render", "teapt", "-o", "{tmp}/x.png"], "teapt: no such file, nor a mesh that ships"),
])
def test_errors_are_one_line_and_exit_2(capsys, tmp_path, argv, fragment):
    (tmp_path / "bad.json").write_text("{oops")
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "views.json").write_text(json.dumps({"flat": {**FRONT, "fov": 0}}))
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code, out, err = _run(capsys, *argv)
    _assert_one_line_error(code, err, fragment)
    assert not (tmp_path / "x.png").exists()


def test_unknown_device_exits_2_without_traceback(capsys, tmp_path):
    # Device errors may add lines (the devices available, a kernel build log).
    code, out, err = _run(capsys, "render", CORNELL, "-o", str(tmp_path / "x.png"),
                          "--device", "no-such-device-xyz")
    assert code == 2 and err.startswith("lbvh: error: no OpenCL device matches 'no-such-device-xyz'")
    assert "Traceback" not in err and not (tmp_path / "x.png").exists()


def test_parse_size():
    assert parse_size("640x480") == (640, 480)
    assert parse_size(" 8 X 6 ") == (8, 6)
    for bad in ("640", "x480", "-1x5", "1.5x2", "99999x2"):
        with pytest.raises(ValueError, match="--size"):
            parse_size(bad)


def test_info_reads_a_scene_description(capsys):
    code, out, err = _run(capsys, "info", CORNELL, "--validate")
    assert code == 0, err
    assert "triangles:   32" in out and "validate:    ok" in out
    code, out, err = _run(capsys, "info", CORNELL, "--json")
    assert code == 0 and json.loads(out)["num_triangles"] == 32


def test_info_builds_with_smaller_treelets(capsys):
    code, out, err = _run(capsys, "info", CORNELL, "--treelets", "1", "--treelet-leaves", "5",
                          "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["builder"] == "lbvh+treelets1-5"
    code, out, err = _run(capsys, "info", CORNELL, "--treelets", "1", "--treelet-leaves", "5",
                          "--validate")
    assert code == 0 and "validate:    ok" in out, err


def test_info_restructures_later_rounds_over_large_subtrees_only(capsys):
    """--treelet-min-leaves reaches the build: beyond every subtree, later rounds
    keep the one-round tree; a bad value is refused by name."""
    def mean_leaf_depth(rounds, *extra):
        code, out, err = _run(capsys, "info", TEAPOT, "--treelets", rounds, "--json", *extra)
        assert code == 0, err
        return json.loads(out)["mean_leaf_depth"]
    one = mean_leaf_depth("1")
    assert mean_leaf_depth("2", "--treelet-min-leaves", "1000000") == one
    assert mean_leaf_depth("2", "--treelet-min-leaves", "0") != one
    code, out, err = _run(capsys, "info", TEAPOT, "--treelets", "2", "--treelet-min-leaves", "-3")
    assert code != 0 and "treelet_min_leaves" in err


def test_devices_lists_the_default(capsys):
    code, out, err = _run(capsys, "devices")
    assert code == 0 and "default:" in out
    assert "self-test: passed" in out


def test_devices_without_self_test(capsys):
    code, out, err = _run(capsys, "devices", "--no-self-test")
    assert code == 0 and "self-test: not run" in out


def test_the_installed_command_runs_in_a_subprocess(tmp_path):
    out_file = tmp_path / "teapot.png"
    env = dict(os.environ)
    done = subprocess.run([sys.executable, "-m", "lbvh.cli", "render", str(REPO / "scenes" / "teapot.json"),
                           "-o", str(out_file), "--size", "32x24", "--mode", "normals"],
                          capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    assert out_file.is_file() and "Mrays/s" in done.stdout
    failed = subprocess.run([sys.executable, "-m", "lbvh.cli", "render", str(REPO / "scenes" / "teapot.json"),
                             "-o", str(tmp_path / "t.png"), "--size", "wide"],
                            capture_output=True, text=True, timeout=120, env=env)
    assert failed.returncode == 2 and failed.stderr.count("\n") == 1 and "Traceback" not in failed.stderr


# -- the version, the shipped mesh, the camera options -------------------------------------

def test_version(capsys):
    code, out, err = _run(capsys, "--version")
    assert code == 0 and out.strip() == f"lbvh {__version__}" and not err


def _camera_line(out: str) -> str:
    lines = [line for line in out.splitlines() if line.startswith("camera:")]
    assert len(lines) == 1, out
    return lines[0]


def _depth(capsys, tmp_path, scene, *options, name="d.exr"):
    """Render ``scene``'s depth at 24x18; the image and the camera: line."""
    code, out, err = _run(capsys, "render", str(scene), "-o", str(tmp_path / name), "--mode",
                          "depth", "--size", "24x18", *options)
    assert code == 0, err
    return read_image(tmp_path / name)[:, :, 0], _camera_line(out)


def _scene_file(tmp_path, camera) -> Path:
    """A scene description of the shipped teapot with ``camera``."""
    path = tmp_path / "teapot_scene.json"
    path.write_text(json.dumps({"mesh": str(lbvh.data.path("teapot")), "camera": camera}))
    return path


def test_render_and_info_take_a_shipped_mesh_by_name(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)          # no file called "teapot" here
    code, out, err = _run(capsys, "info", "teapot")
    assert code == 0, err
    assert "triangles:   6320" in out.replace(",", "") and "shipped with lbvh" in out
    depth, line = _depth(capsys, tmp_path, "teapot")
    assert "framed automatically" in line
    hit = np.isfinite(depth)
    assert hit.mean() > 0.1 and not hit[0].any() and not hit[:, 0].any()


def test_a_file_of_the_shipped_name_wins(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "teapot").write_text("v 0 0 0\n")   # a file named teapot, not a mesh format
    code, out, err = _run(capsys, "info", "teapot")
    _assert_one_line_error(code, err, "teapot: unknown mesh format")


def test_eye_and_target_give_the_camera_a_scene_file_would(capsys, tmp_path):
    from_file, line = _depth(capsys, tmp_path, _scene_file(tmp_path, FRONT), name="a.exr")
    assert "from the scene file:" in line
    options = ["--eye=0.5,2,7", "--target", "0 1.2 0", "--up", "0,1,0", "--fov", "35"]
    from_options, line = _depth(capsys, tmp_path, "teapot", *options, name="b.exr")
    assert line.startswith("camera:    from --eye/--target/--up/--fov:")
    assert "--eye=0.5,2,7 --target=0,1.2,0 --up=0,1,0 --fov=35 --size=24x18" in line
    assert np.isfinite(from_file).mean() > 0.1
    assert np.array_equal(from_file, from_options)


def test_eye_and_target_alone_default_up_and_fov(capsys, tmp_path):
    _, line = _depth(capsys, tmp_path, "teapot", "--eye=0.5,2,7", "--target=0,1.2,0")
    assert line.endswith("from --eye/--target: --eye=0.5,2,7 --target=0,1.2,0 --up=0,1,0 "
                         "--fov=45 --size=24x18")


def test_view_from_the_shipped_views_file(capsys, tmp_path):
    views = json.loads(lbvh.data.views_path().read_text())
    by_view, line = _depth(capsys, tmp_path, "teapot", "--view", "teapot", name="a.exr")
    assert "--view teapot from lbvh/data/cameras.json (shipped with lbvh):" in line
    by_file, _ = _depth(capsys, tmp_path, _scene_file(tmp_path, views["teapot"]), name="b.exr")
    assert np.isfinite(by_view).mean() > 0.1 and np.array_equal(by_view, by_file)


def test_view_from_a_views_file_with_an_option_on_top(capsys, tmp_path):
    views = tmp_path / "my_views.json"
    views.write_text(json.dumps({"_comment": "not a view", "front": FRONT,
                                 "other": {"position": [9, 9, 9], "target": [0, 0, 0]}}))
    by_view, line = _depth(capsys, tmp_path, "teapot", "--view", "front", "--views", str(views),
                           "--fov", "50", name="a.exr")
    assert f"--view front from {views}, with --fov:" in line and "--fov=50 " in line
    by_file, _ = _depth(capsys, tmp_path, _scene_file(tmp_path, {**FRONT, "fov": 50}), name="b.exr")
    assert np.isfinite(by_view).mean() > 0.1 and np.array_equal(by_view, by_file)


def test_fov_alone_frames_the_mesh_again(capsys, tmp_path):
    wide, line = _depth(capsys, tmp_path, "teapot", name="a.exr")
    narrow, line = _depth(capsys, tmp_path, "teapot", "--fov", "15", name="b.exr")
    assert "framed automatically, with --fov:" in line and "--fov=15 " in line
    for depth in (wide, narrow):   # the whole teapot in view, away from the border
        hit = np.isfinite(depth)
        assert hit.mean() > 0.1
        assert not (hit[0].any() or hit[-1].any() or hit[:, 0].any() or hit[:, -1].any())
    assert np.nanmin(narrow) > 2 * np.nanmin(wide)   # from further away


def test_eye_alone_keeps_the_target_of_the_camera_it_changes(capsys, tmp_path):
    scene = _scene_file(tmp_path, FRONT)
    _, line = _depth(capsys, tmp_path, scene, "--eye=-7,2,0.5")
    assert "from the scene file, with --eye: --eye=-7,2,0.5 --target=0,1.2,0 --up=0,1,0" in line


def test_up_turns_the_image(capsys, tmp_path):
    camera = {**FRONT, "position": [0.0, 1.2, 7.0]}   # straight down -z
    upright, _ = _depth(capsys, tmp_path, _scene_file(tmp_path, camera), "--size", "16x16",
                        name="a.exr")
    turned, line = _depth(capsys, tmp_path, _scene_file(tmp_path, camera), "--size", "16x16",
                          "--up", "1,0,0", name="b.exr")
    assert "from the scene file, with --up:" in line and "--up=1,0,0" in line
    # up along +x (right along -y): the upright image turned a quarter counter-clockwise
    expected = np.rot90(upright, k=1)
    same = np.isfinite(expected) == np.isfinite(turned)
    assert same.mean() > 0.97 and not np.array_equal(np.isfinite(upright), np.isfinite(turned))
    both = np.isfinite(expected) & np.isfinite(turned)
    np.testing.assert_allclose(turned[both], expected[both], rtol=1e-4)


def test_parse_vector():
    assert parse_vector("--eye", "1,2,3") == (1.0, 2.0, 3.0)
    assert parse_vector("--eye", " -1.5 2e1, 0 ") == (-1.5, 20.0, 0.0)
    for bad in ("", "1,2", "1,2,3,4", "1,,x", "1;2;3"):
        with pytest.raises(ValueError, match="--eye: .* is not X,Y,Z"):
            parse_vector("--eye", bad)
    for bad in ("nan,0,0", "0,inf,0", "0,0,-inf"):
        with pytest.raises(ValueError, match="NaN or infinite"):
            parse_vector("--eye", bad)


# -- lbvh query closest (issue 17) ---------------------------------------------------

def test_query_closest_writes_the_answers_of_closest_points(capsys, tmp_path):
    import lbvh
    rng = np.random.default_rng(0)
    points = rng.uniform(-3, 3, (500, 3)).astype(np.float32)
    np.save(tmp_path / "points.npy", points)
    out = tmp_path / "near.npz"
    assert main(["query", "closest", "teapot", str(tmp_path / "points.npy"), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "points:    500 from" in text and "wrote:" in text
    want = lbvh.build(*lbvh.data.teapot()).closest_points(points)
    with np.load(out) as got:
        for name in ("distance", "prim", "u", "v", "found"):
            assert np.array_equal(got[name], getattr(want, name)), name
    (tmp_path / "points.csv").write_text("\n".join(",".join(map(str, p)) for p in points[:20]))
    assert main(["query", "closest", "teapot", str(tmp_path / "points.csv"), "--json",
                 "--max-distance", "0.5"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["points"] == 20 and summary["found"] == int((want.distance[:20] <= 0.5).sum())


@pytest.mark.parametrize("make, fragment", [
    (lambda d: d / "absent.npy", "absent.npy: no such file"),
    (lambda d: (np.save(d / "flat.npy", np.zeros((4, 2))), d / "flat.npy")[1],
     "points: shape (4, 2), expected (N, 3)"),
    (lambda d: (np.save(d / "nan.npy", np.float32([[0, 0, 0], [np.nan, 1, 1]])), d / "nan.npy")[1],
     "points: point 1 has a NaN"),
    (lambda d: ((d / "bad.txt").write_text("1 2\n3 4 5\n"), d / "bad.txt")[1], "cannot read points"),
])
def test_query_errors_are_one_line_and_exit_2(capsys, tmp_path, make, fragment):
    assert main(["query", "closest", "teapot", str(make(tmp_path))]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lbvh: error:") and fragment in err[0]


@pytest.mark.parametrize("kind", ["signed-distance", "contains"])
def test_query_inside_and_signed_distance(capsys, tmp_path, kind):
    import lbvh
    v, f = lbvh.data.teapot()
    rng = np.random.default_rng(1)
    points = (v.min(0) + (v.max(0) - v.min(0)) * rng.uniform(0, 1, (300, 3))).astype(np.float32)
    np.save(tmp_path / "points.npy", points)
    out = tmp_path / "answers.npz"
    assert main(["query", kind, "teapot", str(tmp_path / "points.npy"), "-o", str(out),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    bvh = lbvh.build(v, f)
    with np.load(out) as got:
        if kind == "contains":
            assert np.array_equal(got["contains"], bvh.contains(points))
            assert np.array_equal(got["winding"], bvh.winding_numbers(points))
        else:
            assert np.array_equal(got["signed_distance"], bvh.signed_distance(points))
    assert summary["inside"] == int(bvh.contains(points).sum()) and summary["points"] == 300


def test_query_ray_counts_and_all_hits(capsys, tmp_path):
    import lbvh
    v, f = lbvh.data.teapot()
    rng = np.random.default_rng(2)
    o = rng.uniform(-4, 4, (200, 3)).astype(np.float32)
    d = (v[rng.integers(0, len(v), 200)] - o).astype(np.float32)
    np.savetxt(tmp_path / "rays.csv", np.hstack([o, d]), delimiter=",")
    o, d = np.loadtxt(tmp_path / "rays.csv", delimiter=",", ndmin=2).reshape(-1, 2, 3).transpose(1, 0, 2)
    bvh = lbvh.build(v, f)
    assert main(["query", "count-hits", "teapot", str(tmp_path / "rays.csv"), "-o",
                 str(tmp_path / "c.npz")]) == 0
    text = capsys.readouterr().out
    assert "rays:      200 from" in text and "hits:" in text
    with np.load(tmp_path / "c.npz") as got:
        assert np.array_equal(got["counts"], bvh.count_hits(o, d))
    assert main(["query", "all-hits", "teapot", str(tmp_path / "rays.csv"), "--max-hits", "1",
                 "-o", str(tmp_path / "a.npz"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    want = bvh.all_hits(o, d, max_hits=1)
    with np.load(tmp_path / "a.npz") as got:
        for name in ("offsets", "t", "prim", "total"):
            assert np.array_equal(got[name], getattr(want, name)), name
    assert summary["hits"] == len(want.t) and summary["rays"] == 200
    # signed counts: the API's, and refused for another kind
    assert main(["query", "count-hits", "teapot", str(tmp_path / "rays.csv"), "--signed",
                 "-o", str(tmp_path / "s.npz"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    signed = bvh.count_hits(o, d, signed=True)
    with np.load(tmp_path / "s.npz") as got:
        assert np.array_equal(got["counts"], signed)
    assert summary["signed_sum"] == int(signed.sum()) and (signed != 0).any()
    assert summary["rays_negative"] == int((signed < 0).sum())
    assert main(["query", "all-hits", "teapot", str(tmp_path / "rays.csv"), "--signed"]) == 2
    assert "--signed: only for count-hits" in capsys.readouterr().err
    # rays of the wrong shape: one line, exit 2
    np.save(tmp_path / "bad.npy", np.zeros((3, 3)))
    assert main(["query", "count-hits", "teapot", str(tmp_path / "bad.npy")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "expected (N, 6)" in err[0]


def test_render_global_order_gives_the_same_image(capsys, tmp_path):
    base = ["render", "teapot", "--size", "48x32", "--mode", "depth"]
    assert main(base + ["-o", str(tmp_path / "a.exr")]) == 0
    assert main(base + ["-o", str(tmp_path / "b.exr"), "--order", "global"]) == 0
    assert "global order" in capsys.readouterr().out
    from lbvh.rendering.image import read_image
    assert np.array_equal(read_image(tmp_path / "a.exr"), read_image(tmp_path / "b.exr"))


def test_render_with_a_ray_sampled_sah_tree(capsys, tmp_path):
    base = ["render", "teapot", "--size", "48x32", "--mode", "depth", "--builder", "sah"]
    assert main(base + ["-o", str(tmp_path / "a.exr")]) == 0
    assert main(base + ["-o", str(tmp_path / "b.exr"), "--ray-sample", "12x8"]) == 0
    assert "splits by 12x8 camera rays" in capsys.readouterr().out
    # another tree, the same image: every hit is the same triangle test's
    assert np.array_equal(read_image(tmp_path / "a.exr"), read_image(tmp_path / "b.exr"))


def _placed_meshes_file(path) -> None:
    import trimesh
    source = trimesh.Scene()
    box = trimesh.creation.box()
    source.add_geometry(box, geom_name="box", node_name="left",
                        transform=trimesh.transformations.translation_matrix([-1.5, 0, 0]))
    source.graph.update(frame_to="right", geometry="box",
                        matrix=trimesh.transformations.translation_matrix([1.5, 0, 0])
                        @ trimesh.transformations.rotation_matrix(0.6, [0, 1, 0]))
    source.add_geometry(trimesh.creation.icosphere(), geom_name="ball", node_name="ball",
                        transform=trimesh.transformations.translation_matrix([0, 1.6, 0]))
    source.export(str(path))


def test_a_file_of_placed_meshes_keeps_its_instances(capsys, tmp_path):
    import lbvh
    from lbvh.rendering.image import read_image
    from lbvh.rendering.render import render_reference
    from lbvh.files import load_scene
    path = tmp_path / "two.glb"
    _placed_meshes_file(path)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["instances"] == 3 and len(info["meshes"]) == 2   # the box is built once
    assert sorted(info["instance_names"]) == ["ball", "left", "right"]
    out = tmp_path / "depth.exr"
    assert main(["render", str(path), "-o", str(out), "--size", "64x48", "--mode", "depth"]) == 0
    assert "3 instances of 2 meshes" in capsys.readouterr().out
    scene = load_scene(path)
    assert isinstance(lbvh.build(scene.extras["instances"]), lbvh.Scene)
    from lbvh.cli import choose_camera, parse_size
    import argparse
    args = argparse.Namespace(eye=None, target=None, up=None, fov=None, view=None, views=None)
    camera, _ = choose_camera(args, scene, parse_size("64x48"))   # the view the render used
    want = render_reference(scene.vertices, scene.faces, camera, "depth")
    got = read_image(out)
    hit = np.isfinite(want) & np.isfinite(got)
    assert (np.isfinite(want) == np.isfinite(got)).mean() > 0.99
    assert np.allclose(got[hit], want[hit], rtol=1e-4)


def test_query_through_a_file_of_placed_meshes(capsys, tmp_path):
    """lbvh query on a glTF that places meshes answers through its lbvh.Scene, naming the
    instance of each answer, closest points under a shear too."""
    import lbvh
    from lbvh.files import load_scene
    path = tmp_path / "two.glb"
    _placed_meshes_file(path)
    scene = lbvh.build(load_scene(path).extras["instances"])
    v, f, _ = scene.flattened()
    rng = np.random.default_rng(3)
    points = (v.min(0) + (v.max(0) - v.min(0)) * rng.uniform(-0.2, 1.2, (300, 3))).astype(np.float32)
    np.save(tmp_path / "p.npy", points)
    o = rng.uniform(-4, 4, (200, 3)).astype(np.float32)
    d = (v[f[rng.integers(0, len(f), 200)]].mean(axis=1) - o).astype(np.float32)
    np.save(tmp_path / "rays.npy", np.hstack([o, d]))
    out = tmp_path / "out.npz"
    assert main(["query", "closest", str(path), str(tmp_path / "p.npy"), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "3 instances of 2 meshes" in text and "instance" in text.split("wrote:")[1]
    closest = scene.closest_points(points)
    distance, near, instance, prim = closest
    with np.load(out) as got:
        for name, want in (("distance", distance), ("points", near), ("instance", instance),
                           ("prim", prim), ("u", closest.u), ("v", closest.v),
                           ("found", instance >= 0)):
            assert np.array_equal(got[name], want), name
    assert set(np.unique(instance)) == {0, 1, 2}
    for kind, name, want in (("signed-distance", "signed_distance", scene.signed_distance(points)),
                             ("contains", "winding", scene.winding_numbers(points))):
        assert main(["query", kind, str(path), str(tmp_path / "p.npy"), "-o", str(out)]) == 0
        with np.load(out) as got:
            assert np.array_equal(got[name], want), kind
    assert scene.contains(points).any()
    capsys.readouterr()
    assert main(["query", "count-hits", str(path), str(tmp_path / "rays.npy"), "-o", str(out),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    counts = scene.count_hits(o, d)
    assert summary["instances"] == 3 and summary["hits"] == int(counts.sum()) > 0
    with np.load(out) as got:
        assert np.array_equal(got["counts"], counts)
    assert main(["query", "count-hits", str(path), str(tmp_path / "rays.npy"), "--signed"]) == 2
    assert "placed meshes is counted unsigned only" in capsys.readouterr().err
    assert main(["query", "all-hits", str(path), str(tmp_path / "rays.npy"), "-o", str(out),
                 "--max-hits", "2", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    want = scene.all_hits(o, d, max_hits=2)
    assert summary["instances_hit"] == 3 and summary["truncated"] == int(want.truncated.sum())
    with np.load(out) as got:
        for name in ("offsets", "t", "prim", "instance", "u", "v", "total"):
            assert np.array_equal(got[name], getattr(want, name)), name
    # a sheared instance keeps no distances in proportion: closest points answer in world
    # space all the same (the flattened copy's, within the scene's bound)
    import trimesh
    sheared = trimesh.Scene()
    sheared.add_geometry(trimesh.creation.box(), geom_name="box", node_name="plain")
    shear = np.eye(4)
    shear[0, 1], shear[:3, 3] = 0.5, [3, 0, 0]
    sheared.add_geometry(trimesh.creation.box(), geom_name="box2", node_name="sheared",
                         transform=shear)
    sheared.export(str(tmp_path / "sheared.glb"))
    assert main(["query", "closest", str(tmp_path / "sheared.glb"), str(tmp_path / "p.npy"),
                 "-o", str(out)]) == 0
    from lbvh.queries.closest import closest_points_numpy
    from lbvh.metrics.error_bound import scene_closest_distance_bound
    sheared_scene = lbvh.build(load_scene(tmp_path / "sheared.glb").extras["instances"])
    assert sheared_scene.num_instances == 2
    sv, sf, _ = sheared_scene.flattened()
    with np.load(out) as got:
        assert np.array_equal(got["distance"], sheared_scene.closest_points(points).distance)
        assert (np.abs(got["distance"] - closest_points_numpy(sv, sf, points)[0])
                <= scene_closest_distance_bound(sv, points)).all()
        assert set(np.unique(got["instance"])) == {0, 1}
    assert main(["query", "count-hits", str(tmp_path / "sheared.glb"),
                 str(tmp_path / "rays.npy")]) == 0
    assert main(["query", "contains", str(tmp_path / "sheared.glb"), str(tmp_path / "p.npy")]) == 0


# -- lbvh query: ray kinds, output formats, wording ----------------------------------

def _teapot_rays(tmp_path, n, seed=3):
    import lbvh
    v, f = lbvh.data.teapot()
    rng = np.random.default_rng(seed)
    o = rng.uniform(-4, 4, (n, 3)).astype(np.float32)
    d = (v[rng.integers(0, len(v), n)] - o).astype(np.float32)
    np.save(tmp_path / "rays.npy", np.hstack([o, d]))
    return lbvh.build(v, f), o, d


def test_query_closest_and_any_hit_in_every_output_format(capsys, tmp_path):
    bvh, o, d = _teapot_rays(tmp_path, 300)
    want = bvh.intersect(o, d)
    assert main(["query", "closest-hit", "teapot", str(tmp_path / "rays.npy"), "-o",
                 str(tmp_path / "h.npz")]) == 0
    text = capsys.readouterr().out
    assert f"hit:       {int(want.hit.sum())} rays of 300" in text and "t:  " in text
    with np.load(tmp_path / "h.npz") as got:
        for name in ("t", "prim", "u", "v", "hit"):
            assert np.array_equal(got[name], getattr(want, name)), name
    for suffix, delimiter in ((".csv", ","), (".txt", None)):
        out = tmp_path / f"h{suffix}"
        assert main(["query", "closest-hit", "teapot", str(tmp_path / "rays.npy"), "-o",
                     str(out)]) == 0
        capsys.readouterr()
        header = out.read_text().splitlines()[0]
        assert header.lstrip("# ").replace(",", " ").split() == ["t", "prim", "u", "v", "hit"]
        table = np.loadtxt(out, delimiter=delimiter, skiprows=1, ndmin=2)
        assert np.array_equal(table[:, 0].astype(np.float32), want.t)   # 9 digits: float32 exact
        assert np.array_equal(table[:, 1], want.prim) and np.array_equal(table[:, 4], want.hit)
    assert main(["query", "any-hit", "teapot", str(tmp_path / "rays.npy"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["rays_hit"] == int(bvh.occluded(o, d).sum()) and summary["rays"] == 300


def test_query_all_hits_as_a_table_has_a_row_per_hit(capsys, tmp_path):
    bvh, o, d = _teapot_rays(tmp_path, 100)
    want = bvh.all_hits(o, d)
    assert main(["query", "all-hits", "teapot", str(tmp_path / "rays.npy"), "-o",
                 str(tmp_path / "all.csv")]) == 0
    capsys.readouterr()
    table = np.loadtxt(tmp_path / "all.csv", delimiter=",", skiprows=1, ndmin=2)
    assert (tmp_path / "all.csv").read_text().splitlines()[0] == "ray,t,prim,u,v"
    assert len(table) == len(want.t)
    assert np.array_equal(table[:, 0], np.repeat(np.arange(100), np.diff(want.offsets)))
    assert np.array_equal(table[:, 2], want.prim)


@pytest.mark.parametrize("name", ["out.xyz", "out", "out.npy"])
def test_query_output_of_an_unknown_format_is_refused_before_the_build(capsys, tmp_path, name):
    _teapot_rays(tmp_path, 4)
    code, _, err = _run(capsys, "query", "closest-hit", "teapot", str(tmp_path / "rays.npy"),
                        "-o", str(tmp_path / name))
    _assert_one_line_error(code, err, "no output format for")
    assert ".npz, .csv or .txt" in err and not (tmp_path / name).exists()


def test_query_wording_for_one_ray_and_one_point(capsys, tmp_path):
    _teapot_rays(tmp_path, 1, seed=5)
    assert main(["query", "count-hits", "teapot", str(tmp_path / "rays.npy")]) == 0
    text = capsys.readouterr().out
    # "1 rays" as words; a rate such as "481 rays/s" ends in the same characters
    assert "rays:      1 from" in text and not re.search(r"(?<![\d.,])1 rays\b", text)
    assert " ray hit" in text or "0 rays hit" in text
    np.save(tmp_path / "p.npy", np.zeros((1, 3), np.float32))
    assert main(["query", "closest", "teapot", str(tmp_path / "p.npy")]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("query:")][0]
    assert "points/s" in line and "0.00 M" not in line


def test_plural_and_rate_wording():
    from lbvh.cli import plural, rate
    assert plural(1, "ray") == "1 ray" and plural(0, "ray") == "0 rays"
    assert plural(2048, "point") == "2,048 points"
    assert rate(1, 1e-4, "ray") == "10 k rays/s"
    assert rate(5, 1.0, "point") == "5 points/s"
    assert rate(3_000_000, 0.5, "ray") == "6 M rays/s"


def test_the_first_use_of_a_device_says_it_is_compiling_and_testing(tmp_path):
    """A fresh cache: lbvh info says on stderr that the wait is the one-time self-test
    and compile; the next run, with the answer kept, says nothing of it."""
    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "xdg"))
    env.pop("LBVH_SELF_TEST", None)
    runs = [subprocess.run([sys.executable, "-m", "lbvh.cli", "info", "teapot"], cwd=tmp_path,
                           env=env, capture_output=True, text=True, timeout=600)
            for _ in range(2)]
    for proc in runs:
        assert proc.returncode == 0, proc.stderr[-2000:]
    assert "first use of" in runs[0].stderr and "self-test" in runs[0].stderr
    assert "first use of" not in runs[1].stderr
