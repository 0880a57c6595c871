"""Drop-ins for ``trimesh``: lbvh's kernels behind trimesh's ray and proximity APIs.

:class:`ProximityQuery` (what ``mesh.nearest`` is), :func:`closest_point` and
:func:`signed_distance` replace ``trimesh.proximity``'s, with its conventions
(float64 points and distances, int64 triangles, signed distances positive inside)::

    closest, distance, triangle_id = lbvh.trimesh.closest_point(mesh, points)
    sd = lbvh.trimesh.signed_distance(mesh, points)   # positive inside, as trimesh's

:class:`RayMeshIntersector` replaces ``trimesh.ray.ray_triangle.RayMeshIntersector``
(and ``trimesh.ray.ray_pyembree.RayMeshIntersector``) with one line::

    import trimesh, lbvh.trimesh
    mesh = trimesh.load("bunny.obj")
    mesh.ray = lbvh.trimesh.RayMeshIntersector(mesh)
    locations, index_ray, index_tri = mesh.ray.intersects_location(origins, directions)
    inside = mesh.contains(points)        # trimesh calls mesh.ray.contains_points

The constructor takes what trimesh's two intersectors take (the mesh first, or as
``geometry=`` or ``mesh=``; embree's ``scale_to_box``, which changes nothing here)
and refuses anything that is not a mesh (a ``trimesh.Scene``) with a ``ValueError``.
The methods have trimesh's names, argument names, return values and dtypes:
``intersects_id``, ``intersects_location``, ``intersects_first``,
``intersects_any`` and ``contains_points``, and the ``mesh`` attribute. The
module needs numpy only; any object with ``vertices (V, 3)`` and ``faces (F, 3)``
arrays serves as the mesh.

The BVH
    is built on the first query (:func:`lbvh.build`, under a lock, so threads
    sharing one intersector build it once) over the mesh's vertices translated
    by the centre of their bounding box (float32 keeps its precision around
    the mesh, as trimesh's embree wrapper does), and kept. Before each query
    the mesh's ``vertices`` and ``faces`` are hashed (a trimesh
    ``TrackedArray`` keeps its hash until it is written, so this is free; a
    plain numpy array is hashed in full); when they changed
    (``mesh.vertices += 1``, ``mesh.apply_translation(...)``) the BVH is
    rebuilt. (Writes trimesh cannot see, through a plain numpy view of its
    arrays, go unseen here too, as they do by trimesh's own caches.) A mesh
    without faces is hit by nothing and contains nothing.

Rays
    ``ray_origins`` and ``ray_directions`` are ``(N, 3)`` (anything numpy reads
    as float64). Directions need not be unit length; only their direction
    matters (trimesh's results are points, not distances). A NaN or infinite
    origin or direction, or a zero direction, is refused with a ``ValueError``
    naming the first such ray (trimesh's ``ray_triangle`` misses them, or fails
    in its r-tree for a NaN).

Hits and locations
    A ray hits a triangle in front of its origin or at it (``t >= 0``; trimesh
    also keeps hits up to ``1e-6`` direction lengths behind it; a ray starting
    on the surface may or may not report the triangle it starts on, in both).
    The triangles are found by lbvh's watertight float32 test (Woop, Benthin & Wald 2013) on the
    device; each hit's location is then recomputed in float64 as the
    intersection of the ray with the triangle's plane, as trimesh computes it,
    so locations agree with trimesh's to float64 rounding.

Edges and vertices
    A ray that crosses the surface through an edge or vertex that several
    triangles share hits exactly one of them with ``multiple_hits=True``, so
    every crossing is reported once (a ray that only grazes the surface at a
    silhouette edge reports it 0 or 2 times). trimesh's ``ray_triangle`` reports
    each triangle within 1e-13 (barycentric) of the point, so a ray through a
    shared edge hits both triangles and one through a vertex hits every triangle
    around it; its ``return_locations=True`` merges them again (same ray, same
    point). With ``multiple_hits=False`` and in ``intersects_first`` a hit on a
    shared edge is either triangle.

Order
    Hits come ray by ray (increasing ray index), and along each ray nearest
    first (equal distances: increasing triangle index). trimesh promises no
    order (its ``return_locations=True`` answers in hash order).

Differences from trimesh, on purpose
    * Bad rays (NaN, infinite, zero direction) raise instead of missing.
    * No locations comes back as ``float64 (0, 3)`` (embree's shape), where
      ``ray_triangle`` gives ``(0,)``.
    * Coincident (duplicated) faces each report their hit; ``ray_triangle``'s
      ``return_locations=True`` keeps one of the hits at one point.
    * ``contains_points`` is lbvh's generalised winding number
      (``bvh.contains``), not trimesh's ray parity: inside where the winding
      number is at least 1/2. The two agree for points clearly inside or
      outside a closed mesh.
    * The flags of ``intersects_id`` (``multiple_hits``, ``max_hits``,
      ``return_locations``) are keyword-only: trimesh's two intersectors take
      them in different positional orders. Unknown keywords are refused
      (``ray_triangle`` ignores them).
    * ``max_hits`` defaults to ``None``, every hit (``ray_triangle`` ignores
      ``max_hits``; embree's default is 100).
"""
from __future__ import annotations

