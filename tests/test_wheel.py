"""The kernels ship inside the package: a wheel works outside the repository."""
from __future__ import annotations

import subprocess
import sys
import zipfile

from conftest import REPO


def test_wheel_carries_kernels_and_builds_outside_the_repo(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(wheels), str(REPO)],
                   check=True, capture_output=True, timeout=300)
    wheel = next(wheels.glob("lbvh_opencl-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for kernel in ("bounds", "morton", "sort", "emit", "refit"):
        assert f"lbvh/kernels/{kernel}.cl" in names
    assert "lbvh/kernels/common.h" in names
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)],
                   check=True, capture_output=True, timeout=300)
    code = ("import lbvh, numpy as np; from lbvh.device import kernels_dir;"
            "b = lbvh.build(np.eye(3, dtype=np.float32), [[0, 1, 2]]); b.validate();"
            "print(kernels_dir())")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"}, timeout=300)
    assert out.returncode == 0, out.stderr
    assert str(target) in out.stdout
