"""Scenes of many instances (issue 18): one mesh placed K times, against a flattened copy.

For one mesh (the bunny of ``../shared/scenes``; ``--quick``: the shipped
teapot, ``lbvh.data.teapot()``) and each instance count K (default 100 and
1,000), the mesh is placed K times on a grid in the ground plane (y up): a
random rotation about the up axis and a uniform scale in [0.5, 1.5] per
instance, seeded. A pinhole camera over the grid (its near edge, pitched down
so that the top row of pixels meets the ground near the far edge) traces one
primary ray per pixel. Measured, every figure the median of ``--repeats``
rounds in which every contestant runs once (the machine is shared; a
contestant that has spent ``--budget`` seconds sits out the later rounds):

* build: the mesh's BVH (``lbvh.build``, once for all K: the instances share
  it), the top level (``lbvh.Scene(...)``, which also uploads the mesh's tree),
  ``scene.set_transforms`` moving every instance a little (only the top level
  is built again), these two in rounds of their own; then, where the flattened
  copy is built, ``scene.flattened()``
  on the host, ``lbvh.build`` of it and Embree's build of it (embreex:
  scene creation and copy, then the commit);
* rays: closest hit (``scene.intersect``) and any hit (``scene.occluded``,
  ``tmax = inf``) in Mrays/s, the call as users make it (numpy in, numpy out),
  against ``lbvh.build(flattened)`` and Embree on the flattened mesh (two Python
  threads over 16 chunks of the rays; embreex releases the GIL), with nodes and
  triangles per ray from one more ``counters=True`` pass outside the timing;
* agreement: the scene's closest hits against the flattened lbvh tree's on the
  same rays (same hit or miss, the same world triangle via
  ``scene.flat_prim(hits)``, ``t`` within the float32 bound of
  :func:`lbvh.metrics.error_bound.t_bound`) and the any-hit answers; on
  every ray where the whole flattened copy is built, else on the rays of a few
  pixel tiles against a flattened copy of just the instances whose world boxes
  those rays cross (no other instance can be hit by them);
* the device: its ``max_mem_alloc_size`` and ``global_mem_size``, the largest
  mesh one tree takes, and (``--parts-triangles``, default a 4M-triangle
  terrain) ``lbvh.build_parts`` in ``--parts`` parts against one tree, rays
  through both.

Embree's own instancing (``RTC_GEOMETRY_TYPE_INSTANCE``) cannot be expressed
through embreex, which wraps triangle geometry only: Embree is measured on the
flattened mesh. The flattened copy is skipped above ``--flatten-max`` world
triangles (default 20M: 1,000 bunnies are 69M triangles, see
:func:`flatten_skip_reason`).

Outputs in ``--out`` (default ``bench/out``): ``bench_instances.md`` and
``bench_instances.json``.
"""
from __future__ import annotations

import argparse
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

# bench/common.py, beside this script; imported before numpy, for it sets
# OPENBLAS_NUM_THREADS
import common

import numpy as np

import lbvh
from lbvh import device as dev
from lbvh.builders import pipeline
from lbvh.queries.instances import NODE_CHUNKS
from lbvh.files import load_mesh
from lbvh.verification import meshes
from lbvh.metrics.error_bound import t_bound

FULL_MESH, QUICK_MESH = "bunny", "teapot"
FULL_INSTANCES, QUICK_INSTANCES = (100, 1000), (9, 36)
FULL_RAYS, QUICK_RAYS = (512, 384), (128, 96)
#: World triangles up to which the whole flattened copy is built (and Embree on it).
FULL_FLATTEN_MAX, QUICK_FLATTEN_MAX = 20_000_000, 100_000
#: The terrain of the parts section, its triangles (about: 2 k^2).
FULL_PARTS_TRIANGLES, QUICK_PARTS_TRIANGLES = 4_000_000, 20_000
PARTS = 4
FULL_REPEATS, QUICK_REPEATS = 5, 3
SEED = 0
#: Grid spacing in units of the mesh's footprint radius (half the diagonal of its
#: box in the ground plane): below 2 neighbours may overlap, a crowd, whose rows hide
#: most of the ground from the camera.
SPACING = 1.5
SCALES = (0.5, 1.5)
#: set_transforms moves every instance by this fraction of the spacing.
MOVE = 0.01
#: The camera: vertical field of view and pitch below the horizon, degrees.
FOV, PITCH = 40.0, 32.0
#: Embree on the flattened mesh: Python threads and the chunks of rays they pull.
EMBREE_THREADS, EMBREE_CHUNKS = 2, 16
#: The agreement sample where the whole flattened copy is not built: TILE x TILE pixel
#: tiles centred at these fractions of the image's width and height.
TILE = 24
TILE_CENTRES = ((0.5, 0.5), (0.25, 0.3), (0.75, 0.3), (0.25, 0.75), (0.75, 0.75), (0.5, 0.1))
QUERIES = ("closest", "any")
SCENE_TRACER, FLAT_TRACER, EMBREE_TRACER = "lbvh.Scene", "lbvh (flattened)", "embree-2t (flattened)"
ONE_TREE, PARTS_TREE = "lbvh.build (one tree)", "lbvh.build_parts"
#: Hit or miss may differ on rays within rounding of a silhouette edge (the scene moves
#: the ray into each instance's space, the flattened copy moves the vertices): the
#: bound the test holds the quick run to (tests/test_instances.py holds the library
#: to the same one).
HIT_MISS_BOUND = 1e-3
EMBREE_NOTE = ("embreex wraps triangle geometry only (no RTC_GEOMETRY_TYPE_INSTANCE, no "
               "rtcSetGeometryTransform): Embree's instancing cannot be expressed through "
               "embreex, so Embree is measured on the flattened mesh.")


