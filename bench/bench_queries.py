#!/usr/bin/env python
"""Query bench of issue 17: every query of lbvh against every peer that answers it,
speed beside agreement.

For each scene the same inputs go to every tracer of a query, all queries and
tracers in interleaved rounds (medians), so that ratios share the machine's noise.
Who answers what (lbvh's ``bvh.<query>``; warp on the CPU, one thread; Open3D's
``o3d.t.geometry.RaycastingScene``; trimesh on a subsample):

* closest: warp ``mesh_query_point_no_sign``, Open3D ``compute_closest_points``,
  trimesh ``proximity.closest_point``;
* signed_distance: warp ``mesh_query_point_sign_winding_number`` (a mesh with
  ``support_winding_number``), Open3D ``compute_signed_distance``, trimesh
  ``ProximityQuery.signed_distance`` (negated: its inside is positive);
* contains: the sign of that warp query (warp has no inside test without the
  closest point), Open3D ``compute_occupancy``, trimesh ``mesh.contains``;
* winding_numbers: lbvh only;
* count_hits: warp ``mesh_query_ray_count_intersections``, Open3D
  ``count_intersections``;
* all_hits: Open3D ``list_intersections``, trimesh
  ``ray.intersects_id(multiple_hits=True)``;
* overlapping: warp ``mesh_query_aabb`` (a counting pass, then a filling pass),
  trimesh's r-tree of the triangles' boxes (``triangles_tree.intersection``, a
  Python call per box); Open3D has no box query.

lbvh runs on the default tree and on the collapsed tree (``collapse=True``), on
the OpenCL device (PoCL: every core). Open3D runs with ``nthreads=2`` (this
machine's cores), warp's CPU launches on one thread, trimesh in numpy (its rays
through embreex when importable). Embree through embreex has only closest and
any hit, so it is not here; no peer exposes bare winding numbers (warp's are
inside its signed query). Every call takes numpy arrays and answers numpy arrays
(transfers and the peers' wrapping included); builds, and lbvh's winding moments
(made on a tree's first winding query), are not in the rates: the moments' own
time is in the scene table, on the device and by the host twins. trimesh is pure numpy and
slow: it runs on the first ``--subsample`` points (closest and signed distance)
or ``--ray-subsample`` points, rays and boxes (inside, every hit, boxes), its
rate is per second on those. A tracer that has spent ``--budget`` seconds on a
query sits out the later rounds (it always runs once): ``rounds`` says how many
it ran.

Inputs per scene (seeded): 2^20 points uniform in the mesh's box grown by a
fifth on each side; 2^18 rays from uniform origins in that box towards uniform
(area-weighted) points of the surface, unit directions; 2^18 boxes, cubes of a
hundredth of the mesh's largest extent around surface points.

Agreement, on ``--sample`` points and ``--ray-sample`` rays and boxes, against
the package's exact references:

* closest: the distance against the float64 brute force
  (:func:`lbvh.queries.closest.closest_points_numpy`), within
  :func:`lbvh.metrics.error_bound.closest_distance_bound` (``4 u s``);
* signed distance: ``|d|`` as for closest, and the sign against the exact
  float64 winding number (:func:`lbvh.queries.winding.winding_numbers_numpy`):
  inside where ``w > 1/2``; contains: that same inside;
* winding numbers: within :data:`lbvh.metrics.error_bound.WINDING_BOUND`;
* count hits: the count of the float64 oracle
  (:func:`lbvh.verification.oracle.all_hits_brute`); every hit: the same count and
  each ``t`` (nearest first) within the float32 bound of bench/common.py;
* boxes: the same triangles as :func:`lbvh.queries.overlap.overlapping_numpy`.

Inside is well defined on a closed mesh only: on an open one (Sponza, the
terrain, and the bunny's holes) the exact winding number is the reference of
lbvh's definition, and the peers' parity tests answer a different question.

    .venv/bin/python bench/bench_queries.py                # bunny, sponza, terrain-1m: about 20 min on 2 cores
    .venv/bin/python bench/bench_queries.py --quick        # CI: teapot, small counts, seconds

With the peers (see bench/README.md for where they are installed), the venv's
own packages first so that its numpy wins:

    PYTHONPATH=.venv/lib/python3.11/site-packages:/tmp/lbvh_peers:/tmp/lbvh_peers_o3d:/tmp/lbvh_peers_scipy \\
        .venv/bin/python bench/bench_queries.py
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

# bench/common.py, beside this script; imported before numpy, for it sets
# OPENBLAS_NUM_THREADS (see there).
from common import (AGREEMENT_COS_FLOOR, GENERATED_SCENES, FILE_SCENES, QUERY_PEERS, Progress,
                    Variant, command_line, header_lines, interleaved_rounds, known_scenes,
                    load_peers, median, report_start, scene_file, write_report)

import numpy as np

import lbvh
from lbvh import device as dev
from lbvh.queries.closest import closest_points_numpy
from lbvh.queries.overlap import overlapping_numpy
from lbvh.queries.winding import winding_numbers_numpy
from lbvh.queries import winding_moments
from lbvh.files import load_mesh
from lbvh.metrics.error_bound import (CLOSEST_BOUND_ULPS, T_BOUND_ULPS, WINDING_BOUND,
                                           closest_distance_bound, t_bound)
from lbvh.verification.oracle import all_hits_brute

FULL_SCENES = ("bunny", "sponza", "terrain-1m")
QUICK_SCENES = ("teapot",)
FULL_POINTS, QUICK_POINTS = 1 << 20, 20_000
FULL_RAYS, QUICK_RAYS = 1 << 18, 4096
FULL_BOXES, QUICK_BOXES = 1 << 18, 4096
FULL_SAMPLE, QUICK_SAMPLE = 200, 60             # points judged
FULL_RAY_SAMPLE, QUICK_RAY_SAMPLE = 500, 100    # rays and boxes judged
FULL_SUBSAMPLE, QUICK_SUBSAMPLE = 2048, 256     # trimesh's closest points and signed distance
FULL_RAY_SUBSAMPLE, QUICK_RAY_SUBSAMPLE = 1 << 16, 2048   # trimesh's inside, every hit, boxes
FULL_REPEATS, QUICK_REPEATS = 3, 2
FULL_BUDGET, QUICK_BUDGET = 40.0, 5.0
#: The query points and ray origins fill the mesh's box grown by this fraction of it on each side.
GROWTH = 0.2
#: The side of the query boxes, a fraction of the mesh's largest extent.
BOX_SIDE = 0.01

QUERIES = ("closest", "signed_distance", "contains", "winding_numbers", "count_hits",
           "all_hits", "overlapping")
#: What each query takes: points, rays or boxes.
INPUT = {"closest": "points", "signed_distance": "points", "contains": "points",
         "winding_numbers": "points", "count_hits": "rays", "all_hits": "rays",
         "overlapping": "boxes"}
TITLES = {"closest": "Closest points", "signed_distance": "Signed distance",
          "contains": "Inside (contains)", "winding_numbers": "Winding numbers",
          "count_hits": "Hit counts", "all_hits": "Every hit along rays",
          "overlapping": "Box queries (overlapping)"}
#: How each query's agreement is judged (the Markdown's notes).
AGREEMENT_NOTES = {
    "closest": f"agree: distance within {CLOSEST_BOUND_ULPS} u s of the float64 brute force "
               "(u = 2^-24, s = |p| + max |vertex|)",
    "signed_distance": "agree: |d| within the closest-point bound and the sign that of the exact "
                       "winding number (inside: w > 1/2); `sign` and `|d|` each alone",
    "contains": "agree: the inside of the exact float64 winding number (w > 1/2)",
    "winding_numbers": f"agree: |w - w_exact| <= {WINDING_BOUND} (WINDING_BOUND); no peer answers it",
    "count_hits": "agree: the count of the float64 oracle (all_hits_brute)",
    "all_hits": f"agree: the oracle's count and every t, nearest first, within "
                f"{T_BOUND_ULPS} u (t + s) / max(|cos a|, {AGREEMENT_COS_FLOOR}); `count` alone",
    "overlapping": "agree: the same triangles as the brute force (overlapping_numpy); "
                   "Open3D has no box query",
}


# -- inputs ---------------------------------------------------------------------------------

def query_points(vertices: np.ndarray, count: int, seed: int = 17) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    ext = hi - lo
    return (lo + ext * rng.uniform(-GROWTH, 1 + GROWTH, (count, 3))).astype(np.float32)


def surface_points(vertices: np.ndarray, faces: np.ndarray, count: int,
                   rng: np.random.Generator) -> np.ndarray:
    """``float64 (count, 3)`` uniform on the surface (triangles by area, then uniform in each)."""
    tri = vertices[faces].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(faces), count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return (tri[pick] * w[:, :, None]).sum(axis=1)


def query_rays(vertices: np.ndarray, faces: np.ndarray, count: int,
               seed: int = 18) -> tuple[np.ndarray, np.ndarray]:
    """Origins uniform in the grown box, unit directions towards uniform surface points."""
    rng = np.random.default_rng(seed)
    origins = query_points(vertices, count, seed).astype(np.float64)
    d = surface_points(vertices, faces, count, rng) - origins
    n = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(n > 0, d / np.where(n > 0, n, 1), [0.0, 0.0, 1.0])
    return origins.astype(np.float32), d.astype(np.float32)


def query_boxes(vertices: np.ndarray, faces: np.ndarray, count: int,
                seed: int = 19) -> tuple[np.ndarray, np.ndarray]:
    """Cubes of side :data:`BOX_SIDE` of the largest extent, their centres surface points
    moved by up to half a side on each axis."""
    rng = np.random.default_rng(seed)
    side = BOX_SIDE * float(np.ptp(vertices, axis=0).max())
    centre = surface_points(vertices, faces, count, rng) + rng.uniform(-side / 2, side / 2, (count, 3))
    return (centre - side / 2).astype(np.float32), (centre + side / 2).astype(np.float32)


@dataclass
class Inputs:
    points: np.ndarray
    origins: np.ndarray
    directions: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    point_sample: np.ndarray
    ray_sample: np.ndarray
    box_sample: np.ndarray

    def of(self, kind: str, sample: bool = False, first: int | None = None) -> tuple[np.ndarray, ...]:
        """The arrays of one input kind: all of them, the judged sample, or the first ``first``."""
        arrays = {"points": (self.points,), "rays": (self.origins, self.directions),
                  "boxes": (self.lower, self.upper)}[kind]
        if sample:
            idx = {"points": self.point_sample, "rays": self.ray_sample, "boxes": self.box_sample}[kind]
            return tuple(a[idx] for a in arrays)
        return tuple(a[:first] for a in arrays) if first is not None else arrays


def make_inputs(v: np.ndarray, f: np.ndarray, args: argparse.Namespace) -> Inputs:
    points = query_points(v, args.points)
    origins, directions = query_rays(v, f, args.rays)
    lower, upper = query_boxes(v, f, args.boxes)
    rng = np.random.default_rng(5)
    return Inputs(points, origins, directions, lower, upper,
                  np.sort(rng.choice(len(points), min(args.sample, len(points)), replace=False)),
                  np.sort(rng.choice(len(origins), min(args.ray_sample, len(origins)), replace=False)),
                  np.sort(rng.choice(len(lower), min(args.ray_sample, len(lower)), replace=False)))


# -- tracers --------------------------------------------------------------------------------

@dataclass
class Tracer:
    """One tracer: ``answers`` maps a query to a function of its input arrays; trimesh's
    timed inputs are the first ``subsample[query]`` of them."""
    name: str
    family: str
    answers: dict[str, Callable[..., Any]]
    subsample: dict[str, int] = field(default_factory=dict)
    build_seconds: float = 0.0
    moments: dict[str, float] = field(default_factory=dict)


INSIDE_QUERIES = ("signed_distance", "contains", "winding_numbers")


def time_moments(bvh: lbvh.BVH, v: np.ndarray, f: np.ndarray) -> dict[str, float]:
    """Seconds to make the winding moments of ``bvh`` (what its first inside query pays
    before any point is answered): on the device (``bvh.query_data.winding_moments()``, the
    kernels compiled first) and by the numpy twins on the host in the same run (what
    it paid before kernels/winding_moments.cl)."""
    wide = bvh.query_data.wide_records()
    bvh.ctx.memory.free(winding_moments.make_moments(bvh.ctx, bvh.tree, bvh.mesh, wide))
    t0 = time.perf_counter()
    bvh.query_data.winding_moments()
    device = time.perf_counter() - t0
    t0 = time.perf_counter()
    rows = winding_moments.node_moments(bvh.nodes, bvh.prim_order, bvh.root, v, f)
    if wide.packed and wide.count:
        lanes = winding_moments.read_lanes(bvh.ctx, wide)
        winding_moments.wide_moments(rows, lanes, winding_moments.lane_corners(
            lanes, bvh.nodes, bvh.prim_order, v, f))
    return {"device": device, "host": time.perf_counter() - t0}


def lbvh_answers(bvh: lbvh.BVH) -> dict[str, Callable[..., Any]]:
    def all_hits(o, d):
        r = bvh.all_hits(o, d)
        return r.offsets, r.t, r.prim

    def overlapping(lo, hi):
        r = bvh.overlapping(lo, hi)
        return r.offsets, r.prims

    return {"closest": lambda p: bvh.closest_points(p).distance,
            "signed_distance": bvh.signed_distance, "contains": bvh.contains,
            "winding_numbers": bvh.winding_numbers, "count_hits": bvh.count_hits,
            "all_hits": all_hits, "overlapping": overlapping}


def make_tracers(v: np.ndarray, f: np.ndarray, args: argparse.Namespace, peers: dict) -> list[Tracer]:
    """Every tracer of the scene, built (untimed here: ``build_seconds`` is for the JSON)."""
    out = []
    for name, options in (("lbvh", {}), ("lbvh+collapse", {"collapse": True})):
        t0 = time.perf_counter()
        bvh = lbvh.build(v, f, device=args.device, **options)
        built = time.perf_counter() - t0
        moments = time_moments(bvh, v, f) if set(INSIDE_QUERIES) & set(args.queries) else {}
        out.append(Tracer(name, "lbvh", lbvh_answers(bvh), build_seconds=built, moments=moments))
    if "warp" in peers:
        warp = peers["warp"]
        setup, build, mesh = warp.build(v, f)
        setup_w, build_w, wmesh = warp.winding_mesh(v, f)
        out.append(Tracer("warp", "warp", {
            "closest": lambda p: warp.closest_points(mesh, p)[0],
            "signed_distance": lambda p: warp.signed_distance(wmesh, p),
            "contains": lambda p: warp.contains(wmesh, p),
            "count_hits": lambda o, d: warp.count_hits(mesh, o, d),
            "overlapping": lambda lo, hi: warp.overlapping(mesh, lo, hi)},
            build_seconds=setup + build + setup_w + build_w))
    if "open3d" in peers:
        o3d = peers["open3d"]
        setup, build, scene = o3d.build(v, f)
        out.append(Tracer("open3d", "open3d", {
            "closest": lambda p: o3d.closest_points(scene, p)[0],
            "signed_distance": lambda p: o3d.signed_distance(scene, p),
            "contains": lambda p: o3d.contains(scene, p),
            "count_hits": lambda o, d: o3d.count_hits(scene, o, d),
            "all_hits": lambda o, d: o3d.all_hits(scene, o, d)}, build_seconds=setup + build))
    if "trimesh" in peers:
        tm = peers["trimesh"]
        setup, build, mesh_t = tm.build(v, f)
        answers = {"contains": lambda p: tm.contains(mesh_t, p),
                   "all_hits": lambda o, d: tm.all_hits(mesh_t, o, d),
                   "overlapping": lambda lo, hi: tm.overlapping(mesh_t, lo, hi)}
        if tm.has_proximity:
            answers.update(closest=lambda p: tm.closest_points(mesh_t, p)[0],
                           signed_distance=lambda p: tm.signed_distance(mesh_t, p))
        sub = {"closest": args.subsample, "signed_distance": args.subsample,
               "contains": args.ray_subsample, "all_hits": args.ray_subsample,
               "overlapping": args.ray_subsample}
        out.append(Tracer("trimesh", "trimesh", answers, sub, build_seconds=setup + build))
    return out


@dataclass
class Contestant:
    """One tracer on one query: what :func:`common.interleaved_rounds` runs."""
    variant: Variant
    tracer: str
    query: str
    fn: Callable[..., Any]
    inputs: tuple[np.ndarray, ...]
    subsampled: bool
    seconds: list[float] = field(default_factory=list)

    def run(self) -> None:
        t0 = time.perf_counter()
        self.fn(*self.inputs)
        self.seconds.append(time.perf_counter() - t0)


# -- agreement --------------------------------------------------------------------------------

class References:
    """The exact answers on the judged sample, each computed on first use."""

    def __init__(self, v: np.ndarray, f: np.ndarray, inputs: Inputs) -> None:
        self.v, self.f, self.inputs = v, f, inputs
        self._cache: dict[str, Any] = {}

    def _get(self, key: str, make: Callable[[], Any]) -> Any:
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    @property
    def distance(self) -> tuple[np.ndarray, np.ndarray]:
        (p,) = self.inputs.of("points", sample=True)
        return self._get("distance", lambda: (closest_points_numpy(self.v, self.f, p)[0],
                                              closest_distance_bound(self.v, p)))

    @property
    def winding(self) -> np.ndarray:
        (p,) = self.inputs.of("points", sample=True)
        return self._get("winding", lambda: winding_numbers_numpy(self.v, self.f, p))

    @property
    def hits(self) -> tuple[Any, np.ndarray]:
        """The oracle's hits and the bound on each hit's ``t``."""
        def make():
            o, d = self.inputs.of("rays", sample=True)
            ref = all_hits_brute(self.v, self.f, o, d, dtype=np.float64)
            ray = ref.ray
            bound = t_bound(self.v, self.f, o[ray], d[ray], ref.t.astype(np.float64),
                            ref.prim, cos_floor=AGREEMENT_COS_FLOOR)
            return ref, bound
        return self._get("hits", make)

    @property
    def boxes(self) -> Any:
        lo, hi = self.inputs.of("boxes", sample=True)
        return self._get("boxes", lambda: overlapping_numpy(self.v, self.f, lo, hi))


def worst(err: np.ndarray) -> float | None:
    """The largest error, ``None`` (JSON null) when none or not finite (a tracer that
    answered nothing, ``inf``, for some point)."""
    m = float(err.max()) if err.size else 0.0
    return m if np.isfinite(m) else None


def judge(query: str, answer: Any, ref: References) -> dict:
    """The agreement of one answer on the judged sample: ``agree`` (the fraction the
    tables show) and the query's details."""
    if query == "closest":
        d_ref, bound = ref.distance
        err = np.abs(answer.astype(np.float64) - d_ref) / bound
        return {"agree": float(np.mean(err <= 1)), "max_error_over_bound": worst(err)}
    if query == "signed_distance":
        d_ref, bound = ref.distance
        err = np.abs(np.abs(answer.astype(np.float64)) - d_ref) / bound
        sign = (answer < 0) == (ref.winding > 0.5)
        return {"agree": float(np.mean((err <= 1) & sign)), "within_bound": float(np.mean(err <= 1)),
                "sign_agrees": float(np.mean(sign)), "max_error_over_bound": worst(err)}
    if query == "contains":
        inside = ref.winding > 0.5
        return {"agree": float(np.mean(answer == inside)),
                "inside_fraction": float(np.mean(answer))}
    if query == "winding_numbers":
        err = np.abs(answer.astype(np.float64) - ref.winding)
        return {"agree": float(np.mean(err <= WINDING_BOUND)), "max_winding_error": worst(err)}
    if query == "count_hits":
        total = ref.hits[0].total
        return {"agree": float(np.mean(answer == total)),
                "count_differs": int(np.sum(answer != total))}
    if query == "all_hits":
        return judge_all_hits(answer, *ref.hits)
    if query == "overlapping":
        offsets, prims = answer
        r = ref.boxes
        same = [np.array_equal(np.sort(prims[offsets[i]:offsets[i + 1]]),
                               r.prims[r.offsets[i]:r.offsets[i + 1]]) for i in range(len(r))]
        return {"agree": float(np.mean(same)),
                "count_differs": int(np.sum(np.diff(offsets) != r.counts))}
    raise ValueError(query)