import hashlib
import threading
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .api import build
from .bvh import BVH
from .queries.closest import closest_points_numpy, point_triangle_numpy

__all__ = ["RayMeshIntersector", "ProximityQuery", "closest_point", "signed_distance"]

# A hit's float64 plane intersection replaces the kernel's float32 distance unless
# the ray runs within this cosine of the triangle's plane (ill-conditioned) or the
# two disagree by more than _REFINE_AGREE of the distance plus the mesh's extent.
_REFINE_MIN_COSINE = 1e-7
_REFINE_AGREE = 1e-4


@dataclass(frozen=True)
class _Geometry:
    """What one build made: the BVH and the float64 mesh it was built from."""
    key: tuple[Any, ...]
    bvh: BVH | None              # None for a mesh without faces
    center: NDArray[np.float64]  # (3,): the BVH is built over vertices - center
    extent: float                # the bounding box's diagonal (0 for no faces)
    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]


def _array_key(value: Any) -> tuple[Any, ...]:
    """A key that changes when the array's contents change: trimesh's own cached
    content hash for a ``TrackedArray``, a BLAKE2 digest of the bytes otherwise."""
    if isinstance(value, np.ndarray) and type(value).__hash__ is not None:
        return (value.shape, value.dtype.str, hash(value))
    arr = np.ascontiguousarray(np.asarray(value))
    return (arr.shape, arr.dtype.str,
            hashlib.blake2b(arr.view(np.uint8).reshape(-1), digest_size=16).digest())


def _geometry_key(mesh: Any) -> tuple[Any, ...]:
    return _array_key(mesh.vertices) + _array_key(mesh.faces)


