"""A pinhole camera and its primary rays, generated on the host in numpy.

Image convention: pixel ``(row, column)`` with row 0 at the top, rays in
row-major order (ray ``row * width + column``), each through its pixel's centre.
The camera looks from ``position`` towards ``target``; ``fov`` is the vertical
field of view in degrees. Without a camera, :func:`frame_bounds` places one that
sees the whole scene box.

A views file is a JSON object of named cameras, each in the form of a scene
file's ``"camera"`` (:meth:`Camera.from_dict`); keys starting with ``_`` are
comments. :func:`load_views` reads one (by default the file that ships with
the package, :func:`lbvh.data.views_path`: the benchmark scenes' views) and
:func:`view_camera` makes the camera of one view.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .data import views_path
from .mesh import MissingFileError

#: Largest image side accepted (a 16k x 16k render is already 256M rays).
MAX_SIDE = 16384
#: Default image size when neither the scene nor the caller gives one.
DEFAULT_SIZE = (640, 480)
#: Default vertical field of view, degrees.
DEFAULT_FOV = 45.0
#: Direction from the scene centre towards an automatically placed camera: in
#: front (+z), a little to the right and above, for the usual y-up meshes.
DEFAULT_VIEW_DIRECTION = (0.45, 0.35, 1.0)


def _vector3(name: str, value: Any) -> np.ndarray:
    """A finite 3-vector as float64, or ``ValueError`` naming ``name``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"camera {name}: {value!r} is not 3 numbers") from None
    if arr.shape != (3,):
        raise ValueError(f"camera {name}: {value!r} is not 3 numbers")
    if not np.isfinite(arr).all():
        raise ValueError(f"camera {name}: {value!r} has a NaN or infinite component")
    return arr


