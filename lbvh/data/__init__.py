"""Data that ships inside the package: a small mesh and a file of saved views.

So that the examples run from a wheel, with no checkout of the repository::

    import lbvh.data
    vertices, faces = lbvh.data.teapot()       # float32 (V, 3), uint32 (F, 3)
    lbvh.data.MESHES                           # ("teapot",): the shipped meshes' names
    lbvh.data.mesh("teapot")                   # the same arrays, by name
    lbvh.data.path("teapot")                   # pathlib.Path of the OBJ file
    lbvh.data.views_path()                     # pathlib.Path of the saved views (JSON)

``teapot`` is the Utah teapot by Martin Newell (6,320 triangles, positions and
triangles only), from alecjacobson/common-3d-test-models; ``lbvh/data/README.md``
says where it comes from, and ``lbvh/data/licenses/`` holds that collection's
notes. The ``lbvh`` command takes a shipped mesh's name where it takes a file
(``lbvh render teapot -o teapot.png``; a file of that name wins).

The views file (``cameras.json``) is a JSON object of named cameras in the
form of a scene file's ``"camera"`` (``position``, ``target``, ``up``, ``fov``;
keys starting with ``_`` are comments): the views of the benchmark scenes
(the benches' views), read by ``lbvh render --view NAME``.

The files are found with :mod:`importlib.resources`; this module needs numpy only.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from ..mesh import as_mesh

#: Names of the meshes that ship with the package, each a ``<name>.obj`` file here.
MESHES = ("teapot",)
#: The file of saved views (named cameras) that ships with the package.
VIEWS_FILE = "cameras.json"


def _file(filename: str) -> Path:
    # An installed package (wheel, editable or source tree) is a folder on disk;
    # the kernels are read from one too, so a zipped install is not supported.
    return Path(str(resources.files(__name__).joinpath(filename)))


def path(name: str) -> Path:
    """The file of the shipped mesh ``name`` (one of :data:`MESHES`).

    Raises:
        ValueError: for a name that is not shipped, listing those that are.
    """
    if name not in MESHES:
        raise ValueError(f"{name!r} is not a mesh that ships with lbvh (shipped: {', '.join(MESHES)})")
    return _file(f"{name}.obj")


def _read_obj(file: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions and polygons of a plain OBJ file (``v x y z`` and ``f i j k`` lines,
    1-based, ``i/t/n`` forms read as ``i``): enough for the files shipped here."""
    vertices: list[list[str]] = []
    faces: list[list[int]] = []
    for line in file.read_text(encoding="utf-8").splitlines():
        parts = line.split()
        if parts and parts[0] == "v":
            vertices.append(parts[1:4])
        elif parts and parts[0] == "f":
            faces.append([int(item.split("/")[0]) - 1 for item in parts[1:]])
    return as_mesh(np.array(vertices, dtype=np.float64), np.array(faces, dtype=np.int64))


def mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    """The shipped mesh ``name``: ``(vertices float32 (V, 3), faces uint32 (F, 3))``,
    new arrays on every call (the same as reading :func:`path` with trimesh)."""
    return _read_obj(path(name))


def teapot() -> tuple[np.ndarray, np.ndarray]:
    """The Utah teapot: ``(vertices float32 (3644, 3), faces uint32 (6320, 3))``, y up."""
    return mesh("teapot")


def views_path() -> Path:
    """The views file that ships with the package (``lbvh render --view``'s default)."""
    return _file(VIEWS_FILE)