def _build(mesh: Any, key: tuple[Any, ...], device: Any) -> _Geometry:
    vertices = np.array(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.array(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return _Geometry(key, None, np.zeros(3), 0.0, vertices, faces)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    center = (lo + hi) / 2
    bvh = build(vertices - center, faces, device=device)
    return _Geometry(key, bvh, center, float(np.linalg.norm(hi - lo)), vertices, faces)


def _vectors(name: str, value: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: shape {arr.shape}, expected (n, 3)")
    return arr


def _first_bad_row(mask: NDArray[np.bool_]) -> int:
    return int(np.flatnonzero(mask)[0])


def _rays(ray_origins: ArrayLike, ray_directions: ArrayLike
          ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The rays as float64 ``(N, 3)`` origins and unit directions; a ``ValueError``
    naming the first bad ray."""
    o = _vectors("ray_origins", ray_origins)
    d = _vectors("ray_directions", ray_directions)
    if len(o) != len(d):
        raise ValueError(f"ray_directions: {len(d)} rays, but ray_origins has {len(o)}")
    for name, arr in (("ray_origins", o), ("ray_directions", d)):
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            i = _first_bad_row(bad)
            raise ValueError(f"{name}: ray {i} has a NaN or infinite component {arr[i].tolist()}")
    biggest = np.abs(d).max(axis=1) if len(d) else np.zeros(0)
    zero = biggest == 0
    if zero.any():
        i = _first_bad_row(zero)
        raise ValueError(f"ray_directions: ray {i} has a zero-length direction {d[i].tolist()}")
    # scaled first so that neither huge nor tiny directions over- or underflow
    d = d / biggest[:, None]
    d /= np.linalg.norm(d, axis=1)[:, None]
    return o, d


def _no_hits(return_locations: bool) -> tuple[NDArray[Any], ...]:
    empty = np.zeros(0, dtype=np.int64)
    if return_locations:
        return empty, empty.copy(), np.zeros((0, 3), dtype=np.float64)
    return empty, empty.copy()


def _locations(geom: _Geometry, o: NDArray[np.float64], d: NDArray[np.float64],
               t: NDArray[np.floating], tri: NDArray[np.int64]) -> NDArray[np.float64]:
    """``float64 (M, 3)``: where rays ``o + s * d`` (``d`` unit) meet triangles ``tri``:
    the float64 intersection with the triangle's plane, or ``o + t * d`` with the
    kernel's ``t`` where that is ill-conditioned."""
    corners = geom.vertices[geom.faces[tri]]
    p0 = corners[:, 0]
    normal = np.cross(corners[:, 1] - p0, corners[:, 2] - p0)
    along = np.einsum("ij,ij->i", d, normal)
    t64 = np.asarray(t, dtype=np.float64).copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        plane = np.einsum("ij,ij->i", p0 - o, normal) / along
        good = (np.abs(along) > _REFINE_MIN_COSINE * np.linalg.norm(normal, axis=1)) \
            & np.isfinite(plane) & (np.abs(plane - t64) <= _REFINE_AGREE * (np.abs(t64) + geom.extent))
    t64[good] = plane[good]
    return o + t64[:, None] * d


def _the_mesh(who: str, geometry: Any, mesh: Any) -> Any:
    """The mesh given once, as ``geometry`` (first argument) or ``mesh=``, checked to
    be a mesh (``vertices`` and ``faces``); a ``ValueError`` otherwise."""
    if (geometry is None) == (mesh is None):
        raise ValueError(f"{who}: pass the mesh once, as geometry (first argument) or mesh="
                         + ("" if geometry is None else ", not both"))
    mesh = geometry if mesh is None else mesh
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
        hint = (": merge it into one mesh first (scene.to_mesh()), or query its instances "
                "with lbvh.build(scene)" if hasattr(mesh, "geometry") else "")
        raise ValueError(f"{who}: a {type(mesh).__module__}.{type(mesh).__name__} is not a "
                         f"mesh (it has no vertices and faces){hint}")
    return mesh


class _GeometryCache:
    """The :class:`_Geometry` of a mesh, built on first use and again when the mesh's
    arrays change (their key, :func:`_geometry_key`), under a lock: threads sharing
    one drop-in build it once."""

    def __init__(self, device: Any) -> None:
        self._device = device
        self._lock = threading.Lock()
        self._geometry: _Geometry | None = None

    def get(self, mesh: Any) -> _Geometry:
        # the key is read before the arrays: a mesh changed during a build leaves a
        # stale key, and the next query rebuilds
        key = _geometry_key(mesh)
        geom = self._geometry
        if geom is not None and geom.key == key:
            return geom
        with self._lock:
            geom = self._geometry
            if geom is None or geom.key != key:
                geom = _build(mesh, key, self._device)
                self._geometry = geom
            return geom

    @property
    def state(self) -> str:
        return "built" if self._geometry is not None else "not built yet"


class RayMeshIntersector:
    """Ray queries on a trimesh mesh by lbvh: a drop-in for
    ``trimesh.ray.ray_triangle.RayMeshIntersector`` (see the module docstring for
    the conventions).

    Parameters
    ----------
    geometry : trimesh.Trimesh
        The mesh (anything with ``vertices (V, 3)`` and ``faces (F, 3)``); kept as
        :attr:`mesh`, read again whenever it changes. Also accepted by the name
        ``mesh=`` (``ray_triangle``'s). Anything else (a ``trimesh.Scene``, a
        ``PointCloud``) is refused here with a ``ValueError``.
    scale_to_box : bool
        Accepted as trimesh's embree intersector takes it, and changes nothing:
        embree scales the mesh to about a unit box to keep float32's precision,
        which lbvh's decisions do not need (the same hits at every scale; the
        BVH is built over the vertices less their box's centre, as embree's
        wrapper does, and each location recomputed in float64).
    device : optional
        The OpenCL device for :func:`lbvh.build` (a name, a ``pyopencl.Device``;
        ``None``: ``$LBVH_DEVICE`` or PoCL's CPU device).

    Attributes
    ----------
    mesh : trimesh.Trimesh
        The mesh queried (trimesh's ``contains_points`` helpers read ``mesh.bounds``).
    """

    def __init__(self, geometry: Any = None, scale_to_box: bool = True, *, mesh: Any = None,
                 device: Any = None) -> None:
        self.mesh = _the_mesh("RayMeshIntersector", geometry, mesh)
        if not isinstance(scale_to_box, (bool, np.bool_)):
            raise ValueError(f"scale_to_box: {scale_to_box!r}; expected True or False")
        self._device = device
        self._scale_to_box = bool(scale_to_box)
        self._cache = _GeometryCache(device)

    # -- the BVH, built on first use and again when the mesh changes -------------
    def _geometry(self) -> _Geometry:
        return self._cache.get(self.mesh)

    @property
    def bvh(self) -> BVH | None:
        """The :class:`lbvh.BVH` of the current mesh (built now if needed), over the
        vertices translated by ``-center`` (see :attr:`center`); ``None`` for a
        mesh without faces."""
        return self._geometry().bvh

    @property
    def center(self) -> NDArray[np.float64]:
        """``float64 (3,)``: the translation of the :attr:`bvh`'s coordinates: a point
        ``p`` of the mesh is ``p - center`` in the BVH."""
        return self._geometry().center.copy()

    # -- trimesh's API -------------------------------------------------------------
    def intersects_id(self, ray_origins: ArrayLike, ray_directions: ArrayLike, *,
                      multiple_hits: bool = True, max_hits: int | None = None,
                      return_locations: bool = False) -> tuple[NDArray[Any], ...]:
        """The triangles hit by each ray.

        Parameters
        ----------
        ray_origins : (n, 3) float
            Origins of the rays.
        ray_directions : (n, 3) float
            Directions of the rays, of any nonzero length.
        multiple_hits : bool
            Every hit of each ray (``True``), or only its nearest (``False``).
        max_hits : int or None
            With ``multiple_hits``, at most this many hits per ray, the nearest
            (``None``: all).
        return_locations : bool
            Also return where each hit is.

        Returns
        -------
        index_tri : int64 (m,)
            The triangle (index into ``mesh.faces``) of each hit.
        index_ray : int64 (m,)
            The ray of each hit; hits come ray by ray, nearest first.
        locations : float64 (m, 3)
            Only with ``return_locations``: the hit points.

        Raises
        ------
        ValueError
            A bad ray (named), mismatched shapes, a bad ``max_hits``.
        """
        o, d = _rays(ray_origins, ray_directions)
        geom = self._geometry()
        if geom.bvh is None or len(o) == 0:
            return _no_hits(return_locations)
        local = o - geom.center
        if multiple_hits:
            found = geom.bvh.all_hits(local, d, max_hits=max_hits)
            index_tri = found.prim.astype(np.int64)
            index_ray = found.ray.astype(np.int64)
            t = found.t
        else:
            hits = geom.bvh.intersect(local, d)
            index_ray = np.flatnonzero(hits.prim >= 0).astype(np.int64)
            index_tri = hits.prim[index_ray].astype(np.int64)
            t = hits.t[index_ray]
        if not return_locations:
            return index_tri, index_ray
        return index_tri, index_ray, _locations(geom, o[index_ray], d[index_ray], t, index_tri)

    def intersects_location(self, ray_origins: ArrayLike, ray_directions: ArrayLike,
                            multiple_hits: bool = True, *, max_hits: int | None = None
                            ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
        """Where the rays hit the mesh.

        Parameters
        ----------
        ray_origins, ray_directions : (n, 3) float
            The rays, as for :meth:`intersects_id`.
        multiple_hits : bool
            Every hit of each ray, or only the nearest.
        max_hits : int or None
            As for :meth:`intersects_id`.

        Returns
        -------
        locations : float64 (m, 3)
            The hit points (a crossing through a shared edge or vertex once).
        index_ray : int64 (m,)
            The ray of each hit, ray by ray, nearest first.
        index_tri : int64 (m,)
            The triangle of each hit.
        """
        index_tri, index_ray, locations = self.intersects_id(
            ray_origins, ray_directions, multiple_hits=multiple_hits, max_hits=max_hits,
            return_locations=True)
        return locations, index_ray, index_tri

    def intersects_first(self, ray_origins: ArrayLike, ray_directions: ArrayLike
                         ) -> NDArray[np.int64]:
        """The first triangle each ray hits.

        Parameters
        ----------
        ray_origins, ray_directions : (n, 3) float
            The rays, as for :meth:`intersects_id`.

        Returns
        -------
        triangle_index : int64 (n,)
            The nearest triangle hit by each ray, ``-1`` where none is.
        """
        return self._per_ray(ray_origins, ray_directions, -1, np.int64,
                             lambda bvh, o, d: bvh.intersect(o, d).prim.astype(np.int64))

    def intersects_any(self, ray_origins: ArrayLike, ray_directions: ArrayLike
                       ) -> NDArray[np.bool_]:
        """Whether each ray hits the mesh.

        Parameters
        ----------
        ray_origins, ray_directions : (n, 3) float
            The rays, as for :meth:`intersects_id`.

        Returns
        -------
        hit : bool (n,)
        """
        return self._per_ray(ray_origins, ray_directions, False, np.bool_,
                             lambda bvh, o, d: np.asarray(bvh.occluded(o, d), dtype=bool))

    def _per_ray(self, ray_origins: ArrayLike, ray_directions: ArrayLike, miss: Any,
                 dtype: type, answer: Any) -> Any:
        """``answer(bvh, origins, directions)`` on the checked rays, moved to the BVH's
        frame; ``miss`` for every ray where nothing can be hit (no faces, no rays)."""
        o, d = _rays(ray_origins, ray_directions)
        geom = self._geometry()
        if geom.bvh is None or len(o) == 0:
            return np.full(len(o), miss, dtype=dtype)
        return answer(geom.bvh, o - geom.center, d)

    def contains_points(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Whether each point is inside the mesh (``mesh.contains`` calls this).

        lbvh's generalised winding number (``bvh.contains``): inside where it is
        at least 1/2. For points on the surface the answer is either.

        Parameters
        ----------
        points : (n, 3) float
            Points in space.

        Returns
        -------
        contains : bool (n,)
        """
        p = _points(points)
        geom = self._geometry()
        if geom.bvh is None or len(p) == 0:
            return np.zeros(len(p), dtype=bool)
        return np.asarray(geom.bvh.contains(p - geom.center), dtype=bool).reshape(len(p))

    # -- copies and pickles: the mesh travels, the BVH is built again --------------
    def __getstate__(self) -> dict[str, Any]:
        return {"mesh": self.mesh, "device": self._device, "scale_to_box": self._scale_to_box}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["mesh"], state.get("scale_to_box", True),  # type: ignore[misc]
                      device=state["device"])

    def __repr__(self) -> str:
        faces = getattr(self.mesh, "faces", None)
        count = len(faces) if faces is not None else 0
        return f"<lbvh.trimesh.RayMeshIntersector: {count} triangles, BVH {self._cache.state}>"


# -- proximity: trimesh.proximity's calls -------------------------------------------------

#: trimesh's ``tol.merge``: a point this close to the surface has a positive signed
#: distance in trimesh's convention, whatever side it is on.
_ON_SURFACE = 1e-8


def _points(points: ArrayLike) -> NDArray[np.float64]:
    p = _vectors("points", points)
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        i = _first_bad_row(bad)
        raise ValueError(f"points: point {i} has a NaN or infinite component {p[i].tolist()}")
    return p


class ProximityQuery:
    """Proximity queries on a trimesh mesh by lbvh: a drop-in for
    ``trimesh.proximity.ProximityQuery`` (what ``mesh.nearest`` is), with trimesh's
    conventions: float64 points and distances, int64 triangle indices, and a signed
    distance positive inside.

    The closest triangle is found by lbvh's walk (``bvh.closest_points``, float32,
    on the vertices less their box's centre, as the ray drop-in builds them); the
    closest point and the distance are then recomputed in float64 on that triangle,
    as trimesh computes them. Where two triangles are within float32 rounding of the
    same distance either may be reported (trimesh picks between two such by their
    normals); the distance agrees with trimesh's to that rounding. A point whose
    walk overflowed its stack is answered by the float64 brute force. Inside is
    lbvh's winding number (at least 1/2), where trimesh casts rays: the two agree
    for points clearly inside or outside a closed mesh. A mesh without faces has
    no closest point: NaN points, infinite distances, triangle -1 (trimesh fails).
    NaN or infinite points are refused with a ``ValueError`` naming the first.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Anything with ``vertices (V, 3)`` and ``faces (F, 3)``; read again when it
        changes (the BVH is rebuilt), as :class:`RayMeshIntersector` does.
    device : optional
        The OpenCL device for :func:`lbvh.build`.
    """

    def __init__(self, mesh: Any, *, device: Any = None) -> None:
        self._mesh = _the_mesh("ProximityQuery", mesh, None)
        self._device = device
        self._cache = _GeometryCache(device)

    def on_surface(self, points: ArrayLike
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """For each point the closest point on the mesh.

        Parameters
        ----------
        points : (m, 3) float
            Points in space.

        Returns
        -------
        closest : (m, 3) float64
            The closest point of the mesh to each point.
        distance : (m,) float64
            The distance to it.
        triangle_id : (m,) int64
            The triangle it lies on.
        """
        return self._closest(_points(points))[:3]

    def signed_distance(self, points: ArrayLike) -> NDArray[np.float64]:
        """The distance of each point to the mesh, in trimesh's sign: positive inside,
        negative outside, positive within ``1e-8`` (trimesh's ``tol.merge``) of the
        surface.

        Parameters
        ----------
        points : (n, 3) float
            Points in space.

        Returns
        -------
        signed_distance : (n,) float64
        """
        p = _points(points)
        _, distance, _, geom = self._closest(p)
        if geom.bvh is None or len(p) == 0:
            return -distance
        inside = np.asarray(geom.bvh.contains(p - geom.center), dtype=bool).reshape(len(p))
        signed = np.where(inside, distance, -distance)
        near = distance <= _ON_SURFACE
        signed[near] = distance[near]
        return signed

    def vertex(self, points: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The closest vertex of each point: ``(distance, vertex_id)``, by trimesh's own
        ``mesh.kdtree`` (scipy), as trimesh answers it: a nearest vertex is no
        triangle query."""
        return self._mesh.kdtree.query(_points(points))

    def _closest(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                         NDArray[np.int64], _Geometry]:
        geom = self._cache.get(self._mesh)
        n = len(p)
        if geom.bvh is None or n == 0:
            return (np.full((n, 3), np.nan), np.full(n, np.inf), np.full(n, -1, np.int64), geom)
        got = geom.bvh.closest_points(p - geom.center)
        tri = got.prim.astype(np.int64)
        if got.overflow_count:   # never a guess: the float64 brute force for those points
            redo = np.flatnonzero(got.overflow | (tri < 0))
            tri[redo] = closest_points_numpy(geom.vertices, geom.faces, p[redo])[2]
        corners = geom.vertices[geom.faces[tri]]
        closest = point_triangle_numpy(p, corners[:, 0], corners[:, 1], corners[:, 2])
        return closest, np.linalg.norm(p - closest, axis=1), tri, geom

    # -- copies and pickles: the mesh travels, the BVH is built again --------------
    def __getstate__(self) -> dict[str, Any]:
        return {"mesh": self._mesh, "device": self._device}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["mesh"], device=state["device"])  # type: ignore[misc]

    def __repr__(self) -> str:
        faces = getattr(self._mesh, "faces", None)
        count = len(faces) if faces is not None else 0
        return f"<lbvh.trimesh.ProximityQuery: {count} triangles, BVH {self._cache.state}>"


_queries: "weakref.WeakKeyDictionary[Any, ProximityQuery]" = weakref.WeakKeyDictionary()
_queries_lock = threading.Lock()


def _query_of(mesh: Any) -> ProximityQuery:
    """One :class:`ProximityQuery` per mesh object (kept while the mesh lives), so that
    repeated calls of the functions below build the BVH once."""
    with _queries_lock:
        try:
            query = _queries.get(mesh)
        except TypeError:   # not weak-referenceable: a query for this call only
            return ProximityQuery(mesh)
        if query is None:
            query = _queries[mesh] = ProximityQuery(mesh)
        return query


def closest_point(mesh: Any, points: ArrayLike
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """``trimesh.proximity.closest_point(mesh, points)`` by lbvh: ``(closest (m, 3),
    distance (m,), triangle_id (m,))``, float64, float64, int64
    (:meth:`ProximityQuery.on_surface`)."""
    return _query_of(mesh).on_surface(points)


def signed_distance(mesh: Any, points: ArrayLike) -> NDArray[np.float64]:
    """``trimesh.proximity.signed_distance(mesh, points)`` by lbvh: float64, positive
    inside (:meth:`ProximityQuery.signed_distance`)."""
    return _query_of(mesh).signed_distance(points)
