"""Shared fixtures: the PoCL context, the shipped and the shared scenes."""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

import lbvh
from lbvh.scene import load_mesh

REPO = Path(__file__).resolve().parents[1]
SHIPPED_SCENES = REPO / "scenes"
SHARED_SCENES = REPO.parent / "shared" / "scenes"


@pytest.fixture(scope="session")
def ctx():
    return lbvh.get_context()


@functools.lru_cache(maxsize=None)
def _mesh(path: str):
    v, f = load_mesh(path)
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def shipped_mesh(name: str):
    return _mesh(str(SHIPPED_SCENES / name))


def shared_mesh(name: str):
    path = SHARED_SCENES / name
    if not path.is_file():
        pytest.skip(f"shared scene {path} not present")
    return _mesh(str(path))


def random_soup(n: int, seed: int = 0, scale: float = 1.0):
    """n small random triangles in a cube: the generic well-behaved case."""
    rng = np.random.default_rng(seed)
    centres = rng.random((n, 1, 3), dtype=np.float32) * scale
    v = (centres + rng.normal(0, 0.01 * scale, (n, 3, 3)).astype(np.float32)).reshape(-1, 3)
    return v.astype(np.float32), np.arange(3 * n, dtype=np.uint32).reshape(n, 3)