def _side(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise ValueError(f"camera {name}: {value!r} is not a whole number of pixels")
    if not 1 <= value <= MAX_SIDE:
        raise ValueError(f"camera {name}: {value} pixels, expected 1 to {MAX_SIDE}")
    return int(value)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes:
        position, target, up: ``float64 (3,)`` world-space points / direction.
        fov:    vertical field of view in degrees, in ``(0, 180)``.
        width, height: image size in pixels.
    """
    position: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float
    width: int
    height: int

    def __post_init__(self) -> None:
        # Validated on construction so that a camera that exists can always render.
        set_ = object.__setattr__
        set_(self, "position", _vector3("position", self.position))
        set_(self, "target", _vector3("target", self.target))
        set_(self, "up", _vector3("up", self.up))
        set_(self, "width", _side("width", self.width))
        set_(self, "height", _side("height", self.height))
        if isinstance(self.fov, bool) or not isinstance(self.fov, (int, float, np.number)):
            raise ValueError(f"camera fov: {self.fov!r} is not a number")
        fov = float(self.fov)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"camera fov: {self.fov!r} degrees, expected between 0 and 180 (exclusive)")
        set_(self, "fov", fov)
        forward = self.target - self.position
        if not np.linalg.norm(forward) > 0.0:
            raise ValueError(f"camera: position and target are the same point {self.position.tolist()}")
        if np.linalg.norm(self.up) == 0.0:
            raise ValueError("camera up: the zero vector has no direction")
        if np.linalg.norm(np.cross(forward / np.linalg.norm(forward),
                                   self.up / np.linalg.norm(self.up))) < 1e-6:
            raise ValueError(f"camera up: {self.up.tolist()} is parallel to the view direction "
                             f"{forward.tolist()}")

    @classmethod
    def from_dict(cls, data: Any, size: tuple[int, int] | None = None) -> "Camera":
        """A camera from a scene file's ``"camera"`` object.

        Keys: ``position`` and ``target`` (required), ``up`` (default ``[0, 1, 0]``),
        ``fov`` (degrees, default 45), ``width`` and ``height`` (default 640x480).
        ``size = (width, height)`` overrides the stored size.
        """
        if not isinstance(data, dict):
            raise ValueError(f"camera: expected an object with position and target, got {data!r}")
        known = {"position", "target", "up", "fov", "width", "height"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"camera: unknown key {unknown[0]!r} (known: {', '.join(sorted(known))})")
        for key in ("position", "target"):
            if key not in data:
                raise ValueError(f"camera: missing {key!r}")
        width, height = size or (data.get("width", DEFAULT_SIZE[0]), data.get("height", DEFAULT_SIZE[1]))
        return cls(data["position"], data["target"], data.get("up", (0.0, 1.0, 0.0)),
                   data.get("fov", DEFAULT_FOV), width, height)

    def as_dict(self) -> dict[str, Any]:
        """The JSON form read back by :meth:`from_dict`."""
        return {"position": self.position.tolist(), "target": self.target.tolist(),
                "up": self.up.tolist(), "fov": self.fov, "width": self.width, "height": self.height}

    def resized(self, width: int, height: int) -> "Camera":
        """The same view at another image size (the vertical field of view is kept)."""
        return Camera(self.position, self.target, self.up, self.fov, width, height)

    @property
    def num_pixels(self) -> int:
        return self.width * self.height

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Orthonormal ``(right, true_up, forward)``, float64 (3,) each."""
        forward = self.target - self.position
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        right /= np.linalg.norm(right)
        true_up = np.cross(right, forward)
        return right, true_up, forward

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays through the pixel centres.

        Returns:
            ``(origins, directions)``, both ``float32 (height * width, 3)``,
            row-major with row 0 at the top; directions have unit length, so a
            hit distance ``t`` is the distance from the camera.
        """
        right, true_up, forward = self.basis()
        half_h = math.tan(math.radians(self.fov) / 2.0)
        half_w = half_h * self.width / self.height
        # Normalised screen coordinates of the pixel centres, in [-1, 1].
        sx = (np.arange(self.width, dtype=np.float64) + 0.5) / self.width * 2.0 - 1.0
        sy = 1.0 - (np.arange(self.height, dtype=np.float64) + 0.5) / self.height * 2.0
        d = (forward[None, None, :]
             + (sx * half_w)[None, :, None] * right[None, None, :]
             + (sy * half_h)[:, None, None] * true_up[None, None, :])
        d = d.reshape(-1, 3)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        origins = np.broadcast_to(self.position.astype(np.float32), d.shape)
        return np.ascontiguousarray(origins), d.astype(np.float32)


def frame_bounds(lower: Any, upper: Any, width: int = DEFAULT_SIZE[0], height: int = DEFAULT_SIZE[1],
                 fov: float = DEFAULT_FOV,
                 direction: Any = DEFAULT_VIEW_DIRECTION) -> Camera:
    """A camera that sees the whole box ``[lower, upper]`` (each ``(3,)``), y up.

    The camera looks at the box centre from ``direction`` (relative to the
    centre), just far enough that all eight box corners project inside the
    image with a 5% margin.
    """
    lower = _vector3("bounds lower", lower)
    upper = _vector3("bounds upper", upper)
    if (lower > upper).any():
        raise ValueError(f"bounds: lower {lower.tolist()} exceeds upper {upper.tolist()}")
    direction = _vector3("direction", direction)
    if np.linalg.norm(direction) == 0.0:
        raise ValueError("direction: the zero vector has no direction")
    centre = 0.5 * (lower + upper)
    extent = float(np.linalg.norm(upper - lower))
    if extent == 0.0:
        extent = max(1.0, float(np.abs(centre).max())) * 1e-3  # a single point: any small view
    backwards = direction / np.linalg.norm(direction)
    # Straight above or below, "y up" is undefined: use z up instead.
    up = (0.0, 0.0, -1.0) if abs(backwards[1]) > 0.999 else (0.0, 1.0, 0.0)
    probe = Camera(centre + backwards, centre, up, fov, width, height)
    right, true_up, _ = probe.basis()
    tan_v = math.tan(math.radians(fov) / 2.0) / 1.05
    tan_h = tan_v * width / height
    corners = np.array([[x, y, z] for x in (lower[0], upper[0]) for y in (lower[1], upper[1])
                        for z in (lower[2], upper[2])]) - centre
    # A corner c at depth (distance - c.backwards) is inside the image when
    # |c.right| <= tan_h * depth and |c.true_up| <= tan_v * depth.
    along = corners @ backwards
    needed = along + np.maximum(np.abs(corners @ right) / tan_h, np.abs(corners @ true_up) / tan_v)
    distance = max(float(needed.max()), float(along.max()) + 1e-3 * extent)
    return Camera(centre + distance * backwards, centre, up, fov, width, height)


#: How messages name the views file that ships with the package.
SHIPPED_VIEWS = "lbvh/data/cameras.json (shipped with lbvh)"


def views_name(path: str | os.PathLike | None) -> str:
    """How messages name a views file: its path, or :data:`SHIPPED_VIEWS` for ``None``."""
    return SHIPPED_VIEWS if path is None else os.fspath(path)


def read_json(file: Path, label: str | None = None) -> Any:
    """The JSON value in ``file``, or ``ValueError`` starting with ``label`` (default:
    the path) that says why not (unreadable, not UTF-8, not JSON)."""
    label = str(file) if label is None else label
    try:
        return json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{label}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{label}: not valid JSON ({exc})") from None


def load_views(path: str | os.PathLike | None = None) -> dict[str, dict[str, Any]]:
    """The named views of a views file (default: the one that ships with lbvh).

    Returns ``{name: camera object}`` without the ``_`` comment keys; each
    entry is checked when :func:`view_camera` uses it.

    Raises:
        ValueError: naming the file (missing, unreadable, not JSON, not an object
            of objects).
    """
    file, label = Path(path) if path is not None else views_path(), views_name(path)
    if not file.is_file():
        raise MissingFileError(f"{label}: no such views file" + (" (a folder)" if file.is_dir() else ""))
    data = read_json(file, label)
    if not isinstance(data, dict):
        raise ValueError(f"{label}: a views file is a JSON object of named cameras")
    views = {name: view for name, view in data.items() if not name.startswith("_")}
    for name, view in views.items():
        if not isinstance(view, dict):
            raise ValueError(f"{label}: view {name!r}: expected a camera object, got {view!r}")
    return views


def view_camera(name: str, path: str | os.PathLike | None = None,
                size: tuple[int, int] | None = None) -> Camera:
    """The camera of view ``name`` in a views file (default: the shipped one),
    at ``size = (width, height)`` if given, else the view's size or 640x480.

    Raises:
        ValueError: naming the file and the view (unknown view, bad camera).
    """
    views, label = load_views(path), views_name(path)
    if name not in views:
        raise ValueError(f"{label}: no view {name!r} (views: {', '.join(views) or 'none'})")
    try:
        return Camera.from_dict(views[name], size=size)
    except ValueError as exc:
        raise ValueError(f"{label}: view {name!r}: {exc}") from None