# -- the scene ------------------------------------------------------------------------

def load_instance_mesh(name: str, shared: Path) -> tuple[np.ndarray, np.ndarray, str] | str:
    """``(vertices, faces, source)`` of the mesh to place, or why it is skipped."""
    if name == "teapot":
        v, f = lbvh.data.teapot()
        return v, f, "lbvh.data.teapot()"
    if name in common.GENERATED_SCENES:
        v, f = common.GENERATED_SCENES[name]()
        return v, f, "lbvh/verification/meshes.py"
    path = common.scene_file(name, shared)
    if not path.is_file():
        return f"{path} not found"
    v, f = load_mesh(path)
    return v, f, str(path)


@dataclass
class Grid:
    count: int
    cols: int
    rows: int
    spacing: float
    height: float            # the mesh's height at scale 1

    @property
    def depth(self) -> float:
        return self.rows * self.spacing

    @property
    def width(self) -> float:
        return self.cols * self.spacing


def placement(vertices: np.ndarray, count: int, seed: int = SEED) -> tuple[np.ndarray, Grid]:
    """``float64 (K, 3, 4)`` object-to-world transforms of ``count`` instances on a grid
    in the y = 0 plane, each standing on it (its box's bottom centre at its cell's
    centre), turned about y by a random angle and scaled by a random factor in
    :data:`SCALES`; and the grid."""
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    base = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    radius = 0.5 * math.hypot(hi[0] - lo[0], hi[2] - lo[2])
    cols = math.ceil(math.sqrt(count))
    rows = math.ceil(count / cols)
    grid = Grid(count, cols, rows, SPACING * radius, float(hi[1] - lo[1]))
    i = np.arange(count)
    centre = np.stack([(i % cols - (cols - 1) / 2) * grid.spacing, np.zeros(count),
                       (i // cols - (rows - 1) / 2) * grid.spacing], axis=1)
    rng = np.random.default_rng(seed)
    theta, scale = rng.uniform(0.0, 2 * np.pi, count), rng.uniform(*SCALES, count)
    c, s, z, one = np.cos(theta), np.sin(theta), np.zeros(count), np.ones(count)
    rot = np.stack([np.stack([c, z, s], 1), np.stack([z, one, z], 1), np.stack([-s, z, c], 1)], 1)
    a = scale[:, None, None] * rot
    b = centre - np.einsum("ijk,k->ij", a, base)
    return np.concatenate([a, b[:, :, None]], axis=2), grid


def moved(transforms: np.ndarray, grid: Grid, seed: int = SEED + 1) -> np.ndarray:
    """Every instance moved in the ground plane by :data:`MOVE` of the spacing."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, 2 * np.pi, len(transforms))
    out = transforms.copy()
    out[:, 0, 3] += MOVE * grid.spacing * np.cos(angle)
    out[:, 2, 3] += MOVE * grid.spacing * np.sin(angle)
    return out


def grid_camera(grid: Grid, size: tuple[int, int]) -> lbvh.Camera:
    """A camera above the grid's near (+z) edge looking along -z, pitched :data:`PITCH`
    degrees down: the top row of pixels meets the ground at 95% of the grid's depth,
    so that the rows of instances hide most of the ground between them."""
    top = math.radians(PITCH - FOV / 2)          # the top pixels' angle below the horizon
    height = max(0.95 * grid.depth * math.tan(top), 2.0 * SCALES[1] * grid.height)
    eye = np.array([0.0, height, grid.depth / 2])
    look = np.array([0.0, -math.sin(math.radians(PITCH)), -math.cos(math.radians(PITCH))])
    return lbvh.Camera(eye, eye + look, (0.0, 1.0, 0.0), FOV, size[0], size[1])


def world_boxes(scene: lbvh.Scene) -> tuple[np.ndarray, np.ndarray]:
    """``float64 (I, 3)`` each instance's world box (its mesh's root box transformed),
    grown by a millionth of the scene's extent (a conservative test of which boxes a
    ray crosses)."""
    lo = np.stack([m.nodes["lower"][m.root] for m in scene.meshes]).astype(np.float64)
    hi = np.stack([m.nodes["upper"][m.root] for m in scene.meshes]).astype(np.float64)
    bits = np.array([[(c >> k) & 1 for k in range(3)] for c in range(8)], bool)
    corners = np.where(bits[None], hi[:, None], lo[:, None])            # (meshes, 8, 3)
    t = scene.transforms
    world = np.einsum("ijk,imk->imj", t[:, :, :3], corners[scene.mesh_of]) + t[:, None, :, 3]
    wlo, whi = world.min(axis=1), world.max(axis=1)
    pad = 1e-6 * float((whi.max(axis=0) - wlo.min(axis=0)).max())
    return wlo - pad, whi + pad


def crossed_boxes(origins: np.ndarray, directions: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray) -> np.ndarray:
    """Indices of the boxes that at least one ray (``t >= 0``) crosses (float64 slabs)."""
    o, d = origins.astype(np.float64), directions.astype(np.float64)
    d = np.where(np.abs(d) < 1e-300, 1e-300, d)
    crossed = np.zeros(len(lo), bool)
    for start in range(0, len(o), 256):
        inv = 1.0 / d[start:start + 256, None, :]
        t1 = (lo[None] - o[start:start + 256, None, :]) * inv
        t2 = (hi[None] - o[start:start + 256, None, :]) * inv
        near = np.minimum(t1, t2).max(axis=2)
        far = np.maximum(t1, t2).min(axis=2)
        crossed |= (far >= np.maximum(near, 0.0)).any(axis=0)
    return np.flatnonzero(crossed)


def tile_rays(size: tuple[int, int], centres: tuple = TILE_CENTRES, tile: int = TILE) -> np.ndarray:
    """Ray indices (row-major pixels) of ``tile x tile`` tiles centred at ``centres``."""
    w, h = size
    out = []
    for fx, fy in centres:
        x0 = min(max(int(fx * w) - tile // 2, 0), max(w - tile, 0))
        y0 = min(max(int(fy * h) - tile // 2, 0), max(h - tile, 0))
        ys, xs = np.meshgrid(np.arange(y0, min(y0 + tile, h)), np.arange(x0, min(x0 + tile, w)),
                             indexing="ij")
        out.append((ys * w + xs).ravel())
    return np.unique(np.concatenate(out))


def size_text(nbytes: float) -> str:
    return f"{nbytes / 2**30:.1f} GiB" if nbytes >= 2**30 else f"{nbytes / 2**20:.0f} MiB"


def flatten_skip_reason(world_triangles: int, vertices_per_triangle: float, limit: int,
                        ctx: dev.Context, peak_bytes_per_triangle: float) -> str | None:
    """Why the whole flattened copy is not built, or ``None`` when it is."""
    if world_triangles <= limit:
        return None
    host = world_triangles * (12 + 12 * vertices_per_triangle)
    device = world_triangles * peak_bytes_per_triangle
    if host + device < 2**30:
        return (f"{world_triangles:,} world triangles > --flatten-max {limit:,} (a copy this "
                "small would fit: the limit sends this count through the sample agreement)")
    return (f"{world_triangles:,} world triangles > --flatten-max {limit:,}: the "
            f"flattened mesh is {size_text(host)} on the host (its float64 transform twice "
            f"that), our build of it peaks near {size_text(device)} of device memory "
            f"({peak_bytes_per_triangle:.0f} B/triangle beyond the input; the device has "
            f"{ctx.device.global_mem_size / 2**30:.0f} GiB, PoCL's being host memory), and Embree "
            "would hold its own copy and BVH beside them on the same machine: it does not fit "
            "comfortably. The agreement uses a sample instead")


# -- contestants ----------------------------------------------------------------------

@dataclass
class Step:
    """One timed thing, run once per round: ``run()`` returns what it made."""
    variant: common.Variant
    run: Callable[[], Any]
    samples: list[float] = field(default_factory=list)
    result: Any = None

    def once(self) -> None:
        seconds, self.result = common.timed(self.run)
        self.samples.append(seconds)


def run_rounds(steps: list[Step], args: argparse.Namespace, progress: common.Progress,
               what: str) -> None:
    common.interleaved_rounds(steps, args.repeats, args.budget, lambda s: sum(s.samples),
                              lambda s: s.once(), progress, what)


def chunks(count: int, parts: int) -> list[slice]:
    edges = np.linspace(0, count, parts + 1).astype(int)
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def embree_closest(embree: common.Embree, built: Any, pool: ThreadPoolExecutor,
                   o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    parts = list(pool.map(lambda s: embree.trace(built, o[s], d[s]), chunks(len(o), EMBREE_CHUNKS)))
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def embree_any(embree: common.Embree, built: Any, pool: ThreadPoolExecutor,
               o: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.concatenate(list(pool.map(lambda s: embree.occluded(built, o[s], d[s], np.inf),
                                        chunks(len(o), EMBREE_CHUNKS))))


@dataclass
class Tracer:
    """A closest-hit and an any-hit query, numpy rays in. ``closest`` answers ``(t, hits,
    stack overflows)``, ``hits`` the scene's :class:`SceneHits` (:meth:`lbvh.Scene.flat_prim`
    maps them to the flattened mesh) or a tree's triangles (``-1`` on a miss); ``any_hit``
    ``bool (N,)``; ``counters`` the mean nodes and triangles per ray of the closest hits."""
    name: str
    closest: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, Any, int]]
    any_hit: Callable[[np.ndarray, np.ndarray], np.ndarray]
    counters: Callable[[np.ndarray, np.ndarray], tuple[float, float]] | None = None


def scene_tracer(name: str, scene: lbvh.Scene) -> Tracer:
    def closest(o, d):
        hits = scene.intersect(o, d)
        return hits.t, hits, hits.overflow_count

    def counted(o, d):
        hits = scene.intersect(o, d, counters=True)
        return float(hits.nodes_visited.mean()), float(hits.tris_tested.mean())
    return Tracer(name, closest, lambda o, d: scene.occluded(o, d), counted)


def bvh_tracer(name: str, bvh: lbvh.BVH) -> Tracer:
    def closest(o, d):
        hits = bvh.intersect(o, d)
        return hits.t, hits.prim, hits.overflow_count

    def counted(o, d):
        hits = bvh.intersect(o, d, counters=True)
        return float(hits.nodes_visited.mean()), float(hits.tris_tested.mean())
    return Tracer(name, closest, lambda o, d: bvh.occluded(o, d), counted)


def embree_tracer(embree: common.Embree, built: Any, pool: ThreadPoolExecutor) -> Tracer:
    def closest(o, d):
        t, prim = embree_closest(embree, built, pool, o, d)
        return t, prim, 0
    return Tracer(EMBREE_TRACER, closest, lambda o, d: embree_any(embree, built, pool, o, d))


def trace_rounds(tracers: list[Tracer], o: np.ndarray, d: np.ndarray, args: argparse.Namespace,
                 progress: common.Progress, label: str) -> tuple[list[dict], dict[str, dict]]:
    """Every tracer on both queries, interleaved by rounds, after one untimed pass each
    (kernels compile) and one counted pass of the closest hits; rows and the last
    answers ``{tracer: {query: answer}}``."""
    rows, answers = [], {t.name: {} for t in tracers}
    counters = {}
    for t in tracers:
        progress.note(f"{t.name} warm-up")
        t.closest(o, d)
        t.any_hit(o, d)
        counters[t.name] = t.counters(o, d) if t.counters else (None, None)
    for query in QUERIES:
        steps = [Step(common.Variant(t.name, "tracer"),
                      (lambda t=t: t.closest(o, d)) if query == "closest" else
                      (lambda t=t: t.any_hit(o, d))) for t in tracers]
        run_rounds(steps, args, progress, f"{label} {query}")
        for t, s in zip(tracers, steps):
            answers[t.name][query] = s.result
        for t, s in zip(tracers, steps):
            seconds = common.median(s.samples)
            hit = (np.isfinite(s.result[0]) if query == "closest" else np.asarray(s.result))
            ratios = {}
            for u, other in zip(tracers, steps):
                if u is not t:
                    n = min(len(s.samples), len(other.samples))
                    ratios[u.name] = common.median([other.samples[r] / s.samples[r] for r in range(n)])
            nodes, tris = counters[t.name] if query == "closest" else (None, None)
            rows.append({"tracer": t.name, "query": query, "rays": len(o), "samples": s.samples,
                         "seconds": seconds, "mrays_per_second": len(o) / seconds * 1e-6,
                         "nodes_per_ray": nodes, "tris_per_ray": tris,
                         "hit_fraction": float(hit.mean()),
                         "overflow_count": int(s.result[2]) if query == "closest" else None,
                         "speed_over": ratios})
    return rows, answers


# -- agreement -----------------------------------------------------------------------

def agreement_row(what: str, reference: str, rays: int, t: np.ndarray, prim: np.ndarray,
                  t_ref: np.ndarray, prim_ref: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                  o: np.ndarray, d: np.ndarray, any_hit: np.ndarray | None,
                  any_ref: np.ndarray | None, sample: str) -> dict:
    bound = t_bound(vertices, faces, o, d, t_ref.astype(np.float64), prim_ref,
                    cos_floor=common.AGREEMENT_COS_FLOOR)
    row = {"tracer": what, "reference": reference, "rays": rays, "sample": sample,
           **common.agreement(t, prim, t_ref, prim_ref, bound)}
    row["hit_miss_fraction"] = row["hit_miss_differ"] / max(rays, 1)
    row["any_hit_same"] = (None if any_hit is None else
                           float((np.asarray(any_hit) == np.asarray(any_ref)).mean()))
    return row


def sample_agreement(scene: lbvh.Scene, o: np.ndarray, d: np.ndarray, size: tuple[int, int],
                     limit: int, progress: common.Progress) -> dict:
    """The scene against a flattened copy of the instances the sample's rays cross."""
    lo, hi = world_boxes(scene)
    per = np.array([scene.meshes[m].mesh.num_prims for m in scene.mesh_of], np.int64)
    centres = list(TILE_CENTRES)
    while True:
        rays = tile_rays(size, tuple(centres))
        crossed = crossed_boxes(o[rays], d[rays], lo, hi)
        if per[crossed].sum() <= limit or len(centres) == 1:
            break
        centres.pop()
    if per[crossed].sum() > limit:
        return {"skipped": f"one {TILE}x{TILE} tile crosses {len(crossed)} instances, "
                           f"{per[crossed].sum():,} triangles > --flatten-max"}
    progress.note(f"agreement sample: {len(crossed)} instances")
    sub = lbvh.Scene(scene.meshes, scene.mesh_of[crossed], scene.transforms[crossed])
    v, f, _ = sub.flattened()
    ref_bvh = lbvh.build(v, f)
    os_, ds = o[rays], d[rays]
    ref = ref_bvh.intersect(os_, ds)
    hits = scene.intersect(os_, ds)
    where = np.full(scene.num_instances, -1, np.int64)
    where[crossed] = np.arange(len(crossed))
    base = np.concatenate([[0], np.cumsum(per[crossed])[:-1]])
    inst = np.maximum(hits.instance, 0)
    prim = np.where(~hits.mask, -1,
                    np.where(where[inst] >= 0, base[np.maximum(where[inst], 0)] + hits.prim, -2))
    row = agreement_row(SCENE_TRACER, f"lbvh on a flattened copy of the {len(crossed)} instances "
                        "the sample's rays cross", len(rays), hits.t, prim, ref.t, ref.prim, v, f,
                        os_, ds, scene.occluded(os_, ds), ref_bvh.occluded(os_, ds),
                        f"{len(centres)} tiles of {TILE}x{TILE} pixels")
    row["sample_instances"] = int(len(crossed))
    row["sample_triangles"] = int(per[crossed].sum())
    return row


