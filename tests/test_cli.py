"""The command line: `lbvh render`, `lbvh info`, `lbvh devices`; exit codes and one-line errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lbvh.cli import main, parse_size
from lbvh.rendering.image import read_image

REPO = Path(__file__).resolve().parents[1]
CORNELL = str(REPO / "scenes" / "cornell.json")


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
])
def test_errors_are_one_line_and_exit_2(capsys, tmp_path, argv, fragment):
    (tmp_path / "bad.json").write_text("{oops")
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
