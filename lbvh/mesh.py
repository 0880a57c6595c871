"""Checking and converting the caller's mesh before anything touches the device.

Every problem raises a :class:`ValueError` that names it and where it is (the
first bad vertex or face); nothing is allocated on the device before the mesh
has passed.
"""
from __future__ import annotations

from typing import Any

import numpy as np

_FLOAT32_MAX = float(np.finfo(np.float32).max)

#: 2F - 1 nodes of 8 words each must stay addressable by a 32-bit int in the kernels.
MAX_TRIANGLES = 2**27 - 1


class MissingFileError(FileNotFoundError, ValueError):
    """A file the caller named does not exist: a ``FileNotFoundError``, and a
    ``ValueError`` as every other bad input of the package is."""


def _first_row(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask.reshape(len(mask), -1).any(axis=1))[0])


def real_array(name: str, value: Any) -> np.ndarray:
    """``value`` as a numpy array of a real number type, or a ``ValueError`` naming ``name``."""
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name}: cannot be read as an array ({exc})") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating)
                                   or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name}: dtype {arr.dtype} is not a real number type "
                         "(expected float32, float64 or an integer type)")
    return arr


def as_vertices(vertices: Any) -> np.ndarray:
    """Return ``float32 (V, 3)`` C-contiguous vertices, or raise ``ValueError``."""
    arr = real_array("vertices", vertices)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"vertices: shape {arr.shape}, expected (V, 3)")
    if len(arr) == 0:
        raise ValueError("vertices: the mesh has no vertices")
    finite = np.isfinite(arr) if np.issubdtype(arr.dtype, np.floating) else np.ones(arr.shape, bool)
    if not finite.all():
        i = _first_row(~finite)
        raise ValueError(f"vertices: vertex {i} has a NaN or infinite coordinate {arr[i].tolist()}")
    if arr.dtype != np.float32:
        big = np.abs(arr.astype(np.float64)) > _FLOAT32_MAX
        if big.any():
            i = _first_row(big)
            raise ValueError(f"vertices: vertex {i} {arr[i].tolist()} overflows float32")
    return np.ascontiguousarray(arr, dtype=np.float32)


def as_faces(faces: Any, num_vertices: int) -> np.ndarray:
    """Return ``uint32 (F, 3)`` C-contiguous faces, or raise ``ValueError``."""
    try:
        arr = np.asarray(faces)
    except ValueError:
        raise ValueError("faces: ragged faces (rows of different lengths); every face must be "
                         "a triangle of 3 vertex indices (triangulate polygons first)") from None
    if arr.dtype == object:
        raise ValueError("faces: ragged or mixed-type faces; every face must be a triangle "
                         "of 3 vertex indices (polygons must be triangulated first)")
    if arr.ndim == 2 and arr.shape[1] != 3 and len(arr):
        raise ValueError(f"faces: shape {arr.shape}: faces have {arr.shape[1]} vertices, "
                         "only triangles (3 indices per face) are supported")
    if arr.ndim != 2:
        if arr.size == 0:
            raise ValueError("faces: the mesh has no triangles")
        raise ValueError(f"faces: shape {arr.shape}, expected (F, 3)")
    if len(arr) == 0:
        raise ValueError("faces: the mesh has no triangles")
    if np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"faces: dtype {arr.dtype}: vertex indices must be integers")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"faces: dtype {arr.dtype}: vertex indices must be integers")
    wide = arr.astype(np.int64, copy=False)
    negative = wide < 0
    if negative.any():
        i = _first_row(negative)
        raise ValueError(f"faces: face {i} {arr[i].tolist()} has a negative vertex index")
    outside = wide >= num_vertices
    if outside.any():
        i = _first_row(outside)
        raise ValueError(f"faces: face {i} {arr[i].tolist()} indexes a vertex outside "
                         f"[0, {num_vertices})")
    if len(arr) > MAX_TRIANGLES:
        raise ValueError(f"faces: {len(arr):,} triangles; at most {MAX_TRIANGLES:,} are supported "
                         "(the kernels address 32-byte node records with 32-bit offsets)")
    return np.ascontiguousarray(wide, dtype=np.uint32)


