"""The device self-test (lbvh/selftest.py): it passes here, and it catches real bad kernels.

The bad kernels are real: a copy of the package whose bounds kernel gives one
wrong box, or writes through a wild pointer, compiled and run on this
device. Each runs in a subprocess with its own self-test cache.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

import lbvh
from lbvh.verification import selftest
from lbvh.device import get_context

BOX_LINE = "boxes[2 * t + 1] = (float4)(hi.x, hi.y, hi.z, 0.0f);"


def test_default_device_passes_and_the_answer_is_kept():
    ctx = get_context()
    result = selftest.self_test(ctx)
    assert result.passed, result.failure
    assert selftest.results()[selftest.device_key(ctx.device)] is result
    kept = json.loads(selftest._cache_file(ctx.device).read_text())
    assert kept["passed"] is True and kept["device"] == result.device


def test_run_here_checks_every_stage(capsys):
    result = selftest.run_here(get_context())
    assert result.passed, result.failure
    stages = [line for line in capsys.readouterr().out.splitlines() if line.startswith("stage: ")]
    for name in ("bounds.cl", "morton.cl", "sort.cl", "emit.cl", "traverse.cl"):
        assert any(name in line for line in stages), (name, stages)


def _broken_copy(tmp_path: Path, replacement: str) -> Path:
    root = tmp_path / "pkg"
    shutil.copytree(REPO / "lbvh", root / "lbvh", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(REPO / "kernels", root / "lbvh" / "kernels")
    bounds = root / "lbvh" / "kernels" / "bounds.cl"
    text = bounds.read_text()
    assert text.count(BOX_LINE) == 1
    bounds.write_text(text.replace(BOX_LINE, replacement))
    return root


def _build_with(root: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(root), XDG_CACHE_HOME=str(tmp_path / "xdg"))
    code = ("import lbvh\n"
            "try:\n"
            "    lbvh.build([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])\n"
            "    print('built')\n"
            "except lbvh.DeviceError as exc:\n"
            "    print('DeviceError:', exc)\n")
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)


def test_a_wrong_kernel_answer_is_a_device_error(tmp_path):
    root = _broken_copy(tmp_path, "boxes[2 * t + 1] = (float4)(hi.x, hi.y, "
                                  "hi.z + (t == 17 ? 1.0f : 0.0f), 0.0f);")
    proc = _build_with(root, tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "DeviceError:" in proc.stdout, out[-3000:]
    assert "fails the self-test" in out and "bounds.cl triangle_bounds" in out, out[-3000:]
    assert "entry 17 is" in out and "expected" in out, out[-3000:]
    assert "built" not in proc.stdout.splitlines()


def test_a_crashing_kernel_is_a_device_error_not_a_crash(tmp_path):
    root = _broken_copy(tmp_path, BOX_LINE + " if (t == 5) "
                                  "((__global volatile int *)(size_t)16)[n] = 1;")
    proc = _build_with(root, tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "DeviceError:" in proc.stdout, out[-3000:]
    assert "died (signal" in out and "bounds.cl triangle_bounds" in out, out[-3000:]


def test_self_test_can_be_switched_off(tmp_path):
    root = _broken_copy(tmp_path, "boxes[2 * t + 1] = (float4)(hi.x, hi.y, "
                                  "hi.z + (t == 17 ? 1.0f : 0.0f), 0.0f);")
    env = dict(os.environ, PYTHONPATH=str(root), XDG_CACHE_HOME=str(tmp_path / "xdg"),
               LBVH_SELF_TEST="0")
    proc = subprocess.run([sys.executable, "-c", "import lbvh.device; lbvh.device.get_context(); print('ok')"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.stdout.strip() == "ok", proc.stderr[-2000:]


@pytest.mark.parametrize("cpu", ["znver3", "haswell"])
def test_self_test_passes_when_compiled_for_an_avx2_cpu(tmp_path, cpu):
    # PoCL's kernel library here is its AVX-512 one; compiling the kernels for
    # an AVX2 CPU is the configuration of PoCL 3.0 on AMD Zen 4 (znver3 and the
    # avx512 library), where 64-byte vectors crossing into the library crashed.
    env = dict(os.environ, LBVH_POCL_CPU=cpu, XDG_CACHE_HOME=str(tmp_path / "xdg"))
    code = ("import lbvh, lbvh.verification.selftest as s\n"
            "from lbvh.device.pocl_target import target_cpu\n"
            "ctx = lbvh.device.get_context()\n"
            "print('target', target_cpu(ctx.device))\n"
            "print([r.summary() for r in s.results().values()])\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    out = proc.stdout + proc.stderr
    if "target None" in proc.stdout:
        pytest.skip("PoCL's device record could not be read: the compile target cannot be set")
    assert proc.returncode == 0 and f"'{cpu}')" in proc.stdout, out[-3000:]
    assert "passed (in" in proc.stdout, out[-3000:]


def test_a_fresh_compile_is_quiet(tmp_path):
    # The README's main job with PoCL's cache off (every program compiled):
    # nothing on stderr, no "N warnings generated.", no CompilerWarning; only the
    # command line's notice that this first use compiles and runs the self-test.
    env = dict(os.environ, POCL_KERNEL_CACHE="0", XDG_CACHE_HOME=str(tmp_path / "xdg"),
               PYTHONWARNINGS="always")
    proc = subprocess.run([sys.executable, "-m", "lbvh.cli", "render",
                           str(REPO / "scenes" / "teapot.json"), "-o", str(tmp_path / "t.png"),
                           "--size", "32x24"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("lbvh: first use of ") \
        and lines[0].endswith("running the self-test (once; later runs reuse the answer)"), \
        proc.stderr[-3000:]
