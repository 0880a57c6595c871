"""What the bench scripts share (bench_build, bench_builders, bench_traverse, bench_queries):
one home each.

bench/ is not a package. A script run as ``python bench/<script>.py`` has its
own folder on ``sys.path`` and imports this module as ``common``; the tests
put bench/ on ``sys.path`` before they load a script. No bench script imports
another one: what two of them need lives here.

* the environment: ``OPENBLAS_NUM_THREADS=1``, set before numpy loads (so a
  script imports this module before numpy);
* scenes: the shipped (``scenes/``), shared (``../shared/scenes``) and
  generated (:mod:`lbvh.verification.meshes`) scenes by name, the cameras of
  ``lbvh/data/cameras.json``, :class:`Scene` and its loading;
* the peers: :class:`Embree` (embreex) and :class:`Warp` (warp-lang on the
  CPU), each with its build, closest-hit and any-hit query, and
  :func:`load_peers`; for bench_queries, :class:`Open3D` (``RaycastingScene``),
  :class:`Trimesh` and warp's point, hit-count and box queries (:data:`QUERY_PEERS`);
* the machine: :func:`cpu_model`, :func:`library_versions`, :func:`machine_info`;
* timing: :func:`median`, :func:`timed`, :func:`cores_used`,
  :func:`interleaved_rounds`, :class:`Progress`;
* hits: :func:`agreement` with a reference tracer, and the floor of ``|cos a|``
  in the float32 bound on ``t`` the benches use (the bound itself is
  :func:`lbvh.metrics.error_bound.t_bound`);
* the command-line options and the report writing of the benches that trace
  camera rays, and :func:`save_view`.

The cost constants of the SAH come from :mod:`lbvh.metrics.cost`.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib
import json
import os
import platform
import statistics
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

# numpy's OpenBLAS threads spin for a while after any BLAS call and take cycles
# from the device's threads (about 5% of a build profile); nothing measured here
# uses BLAS. Set before numpy is imported: the scripts import this module first.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pyopencl as cl  # noqa: E402

from lbvh.verification import meshes  # noqa: E402

import lbvh  # noqa: E402
from lbvh import device as dev  # noqa: E402
from lbvh.progress import bar as progress_bar  # noqa: E402
from lbvh.camera import Camera  # noqa: E402
from lbvh.rendering.image import write_image  # noqa: E402
from lbvh.rendering.render import display, shade_primary  # noqa: E402
from lbvh.files import load_mesh  # noqa: E402
from lbvh.metrics.error_bound import T_BOUND_ULPS  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
SHIPPED_SCENES = REPO / "scenes"
SHARED_SCENES = REPO.parent / "shared" / "scenes"
CAMERAS = lbvh.data.views_path()   # one set of views: the one that ships with lbvh
#: Default output folder of the benches (git-ignored).
DEFAULT_OUT = HERE / "out"


# -- hits --------------------------------------------------------------------------

#: Floor of ``|cos a|`` in the benches' agreement test: the float32 bound on ``t``
#: (:func:`lbvh.metrics.error_bound.t_bound`, whose own floor only keeps the
#: quotient finite) with a floor of 1e-3, a stricter test for grazing rays, as the
#: tables' column notes say.
AGREEMENT_COS_FLOOR = 1e-3
#: The bound of the agreement test, as the reports' settings state it.
AGREEMENT_T_BOUND = f"{T_BOUND_ULPS} * 2^-24 * (t_ref + s) / max(|cos a|, {AGREEMENT_COS_FLOOR})"


def agreement(t: np.ndarray, prim: np.ndarray, t_ref: np.ndarray, prim_ref: np.ndarray,
              bound: np.ndarray) -> dict:
    """How far a ray query's closest hits agree with the reference's: the fraction of
    rays with the same hit or miss, the same primitive and ``t`` within ``bound``
    (``fraction``), and the same counting another primitive at ``t`` within the
    bound (``fraction_with_ties``: two triangles meeting the ray at one point)."""
    hit, hit_ref = prim >= 0, prim_ref >= 0
    same_status = hit == hit_ref
    both = hit & hit_ref
    err = np.zeros(len(t))
    err[both] = np.abs(t[both].astype(np.float64) - t_ref[both])
    t_ok = ~both | (err <= bound)
    same_prim = prim == prim_ref
    strict = same_status & t_ok & (~both | same_prim)
    with_ties = same_status & t_ok
    n = max(len(t), 1)
    worst = float((err[both] / bound[both]).max()) if both.any() else 0.0
    return {"fraction": float(strict.sum() / n), "fraction_with_ties": float(with_ties.sum() / n),
            "hit_miss_differ": int((~same_status).sum()),
            "ties": int((both & ~same_prim & t_ok).sum()),
            "t_out_of_bound": int((both & ~t_ok).sum()), "max_t_error_over_bound": worst}


# -- scenes ------------------------------------------------------------------------

#: Scenes read from files: name -> (folder, file).
FILE_SCENES = {
    "teapot": (SHIPPED_SCENES, "teapot.obj"),
    "suzanne": (SHIPPED_SCENES, "suzanne.obj"),
    "bunny": (SHARED_SCENES, "stanford-bunny.obj"),
    "sponza": (SHARED_SCENES, "crytek_sponza.obj"),
    "sibenik": (SHARED_SCENES, "sibenik.obj"),
    "conference": (SHARED_SCENES, "conference.obj"),
}
#: Generated scenes (lbvh/verification/meshes.py), at least 1M triangles each.
GENERATED_SCENES: dict[str, Callable[[], tuple[np.ndarray, np.ndarray]]] = {
    "soup-1m": lambda: meshes.soup(1_000_000, seed=0),
    "terrain-1m": lambda: meshes.terrain(1_002_528, seed=0),   # 2 * 708^2 triangles
    "blob-1m": lambda: meshes.blob(1_000_000, seed=0),         # closed: 4 * 500^2 triangles
}


@dataclass
class Scene:
    name: str
    source: str
    vertices: np.ndarray
    faces: np.ndarray
    camera: Camera


def load_cameras(path: Path = CAMERAS) -> dict[str, dict]:
    data = json.loads(Path(path).read_text())
    return {k: v for k, v in data.items() if not k.startswith("_")}


def known_scenes() -> list[str]:
    return [*FILE_SCENES, *GENERATED_SCENES]


def scene_file(name: str, shared: Path = SHARED_SCENES) -> Path:
    """The file of scene ``name`` (:data:`FILE_SCENES`; another name: ``<name>.obj``
    in the shared folder), with ``shared`` in place of the shared scenes' folder."""
    folder, filename = FILE_SCENES.get(name, (SHARED_SCENES, f"{name}.obj"))
    return (shared if folder == SHARED_SCENES else folder) / filename


