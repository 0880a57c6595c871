"""A crash leaves no poison, and the compiler cache does not depend on the install path.

After a process died mid-run, the issue-14 report saw the next run fail with
``clCreateKernel failed: INVALID_KERNEL_NAME``: PoCL loads whatever its kernel
cache holds, and an empty or cut ``program.bc`` gives a program without
kernels, a cut shared object aborts the process. Each test here runs the
package in subprocesses over a private PoCL cache (``POCL_CACHE_DIR``):
killed while it compiles and while it traces, or with its cache files damaged
by hand, the next run must give the same answers as a clean one.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO

JOB = r"""
import sys, time
import numpy as np
import lbvh
sys.path.insert(0, sys.argv[1])
from conftest import random_soup
print("started", flush=True)
v, f = random_soup(3000, seed=5)
rng = np.random.default_rng(1)
o = rng.normal(size=(20000, 3)).astype(np.float32) * 3
d = -o + rng.normal(size=o.shape).astype(np.float32) * 0.3
answers = []
for kw in ({}, {"key_bits": 63}, {"collapse": True}, {"treelet_rounds": 1}):
    b = lbvh.build(v, f, **kw)
    b.validate()
    answers.append(b.intersect(o, d).prim)
    answers.append(b.occluded(o, d, tmax=0.5))
print("tracing", flush=True)
for _ in range(int(sys.argv[2])):
    b.intersect(o, d)
digest = sum(int(np.asarray(a, np.int64).sum()) * (k + 1) for k, a in enumerate(answers))
print("answers", digest, flush=True)
"""


def _env(cache: Path) -> dict[str, str]:
    """The job's environment: PoCL's cache in ``cache``, and PoCL as the device whatever
    ``LBVH_DEVICE`` names (these tests are about PoCL's kernel cache; another device,
    Intel's CPU runtime say, keeps none there, and the tests would damage nothing)."""
    env = dict(os.environ)
    env.pop("LBVH_DEVICE", None)
    env["POCL_CACHE_DIR"] = str(cache)
    env["POCL_KERNEL_CACHE"] = "1"
    return env


def _run(cache: Path, loops: int = 0, cwd: Path = REPO, python_path: str | None = None) -> str:
    env = _env(cache)
    if python_path:
        env["PYTHONPATH"] = python_path
    proc = subprocess.run([sys.executable, "-c", JOB, str(REPO / "tests"), str(loops)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    return next(line for line in proc.stdout.splitlines() if line.startswith("answers"))


def _kill_after(cache: Path, marker: str, delay: float, loops: int = 0) -> None:
    """Start the job, wait for ``marker`` on its output, then SIGKILL it ``delay`` s later."""
    proc = subprocess.Popen([sys.executable, "-c", JOB, str(REPO / "tests"), str(loops)],
                            cwd=REPO, env=_env(cache), stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        for line in proc.stdout:
            if line.startswith(marker):
                break
        time.sleep(delay)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)


@pytest.fixture(scope="module")
def warm(tmp_path_factory) -> tuple[str, Path]:
    """The answers of a clean run, and the PoCL cache it filled (copied by each test)."""
    cache = tmp_path_factory.mktemp("warm-cache")
    return _run(cache), cache


def _copy(cache: Path, tmp_path: Path) -> Path:
    target = tmp_path / "cache"
    shutil.copytree(cache, target)
    return target


@pytest.mark.parametrize("delay", [0.4, 1.5])
def test_killed_while_compiling_then_rerun(tmp_path, warm, delay):
    _kill_after(tmp_path, "started", delay)     # an empty cache: killed among the compiles
    assert _run(tmp_path) == warm[0]


def test_killed_while_tracing_then_rerun(tmp_path, warm):
    cache = _copy(warm[1], tmp_path)
    _kill_after(cache, "tracing", 0.5, loops=1000)
    assert _run(cache) == warm[0]


def _damage(cache: Path, how: str) -> int:
    count = 0
    pattern = "*/*/program.bc" if how.endswith("bc") else "*/*/*/*/*.so"
    for f in cache.glob(pattern):
        data = f.read_bytes()
        f.write_bytes(b"" if how == "empty bc" else data[: len(data) // 3])
        count += 1
    return count


@pytest.mark.parametrize("how", ["empty bc", "cut bc", "cut so"])
def test_damaged_cache_files_are_rebuilt(tmp_path, warm, how):
    cache = _copy(warm[1], tmp_path)
    assert _damage(cache, how) > 0
    assert _run(cache) == warm[0]


def test_program_without_kernels_is_compiled_afresh(tmp_path, warm):
    # The cache check before the first compile is switched off here, so the
    # second line of defence (a program that lacks the kernel asked for is
    # compiled again from a source no cache holds) is what recovers.
    cache = _copy(warm[1], tmp_path)
    assert _damage(cache, "empty bc") > 0
    shim = tmp_path / "shim"
    shim.mkdir()
    (shim / "sitecustomize.py").write_text(
        "import lbvh.device as d\nd.check_compiler_cache = lambda root=None: []\n")
    assert _run(cache, python_path=str(shim)) == warm[0]


def test_cache_check_finds_exactly_the_damaged_entries(tmp_path, warm):
    from lbvh.device import check_compiler_cache
    cache = _copy(warm[1], tmp_path)
    entries = sorted(p for p in cache.glob("*/*") if p.is_dir())
    assert entries and check_compiler_cache(cache) == []
    victim = next(p for p in entries if (p / "program.bc").exists())
    data = (victim / "program.bc").read_bytes()
    (victim / "program.bc").write_bytes(data[:-8])
    assert check_compiler_cache(cache) == [str(victim)]
    assert not victim.exists() and all(p.exists() for p in entries if p != victim)


def test_another_install_path_compiles_nothing(tmp_path, warm):
    # The warm cache was filled by the package in this checkout; a copy of the
    # package elsewhere (as a second virtual environment has) must find every
    # program in it.
    cache = _copy(warm[1], tmp_path)
    entries = {p.name for p in cache.glob("*/*")}
    root = tmp_path / "elsewhere" / "site-packages"
    shutil.copytree(REPO / "lbvh", root / "lbvh", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(REPO / "kernels", root / "lbvh" / "kernels")   # the wheel's layout
    assert _run(cache, cwd=tmp_path, python_path=str(root)) == warm[0]
    assert {p.name for p in cache.glob("*/*")} == entries, "the copy elsewhere compiled again"
