"""Loading scenes: a mesh file through trimesh, flattened to one triangle soup.

A multi-mesh file (a scene graph in GLB/GLTF, several objects in an OBJ) is
flattened with each node's transform applied. Problems (missing or unreadable
file, no triangles, NaN coordinates) raise ``ValueError`` naming the file.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .geometry import as_mesh

MESH_SUFFIXES = {".obj", ".ply", ".stl", ".glb", ".gltf", ".off"}


@dataclass
class Scene:
    """A triangle mesh (``float32 (V, 3)`` vertices, ``uint32 (F, 3)`` faces) and its settings."""
    vertices: np.ndarray
    faces: np.ndarray
    name: str = ""
    extras: dict[str, Any] = field(default_factory=dict)


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh file with trimesh and return validated ``(vertices, faces)``."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{path}: unknown mesh format {path.suffix!r} "
                         f"(expected one of {', '.join(sorted(MESH_SUFFIXES))})")
    try:
        loaded = trimesh.load(str(path), process=False, force=None)
    except Exception as exc:  # trimesh raises many kinds on a broken file
        raise ValueError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        if not loaded.geometry:
            raise ValueError(f"{path}: the file holds no mesh")
        try:
            loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
        except Exception as exc:
            raise ValueError(f"{path}: cannot flatten the scene ({exc})") from None
    if not hasattr(loaded, "faces") or len(getattr(loaded, "faces", [])) == 0:
        raise ValueError(f"{path}: the file holds no triangles")
    try:
        return as_mesh(np.asarray(loaded.vertices), np.asarray(loaded.faces))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def load_scene(path: str | os.PathLike) -> Scene:
    """Load a scene: for now a mesh file (see :data:`MESH_SUFFIXES`)."""
    v, f = load_mesh(path)
    return Scene(v, f, name=Path(path).stem)