def judge_all_hits(answer: tuple[np.ndarray, np.ndarray, np.ndarray], ref: Any,
                   bound: np.ndarray) -> dict:
    """Same count as the oracle, and the ``t`` of each hit (both nearest first) within
    ``bound`` (the oracle's, per hit)."""
    offsets, t, _ = answer
    n = len(ref)
    counts = np.diff(offsets)
    same = counts == ref.total
    ray = np.repeat(np.arange(n), counts)
    order = np.lexsort((t, ray))                       # nearest first per ray
    t_sorted, ray_sorted = t[order].astype(np.float64), ray[order]
    keep, keep_ref = same[ray_sorted], same[ref.ray]
    err = np.abs(t_sorted[keep] - ref.t[keep_ref].astype(np.float64)) / bound[keep_ref]
    bad = np.zeros(n, bool)
    np.logical_or.at(bad, ref.ray[keep_ref], err > 1)
    return {"agree": float(np.mean(same & ~bad)), "same_count": float(np.mean(same)),
            "max_t_error_over_bound": worst(err)}


# -- one scene ----------------------------------------------------------------------------------

def boundary_edges(faces: np.ndarray) -> int:
    """Edges of one triangle only: 0 for a closed mesh."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    key = e[:, 0].astype(np.int64) * (int(faces.max()) + 1) + e[:, 1]
    _, count = np.unique(key, return_counts=True)
    return int(np.sum(count == 1))


def bench_scene(name: str, v: np.ndarray, f: np.ndarray, args: argparse.Namespace,
                peers: dict, progress: Progress) -> tuple[dict, list[dict]]:
    progress.note("inputs")
    inputs = make_inputs(v, f, args)
    progress.note("builds")
    tracers = make_tracers(v, f, args, peers)
    contestants = []
    for tr in tracers:
        for query in args.queries:
            if query not in tr.answers:
                continue
            kind = INPUT[query]
            first = tr.subsample.get(query)
            arrays = inputs.of(kind, first=first)
            c = Contestant(Variant(f"{tr.name} {query}", tr.family), tr.name, query,
                           tr.answers[query], arrays, first is not None and first < len(arrays[0]))
            progress.note(f"{tr.name} {query} warm-up")
            c.fn(*(a[:64] for a in arrays))          # compile, commit, caches, winding moments
            contestants.append(c)
    interleaved_rounds(contestants, args.repeats, args.budget, lambda c: sum(c.seconds),
                       lambda c: c.run(), progress, "round")
    ref = References(v, f, inputs)
    rows = []
    for c in contestants:
        progress.note(f"judging {c.variant.name}")
        answer = c.fn(*inputs.of(INPUT[c.query], sample=True))
        med = median(c.seconds)
        count = len(c.inputs[0])
        rows.append({"scene": name, "triangles": int(len(f)), "query": c.query,
                     "tracer": c.tracer, "family": c.variant.family, "count": count,
                     "subsample": c.subsampled, "seconds": med, "samples": c.seconds,
                     "rounds": len(c.seconds), "per_second": count / med,
                     "judged": int(len(inputs.of(INPUT[c.query], sample=True)[0])),
                     **judge(c.query, answer, ref)})
    info = {"scene": name, "triangles": int(len(f)), "vertices": int(len(v)),
            "boundary_edges": boundary_edges(f),
            "builds": {tr.name: tr.build_seconds for tr in tracers},
            "winding_moments": {tr.name: tr.moments for tr in tracers if tr.moments}}
    if "winding" in ref._cache:
        info["inside_fraction"] = float(np.mean(ref.winding > 0.5))
    if "hits" in ref._cache:
        info["mean_hits"] = float(ref.hits[0].total.mean())
    if "boxes" in ref._cache:
        info["mean_overlaps"] = float(ref.boxes.counts.mean())
    return info, rows


# -- the report ----------------------------------------------------------------------------------

def rate(x: float) -> str:
    """Queries per second, short: ``1.45 M``, ``812 K``, ``96``."""
    if x >= 1e6:
        return f"{x / 1e6:.3g} M"
    if x >= 1e3:
        return f"{x / 1e3:.3g} K"
    return f"{x:.3g}"


def num(x: float | None, spec: str) -> str:
    return "inf" if x is None else format(x, spec)


def detail(r: dict) -> str:
    q = r["query"]
    if q == "closest":
        return f"max err/bound {num(r['max_error_over_bound'], '.2f')}"
    if q == "signed_distance":
        return (f"sign {r['sign_agrees']:.3f}, \\|d\\| {r['within_bound']:.3f}, "
                f"max err/bound {num(r['max_error_over_bound'], '.2f')}")
    if q == "contains":
        return f"inside {r['inside_fraction']:.3f}"
    if q == "winding_numbers":
        return f"max \\|w - w_exact\\| {num(r['max_winding_error'], '.3g')}"
    if q == "count_hits":
        return f"{r['count_differs']} counts differ"
    if q == "all_hits":
        return f"count {r['same_count']:.3f}, max t err/bound {num(r['max_t_error_over_bound'], '.2f')}"
    return f"{r['count_differs']} counts differ"


def summary_lines(report: dict) -> list[str]:
    """Issue 17's goal, per scene and query: lbvh (the default tree) against each peer."""
    lines = ["## lbvh against each peer", "",
             "lbvh's default tree against every peer that answers the query; `lbvh / peer` above 1: "
             "lbvh is faster. trimesh's rate is on its subsample (`n`).", "",
             "| scene | query | peer | n peer | lbvh /s | peer /s | lbvh / peer | agree lbvh | agree peer |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    rows = report["rows"]
    base = {(r["scene"], r["query"]): r for r in rows if r["tracer"] == "lbvh"}
    slower = []
    for r in rows:
        if r["family"] == "lbvh" or (r["scene"], r["query"]) not in base:
            continue
        b = base[(r["scene"], r["query"])]
        ratio = b["per_second"] / r["per_second"]
        mark = f"{ratio:.3g}" if ratio >= 1 else f"**{ratio:.3g}**"
        if ratio < 1:
            slower.append(f"{r['scene']} {r['query']} vs {r['tracer']} ({ratio:.3g}x)")
        lines.append(f"| {r['scene']} | {r['query']} | {r['tracer']} | {r['count']:,} | "
                     f"{rate(b['per_second'])} | {rate(r['per_second'])} | {mark} | "
                     f"{b['agree']:.3f} | {r['agree']:.3f} |")
    if len(lines) == 6:
        return lines[:3] + ["No peer ran (none installed, or --no-peers)."]
    lines += ["", "lbvh slower (bold above): " + ("; ".join(slower) if slower else "nowhere") + "."]
    return lines


def markdown(report: dict) -> str:
    s = report["settings"]
    path = [f"PYTHONPATH: `{report['pythonpath']}`.  "] if report.get("pythonpath") else []
    lines = ["# Queries of issue 17: lbvh against its peers", "", *header_lines(report), *path, "",
             f"Per scene: {s['points']:,} points uniform in the mesh's box grown by {GROWTH:.0%} on "
             f"each side; {s['rays']:,} rays from uniform origins in that box towards uniform "
             f"surface points; {s['boxes']:,} cubes of side {BOX_SIDE:.0%} of the largest extent "
             f"around surface points. Medians of up to {s['repeats']} interleaved rounds (a tracer "
             f"past {s['budget']:.0f} s on a query sits out later rounds: `rounds`). trimesh runs "
             f"on the first {s['subsample']:,} points (closest, signed distance) or "
             f"{s['ray_subsample']:,} points, rays and boxes (contains, every hit, boxes). Agreement on "
             f"{s['sample']} points and {s['ray_sample']} rays and boxes per scene against the "
             "exact references; inside is that of the exact winding number (w > 1/2), "
             "ill-defined on an open mesh (boundary edges > 0): there the parity tests of "
             "Open3D and trimesh answer another question, and lbvh's own agreement can fall "
             "where the exact w is near 1/2.", "",
             "The winding moments (made once per tree, at its first inside query; not in the "
             "rates): seconds on the device (kernels/winding_moments.cl) and by the numpy "
             "twins on the host, the same tree in the same run, default tree / collapsed.", "",
             "| scene | triangles | boundary edges | judged inside | mean hits per ray | "
             "mean triangles per box | winding moments, device | host twins |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for sc in report["scenes"]:
        def opt(key, fmt):
            return format(sc[key], fmt) if key in sc else "-"
        mom = sc.get("winding_moments", {})

        def secs(where):
            return " / ".join(f"{mom[t][where]:.2f}" for t in mom) or "-"
        lines.append(f"| {sc['scene']} | {sc['triangles']:,} | {sc['boundary_edges']:,} | "
                     f"{opt('inside_fraction', '.3f')} | {opt('mean_hits', '.2f')} | "
                     f"{opt('mean_overlaps', '.1f')} | {secs('device')} | {secs('host')} |")
    lines += [""] + summary_lines(report)
    rows = report["rows"]
    base = {(r["scene"], r["query"]): r["per_second"] for r in rows if r["tracer"] == "lbvh"}
    for q in s["queries"]:
        qrows = [r for r in rows if r["query"] == q]
        if not qrows:
            continue
        lines += ["", f"## {TITLES[q]}", "", AGREEMENT_NOTES[q] + ".", "",
                  "| scene | tracer | n | per s | ms | rounds | vs lbvh | agree | details |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---|"]
        for r in qrows:
            n = f"{r['count']:,}" + (" (sub)" if r["subsample"] else "")
            vs = r["per_second"] / base[(r["scene"], q)] if (r["scene"], q) in base else float("nan")
            lines.append(f"| {r['scene']} | {r['tracer']} | {n} | {rate(r['per_second'])} | "
                         f"{r['seconds'] * 1e3:.1f} | {r['rounds']} | {vs:.2f} | {r['agree']:.3f} | "
                         f"{detail(r)} |")
    for sk in report["skipped"]:
        lines.append(f"\nskipped {sk['scene']}: {sk['reason']}")
    return "\n".join(lines) + "\n"


# -- command line ----------------------------------------------------------------------------------

def load_scene_mesh(name: str, shared: Path) -> tuple[np.ndarray, np.ndarray] | str:
    if name in GENERATED_SCENES:
        return GENERATED_SCENES[name]()
    path = scene_file(name, shared)
    if not path.is_file():
        return f"{path} not found"
    return load_mesh(path)


def split_names(items: list[str] | None) -> list[str]:
    return [n for item in (items or []) for n in item.split(",") if n]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true",
                   help=f"CI mode: {', '.join(QUICK_SCENES)}, {QUICK_POINTS:,} points, "
                        f"{QUICK_RAYS:,} rays and boxes")
    p.add_argument("--scenes", nargs="+", metavar="NAME",
                   help=f"from {', '.join(known_scenes())}; default {','.join(FULL_SCENES)}")
    p.add_argument("--queries", nargs="+", metavar="QUERY",
                   help=f"from {', '.join(QUERIES)} (default all)")
    p.add_argument("--points", type=int, help=f"query points per scene (default {FULL_POINTS:,})")
    p.add_argument("--rays", type=int, help=f"rays per scene (default {FULL_RAYS:,})")
    p.add_argument("--boxes", type=int, help=f"boxes per scene (default {FULL_BOXES:,})")
    p.add_argument("--sample", type=int, help=f"points judged (default {FULL_SAMPLE})")
    p.add_argument("--ray-sample", type=int, help=f"rays and boxes judged (default {FULL_RAY_SAMPLE})")
    p.add_argument("--subsample", type=int,
                   help=f"trimesh's points for closest and signed distance (default {FULL_SUBSAMPLE:,})")
    p.add_argument("--ray-subsample", type=int,
                   help=f"trimesh's points, rays and boxes for contains, every hit and boxes "
                        f"(default {FULL_RAY_SUBSAMPLE:,})")
    p.add_argument("--repeats", type=int, default=None, help="interleaved rounds (median)")
    p.add_argument("--budget", type=float, default=None,
                   help="seconds a tracer spends on a query before it sits out later rounds")
    p.add_argument("--no-peers", action="store_true", help="skip warp, Open3D and trimesh")
    p.add_argument("--device", default=None, help="OpenCL device (default: $LBVH_DEVICE or PoCL)")
    p.add_argument("--shared", type=Path, default=FILE_SCENES["bunny"][0],
                   help="folder of the shared scenes")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "out")
    args = p.parse_args(argv)
    names = split_names(args.scenes) or list(QUICK_SCENES if args.quick else FULL_SCENES)
    unknown = [n for n in names if n not in known_scenes()]
    if unknown:
        p.error(f"--scenes: unknown scene {unknown[0]!r}; known: {', '.join(known_scenes())}")
    args.queries = split_names(args.queries) or list(QUERIES)
    unknown = [q for q in args.queries if q not in QUERIES]
    if unknown:
        p.error(f"--queries: unknown query {unknown[0]!r}; known: {', '.join(QUERIES)}")
    q = args.quick
    for key, full, quick in (("points", FULL_POINTS, QUICK_POINTS), ("rays", FULL_RAYS, QUICK_RAYS),
                             ("boxes", FULL_BOXES, QUICK_BOXES), ("sample", FULL_SAMPLE, QUICK_SAMPLE),
                             ("ray_sample", FULL_RAY_SAMPLE, QUICK_RAY_SAMPLE),
                             ("subsample", FULL_SUBSAMPLE, QUICK_SUBSAMPLE),
                             ("ray_subsample", FULL_RAY_SUBSAMPLE, QUICK_RAY_SUBSAMPLE),
                             ("repeats", FULL_REPEATS, QUICK_REPEATS),
                             ("budget", FULL_BUDGET, QUICK_BUDGET)):
        if getattr(args, key) is None:
            setattr(args, key, quick if q else full)
    peers, status = load_peers(not args.no_peers, QUERY_PEERS)
    status = {k: v if v.startswith(k) else f"{k} {v}" for k, v in status.items()}
    ctx = dev.get_context(args.device)
    start = time.perf_counter()
    report = report_start(command_line("bench_queries.py", argv), ctx, status)
    report["pythonpath"] = os.environ.get("PYTHONPATH", "")     # where the peers came from
    report.update(settings={k: getattr(args, k) for k in (
        "points", "rays", "boxes", "sample", "ray_sample", "subsample", "ray_subsample",
        "repeats", "budget", "queries")} | {"scenes": names, "growth": GROWTH, "box_side": BOX_SIDE},
        scenes=[], rows=[], skipped=[])
    progress = Progress(len(names) * args.repeats)
    for name in names:
        progress.begin(f"{name}:")
        progress.note("loading")
        mesh = load_scene_mesh(name, args.shared)
        if isinstance(mesh, str):
            report["skipped"].append({"scene": name, "reason": mesh})
            progress.skip(args.repeats)
            continue
        info, rows = bench_scene(name, *mesh, args, peers, progress)
        report["scenes"].append(info)
        report["rows"] += rows
    progress.close()
    report["duration_seconds"] = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": args.out / "bench_queries.md", "json": args.out / "bench_queries.json"}
    write_report(report, markdown(report), paths, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
