"""Shared fixtures: the PoCL context, the shipped and the shared scenes."""
from __future__ import annotations

import functools
import importlib.util
import sys
from pathlib import Path

import pytest

from lbvh.device import get_context
from lbvh.files import load_mesh
from lbvh.verification.meshes import soup

REPO = Path(__file__).resolve().parents[1]
SHIPPED_SCENES = REPO / "scenes"
SHARED_SCENES = REPO.parent / "shared" / "scenes"


@pytest.fixture(scope="session")
def ctx():
    return get_context()


@functools.lru_cache(maxsize=None)
def _mesh(path: str):
    v, f = load_mesh(path)
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def pocl_cpu_device(why: str):
    """PoCL's CPU device, for tests whose device (LBVH_DEVICE) is a GPU but which need
    the CPU's choices on a CPU; skips, saying ``why``, where there is none."""
    from lbvh import device as dev
    try:
        return dev.find_device("pocl")
    except dev.DeviceError:
        pytest.skip(f"no PoCL CPU device beside the GPU: {why}")


def shipped_mesh(name: str):
    return _mesh(str(SHIPPED_SCENES / name))


def shared_mesh(name: str):
    path = SHARED_SCENES / name
    if not path.is_file():
        pytest.skip(f"shared scene {path} not present")
    return _mesh(str(path))


def random_soup(n: int, seed: int = 0, scale: float = 1.0):
    """n small random triangles in a cube: the generic well-behaved case."""
    return soup(n, seed, scale=scale, spread="normal")


def load_bench(name: str):
    """The bench script ``bench/<name>.py`` as a module (bench/ is not a package: the
    folder goes on ``sys.path``, as the scripts import ``common``; the module is
    registered under its name, where dataclasses look it up)."""
    if str(REPO / "bench") not in sys.path:
        sys.path.insert(0, str(REPO / "bench"))
    spec = importlib.util.spec_from_file_location(name, REPO / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