# -- the sections --------------------------------------------------------------------

def bench_count(count: int, v: np.ndarray, f: np.ndarray, bvh: lbvh.BVH, ctx: dev.Context,
                peers: dict, pool: ThreadPoolExecutor, args: argparse.Namespace,
                progress: common.Progress, peak_bpt: float) -> dict:
    transforms, grid = placement(v, count)
    there = moved(transforms, grid)
    mesh_of = np.zeros(count, np.int64)
    camera = grid_camera(grid, args.size)
    o, d = camera.rays()
    world = count * len(f)
    skip = flatten_skip_reason(world, len(v) / len(f), args.flatten_max, ctx, peak_bpt)
    progress.begin(f"K={count}:")
    state: dict[str, Any] = {"scene": lbvh.Scene([bvh], mesh_of, transforms)}

    def new_scene():
        state["scene"] = None
        state["scene"] = lbvh.Scene([bvh], mesh_of, transforms)
        return None

    def move_all():
        state["scene"].set_transforms(state["scene"].ids, there)

    top_steps = [Step(common.Variant("Scene()", "top"), new_scene),
                 Step(common.Variant("set_transforms", "top"), move_all)]
    steps: list[Step] = []
    flat_v = flat_f = None
    if skip is None:
        progress.note("flattening")
        flatten_s, (flat_v, flat_f, _) = common.timed(state["scene"].flattened)

        def build_flat():
            state["flat"] = None
            state["flat"] = lbvh.build(flat_v, flat_f)
        steps.append(Step(common.Variant("lbvh.build (flattened)", "flat"), build_flat))
        if "embree" in peers:
            embree = peers["embree"]

            def build_embree():
                state["embree"] = None
                setup, commit, built = embree.build(flat_v, flat_f)
                state["embree"] = built
                return setup, commit
            steps.append(Step(common.Variant("Embree build (flattened)", "embree"), build_embree))
    # warm: the top level's kernels (the mesh build compiled the pipeline). The top
    # level's rounds (milliseconds) run apart from the flattened builds' (seconds, and
    # Embree's threads and memory linger after its build)
    new_scene()
    move_all()
    run_rounds(top_steps, args, progress, "top level")
    if steps:
        run_rounds(steps, args, progress, "flattened build")
    scene = state["scene"]
    scene.set_transforms(scene.ids, transforms)   # back where the flattened copy is
    build = {s.variant.name: {"samples": s.samples, "seconds": common.median(s.samples)}
             for s in top_steps + steps}
    if skip is None:
        build["flatten (host)"] = {"samples": [flatten_s], "seconds": flatten_s}
        if "Embree build (flattened)" in build:
            last = steps[-1].result
            build["Embree build (flattened)"].update(setup_seconds=last[0], commit_seconds=last[1])
    tracers = [scene_tracer(SCENE_TRACER, scene)]
    if skip is None:
        tracers.append(bvh_tracer(FLAT_TRACER, state["flat"]))
        if "embree" in peers:
            tracers.append(embree_tracer(peers["embree"], state["embree"], pool))
    rows, answers = trace_rounds(tracers, o, d, args, progress, f"K={count}")
    agreement = []
    if skip is None:
        hits = answers[SCENE_TRACER]["closest"][1]
        prim = scene.flat_prim(hits)
        t_ref, prim_ref = answers[FLAT_TRACER]["closest"][:2]
        agreement.append(agreement_row(SCENE_TRACER, FLAT_TRACER, len(o), hits.t, prim, t_ref,
                                       prim_ref, flat_v, flat_f, o, d,
                                       answers[SCENE_TRACER]["any"], answers[FLAT_TRACER]["any"],
                                       "every ray"))
        if EMBREE_TRACER in answers:
            t_e, prim_e = answers[EMBREE_TRACER]["closest"][:2]
            agreement.append(agreement_row(SCENE_TRACER, EMBREE_TRACER, len(o), hits.t, prim,
                                           t_e, prim_e, flat_v, flat_f, o, d,
                                           answers[SCENE_TRACER]["any"],
                                           answers[EMBREE_TRACER]["any"], "every ray"))
    else:
        agreement.append(sample_agreement(scene, o, d, args.size, args.flatten_max, progress))
    state.clear()
    return {"instances": count, "world_triangles": world, "grid": {"cols": grid.cols,
            "rows": grid.rows, "spacing": grid.spacing}, "camera": camera.as_dict(),
            "rays": len(o), "flattened": skip is None, "flattened_skipped": skip,
            "build": build, "rows": rows, "agreement": agreement,
            "top_nodes": int(scene.top.tree.num_nodes)}