def load_bench_scene(name: str, size: tuple[int, int], cameras: dict[str, dict],
                     shared: Path = SHARED_SCENES) -> Scene | str:
    """The scene and its camera at ``size = (width, height)``, or why it is skipped."""
    if name not in cameras:
        return f"no camera for {name!r} in {CAMERAS.name}"
    camera = Camera.from_dict(cameras[name], size=size)
    if name in GENERATED_SCENES:
        v, f = GENERATED_SCENES[name]()
        return Scene(name, "lbvh/verification/meshes.py", v, f, camera)
    path = scene_file(name, shared)
    if not path.is_file():
        return f"{path} not found"
    v, f = load_mesh(path)
    return Scene(name, str(path), v, f, camera)


def loaded_scenes(names: list[str], load: Callable[[str], "Scene | str"], progress: "Progress",
                  steps: int, skipped: list[dict]) -> Iterator[Scene]:
    """Each scene that ``load(name)`` returns, in order, with progress. A scene it
    cannot load (it returns the reason, a string) goes to ``skipped``, and its
    ``steps`` count as done."""
    for name in names:
        progress.begin(f"{name}:")
        progress.note("loading")
        scene = load(name)
        if isinstance(scene, str):
            skipped.append({"scene": name, "reason": scene})
            progress.skip(steps)
            continue
        yield scene


def save_view(path: Path, scene: Scene, directions: np.ndarray, t: np.ndarray, prim: np.ndarray) -> None:
    """What the camera sees (headlight shading of the given hits), for choosing cameras."""
    image = shade_primary("diffuse", t, prim, directions, scene.vertices, scene.faces,
                          scene.camera.width, scene.camera.height)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, display("diffuse", image))


# -- the peers ------------------------------------------------------------------------

@dataclass(frozen=True)
class Variant:
    """One builder or tracer configuration: ``family`` is ``lbvh`` or ``sah`` (our
    trees, traced by our kernel), ``embree`` or ``warp`` (peers), or another word a
    bench gives its own rows; ``options`` are the builder's keyword arguments."""
    name: str
    family: str
    options: dict = field(default_factory=dict, hash=False)

    @property
    def ours(self) -> bool:
        return self.family in ("lbvh", "sah")


