"""Loading scenes: a mesh file through trimesh, or a JSON scene description.

A multi-mesh file (a scene graph in GLB/GLTF, several objects in an OBJ) is
flattened with each node's transform applied. :func:`load_scene` also takes the
name of a mesh that ships with the package (``"teapot"``, :data:`lbvh.data.MESHES`)
where no file of that name exists (:func:`find_scene`). Problems (missing or unreadable
file, no triangles, NaN coordinates) raise ``ValueError`` naming the file.

A scene description (``.json``) saves a view of a mesh::

    {
      "mesh": "teapot.obj",                  # required, relative to the JSON file
      "camera": {"position": [x, y, z], "target": [x, y, z], "up": [0, 1, 0],
                 "fov": 45, "width": 640, "height": 480},     # optional
      "transforms": [                         # optional, applied first to last
        {"scale": 2.0},                       # or [sx, sy, sz]
        {"rotate": {"axis": [0, 1, 0], "degrees": 90}},
        {"translate": [x, y, z]},
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]   # a 4x4 matrix
      ],
      "name": "...", "credit": "..."          # optional text
    }

Camera keys are described in :meth:`lbvh.camera.Camera.from_dict`; without a
camera the renderer frames the scene's bounds.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .camera import Camera, read_json
from .data import MESHES
from .data import path as shipped_mesh_path
from .mesh import MissingFileError, as_mesh, as_vertices

MESH_SUFFIXES = {".obj", ".ply", ".stl", ".glb", ".gltf", ".off"}
SCENE_SUFFIX = ".json"
SCENE_KEYS = ("mesh", "camera", "transforms", "name", "credit")


@dataclass
class SceneFile:
    """A triangle mesh (``float32 (V, 3)`` vertices, ``uint32 (F, 3)`` faces) and its settings.

    ``camera`` is the saved view of a scene description, ``None`` for a bare mesh.
    A mesh file that places several meshes (a glTF scene) is flattened into
    ``vertices`` and ``faces`` and also kept whole as ``extras["instances"]``, the
    ``trimesh.Scene``, from which ``lbvh.build`` makes an :class:`lbvh.Scene`.
    """
    vertices: np.ndarray
    faces: np.ndarray
    name: str = ""
    extras: dict[str, Any] = field(default_factory=dict)
    camera: Camera | None = None


def _require_file(path: Path) -> None:
    if path.is_dir():
        raise ValueError(f"{path}: a folder, not a file")
    if not path.is_file():
        raise MissingFileError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: the file is empty")


def _obj_index_problem(path: Path) -> str | None:
    """The first OBJ face that names a vertex the file does not define, or None.

    Only run after trimesh failed (a plain scan of the text): trimesh reports
    such a face as a bare IndexError.
    """
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return None
    total = sum(1 for line in lines if line.startswith("v "))
    seen = 0
    for number, line in enumerate(lines, 1):
        if line.startswith("v "):
            seen += 1
        elif line.startswith("f "):
            for item in line.split()[1:]:
                try:
                    index = int(item.split("/")[0])
                except ValueError:
                    continue
                # 1-based; negative counts back from the last vertex defined so far
                if not (1 <= index <= total if index > 0 else 1 <= seen + index + 1 <= seen):
                    return (f"line {number}: face vertex index {index} is outside the "
                            f"{total if index > 0 else seen} vertices "
                            f"{'in the file' if index > 0 else 'defined before it'}")
    return None


def _stl_problem(path: Path) -> str | None:
    """Why ``path`` is neither a binary nor an ASCII STL file, or ``None``.

    Checked before trimesh reads it, since what trimesh makes of a broken STL
    depends on the optional modules installed (with charset_normalizer it decodes
    any bytes as text and finds no mesh; without, it raises ImportError).
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
        if size >= 84:
            count = int.from_bytes(head[80:84], "little")
            if size == 84 + 50 * count:
                return None                     # binary: header, count, 50 bytes a triangle
        f.seek(max(0, size - 1024))
        tail = f.read()
    is_ascii = head.lstrip().lower().startswith(b"solid")
    if is_ascii and b"endsolid" in tail.lower():
        return None                             # ASCII: "solid name" ... "endsolid name"
    if is_ascii:
        return (f"not a valid STL file ({size:,} bytes): it begins as ASCII STL ('solid') "
                f"but does not end with 'endsolid' (cut short?)")
    binary = (f"as binary STL its header's count of {count:,} triangles needs "
              f"{84 + 50 * count:,} bytes" if size >= 84
              else "too short for binary STL's 84-byte header")
    return f"not a valid STL file ({size:,} bytes): not ASCII STL ('solid' ...), and {binary}"


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh file with trimesh and return validated ``(vertices, faces)``: the
    meshes of a file of several (a glTF scene) flattened into one."""
    return _load(path)[:2]


def placed_geometries(loaded: Any) -> list[str]:
    """The geometry name of each node of a trimesh scene's graph that places a
    triangle mesh (a name once per placement)."""
    names = [loaded.graph[node][1] for node in loaded.graph.nodes_geometry]
    return [g for g in names if len(getattr(loaded.geometry.get(g), "faces", ())) > 0]


def _load(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, Any]:
    """``(vertices, faces, structure)``: the flattened mesh, and the ``trimesh.Scene``
    itself where the file places more than one mesh (else ``None``)."""
    import trimesh

    path = Path(path)
    _require_file(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{path}: unknown mesh format {path.suffix!r} "
                         f"(expected one of {', '.join(sorted(MESH_SUFFIXES))})")
    problem = _stl_problem(path) if path.suffix.lower() == ".stl" else None
    if problem:
        raise ValueError(f"{path}: {problem}")
    try:
        loaded = trimesh.load(str(path), process=False, force=None)
    except ImportError as exc:
        # trimesh reaches for optional modules (charset_normalizer to decode
        # text) only once the file failed to parse as what its suffix says; a
        # broken STL is refused before (_stl_problem)
        raise ValueError(f"{path}: not a valid {path.suffix.lstrip('.').upper()} file "
                         f"(trimesh could not parse it; it wanted the optional module "
                         f"{exc.name!r} for a last try)") from None
    except Exception as exc:  # trimesh raises many kinds on a broken file
        problem = _obj_index_problem(path) if path.suffix.lower() == ".obj" else None
        if problem:
            raise ValueError(f"{path}: {problem}") from None
        raise ValueError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    structure = None
    if isinstance(loaded, trimesh.Scene):
        if not loaded.geometry:
            raise ValueError(f"{path}: the file holds no mesh")
        structure = loaded if len(placed_geometries(loaded)) > 1 else None
        try:
            loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
        except Exception as exc:
            raise ValueError(f"{path}: cannot flatten the scene ({exc})") from None
    if not hasattr(loaded, "faces") or len(getattr(loaded, "faces", [])) == 0:
        raise ValueError(f"{path}: the file holds no triangles")
    try:
        return (*as_mesh(np.asarray(loaded.vertices), np.asarray(loaded.faces)), structure)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def find_scene(path: str | os.PathLike) -> Path:
    """The file :func:`load_scene` reads for ``path``: ``path`` itself when it
    exists, else the shipped mesh of that name (``"teapot"``: ``lbvh/data/teapot.obj``),
    else ``path`` (which is then reported missing)."""
    file = Path(path)
    if not file.exists() and os.fspath(path) in MESHES:
        return shipped_mesh_path(os.fspath(path))
    return file


def load_scene(path: str | os.PathLike) -> SceneFile:
    """Load a mesh file (see :data:`MESH_SUFFIXES`), a ``.json`` scene description,
    or a shipped mesh by name (:func:`find_scene`; a file of that name wins).

    Raises:
        ValueError: naming the file and the problem (missing file, bad JSON,
            unknown key, bad camera or transform, bad mesh).
    """
    path = find_scene(path)
    if not path.exists() and not path.suffix and len(path.parts) == 1:
        raise MissingFileError(f"{path}: no such file, nor a mesh that ships with lbvh "
                               f"(shipped: {', '.join(MESHES)})")
    if path.suffix.lower() == SCENE_SUFFIX:
        return load_scene_description(path)
    v, f, structure = _load(path)
    # a file placing several meshes keeps its structure (lbvh.build makes instances of it)
    return SceneFile(v, f, name=path.stem, extras={"instances": structure} if structure else {})


def load_scene_description(path: str | os.PathLike) -> SceneFile:
    """Load a ``.json`` scene description (format in the module docstring)."""
    path = Path(path)
    _require_file(path)
    data = read_json(path)
    try:
        return _scene_from_dict(data, path)
    except ValueError as exc:
        message = str(exc)
        raise ValueError(message if message.startswith(str(path)) else f"{path}: {message}") from None


def _scene_from_dict(data: Any, path: Path) -> SceneFile:
    if not isinstance(data, dict):
        raise ValueError("a scene description is a JSON object with a \"mesh\" key")
    unknown = sorted(set(data) - set(SCENE_KEYS))
    if unknown:
        raise ValueError(f"unknown key {unknown[0]!r} (known: {', '.join(SCENE_KEYS)})")
    if "mesh" not in data:
        raise ValueError("missing \"mesh\" (the mesh file, relative to the scene file)")
    if not isinstance(data["mesh"], str) or not data["mesh"]:
        raise ValueError(f"mesh: {data['mesh']!r} is not a file name")
    mesh_path = path.parent / data["mesh"]
    if mesh_path.suffix.lower() == SCENE_SUFFIX:
        raise ValueError(f"mesh: {data['mesh']!r} is a scene description, not a mesh file")
    matrix = transform_matrix(data.get("transforms", []))
    camera = Camera.from_dict(data["camera"]) if data.get("camera") is not None else None
    v, f = load_mesh(mesh_path)
    v = apply_transform(matrix, v)
    extras = {"mesh_path": str(mesh_path), "transform": matrix}
    if "credit" in data:
        extras["credit"] = str(data["credit"])
    return SceneFile(v, f, name=str(data.get("name", path.stem)), extras=extras, camera=camera)


# -- transforms ---------------------------------------------------------------
def _numbers(name: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: {value!r} is not numbers of shape {shape}") from None
    if arr.shape != shape:
        raise ValueError(f"{name}: {value!r} is not numbers of shape {shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: {value!r} has a NaN or infinite entry")
    return arr


def _rotation(name: str, spec: Any) -> np.ndarray:
    """4x4 rotation by ``degrees`` about ``axis`` (Rodrigues' formula), counter-clockwise
    when the axis points at the viewer."""
    if not isinstance(spec, dict) or set(spec) != {"axis", "degrees"}:
        raise ValueError(f"{name}: expected {{\"axis\": [x, y, z], \"degrees\": angle}}, got {spec!r}")
    axis = _numbers(f"{name} axis", spec["axis"], (3,))
    length = np.linalg.norm(axis)
    if length == 0.0:
        raise ValueError(f"{name} axis: the zero vector has no direction")
    k = axis / length
    angle = math.radians(float(_numbers(f"{name} degrees", spec["degrees"], ())))
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross
    return m


def _transform_entry(index: int, entry: Any) -> np.ndarray:
    name = f"transforms[{index}]"
    if isinstance(entry, list):
        m = _numbers(name, entry, (4, 4))
        if abs(np.linalg.det(m[:3, :3])) < 1e-300:
            raise ValueError(f"{name}: the matrix is singular (flattens the mesh)")
        return m
    if not isinstance(entry, dict) or len(entry) != 1:
        raise ValueError(f"{name}: expected a 4x4 matrix or one of "
                         f"{{\"translate\": ...}}, {{\"scale\": ...}}, {{\"rotate\": ...}}, got {entry!r}")
    (kind, value), = entry.items()
    m = np.eye(4)
    if kind == "translate":
        m[:3, 3] = _numbers(f"{name} translate", value, (3,))
    elif kind == "scale":
        factors = _numbers(f"{name} scale", value, () if np.ndim(value) == 0 else (3,))
        if (factors == 0).any():
            raise ValueError(f"{name} scale: {value!r} has a zero factor (flattens the mesh)")
        m[:3, :3] = np.diag(np.broadcast_to(factors, (3,)))
    elif kind == "rotate":
        m = _rotation(f"{name} rotate", value)
    else:
        raise ValueError(f"{name}: unknown transform {kind!r} (expected translate, scale, rotate "
                         "or a 4x4 matrix)")
    return m


def transform_matrix(transforms: Any) -> np.ndarray:
    """The ``float64 (4, 4)`` matrix of a scene's ``transforms`` list, first entry applied first."""
    if not isinstance(transforms, list):
        raise ValueError(f"transforms: expected a list, got {transforms!r}")
    total = np.eye(4)
    for index, entry in enumerate(transforms):
        total = _transform_entry(index, entry) @ total
    return total


def apply_transform(matrix: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Vertices ``float32 (V, 3)`` moved by an affine or projective ``(4, 4)`` matrix, in float64."""
    if np.array_equal(matrix, np.eye(4)):
        return vertices
    homogeneous = np.concatenate([vertices.astype(np.float64), np.ones((len(vertices), 1))], axis=1)
    moved = homogeneous @ matrix.T
    w = moved[:, 3:4]
    if (w == 0).any():
        raise ValueError(f"transforms: vertex {int(np.flatnonzero(w[:, 0] == 0)[0])} goes to infinity")
    return as_vertices(moved[:, :3] / w)