def bench_parts(ctx: dev.Context, args: argparse.Namespace, progress: common.Progress,
                cameras: dict) -> dict:
    """``lbvh.build_parts`` on a terrain against one tree: builds and rays."""
    progress.begin("parts:")
    progress.note("terrain")
    v, f = meshes.terrain(args.parts_triangles, seed=SEED)
    part = -(-len(f) // args.parts)
    state: dict[str, Any] = {}

    def one():
        state["one"] = None
        state["one"] = lbvh.build(v, f)

    def parts():
        state["parts"] = None
        state["parts"] = lbvh.build_parts(v, f, part_triangles=part)
    steps = [Step(common.Variant(ONE_TREE, "one"), one),
             Step(common.Variant(PARTS_TREE, "parts"), parts)]
    run_rounds(steps, args, progress, "build")
    camera = lbvh.Camera.from_dict(cameras["terrain-1m"], size=args.size)
    o, d = camera.rays()
    tracers = [bvh_tracer(ONE_TREE, state["one"]), scene_tracer(PARTS_TREE, state["parts"])]
    rows, answers = trace_rounds(tracers, o, d, args, progress, "parts")
    hits = answers[PARTS_TREE]["closest"][1]
    t_ref, prim_ref = answers[ONE_TREE]["closest"][:2]
    agree = agreement_row(PARTS_TREE, ONE_TREE, len(o), hits.t, state["parts"].flat_prim(hits),
                          t_ref, prim_ref, v, f, o, d, answers[PARTS_TREE]["any"],
                          answers[ONE_TREE]["any"], "every ray")
    report = state["one"].report()
    out = {"triangles": int(len(f)), "vertices": int(len(v)), "parts": len(state["parts"].meshes),
           "part_triangles": part,
           "build": {s.variant.name: {"samples": s.samples, "seconds": common.median(s.samples)}
                     for s in steps},
           "one_tree_bytes_per_triangle": float(report.bytes_per_triangle),
           "camera": camera.as_dict(), "rows": rows, "agreement": agree}
    state.clear()
    return out


def device_limits(ctx: dev.Context, peak_bpt: float, input_bpt: float) -> dict:
    alloc, total = int(ctx.device.max_mem_alloc_size), int(ctx.device.global_mem_size)
    one = pipeline.max_triangles(ctx)
    by_memory = int(total / (peak_bpt + input_bpt))
    # the parts' trees in NODE_CHUNKS node buffers; their faces in slot order (12 B a
    # triangle) in one buffer
    in_parts = min(NODE_CHUNKS * one, alloc // 12)
    return {"device": ctx.name, "max_mem_alloc_size": alloc, "global_mem_size": total,
            "max_triangles_one_tree": one, "max_triangles_in_parts": in_parts,
            "bytes_per_triangle_peak": peak_bpt,
            "bytes_per_triangle_input": input_bpt, "max_triangles_by_global_memory": by_memory,
            "meaning": (
                f"One tree's node buffer (32 B x (2F - 1)) must fit one allocation of "
                f"{alloc / 2**30:.1f} GiB: up to {one:,} triangles in one tree "
                "(lbvh.builders.pipeline.max_triangles). lbvh.build cuts a larger mesh into "
                "parts of that many triangles, consecutive in Morton order, and returns a "
                "lbvh.Scene of them (lbvh.build_parts; hits keep the mesh's own triangle "
                f"numbers), whose kernels read the parts' trees from {NODE_CHUNKS} node "
                f"buffers of one allocation each and their faces from one: up to {in_parts:,} "
                "triangles in parts (lbvh.queries.instances.NODE_CHUNKS). The whole build must "
                f"also fit the device's {total / 2**30:.1f} GiB: "
                f"at {peak_bpt:.0f} B/triangle of build peak beyond the input and "
                f"{input_bpt:.0f} B/triangle of input, about {by_memory:,} triangles in one "
                "build; a mesh in parts keeps every part's tree and mesh on the device, only "
                "the build's scratch is per part.")}


# -- report ----------------------------------------------------------------------------

def fmt(x: Any, spec: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def ms(entry: dict | None) -> str:
    return "-" if entry is None else fmt(entry["seconds"] * 1e3, ".1f")


def markdown(report: dict) -> str:
    s = report["settings"]
    lines = ["# Scenes of many instances (issue 18)", "", *common.header_lines(report), ""]
    mesh = report.get("mesh")
    if mesh is None:
        lines += [f"Mesh {s['mesh']!r} skipped: {report['skipped']}.", ""]
    else:
        lines += [
            f"Mesh: {mesh['name']} ({mesh['triangles']:,} triangles, {mesh['source']}), placed K "
            f"times on a grid in the ground plane: a random turn about the up axis and a scale "
            f"in [{SCALES[0]}, {SCALES[1]}] per instance (seed {SEED}), spacing {SPACING} "
            f"footprint radii. Camera over the grid's near edge, {PITCH:.0f} degrees down, "
            f"fov {FOV:.0f}; {s['width']}x{s['height']} primary rays. Medians of {s['repeats']} "
            f"interleaved rounds (a contestant past {s['budget']:.0f} s sits out later rounds). "
            f"{EMBREE_NOTE}", "",
            f"The mesh's BVH (`lbvh.build`, built once and shared by every instance): "
            f"{mesh['build']['seconds'] * 1e3:.1f} ms.", "",
            "## Build", "",
            "| instances | world triangles | `Scene()` ms | `set_transforms` ms (all moved) "
            "| top nodes | `flattened()` s | `lbvh.build` flattened s | Embree build flattened s |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for k in report["instances"]:
            b = k["build"]
            sec = (lambda name: fmt(b[name]["seconds"], ".2f") if name in b else "-")
            lines.append(f"| {k['instances']:,} | {k['world_triangles']:,} | {ms(b['Scene()'])} "
                         f"| {ms(b['set_transforms'])} | {k['top_nodes']:,} | {sec('flatten (host)')} "
                         f"| {sec('lbvh.build (flattened)')} | {sec('Embree build (flattened)')} |")
        lines += ["", "`Scene()`: `lbvh.Scene([bvh], mesh_of, transforms)`, the top level over the "
                  "instances' world boxes plus the upload of the mesh's tree; `set_transforms`: "
                  f"every instance moved by {MOVE:.0%} of the spacing, only the top level built "
                  "again. Embree: scene creation and copy plus commit (its BVH build, on Embree's "
                  "own TBB threads: every core).", ""]
        for k in report["instances"]:
            if k["flattened_skipped"]:
                lines += [f"K = {k['instances']:,}: no flattened copy. {k['flattened_skipped']}.", ""]
        lines += ["## Rays", "",
                  "| instances | query | tracer | Mrays/s | ms | nodes/ray | tris/ray | hit fraction "
                  f"| {SCENE_TRACER} speed over it |", "|---:|---|---|---:|---:|---:|---:|---:|---:|"]
        for k in report["instances"]:
            ours = {r["query"]: r["speed_over"] for r in k["rows"] if r["tracer"] == SCENE_TRACER}
            for r in k["rows"]:
                ratio = ("-" if r["tracer"] == SCENE_TRACER else
                         fmt(ours[r["query"]][r["tracer"]], ".2f"))
                lines.append(f"| {k['instances']:,} | {r['query']} | {r['tracer']} "
                             f"| {fmt(r['mrays_per_second'])} | {fmt(r['seconds'] * 1e3, '.1f')} "
                             f"| {fmt(r['nodes_per_ray'], '.1f')} | {fmt(r['tris_per_ray'], '.1f')} "
                             f"| {fmt(r['hit_fraction'], '.3f')} | {ratio} |")
        lines += ["", "Each call as users make it (numpy rays in, numpy hits out). Any hit: "
                  "`tmax = inf` on the same rays. `nodes/ray`, `tris/ray`: one more closest-hit "
                  "pass with `counters=True`, outside the timing (Embree has no counters). "
                  f"`{SCENE_TRACER} speed over it`: the median over rounds of this tracer's time "
                  "over the scene's, so above 1 the scene is faster.", "",
                  "## Agreement", "",
                  "| instances | reference | rays | sample | agree | agree (ties) | hit/miss differ "
                  "| t out of bound | max t error / bound | any hit same |",
                  "|---:|---|---:|---|---:|---:|---:|---:|---:|---:|"]
        for k in report["instances"]:
            for a in k["agreement"]:
                if "skipped" in a:
                    lines.append(f"| {k['instances']:,} | skipped: {a['skipped']} | | | | | | | | |")
                    continue
                lines.append(agreement_line(f"{k['instances']:,}", a))
        lines += ["", "The scene's closest hits against the reference's on the same rays: "
                  "the same hit or miss, the same world triangle (`scene.flat_prim(hits)` against "
                  "the flattened mesh's face) and `t` within the float32 bound "
                  f"`{common.AGREEMENT_T_BOUND}` of `lbvh.metrics.error_bound.t_bound` "
                  "(with ties: another triangle at the same `t`). The scene moves the ray into "
                  "each instance's space, the flattened copy moves the vertices: a ray within "
                  "rounding of a silhouette edge may hit on one side only (at most "
                  f"{HIT_MISS_BOUND:.1%} of rays, the bound tests/test_instances.py holds the "
                  "library to). Where no flattened copy is built, the rays of pixel tiles go "
                  "against a flattened copy of only the instances whose world boxes they cross "
                  "(no other instance can be hit by them).", ""]
    dl = report["device_limits"]
    lines += ["## The largest mesh the device takes", "",
              "| device | max_mem_alloc_size | global_mem_size | triangles in one tree | "
              "triangles in parts | triangles by global memory |", "|---|---:|---:|---:|---:|---:|",
              f"| {dl['device']} | {dl['max_mem_alloc_size'] / 2**30:.2f} GiB "
              f"| {dl['global_mem_size'] / 2**30:.2f} GiB | {dl['max_triangles_one_tree']:,} "
              f"| {dl['max_triangles_in_parts']:,} "
              f"| {dl['max_triangles_by_global_memory']:,} |", "", dl["meaning"], ""]
    p = report.get("parts")
    if p is not None:
        b = p["build"]
        lines += [f"## One mesh in parts: a terrain of {p['triangles']:,} triangles", "",
                  f"`lbvh.build_parts(v, f, part_triangles={p['part_triangles']:,})` "
                  f"({p['parts']} parts, the host's Morton split included) against "
                  f"`lbvh.build(v, f)` (one tree, {p['one_tree_bytes_per_triangle']:.0f} B/triangle "
                  "peak beyond the input), and closest and any hits through both (camera "
                  "`terrain-1m`).", "",
                  "| tree | build ms | closest Mrays/s | any Mrays/s | nodes/ray | tris/ray |",
                  "|---|---:|---:|---:|---:|---:|"]
        for name in (ONE_TREE, PARTS_TREE):
            rs = {r["query"]: r for r in p["rows"] if r["tracer"] == name}
            lines.append(f"| {name} | {ms(b[name])} | {fmt(rs['closest']['mrays_per_second'])} "
                         f"| {fmt(rs['any']['mrays_per_second'])} "
                         f"| {fmt(rs['closest']['nodes_per_ray'], '.1f')} "
                         f"| {fmt(rs['closest']['tris_per_ray'], '.1f')} |")
        lines += ["", "| parts against | rays | sample | agree | agree (ties) | hit/miss differ "
                  "| t out of bound | max t error / bound | any hit same |",
                  "|---|---:|---|---:|---:|---:|---:|---:|---:|",
                  agreement_line(None, p["agreement"]), ""]
    elif report.get("parts_skipped"):
        lines += [f"Parts section skipped: {report['parts_skipped']}.", ""]
    return "\n".join(lines)


def agreement_line(first: str | None, a: dict) -> str:
    cells = [a["reference"], f"{a['rays']:,}", a["sample"], fmt(a["fraction"], ".4f"),
             fmt(a["fraction_with_ties"], ".4f"), f"{a['hit_miss_differ']:,}",
             f"{a['t_out_of_bound']:,}", fmt(a["max_t_error_over_bound"], ".3f"),
             fmt(a["any_hit_same"], ".4f")]
    return "| " + " | ".join(([first] if first is not None else []) + cells) + " |"


# -- main ------------------------------------------------------------------------------

def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--quick", action="store_true",
                   help=f"CI mode: {QUICK_MESH} x {QUICK_INSTANCES}, {QUICK_RAYS[0]}x{QUICK_RAYS[1]} "
                        f"rays, a {QUICK_PARTS_TRIANGLES:,}-triangle terrain, a few seconds")
    p.add_argument("--mesh", default=None, help=f"the mesh to place, from: {', '.join(common.known_scenes())} "
                   f"(default {FULL_MESH}, quick {QUICK_MESH})")
    p.add_argument("--instances", default=None,
                   help=f"instance counts, comma separated (default {','.join(map(str, FULL_INSTANCES))})")
    p.add_argument("--rays", type=common.parse_rays, default=None,
                   help=f"primary rays WIDTHxHEIGHT (default {FULL_RAYS[0]}x{FULL_RAYS[1]})")
    p.add_argument("--repeats", type=int, default=None, help=f"rounds (default {FULL_REPEATS})")
    p.add_argument("--budget", type=float, default=60.0,
                   help="a contestant stops repeating after this many seconds (default 60)")
    p.add_argument("--flatten-max", type=int, default=None,
                   help=f"world triangles up to which the whole flattened copy is built "
                        f"(default {FULL_FLATTEN_MAX:,})")
    p.add_argument("--parts-triangles", type=int, default=None,
                   help=f"triangles of the terrain built in parts (default {FULL_PARTS_TRIANGLES:,}; "
                        "0: skip that section)")
    p.add_argument("--parts", type=int, default=PARTS, help=f"parts of the terrain (default {PARTS})")
    common.add_run_options(p)
    p._option_string_actions["--no-peers"].help = "skip Embree"
    args = p.parse_args(argv)
    args.mesh = args.mesh or (QUICK_MESH if args.quick else FULL_MESH)
    if args.mesh not in common.known_scenes():
        p.error(f"--mesh: unknown {args.mesh!r}; known: {', '.join(common.known_scenes())}")
    try:
        counts = ([int(x) for x in args.instances.split(",") if x] if args.instances else
                  list(QUICK_INSTANCES if args.quick else FULL_INSTANCES))
    except ValueError:
        p.error(f"--instances: {args.instances!r}, expected counts like 100,1000")
    if not counts or min(counts) < 1:
        p.error("--instances: at least one count, each at least 1")
    args.counts = counts
    args.size = args.rays or (QUICK_RAYS if args.quick else FULL_RAYS)
    args.repeats = args.repeats or (QUICK_REPEATS if args.quick else FULL_REPEATS)
    if args.repeats < 1:
        p.error("--repeats: at least 1")
    if args.flatten_max is None:
        args.flatten_max = QUICK_FLATTEN_MAX if args.quick else FULL_FLATTEN_MAX
    if args.parts_triangles is None:
        args.parts_triangles = QUICK_PARTS_TRIANGLES if args.quick else FULL_PARTS_TRIANGLES
    if args.parts < 1 or args.parts_triangles < 0:
        p.error("--parts: at least 1; --parts-triangles: at least 0")
    return args


def main(argv: list[str] | None = None) -> dict:
    """Run the bench; returns the report (also written as JSON and Markdown)."""
    args = parse_args(argv)
    started = time.perf_counter()
    command = common.command_line("bench_instances.py", argv)
    ctx = dev.get_context(args.device)
    peers, peer_status = common.load_peers(not args.no_peers, {"embree": common.Embree})
    cameras = common.load_cameras()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    steps = args.repeats * (1 + 4 * len(args.counts) + (3 if args.parts_triangles else 0))
    progress = common.Progress(steps)
    report: dict[str, Any] = {
        **common.report_start(command, ctx, peer_status),
        "settings": {"mesh": args.mesh, "instances": args.counts, "width": args.size[0],
                     "height": args.size[1], "repeats": args.repeats, "budget": args.budget,
                     "flatten_max": args.flatten_max, "parts_triangles": args.parts_triangles,
                     "parts": args.parts, "quick": args.quick, "seed": SEED, "spacing": SPACING,
                     "scales": list(SCALES), "move": MOVE, "fov": FOV, "pitch": PITCH,
                     "embree_threads": EMBREE_THREADS, "embree_chunks": EMBREE_CHUNKS,
                     "t_bound": common.AGREEMENT_T_BOUND, "hit_miss_bound": HIT_MISS_BOUND,
                     "embree_note": EMBREE_NOTE},
        "instances": [], "skipped": None}
    progress.begin(f"{args.mesh}:")
    progress.note("loading")
    loaded = load_instance_mesh(args.mesh, args.shared)
    peak_bpt, input_bpt = 112.0, 18.0
    with ThreadPoolExecutor(max_workers=EMBREE_THREADS) as pool:
        if isinstance(loaded, str):
            report["skipped"] = loaded
        else:
            v, f, source = loaded
            input_bpt = (v.nbytes + f.nbytes) / len(f)
            lbvh.build(v, f)                        # warm-up: the kernels compile
            mesh_step = Step(common.Variant("mesh", "mesh"), lambda: lbvh.build(v, f))
            run_rounds([mesh_step], args, progress, "mesh build")
            bvh = mesh_step.result
            peak_bpt = float(bvh.report().bytes_per_triangle) or peak_bpt
            report["mesh"] = {"name": args.mesh, "source": source, "triangles": int(len(f)),
                              "vertices": int(len(v)),
                              "build": {"samples": mesh_step.samples,
                                        "seconds": common.median(mesh_step.samples)},
                              "bytes_per_triangle": peak_bpt}
            for count in args.counts:
                report["instances"].append(bench_count(count, v, f, bvh, ctx, peers, pool, args,
                                                       progress, peak_bpt))
        if args.parts_triangles:
            report["parts"] = bench_parts(ctx, args, progress, cameras)
            peak_bpt = report["parts"]["one_tree_bytes_per_triangle"] or peak_bpt
        else:
            report["parts_skipped"] = "--parts-triangles 0"
    progress.close()
    report["device_limits"] = device_limits(ctx, peak_bpt, input_bpt)
    report["duration_seconds"] = time.perf_counter() - started
    paths = {"json": out / "bench_instances.json", "markdown": out / "bench_instances.md"}
    report["outputs"] = {k: str(p) for k, p in paths.items()}
    common.write_report(report, markdown(report), paths, out)
    return report


if __name__ == "__main__":
    main()
