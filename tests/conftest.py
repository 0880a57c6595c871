"""Shared fixtures: the PoCL context, the shipped and the shared scenes."""
from __future__ import annotations

import functools
from pathlib import Path

import pytest

from lbvh.device import get_context
from lbvh.rendering.scene import load_mesh
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