def _kind(value: Any) -> str:
    """How a value is named in messages: its module and class."""
    cls = type(value)
    module = cls.__module__.split(".")[0]
    return cls.__name__ if module == "builtins" else f"{module}.{cls.__name__}"


def as_mesh(vertices: Any, faces: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Accept ``(vertices, faces)`` arrays or a ``trimesh.Trimesh``; validate both.

    Anything else is refused with a message that says what was passed and
    what to pass instead (a ``trimesh.Scene``, a ``PointCloud``, a mesh object
    together with faces, ...). Paths are read by :func:`lbvh.build` itself.
    """
    is_mesh = hasattr(vertices, "vertices") and hasattr(vertices, "faces")
    if faces is None:
        if is_mesh:
            return as_mesh(vertices.vertices, vertices.faces)
        raise ValueError(_missing_faces(vertices))
    if hasattr(vertices, "geometry") and isinstance(getattr(vertices, "geometry"), dict):
        count = len(vertices.geometry)
        raise ValueError(f"vertices: a {_kind(vertices)} of {count} geometr"
                         f"{'y' if count == 1 else 'ies'} was passed together with faces; pass "
                         "the scene alone (lbvh.build(scene) makes an lbvh.Scene)")
    if is_mesh:
        raise ValueError(f"vertices: a {_kind(vertices)} was passed together with faces; pass the "
                         "mesh alone (lbvh.build(mesh)) or its arrays "
                         "(lbvh.build(mesh.vertices, mesh.faces))")
    v = as_vertices(vertices)
    f = as_faces(faces, len(v))
    return v, f


def _missing_faces(value: Any) -> str:
    kind = _kind(value)
    if hasattr(value, "geometry") and isinstance(getattr(value, "geometry"), dict):
        count = len(value.geometry)
        return (f"faces: missing: a {kind} of {count} geometr{'y' if count == 1 else 'ies'} was "
                "passed; lbvh.build(scene) alone makes an lbvh.Scene of its instances, "
                "scene.to_mesh() flattens it into one mesh")
    if hasattr(value, "vertices"):
        return (f"faces: missing: a {kind} has vertices but no faces; a BVH is built over "
                "triangles (pass a triangle mesh, or vertices and faces)")
    return (f"faces: missing: got a {kind} alone; pass vertices and faces, a trimesh.Trimesh, "
            "or the path of a mesh file")


def is_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether checked ``vertices`` (``float32 (V, 3)``) and ``faces`` (``(F, 3)``)
    form a closed surface: every edge, between corners of equal coordinates, is
    used as often in one direction as in the other (the faces' boundary, as a
    chain of directed edges, is zero; a zero-length edge cancels itself). Then
    the winding number off the surface is an integer everywhere, the signed
    count of the crossings of any ray from the point (kernels/every_hit.h
    ``SIGNED``). A hole, a flipped face, a face of three collinear corners or an
    edge shared by three faces makes a surface not closed; corners repeated at
    the same coordinates (a seam of split vertices) do not."""
    f = np.asarray(faces, np.int64)
    if _edges_cancel(f, len(vertices)):
        return True
    # one index per position; + 0 makes -0.0 +0.0, the same value for the kernels
    v = np.asarray(vertices, np.float32) + np.float32(0.0)
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    sv = v[order]
    new = np.ones(len(v), bool)
    new[1:] = (sv[1:] != sv[:-1]).any(axis=1)
    position = np.empty(len(v), np.int64)
    position[order] = np.cumsum(new) - 1
    return _edges_cancel(position[f], int(new.sum()))


def _edges_cancel(faces: np.ndarray, count: int) -> bool:
    """Whether the directed edges of ``faces`` (indices below ``count``) are, as a
    multiset, the same as the reversed ones."""
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    return bool(np.array_equal(np.sort(a * count + b), np.sort(b * count + a)))