class Embree:
    """Embree 4 through embreex: the build is the scene commit, run by the first query.
    Raises ``ImportError`` when embreex is not installed."""

    def __init__(self) -> None:
        from embreex import mesh_construction, rtcore_scene
        self.rtcs, self.mc = rtcore_scene, mesh_construction
        import embreex
        self.version = getattr(embreex, "__version__", "installed")

    def variants(self) -> list[Variant]:
        return [Variant("embree", "embree")]

    def build(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float, Any]:
        """``(setup seconds, build seconds, scene)``: setup is the scene's creation and
        the copy of the mesh into it, build the commit (a one-ray query)."""
        faces_i32 = faces.astype(np.int32)
        t0 = time.perf_counter()
        scene = self.rtcs.EmbreeScene()
        mesh = self.mc.TriangleMesh(scene, vertices, faces_i32)
        t1 = time.perf_counter()
        scene.run(np.zeros((1, 3), np.float32), np.float32([[0.0, 0.0, 1.0]]))   # commit = build
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1, (scene, mesh)

    def trace(self, built: Any, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest hits ``(t float32, prim int32)``, ``inf`` / ``-1`` on a miss."""
        out = built[0].run(origins, directions, output=1)
        prim = out["primID"].astype(np.int32)
        t = np.where(prim >= 0, out["tfar"], np.inf).astype(np.float32)
        return t, prim

    def occluded(self, built: Any, origins: np.ndarray, directions: np.ndarray,
                 tmax: float) -> np.ndarray:
        """Any hit within ``tmax``: ``bool (N,)``."""
        # dists is Embree's tfar per ray; a fresh array (embreex writes into it)
        hit_geometry = built[0].run(origins, directions, dists=np.full(len(origins), tmax, np.float32),
                                    query="OCCLUDED")
        return hit_geometry >= 0


def warp_has_builtin(wp: Any, name: str) -> bool:
    """Whether this warp's kernels can call builtin ``name`` (builtins are not module
    attributes; their table moved to ``warp._src`` in warp 1.10)."""
    for module in ("warp._src.context", "warp.context"):
        try:
            return name in importlib.import_module(module).builtin_functions
        except (ImportError, AttributeError):
            continue
    return hasattr(wp, name)


class Warp:
    """warp-lang's ``wp.Mesh`` on the CPU device, one variant per BVH constructor; a
    CPU launch runs on one thread. Raises ``ImportError`` when warp is not installed."""

    CONSTRUCTORS = ("sah", "median", "cubql")

    def __init__(self) -> None:
        import warp as wp
        wp.config.quiet = True
        with contextlib.redirect_stdout(sys.stderr):   # keep stdout pure Markdown
            wp.init()
        self.wp = wp
        self.version = wp.__version__
        self.has_any_hit = warp_has_builtin(wp, "mesh_query_ray_anyhit")
        self._kernels: tuple[Any, Any] | None = None

    @property
    def any_hit_note(self) -> str:
        return ("wp.mesh_query_ray_anyhit" if self.has_any_hit else
                "this warp has no any-hit query: closest hit wp.mesh_query_ray with max_t")

    def variants(self) -> list[Variant]:
        return [Variant(f"warp-{c}", "warp", {"bvh_constructor": c}) for c in self.CONSTRUCTORS]

    def arrays(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[Any, Any]:
        """The mesh as warp arrays on the CPU: ``(points, indices)``."""
        wp = self.wp
        return (wp.array(vertices, dtype=wp.vec3, device="cpu"),
                wp.array(faces.astype(np.int32).ravel(), dtype=wp.int32, device="cpu"))

    def mesh(self, points: Any, indices: Any, bvh_constructor: str) -> Any:
        """``wp.Mesh`` with this constructor; a warning (warp's silent fallback to
        another constructor) raises instead."""
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            return self.wp.Mesh(points, indices, bvh_constructor=bvh_constructor)

    def build(self, vertices: np.ndarray, faces: np.ndarray,
              bvh_constructor: str = "sah") -> tuple[float, float, Any]:
        """``(setup seconds, build seconds, mesh)``: setup is the copy into warp arrays."""
        t0 = time.perf_counter()
        points, indices = self.arrays(vertices, faces)
        t1 = time.perf_counter()
        mesh = self.mesh(points, indices, bvh_constructor)
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1, mesh

    def kernels(self) -> tuple[Any, Any]:
        """The closest-hit and any-hit kernels, made together on first use (warp
        compiles a module's kernels at once, and caches them on disk)."""
        if self._kernels is None:
            wp = self.wp

            @wp.kernel
            def closest_hit(mesh: wp.uint64, origins: wp.array(dtype=wp.vec3),
                            directions: wp.array(dtype=wp.vec3), t_out: wp.array(dtype=float),
                            prim_out: wp.array(dtype=int)):
                i = wp.tid()
                q = wp.mesh_query_ray(mesh, origins[i], directions[i], 1.0e30)
                if q.result:
                    t_out[i] = q.t
                    prim_out[i] = q.face
                else:
                    t_out[i] = wp.inf
                    prim_out[i] = -1

            if self.has_any_hit:
                @wp.func
                def blocked(mesh: wp.uint64, o: wp.vec3, d: wp.vec3, max_t: float) -> bool:
                    return wp.mesh_query_ray_anyhit(mesh, o, d, max_t)
            else:
                @wp.func
                def blocked(mesh: wp.uint64, o: wp.vec3, d: wp.vec3, max_t: float) -> bool:
                    return wp.mesh_query_ray(mesh, o, d, max_t).result

            @wp.kernel
            def any_hit(mesh: wp.uint64, origins: wp.array(dtype=wp.vec3),
                        directions: wp.array(dtype=wp.vec3), max_t: float,
                        hit_out: wp.array(dtype=wp.int32)):
                i = wp.tid()
                hit_out[i] = 0
                if blocked(mesh, origins[i], directions[i], max_t):
                    hit_out[i] = 1

            self._kernels = (closest_hit, any_hit)
        return self._kernels

    def _launch(self, kernel: Any, n: int, inputs: list) -> None:
        with contextlib.redirect_stdout(sys.stderr):   # warp reports module loads on stdout
            self.wp.launch(kernel, dim=n, device="cpu", inputs=inputs)
            self.wp.synchronize()

    def _vec3(self, a: np.ndarray) -> Any:
        return self.wp.array(a, dtype=self.wp.vec3, device="cpu")

    def trace(self, mesh: Any, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest hits ``(t float32, prim int32)``, ``inf`` / ``-1`` on a miss."""
        wp = self.wp
        n = len(origins)
        t = wp.empty(n, dtype=float, device="cpu")
        prim = wp.empty(n, dtype=int, device="cpu")
        self._launch(self.kernels()[0], n,
                     [mesh.id, self._vec3(origins), self._vec3(directions), t, prim])
        return t.numpy().astype(np.float32), prim.numpy().astype(np.int32)

    def occluded(self, mesh: Any, origins: np.ndarray, directions: np.ndarray,
                 tmax: float) -> np.ndarray:
        """Any hit within ``tmax`` (:attr:`any_hit_note` says which query): ``bool (N,)``."""
        n = len(origins)
        hit = self.wp.empty(n, dtype=self.wp.int32, device="cpu")
        self._launch(self.kernels()[1], n,
                     [mesh.id, self._vec3(origins), self._vec3(directions), float(tmax), hit])
        return hit.numpy() != 0


    def closest_points(self, mesh: Any, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest points by ``wp.mesh_query_point_no_sign``: ``(distance float32, face
        int32)``; ``inf`` / ``-1`` where nothing was found."""
        wp = self.wp
        if getattr(self, "_closest", None) is None:
            @wp.kernel
            def closest(mesh: wp.uint64, points: wp.array(dtype=wp.vec3),
                        d_out: wp.array(dtype=float), face_out: wp.array(dtype=int)):
                i = wp.tid()
                q = wp.mesh_query_point_no_sign(mesh, points[i], 1.0e30)
                if q.result:
                    d_out[i] = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - points[i])
                    face_out[i] = q.face
                else:
                    d_out[i] = wp.inf
                    face_out[i] = -1
            self._closest = closest
        n = len(points)
        d, face = wp.empty(n, dtype=float, device="cpu"), wp.empty(n, dtype=int, device="cpu")
        self._launch(self._closest, n, [mesh.id, self._vec3(points), d, face])
        return d.numpy().astype(np.float32), face.numpy().astype(np.int32)

    # -- the other point, ray and box queries (bench_queries.py) ----------------------

    def winding_mesh(self, vertices: np.ndarray, faces: np.ndarray,
                     bvh_constructor: str = "sah") -> tuple[float, float, Any]:
        """``(setup seconds, build seconds, mesh)`` like :meth:`build`, the mesh made with
        ``support_winding_number=True``: what ``wp.mesh_query_point_sign_winding_number``
        needs (without it warp falls back, silently, to its three-ray vote)."""
        t0 = time.perf_counter()
        points, indices = self.arrays(vertices, faces)
        t1 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            mesh = self.wp.Mesh(points, indices, support_winding_number=True,
                                bvh_constructor=bvh_constructor)
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1, mesh

    def query_kernels(self) -> dict[str, Any]:
        """The kernels of :meth:`signed_distance`, :meth:`count_hits` and :meth:`overlapping`,
        made together on first use (one compilation of this module)."""
        if getattr(self, "_query_kernels", None) is None:
            wp = self.wp

            @wp.kernel
            def signed(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), accuracy: float,
                       d_out: wp.array(dtype=float), inside_out: wp.array(dtype=wp.int32)):
                i = wp.tid()
                q = wp.mesh_query_point_sign_winding_number(mesh, points[i], 1.0e30, accuracy, 0.5)
                d_out[i] = wp.inf
                inside_out[i] = 0
                if q.result:
                    d = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - points[i])
                    d_out[i] = q.sign * d
                    if q.sign < 0.0:
                        inside_out[i] = 1

            @wp.kernel
            def count(mesh: wp.uint64, origins: wp.array(dtype=wp.vec3),
                      directions: wp.array(dtype=wp.vec3), n_out: wp.array(dtype=wp.int32)):
                i = wp.tid()
                n_out[i] = wp.mesh_query_ray_count_intersections(mesh, origins[i], directions[i])

            @wp.kernel
            def box_count(mesh: wp.uint64, lower: wp.array(dtype=wp.vec3),
                          upper: wp.array(dtype=wp.vec3), n_out: wp.array(dtype=wp.int32)):
                i = wp.tid()
                q = wp.mesh_query_aabb(mesh, lower[i], upper[i])
                face = int(0)
                n = int(0)
                while wp.mesh_query_aabb_next(q, face):
                    n += 1
                n_out[i] = n

            @wp.kernel
            def box_fill(mesh: wp.uint64, lower: wp.array(dtype=wp.vec3),
                         upper: wp.array(dtype=wp.vec3), offsets: wp.array(dtype=wp.int32),
                         prims: wp.array(dtype=wp.int32)):
                i = wp.tid()
                q = wp.mesh_query_aabb(mesh, lower[i], upper[i])
                face = int(0)
                k = offsets[i]
                while wp.mesh_query_aabb_next(q, face):
                    prims[k] = face
                    k += 1

            self._query_kernels = {"signed": signed, "count": count, "box_count": box_count,
                                   "box_fill": box_fill}
        return self._query_kernels

    def _signed(self, mesh: Any, points: np.ndarray, accuracy: float) -> tuple[np.ndarray, np.ndarray]:
        wp = self.wp
        n = len(points)
        d = wp.empty(n, dtype=float, device="cpu")
        inside = wp.empty(n, dtype=wp.int32, device="cpu")
        self._launch(self.query_kernels()["signed"], n,
                     [mesh.id, self._vec3(points), float(accuracy), d, inside])
        return d.numpy().astype(np.float32), inside.numpy() != 0

    def signed_distance(self, mesh: Any, points: np.ndarray, accuracy: float = 2.0) -> np.ndarray:
        """``float32 (N,)`` by ``wp.mesh_query_point_sign_winding_number`` (fast winding
        numbers, ``accuracy`` its beta, inside where ``w > 0.5``), negative inside; the
        mesh from :meth:`winding_mesh`."""
        return self._signed(mesh, points, accuracy)[0]

    def contains(self, mesh: Any, points: np.ndarray, accuracy: float = 2.0) -> np.ndarray:
        """``bool (N,)``: the sign of the same query (warp has no inside test without the
        closest point)."""
        return self._signed(mesh, points, accuracy)[1]

    def count_hits(self, mesh: Any, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """``int32 (N,)`` by ``wp.mesh_query_ray_count_intersections`` (hits with ``t >= 0``)."""
        n = len(origins)
        out = self.wp.empty(n, dtype=self.wp.int32, device="cpu")
        self._launch(self.query_kernels()["count"], n,
                     [mesh.id, self._vec3(origins), self._vec3(directions), out])
        return out.numpy()

    def overlapping(self, mesh: Any, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The triangles whose boxes overlap each box by ``wp.mesh_query_aabb``, as
        ``(offsets int64 (N + 1,), prims int32)``: one pass counts, numpy's cumulative
        sum places, a second pass writes (each box's triangles in warp's traversal order)."""
        wp, kernels = self.wp, self.query_kernels()
        n = len(lower)
        lo, hi = self._vec3(lower), self._vec3(upper)
        counts = wp.empty(n, dtype=wp.int32, device="cpu")
        self._launch(kernels["box_count"], n, [mesh.id, lo, hi, counts])
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(counts.numpy(), out=offsets[1:])
        prims = wp.empty(max(int(offsets[-1]), 1), dtype=wp.int32, device="cpu")
        self._launch(kernels["box_fill"], n,
                     [mesh.id, lo, hi, wp.array(offsets[:-1].astype(np.int32), dtype=wp.int32,
                                                device="cpu"), prims])
        return offsets, prims.numpy()[:int(offsets[-1])]


class Open3D:
    """Open3D's ``o3d.t.geometry.RaycastingScene`` on the CPU (Embree inside), each query
    on ``threads`` threads (its ``nthreads``; 0 would be its own choice). Raises
    ``ImportError`` when open3d is not installed. Every query takes numpy arrays and
    answers numpy arrays: the tensor wrapping is part of each call."""

    def __init__(self, threads: int = 2) -> None:
        import open3d as o3d
        self.o3d = o3d
        self.threads = threads
        self.version = f"{o3d.__version__} (nthreads={threads})"

    def _tensor(self, a: np.ndarray) -> Any:
        return self.o3d.core.Tensor.from_numpy(np.ascontiguousarray(a))

    def build(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float, Any]:
        """``(setup seconds, build seconds, scene)``: setup is the scene's creation and
        ``add_triangles``, build the commit that the first query runs."""
        t0 = time.perf_counter()
        scene = self.o3d.t.geometry.RaycastingScene(nthreads=self.threads)
        scene.add_triangles(self._tensor(vertices.astype(np.float32)),
                            self._tensor(faces.astype(np.uint32)))
        t1 = time.perf_counter()
        scene.count_intersections(self._tensor(np.float32([[0, 0, 0, 0, 0, 1]])), nthreads=self.threads)
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1, scene

    def _rays(self, origins: np.ndarray, directions: np.ndarray) -> Any:
        return self._tensor(np.hstack([origins, directions]).astype(np.float32))

    # -- ray casting (bench_traverse.py) ------------------------------------------------
    # Open3D 0.20's CPU RaycastingScene (RaycastingScene.cpp): an Embree 4 device made
    # with "threads=<nthreads>" (the build), a scene with RTC_SCENE_FLAG_ROBUST, and each
    # query one rtcIntersect1 / rtcOccluded1 per ray, the rays in blocks of 1024 spread
    # over a TBB arena of nthreads threads; cast_rays also writes the barycentrics and
    # the unit normals of the hits (its dictionary's other entries).

    def cast_rays(self, scene: Any, origins: np.ndarray,
                  directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``cast_rays``: closest hits ``(t float32, prim int32)``, ``inf`` / ``-1`` on a
        miss (its ``INVALID_ID``, 2^32 - 1, read as int32), ``t`` in units of the
        direction's length, from ``tnear = 0``."""
        out = scene.cast_rays(self._rays(origins, directions), nthreads=self.threads)
        prim = out["primitive_ids"].numpy().view(np.int32)
        t = np.where(prim >= 0, out["t_hit"].numpy(), np.inf).astype(np.float32)
        return t, prim

    def test_occlusions(self, scene: Any, origins: np.ndarray, directions: np.ndarray,
                        tmax: float = float("inf")) -> np.ndarray:
        """``test_occlusions`` with ``tnear = 0``, ``tfar = tmax``: any hit, ``bool (N,)``."""
        return scene.test_occlusions(self._rays(origins, directions), tnear=0.0,
                                     tfar=float(tmax), nthreads=self.threads).numpy()

    def closest_points(self, scene: Any, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``compute_closest_points``: ``(distance float32, triangle int32)``, the distance
        that of the closest point it answers (in numpy, float32)."""
        p = np.ascontiguousarray(points, np.float32)
        out = scene.compute_closest_points(self._tensor(p), nthreads=self.threads)
        d = np.linalg.norm(out["points"].numpy() - p, axis=1).astype(np.float32)
        return d, out["primitive_ids"].numpy().view(np.int32)

    def signed_distance(self, scene: Any, points: np.ndarray, nsamples: int = 1) -> np.ndarray:
        """``compute_signed_distance``: ``float32 (N,)``, negative inside by the parity of
        ``nsamples`` rays from each point."""
        return scene.compute_signed_distance(self._tensor(points.astype(np.float32)),
                                             nthreads=self.threads, nsamples=nsamples).numpy()

    def contains(self, scene: Any, points: np.ndarray, nsamples: int = 1) -> np.ndarray:
        """``compute_occupancy``: ``bool (N,)``, the parity of ``nsamples`` rays."""
        return scene.compute_occupancy(self._tensor(points.astype(np.float32)),
                                       nthreads=self.threads, nsamples=nsamples).numpy() > 0.5

    def count_hits(self, scene: Any, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """``count_intersections``: ``int32 (N,)``."""
        return scene.count_intersections(self._rays(origins, directions),
                                         nthreads=self.threads).numpy().astype(np.int32)

    def all_hits(self, scene: Any, origins: np.ndarray,
                 directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``list_intersections``: ``(offsets int64 (N + 1,), t float32, triangle int32)``,
        grouped by ray (its ``ray_splits``), in its order within a ray."""
        out = scene.list_intersections(self._rays(origins, directions), nthreads=self.threads)
        return (out["ray_splits"].numpy().astype(np.int64), out["t_hit"].numpy(),
                out["primitive_ids"].numpy().view(np.int32))


class Trimesh:
    """trimesh's queries, numpy with rtree and scipy's k-d tree (closest points, signed
    distance), rtree (boxes) and its ray intersector (inside, every hit): Embree through embreex when
    that is importable, else its numpy ``ray_triangle``. Raises ``ImportError`` when
    trimesh is not installed; :attr:`has_proximity` is False without scipy."""

    def __init__(self) -> None:
        import trimesh
        self.trimesh = trimesh
        try:
            importlib.import_module("scipy.spatial")   # trimesh's closest points need it
            self.has_proximity = True
        except ImportError:
            self.has_proximity = False
        self.rays = "embreex" if trimesh.ray.has_embree else "numpy ray_triangle"
        self.version = (f"{trimesh.__version__} (rays: {self.rays}; closest points: "
                        f"{'rtree + scipy' if self.has_proximity else 'none, scipy not installed'})")

    def build(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float, Any]:
        """``(setup seconds, build seconds, mesh)``: setup makes the ``Trimesh`` (unprocessed),
        build fills its caches (the ray intersector's scene, by a one-ray query; the
        r-tree of the triangles' boxes; the k-d tree of the closest-point query, by a
        one-point query)."""
        t0 = time.perf_counter()
        mesh = self.trimesh.Trimesh(vertices, faces, process=False)
        t1 = time.perf_counter()
        p = np.asarray(vertices[:1], np.float64) + 1e-3
        mesh.ray.intersects_id(p, np.float64([[0.0, 0.0, 1.0]]), multiple_hits=True)
        mesh.triangles_tree
        if self.has_proximity:
            self.trimesh.proximity.closest_point(mesh, p)
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1, mesh

    def closest_points(self, mesh: Any, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``trimesh.proximity.closest_point``: ``(distance float32, triangle int32)``."""
        _, d, tri = self.trimesh.proximity.closest_point(mesh, points)
        return d.astype(np.float32), tri.astype(np.int32)

    def signed_distance(self, mesh: Any, points: np.ndarray) -> np.ndarray:
        """``ProximityQuery.signed_distance``, negated to negative inside (trimesh's own
        convention is positive inside): ``float32 (N,)``."""
        return (-self.trimesh.proximity.ProximityQuery(mesh).signed_distance(points)).astype(np.float32)

    def contains(self, mesh: Any, points: np.ndarray) -> np.ndarray:
        """``mesh.contains``: ``bool (N,)`` by the parity of a ray both ways."""
        return np.asarray(mesh.contains(points), bool)

    def overlapping(self, mesh: Any, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The triangles whose boxes overlap each box, from trimesh's r-tree of the
        triangles' boxes (``mesh.triangles_tree.intersection``, one call per box):
        ``(offsets int64 (N + 1,), prims int32)``, each box's in the r-tree's order."""
        tree = mesh.triangles_tree
        boxes = np.hstack([lower, upper]).astype(np.float64)
        per_box = [np.fromiter(tree.intersection(b), np.int64) for b in boxes]
        offsets = np.zeros(len(boxes) + 1, np.int64)
        np.cumsum([len(x) for x in per_box], out=offsets[1:])
        prims = np.concatenate(per_box) if per_box else np.zeros(0, np.int64)
        return offsets, prims.astype(np.int32)

    def all_hits(self, mesh: Any, origins: np.ndarray, directions: np.ndarray,
                 max_hits: int = 1000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``mesh.ray.intersects_id(multiple_hits=True)``: ``(offsets int64 (N + 1,),
        t float32, triangle int32)``, by ray then ``t``; ``t`` from its hit locations."""
        o, d = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
        tri, ray, loc = mesh.ray.intersects_id(o, d, multiple_hits=True, max_hits=max_hits,
                                               return_locations=True)
        t = ((loc - o[ray]) * d[ray]).sum(axis=1) / (d[ray] ** 2).sum(axis=1)
        order = np.lexsort((t, ray))
        offsets = np.zeros(len(o) + 1, np.int64)
        np.cumsum(np.bincount(ray, minlength=len(o)), out=offsets[1:])
        return offsets, t[order].astype(np.float32), tri[order].astype(np.int32)


#: The peers in the order the benches list them: family -> adapter class.
PEERS = {"embree": Embree, "warp": Warp}
#: The peers of bench_queries.py (closest points, signed distance, inside, hit counts,
#: every hit, boxes): Embree (embreex) answers none of these, so it is not one of them.
QUERY_PEERS = {"warp": Warp, "open3d": Open3D, "trimesh": Trimesh}


def load_peers(enabled: bool, classes: dict[str, Any] | None = None
               ) -> tuple[dict[str, Any], dict[str, str]]:
    """Importable peers ``{family: peer}`` and a status line for each, of ``classes``
    (family -> adapter class; default :data:`PEERS`)."""
    peers, status = {}, {}
    for family, cls in (PEERS if classes is None else classes).items():
        if not enabled:
            status[family] = "disabled (--no-peers)"
            continue
        try:
            peers[family] = cls()
            status[family] = f"{family} {peers[family].version}"
        except ImportError as exc:
            status[family] = f"not installed ({exc})"
    return peers, status


# -- the machine -----------------------------------------------------------------------

def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def library_versions() -> dict[str, str]:
    return {"python": platform.python_version(), "numpy": np.__version__,
            "pyopencl": cl.VERSION_TEXT, "lbvh": lbvh.__version__}


def machine_info(ctx: dev.Context, peer_status: dict[str, str]) -> dict:
    """The machine, the OpenCL device, the library versions and the peers' status."""
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "platform": platform.platform(),
            "opencl_device": ctx.name, "device_compute_units": ctx.compute_units,
            **library_versions(), "peers": peer_status}


# -- timing ----------------------------------------------------------------------------

def median(values: list[float]) -> float:
    """The median as a float; ``nan`` for no values."""
    return float(statistics.median(values)) if values else float("nan")


def timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    """``(wall seconds, fn())``."""
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def cores_used(cpu: list[float], wall: list[float]) -> float:
    """Process CPU seconds over wall seconds: about the number of busy cores."""
    return float(sum(cpu) / sum(wall)) if sum(wall) > 0 else 0.0


def interleaved_rounds(contestants: list[Any], repeats: int, budget: float,
                       spent: Callable[[Any], float], run: Callable[[Any], None],
                       progress: "Progress", what: str) -> None:
    """``repeats`` rounds, each running every contestant (anything with a
    ``variant.name``) once, so that the machine's noise hits all of them alike; a
    contestant that has spent ``budget`` seconds sits out the later rounds (it
    always runs once)."""
    for r in range(repeats):
        for c in contestants:
            if r and spent(c) >= budget:
                continue
            progress.note(f"{c.variant.name} {what} {r + 1}/{repeats}")
            run(c)
        progress.advance()


class Progress:
    """The benches' progress: a tqdm bar on stderr (:func:`lbvh.progress.bar`), shown
    only when stderr is a terminal; ``note`` names the step running."""

    def __init__(self, total: int) -> None:
        self.bar = progress_bar(max(total, 1), "bench", "step")

    def begin(self, label: str) -> None:
        self.bar.set_description(label, refresh=False)
        self.note("")

    def note(self, step: str) -> None:
        self.bar.set_postfix_str(step)

    def advance(self) -> None:
        self.bar.update(1)

    def skip(self, steps: int) -> None:
        """Count ``steps`` as done without running them (a scene that did not load)."""
        self.bar.update(steps)

    def close(self) -> None:
        self.bar.close()


# -- command line and report of the benches that trace camera rays ------------------------

def parse_rays(text: str) -> tuple[int, int]:
    """``"512x384"`` -> ``(512, 384)``."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--rays: {text!r}, expected WIDTHxHEIGHT") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"--rays: {text!r}, both sides must be positive")
    return w, h


def add_scene_options(p: argparse.ArgumentParser, quick_scenes: Sequence[str],
                      full_scenes: Sequence[str], quick_rays: tuple[int, int],
                      full_rays: tuple[int, int]) -> None:
    """--quick, --scenes and --rays."""
    p.add_argument("--quick", action="store_true",
                   help=f"CI mode: {', '.join(quick_scenes)} at {quick_rays[0]}x{quick_rays[1]} rays")
    p.add_argument("--scenes", nargs="+", metavar="NAME",
                   help=f"scenes (comma or space separated) from: {', '.join(known_scenes())}; "
                        f"default {','.join(full_scenes)}")
    p.add_argument("--rays", type=parse_rays, help="primary rays WIDTHxHEIGHT per scene "
                   f"(default {full_rays[0]}x{full_rays[1]}, quick {quick_rays[0]}x{quick_rays[1]})")


def add_run_options(p: argparse.ArgumentParser) -> None:
    """--no-peers, --device, --shared and --out."""
    p.add_argument("--no-peers", action="store_true", help="skip Embree and warp")
    p.add_argument("--device", default=None, help="OpenCL device (default: $LBVH_DEVICE or PoCL)")
    p.add_argument("--shared", type=Path, default=SHARED_SCENES, help="folder of the shared scenes")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default bench/out)")


def resolve_scenes(p: argparse.ArgumentParser, args: argparse.Namespace,
                   quick_scenes: Sequence[str], full_scenes: Sequence[str],
                   quick_rays: tuple[int, int], full_rays: tuple[int, int]) -> None:
    """Set ``args.scene_names`` and ``args.size`` from --scenes, --rays and --quick."""
    names = [n for item in (args.scenes or []) for n in item.split(",") if n]
    unknown = [n for n in names if n not in known_scenes()]
    if unknown:
        p.error(f"--scenes: unknown scene {unknown[0]!r}; known: {', '.join(known_scenes())}")
    args.scene_names = names or list(quick_scenes if args.quick else full_scenes)
    args.size = args.rays or (quick_rays if args.quick else full_rays)


def command_line(script: str, argv: list[str] | None) -> str:
    """The command that ran ``bench/<script>`` with ``argv`` (default: this process's):
    this interpreter, relative to the working folder where it lies below it
    (``.venv/bin/python``), else as its full path."""
    exe = Path(sys.executable)
    try:
        python = str(exe.relative_to(Path.cwd()))
    except ValueError:
        python = str(exe)
    return " ".join([python, f"bench/{script}", *(sys.argv[1:] if argv is None else argv)])


def report_start(command: str, ctx: dev.Context, peer_status: dict[str, str]) -> dict:
    """The first fields of a report: the command, the date (now) and the machine."""
    return {"command": command,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine_info(ctx, peer_status)}


def header_lines(report: dict) -> list[str]:
    """The Markdown lines under a report's title: command, run time, machine, peers."""
    m = report["machine"]
    return [f"Command: `{report['command']}`  ",
            f"Run time: {report['duration_seconds']:.0f} s on {m['cpu']}, {m['cores']} cores; "
            f"OpenCL device: {m['opencl_device']}.  ",
            f"Peers: {', '.join(m['peers'].values())}.  "]


def write_report(report: dict, text: str, paths: dict[str, Path], out: Path) -> None:
    """The Markdown ``text`` and the JSON ``report`` to ``paths``, the text to stdout."""
    paths["markdown"].write_text(text)
    paths["json"].write_text(json.dumps(report, indent=1, allow_nan=False) + "\n")
    print(text)
    print(f"[bench] written to {out}", file=sys.stderr)
