#!/usr/bin/env python
"""Every builder on every scene: which BVH is best, and for how many rays? (issues 4, 20)

    .venv/bin/python bench/bench_builders.py [--quick] [--scenes bunny,sponza ...]
        [--rays 512x384] [--repeats 3] [--out bench/out] [--no-peers]

For each (scene, builder) it measures, in one run (builds, then renders, go in
rounds that run every builder once, so that the machine's noise hits all alike):

* the build: wall time from host arrays to a tree on the device (mesh
  validation, upload and, for the SAH reference, the host build and the tree
  upload included; likewise for the median and midpoint host builds), median
  of ``--repeats`` builds; a builder stops repeating once its builds have taken
  ``--build-budget`` seconds (the serial SAH on 1M triangles is built once);
* the render: closest-hit traversal of one fixed set of primary rays (one per
  pixel of the scene's camera from ``lbvh/data/cameras.json``), median wall time
  of ``lbvh.queries.traverse.intersect`` (ray packing, transfers and read-back
  included, counters off), hence rays per second; for each of our trees, in the
  same rounds, also the global-order traversal (``order="global"``: the nearest
  pending node of all first, from a heap; Kay & Kajiya 1986);
* the tree: SAH cost normalised by the root area (``lbvh.metrics.quality.sah_cost``,
  C_node = C_tri = 1) and its ratio to the serial SAH tree's; depth, nodes,
  leaves, memory; the sampled EPO (end-point overlap, Aila, Karras & Laine
  2013; ``tree_quality``, 32K surface samples); the ray-sampled cost of the same
  primary rays (``lbvh.verification.ray_cost.ray_sampled_cost``: the inner nodes
  and leaf triangles each ray's segment up to its closest hit enters); the
  traversal counters of the same rays: mean nodes visited and triangles tested
  per ray, and their sum relative to the SAH tree's, for the ordered and the
  global-order traversal, with the fraction of rays whose ``t`` the two give
  identically and the global order's stack (heap) overflows;
* hit agreement with the reference (the SAH tree's hits, same kernel): the
  fraction of rays with the same hit or miss, the same primitive and ``t``
  within the float32 bound :func:`lbvh.metrics.error_bound.t_bound`,
  ``|cos a|`` floored at :data:`common.AGREEMENT_COS_FLOOR` (:func:`common.agreement`);
  ``with ties`` also accepts another primitive at ``t`` within the bound (two
  triangles meeting the ray at one point);
* break-even ray counts: ``build_a + n cost_a = build_b + n cost_b``, against
  the fastest build of the scene and against the SAH reference, and the lower
  envelope ("which builder for how many rays") over all builders;
* which cost metric predicts the render time: Spearman's rank correlation
  (:func:`spearman`, ties as average ranks) between each metric (SAH cost, EPO,
  ray-sampled cost, measured nodes and triangles per ray) and the render time,
  over our trees within each scene, and its mean over the scenes.

Builders: the device LBVH with 30-bit, 63-bit and automatic Morton keys, each
without and with the SAH leaf collapse (``max_leaf_size`` 8), automatic keys
with treelet restructuring (without and with the collapse), the device PLOC
build (``builder="ploc"``, Meister & Bittner 2018, radius 16), the host top-down
median and midpoint splits (``lbvh/builders/topdown.py``, leaves of one
triangle), the serial SAH reference and the SAH reference costed by a 64x48 grid of
the scene camera's rays (``sah+rays``, :mod:`lbvh.builders.ray_sampled`), and as peers when installed Embree (embreex) and warp-lang's CPU
mesh constructors. The peers' trees are not visible: they get a build time, a
render time through their own traversal, and hit agreement, no tree figures
(and no place in the correlation or traversal-order tables).
Embree's build is the scene commit (the copy into its scene is reported as
``setup``); warp traces with ``wp.mesh_query_ray`` in a CPU kernel (one thread).

Outputs in ``--out``: ``bench_builders.json`` (every figure, the machine and
the OpenCL device), ``bench_builders.md`` (also printed: the table, the metric
correlations, ordered against global traversal, which builder for how many rays), ``bench_builders.png``
(speed against error, needs matplotlib) and ``views/<scene>.png`` (what the
camera sees). Progress goes to stderr.

The scenes and cameras, the peers' adapters, the agreement and the timing
helpers are shared with the other benches in ``bench/common.py``; the SAH
cost constants come from :mod:`lbvh.metrics.cost`.
"""
from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# bench/common.py, beside this script; imported before numpy, for it sets
# OPENBLAS_NUM_THREADS (see there).
from common import (AGREEMENT_COS_FLOOR, AGREEMENT_T_BOUND, Progress, Scene, Variant,
                    add_run_options, add_scene_options, agreement, command_line, cores_used,
                    header_lines, interleaved_rounds, load_bench_scene, load_cameras, load_peers,
                    loaded_scenes, median, report_start, resolve_scenes, save_view, write_report)

import numpy as np

import lbvh
from lbvh import device as dev
from lbvh.metrics.cost import C_NODE, C_TRI, MAX_LEAF_SIZE
from lbvh.camera import frame_bounds
from lbvh.queries.traverse import intersect
from lbvh.verification import meshes
from lbvh.metrics.error_bound import t_bound
from lbvh.metrics.quality import EPO_SAMPLES, tree_quality
from lbvh.verification.ray_cost import ray_sampled_cost

FULL_SCENES = ("bunny", "sponza", "sibenik", "conference", "soup-1m", "terrain-1m")
QUICK_SCENES = ("teapot",)

FULL_RAYS = (512, 384)
QUICK_RAYS = (128, 96)
#: Ray count of the "build + render" axis of the chart: ten 1-megapixel frames.
CHART_RAYS = 10_000_000

REFERENCE = "sah"
#: Families of our trees (traced by our kernel): the device LBVH, the device PLOC, the
#: host top-down median / midpoint splits and the SAH reference.
OUR_FAMILIES = ("lbvh", "ploc", "topdown", "sbvh", "sah")
#: The host SBVH builds about 4,500 triangles a second (Sponza, 262K: 56 s): scenes
#: above this size leave it out (a 1M-triangle scene would take about 4 minutes a build).
SBVH_MAX_TRIANGLES = 400_000
#: Cost constants of the collapse and of the SAH reference (the same for both).
SAH_OPTIONS = {"c_node": C_NODE, "c_tri": C_TRI, "max_leaf_size": MAX_LEAF_SIZE}


# -- builders ---------------------------------------------------------------------

#: Rounds of treelet restructuring in the restructured variants.
TREELET_ROUNDS = 2


def ours(variant: Variant) -> bool:
    """One of our trees (:data:`OUR_FAMILIES`), traced by our kernel, with tree figures."""
    return variant.family in OUR_FAMILIES


def our_variants() -> list[Variant]:
    """The device LBVH (3 key widths x with/without collapse), the automatic width with
    treelet restructuring (with/without collapse), the device PLOC (its default
    radius), the host median and midpoint splits (leaves of one triangle, their
    default) and the SAH reference."""
    out = []
    for bits in (30, 63, "auto"):
        out.append(Variant(f"lbvh-{bits}", "lbvh", {"key_bits": bits}))
        out.append(Variant(f"lbvh-{bits}+collapse", "lbvh", {"key_bits": bits, "collapse": True,
                                                              **SAH_OPTIONS}))
    treelets = {"key_bits": "auto", "treelet_rounds": TREELET_ROUNDS}
    out.append(Variant(f"lbvh-auto+treelets{TREELET_ROUNDS}", "lbvh", treelets))
    out.append(Variant(f"lbvh-auto+treelets{TREELET_ROUNDS}+collapse", "lbvh",
                       {**treelets, "collapse": True, **SAH_OPTIONS}))
    out.append(Variant("ploc", "ploc", {"builder": "ploc"}))
    for rule in ("median", "midpoint"):
        out.append(Variant(rule, "topdown", {"builder": rule}))
    out.append(Variant("sbvh", "sbvh", {"builder": "sbvh", **SAH_OPTIONS}))
    out.append(Variant(REFERENCE, "sah", {"builder": "sah", **SAH_OPTIONS}))
    out.append(Variant(f"{REFERENCE}+rays", "sah", {"builder": "sah", **SAH_OPTIONS,
                                                    "camera_sample": CAMERA_SAMPLE}))
    return out


#: The ray-sampled SAH's sample: a grid of this many of the bench camera's rays
#: (``camera.resized(64, 48)``: 1/64 of the render's 512x384, not the same rays).
CAMERA_SAMPLE = (64, 48)


def build_options(options: dict, camera: Any) -> dict:
    """``lbvh.build``'s keywords of a variant: ``camera_sample=(w, h)`` becomes
    ``rays``, a ``w x h`` grid of ``camera``'s rays (the ray-sampled SAH)."""
    if "camera_sample" not in options:
        return options
    out = {k: v for k, v in options.items() if k != "camera_sample"}
    out["rays"] = camera.resized(*options["camera_sample"]).rays()
    return out


def build_tree(variant: Variant, vertices: np.ndarray, faces: np.ndarray, ctx: dev.Context,
               camera: Any = None) -> lbvh.BVH:
    """Build one of our trees on ``ctx`` (``camera``: the view a ray-sampled tree is for;
    default, one framing the mesh)."""
    if camera is None:
        camera = frame_bounds(vertices.min(axis=0), vertices.max(axis=0))
    return lbvh.build(vertices, faces, device=ctx, **build_options(variant.options, camera))


# -- measuring the builders of one scene ---------------------------------------------

class Ours:
    """Our builders behind the peers' interface (:class:`common.Embree`, :class:`common.Warp`):
    ``build(vertices, faces, **options)`` returns ``(setup, build, tree)`` seconds and
    handle, ``trace`` the closest hits ``(t, prim)``."""
    version = lbvh.__version__

    def __init__(self, ctx: dev.Context) -> None:
        self.ctx = ctx

    def build(self, vertices: np.ndarray, faces: np.ndarray, **options: Any) -> tuple[float, float, Any]:
        t0 = time.perf_counter()
        bvh = lbvh.build(vertices, faces, device=self.ctx, **options)
        return 0.0, time.perf_counter() - t0, bvh

    def trace(self, bvh: lbvh.BVH, origins: np.ndarray, directions: np.ndarray,
              order: str = "ordered") -> tuple[np.ndarray, np.ndarray]:
        hits = intersect(bvh, origins, directions, order=order)
        return hits.t, hits.prim


@dataclass
class Settings:
    repeats: int
    build_budget: float
    render_budget: float


@dataclass
class Contestant:
    """One builder on one scene: its samples, its latest tree and its latest hits."""
    variant: Variant
    builder: Any                     # Ours, Embree or Warp
    setup: list[float] = field(default_factory=list)
    build: list[float] = field(default_factory=list)
    build_cpu: list[float] = field(default_factory=list)
    render: list[float] = field(default_factory=list)
    render_cpu: list[float] = field(default_factory=list)
    render_global: list[float] = field(default_factory=list)   # ours: order="global"
    handle: Any = None
    t: np.ndarray | None = None
    prim: np.ndarray | None = None

    def run_build(self, scene: Scene) -> None:
        self.handle = None                       # one tree per builder alive at a time
        c0 = time.process_time()
        options = build_options(self.variant.options, scene.camera) if ours(self.variant) \
            else self.variant.options
        setup, seconds, self.handle = self.builder.build(scene.vertices, scene.faces, **options)
        self.build_cpu.append(time.process_time() - c0)
        self.setup.append(setup)
        self.build.append(seconds)

    def run_render(self, origins: np.ndarray, directions: np.ndarray) -> None:
        c0, t0 = time.process_time(), time.perf_counter()
        self.t, self.prim = self.builder.trace(self.handle, origins, directions)
        self.render.append(time.perf_counter() - t0)
        self.render_cpu.append(time.process_time() - c0)
        if ours(self.variant):          # the same round: the pair shares the machine's noise
            t0 = time.perf_counter()
            self.builder.trace(self.handle, origins, directions, order="global")
            self.render_global.append(time.perf_counter() - t0)


ROW_FIELDS = ("scene", "builder", "family", "options", "triangles", "rays", "build_seconds",
              "build", "render_seconds", "render", "rays_per_second", "seconds_per_ray",
              "sah_cost", "sah_ratio", "epo", "ray_cost", "nodes_per_ray", "tris_per_ray",
              "traversal_cost_per_ray", "traversal_ratio", "hit_fraction", "overflow_count",
              "agreement", "global_order", "break_even_vs_fastest", "break_even_vs_reference",
              "tree", "null_reasons")

PEER_NULLS = {name: "peer: its tree is not visible" for name in
              ("sah_cost", "sah_ratio", "epo", "ray_cost", "nodes_per_ray", "tris_per_ray",
               "traversal_cost_per_ray", "traversal_ratio", "overflow_count", "global_order",
               "tree")}


def tree_figures(bvh: lbvh.BVH) -> dict:
    """Depth, nodes, leaves, memory, SAH cost and sampled EPO (``epo``, ``epo_stderr``,
    ``epo_samples``) of one of our trees."""
    q = tree_quality(bvh, C_NODE, C_TRI, epo=True, epo_samples=EPO_SAMPLES)
    report = bvh.report()
    q["leaf_size_histogram"] = {str(k): int(v) for k, v in q["leaf_size_histogram"].items()}
    q["key_bits"] = report.key_bits   # code bits used: 30 or 63
    q["device_build_seconds"] = report.device_seconds or None
    return q


def base_row(scene: Scene, c: Contestant, rays: int) -> dict:
    """The fields every row has, from the timings and the latest hits."""
    row = dict.fromkeys(ROW_FIELDS)
    build_s, render_s = median(c.build), median(c.render)
    row.update(scene=scene.name, builder=c.variant.name, family=c.variant.family,
               options={k: v for k, v in c.variant.options.items() if k != "builder"},
               triangles=len(scene.faces), rays=rays, null_reasons={},
               build_seconds=build_s,
               build={"median": build_s, "samples": c.build, "setup_samples": c.setup,
                      "cpu_over_wall": cores_used(c.build_cpu, np.add(c.build, c.setup).tolist())},
               render_seconds=render_s,
               render={"median": render_s, "samples": c.render,
                       "cpu_over_wall": cores_used(c.render_cpu, c.render)},
               seconds_per_ray=render_s / rays, rays_per_second=rays / render_s,
               hit_fraction=float((c.prim >= 0).mean()))
    return row


def our_row(scene: Scene, c: Contestant, origins: np.ndarray, directions: np.ndarray) -> dict:
    """Tree figures, EPO, ray-sampled cost and the traversal counters of one of our
    trees, ordered and global order (hits from the ordered counted run)."""
    row = base_row(scene, c, len(origins))
    bvh = c.handle
    hits = intersect(bvh, origins, directions, counters=True)
    c.t, c.prim = hits.t, hits.prim
    tree = tree_figures(bvh)
    rc = ray_sampled_cost(bvh, origins, directions, c_node=C_NODE, c_tri=C_TRI)
    nodes, tris = float(hits.nodes_visited.mean()), float(hits.tris_tested.mean())
    row.update(sah_cost=tree["sah_cost"], epo=tree["epo"], ray_cost=rc.cost,
               nodes_per_ray=nodes, tris_per_ray=tris,
               traversal_cost_per_ray=C_NODE * nodes + C_TRI * tris,
               overflow_count=int(hits.overflow_count), tree=tree)
    tree["ray_cost"] = {"cost": rc.cost, "inner": rc.inner, "leaves": rc.leaves,
                        "triangles": rc.triangles, "rays": rc.rays}
    row["global_order"] = global_order_figures(c, hits, bvh, origins, directions)
    return row


def global_order_figures(c: Contestant, ordered: Any, bvh: lbvh.BVH, origins: np.ndarray,
                         directions: np.ndarray) -> dict:
    """The global-order traversal of the tree against the ordered one (``ordered``: its
    counted hits): speed, counters, their ratios and the rays with identical hits."""
    g = intersect(bvh, origins, directions, counters=True, order="global")
    rays = len(origins)
    render_s = median(c.render_global)
    nodes, tris = float(g.nodes_visited.mean()), float(g.tris_tested.mean())
    o_nodes, o_tris = float(ordered.nodes_visited.mean()), float(ordered.tris_tested.mean())
    paired = [gs / os for gs, os in zip(c.render_global, c.render)]   # same round
    return {"render_seconds": render_s, "samples": c.render_global, "rays_per_second": rays / render_s,
            "time_ratio": median(paired), "nodes_per_ray": nodes, "tris_per_ray": tris,
            "nodes_ratio": nodes / o_nodes if o_nodes else None,
            "tris_ratio": tris / o_tris if o_tris else None,
            "overflow_count": int(g.overflow_count),
            "same_t": float(np.mean(g.t == ordered.t)) if rays else 1.0,
            "same_prim": float(np.mean(g.prim == ordered.prim)) if rays else 1.0}


def peer_row(scene: Scene, c: Contestant, rays: int) -> dict:
    row = base_row(scene, c, rays)
    row["null_reasons"].update(PEER_NULLS)
    return row


# -- comparisons within a scene ------------------------------------------------------

def crossing(row: dict, other: dict) -> dict:
    """Where the total-time lines ``build + n * seconds_per_ray`` of ``row`` and ``other`` cross.

    ``rays``: the break-even ray count ``n > 0``, with ``cheaper_before`` (the faster
    build) and ``cheaper_after`` (the faster tracer); ``None`` with a ``reason`` when
    the lines do not cross at a positive ``n`` (one is never more expensive).
    """
    out = {"against": other["builder"], "rays": None, "reason": None,
           "cheaper_before": None, "cheaper_after": None}
    if row["builder"] == other["builder"]:
        out["reason"] = f"is {other['builder']} itself"
        return out
    extra_build = row["build_seconds"] - other["build_seconds"]
    saved_per_ray = other["seconds_per_ray"] - row["seconds_per_ray"]
    if extra_build * saved_per_ray > 0:
        faster_build, faster_trace = (other, row) if extra_build > 0 else (row, other)
        out.update(rays=extra_build / saved_per_ray, cheaper_before=faster_build["builder"],
                   cheaper_after=faster_trace["builder"])
    elif extra_build <= 0 and saved_per_ray >= 0:
        out.update(cheaper_before=row["builder"], cheaper_after=row["builder"],
                   reason=f"never: {row['builder']} builds and traces no slower than "
                          f"{other['builder']}, it is cheaper for any number of rays")
    else:
        out.update(cheaper_before=other["builder"], cheaper_after=other["builder"],
                   reason=f"never: {row['builder']} builds and traces no faster than "
                          f"{other['builder']}, which is cheaper for any number of rays")
    return out


def lower_envelope(rows: list[dict]) -> list[dict]:
    """The cheapest builder for each ray count: segments ``[from_rays, to_rays)`` of the
    lower envelope of the lines ``build + n * seconds_per_ray`` (``to_rays`` None: forever)."""
    lines = sorted(rows, key=lambda r: (r["build_seconds"], r["seconds_per_ray"]))
    current, n, segments = lines[0], 0.0, []
    while True:
        best, best_n = None, math.inf
        for other in lines:
            saved = current["seconds_per_ray"] - other["seconds_per_ray"]
            if saved <= 0:
                continue
            at = max(n, (other["build_seconds"] - current["build_seconds"]) / saved)
            if at < best_n or (at == best_n and other["seconds_per_ray"] < best["seconds_per_ray"]):
                best, best_n = other, at
        segments.append({"builder": current["builder"], "from_rays": n,
                         "to_rays": None if best is None else best_n})
        if best is None:
            return segments
        current, n = best, best_n


def compare_within_scene(scene: Scene, contestants: list[Contestant], rows: list[dict],
                         origins: np.ndarray, directions: np.ndarray) -> dict:
    """Fill the ratios, agreement and break-even fields of the scene's rows; return the
    scene's summary (fastest build, envelopes)."""
    i_ref = [r["builder"] for r in rows].index(REFERENCE)
    ref, ref_row = contestants[i_ref], rows[i_ref]
    bound = t_bound(scene.vertices, scene.faces, origins, directions, ref.t, ref.prim,
                    cos_floor=AGREEMENT_COS_FLOOR)
    mine = [r for r in rows if r["family"] in OUR_FAMILIES]
    fastest = min(mine, key=lambda r: r["build_seconds"])
    for c, row in zip(contestants, rows):
        row["agreement"] = agreement(c.t, c.prim, ref.t, ref.prim, bound)
        if row["sah_cost"] is not None:
            row["sah_ratio"] = row["sah_cost"] / ref_row["sah_cost"]
            row["traversal_ratio"] = row["traversal_cost_per_ray"] / ref_row["traversal_cost_per_ray"]
        row["break_even_vs_fastest"] = crossing(row, fastest)
        row["break_even_vs_reference"] = crossing(row, ref_row)
    return {"fastest_build": fastest["builder"], "best_by_rays_ours": lower_envelope(mine),
            "best_by_rays": lower_envelope(rows)}


# -- one scene, all builders ----------------------------------------------------------

def warm_up(ctx: dev.Context, variants: list[Variant]) -> None:
    """Compile every device program once, outside any timing (a small mesh, one ray)."""
    v, f = meshes.sphere(2000)
    o, d = np.zeros((1, 3), np.float32), np.float32([[0.0, 0.0, 1.0]])
    for variant in variants:
        if variant.family in ("lbvh", "ploc"):
            bvh = build_tree(variant, v, f, ctx)
            for order in ("ordered", "global"):
                intersect(bvh, o, d, order=order)


def steps_per_scene(repeats: int) -> int:
    """Progress steps of one scene: build rounds, checks, render rounds, counters."""
    return 2 * repeats + 2


def bench_scene(scene: Scene, contestants: list[Contestant], settings: Settings,
                progress: Progress, views: Path | None) -> tuple[dict, list[dict]]:
    """Build rounds, then render rounds, then the comparisons; returns the scene's
    summary and its rows."""
    origins, directions = scene.camera.rays()
    interleaved_rounds(contestants, settings.repeats, settings.build_budget,
                       lambda c: sum(c.build) + sum(c.setup), lambda c: c.run_build(scene),
                       progress, "build")
    for c in contestants:
        progress.note(f"{c.variant.name} validate, warm up")
        c.builder.trace(c.handle, origins[:1], directions[:1])   # compiles the trace kernel
        if ours(c.variant):
            c.handle.validate()
            c.builder.trace(c.handle, origins[:1], directions[:1], order="global")
    progress.advance()
    interleaved_rounds(contestants, settings.repeats, settings.render_budget,
                       lambda c: sum(c.render) + sum(c.render_global),
                       lambda c: c.run_render(origins, directions), progress, "render")
    rows = []
    for c in contestants:
        progress.note(f"{c.variant.name} counters, EPO, ray cost")
        rows.append(our_row(scene, c, origins, directions) if ours(c.variant)
                    else peer_row(scene, c, len(origins)))
    progress.advance()
    summary = compare_within_scene(scene, contestants, rows, origins, directions)
    ref = contestants[[r["builder"] for r in rows].index(REFERENCE)]
    if views is not None:
        save_view(views / f"{scene.name}.png", scene, directions, ref.t, ref.prim)
    for c in contestants:
        c.handle = None
    summary.update(name=scene.name, source=scene.source, triangles=len(scene.faces),
                   vertices=len(scene.vertices), camera=scene.camera.as_dict(),
                   rays=len(origins), hit_fraction=float((ref.prim >= 0).mean()))
    return summary, rows


# -- which cost metric predicts the render time -----------------------------------------

#: The metrics ranked against the render time: row field -> column title. The first
#: three are figures of the tree (SAH and EPO need no rays; the ray-sampled cost needs
#: the rays but not the traversal order); the last three are the ordered traversal's
#: own counters.
METRICS = {"sah_cost": "SAH cost", "epo": "EPO", "ray_cost": "ray-sampled cost",
           "nodes_per_ray": "nodes/ray", "tris_per_ray": "tris/ray",
           "traversal_cost_per_ray": "nodes + tris/ray"}
#: The metrics that are figures of the tree, not counters of the render itself.
TREE_METRICS = ("sah_cost", "epo", "ray_cost")


def average_ranks(values: Any) -> np.ndarray:
    """Ranks 1..n of ``values``, ties sharing the mean of the ranks they span."""
    x = np.asarray(values, np.float64)
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x), np.float64)
    sorted_x = x[order]
    start = 0
    for end in range(1, len(x) + 1):
        if end == len(x) or sorted_x[end] != sorted_x[start]:
            ranks[order[start:end]] = (start + end + 1) / 2    # mean of ranks start+1 .. end
            start = end
    return ranks


def spearman(x: Any, y: Any) -> float | None:
    """Spearman's rank correlation of ``x`` and ``y``: the Pearson correlation of their
    average ranks (ties shared); ``None`` for fewer than 3 pairs or a constant side."""
    if len(x) != len(y):
        raise ValueError(f"spearman: {len(x)} values against {len(y)}")
    if len(x) < 3:
        return None
    rx, ry = average_ranks(x), average_ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    norm = math.sqrt(float(rx @ rx) * float(ry @ ry))
    if norm == 0:
        return None
    return max(-1.0, min(1.0, float(rx @ ry) / norm))


def metric_correlation(rows: list[dict]) -> dict:
    """For each metric (:data:`METRICS`), Spearman's rho between it and the measured
    render time over our trees, per scene and its mean over the scenes; ``best``: the
    metric with the highest mean rho, ``best_tree_metric`` the same among
    :data:`TREE_METRICS`. Peers (no tree) are left out."""
    per_scene: dict[str, dict[str, float | None]] = {}
    trees: dict[str, int] = {}
    for scene in dict.fromkeys(r["scene"] for r in rows):
        mine = [r for r in rows if r["scene"] == scene and r["family"] in OUR_FAMILIES]
        trees[scene] = len(mine)
        render = [r["render_seconds"] for r in mine]
        per_scene[scene] = {m: spearman([r[m] for r in mine], render) for m in METRICS}
    mean: dict[str, float | None] = {}
    for m in METRICS:
        values = [rhos[m] for rhos in per_scene.values() if rhos[m] is not None]
        mean[m] = float(np.mean(values)) if values else None

    return {"against": "render_seconds", "method": "Spearman, ties as average ranks",
            "metrics": dict(METRICS), "trees": trees, "per_scene": per_scene, "mean": mean,
            "best": best_metrics(mean, tuple(METRICS)),
            "best_tree_metric": best_metrics(mean, TREE_METRICS)}


def best_metrics(mean: dict[str, float | None], names: tuple[str, ...]) -> list[str]:
    """The metrics among ``names`` with the highest mean rho (several when tied within
    1e-9), in the order of ``names``; empty when none has a rho."""
    ranked = [m for m in names if mean[m] is not None]
    if not ranked:
        return []
    top = max(mean[m] for m in ranked)
    return [m for m in ranked if mean[m] >= top - 1e-9]


# -- aggregate, Markdown, chart ----------------------------------------------------

def geomean(values: list[float]) -> float | None:
    values = [v for v in values if v is not None and v > 0]
    return float(math.exp(sum(math.log(v) for v in values) / len(values))) if values else None


def aggregate(rows: list[dict], chart_rays: int) -> dict[str, dict]:
    """Per builder, geometric means over the scenes (the chart's points)."""
    out: dict[str, dict] = {}
    for builder in dict.fromkeys(r["builder"] for r in rows):
        mine = [r for r in rows if r["builder"] == builder]
        out[builder] = {
            "family": mine[0]["family"], "scenes": len(mine),
            "build_seconds": geomean([r["build_seconds"] for r in mine]),
            "build_plus_render_seconds": geomean(
                [r["build_seconds"] + chart_rays * r["seconds_per_ray"] for r in mine]),
            "seconds_per_ray": geomean([r["seconds_per_ray"] for r in mine]),
            "sah_ratio": geomean([r["sah_ratio"] for r in mine]),
            "traversal_ratio": geomean([r["traversal_ratio"] for r in mine]),
        }
    return out


def fmt_rays(n: float | None) -> str:
    if n is None:
        return "-"
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "K")):
        if n >= scale:
            return f"{n / scale:.3g}{suffix}"
    return f"{n:.3g}"


def fmt(x: float | None, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def fmt_build(row: dict, repeats: int) -> str:
    """Median build in ms, with the number of builds when the budget cut the repeats."""
    n = len(row["build"]["samples"])
    return f"{row['build_seconds'] * 1e3:.1f}" + ("" if n == repeats else f" ({n}x)")


def fmt_break_even(b: dict) -> str:
    """``1.2M -> sah`` (past 1.2M rays sah is cheaper), ``embree always``, or ``-`` (itself)."""
    if b["rays"] is not None:
        return f"{fmt_rays(b['rays'])} → {b['cheaper_after']}"
    return "-" if b["cheaper_after"] is None else f"{b['cheaper_after']} always"


def markdown(report: dict) -> str:
    m = report["machine"]
    s = report["settings"]
    spread = render_spread(report["rows"])
    lines = [
        "# Builders: speed against error", "",
        *header_lines(report),
        f"CPU use of this process (CPU seconds over wall seconds): builds "
        f"{report['cpu_use']['build']:.2f}, renders {report['cpu_use']['render']:.2f} of "
        f"{m['cores']} cores (less than the builder can use means other load on the machine).  ",
        f"Noise: the render samples of a row spread by {spread[0]:.0%} of their median "
        f"(median over rows; worst {spread[1]:.0%}): smaller render differences are noise.  ",
        f"Rays: {s['width']}x{s['height']} primary rays per scene; medians of up to "
        f"{s['repeats']} builds (fewer past {s['build_budget']:g} s of building) and renders. "
        f"SAH cost with C_node = C_tri = 1, normalised by the root area; reference "
        f"`{REFERENCE}` (serial full-sweep SAH, leaves up to {MAX_LEAF_SIZE}).", "",
        "| scene | tris | builder | build ms | render ms | Mrays/s | SAH cost | SAH / ref "
        "| EPO | ray cost | nodes/ray | tris/ray | trav / ref | agree | agree (ties) "
        "| break-even vs fastest | break-even vs ref |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["rows"]:
        a = r["agreement"]
        lines.append(
            f"| {r['scene']} | {r['triangles']:,} | {r['builder']} | {fmt_build(r, s['repeats'])} "
            f"| {r['render_seconds'] * 1e3:.1f} | {r['rays_per_second'] / 1e6:.2f} "
            f"| {fmt(r['sah_cost'], 4)} | {fmt(r['sah_ratio'])} | {fmt(r['epo'], 4)} "
            f"| {fmt(r['ray_cost'], 4)} | {fmt(r['nodes_per_ray'])} "
            f"| {fmt(r['tris_per_ray'])} | {fmt(r['traversal_ratio'])} | {a['fraction']:.4f} "
            f"| {a['fraction_with_ties']:.4f} | {fmt_break_even(r['break_even_vs_fastest'])} "
            f"| {fmt_break_even(r['break_even_vs_reference'])} |")
    lines += correlation_lines(report["metric_correlation"])
    lines += global_order_lines(report["rows"])
    lines += ["", "## Which builder for how many rays", "",
              "Cheapest total time (build + rays x time per ray) by ray count, "
              "among our trees (same kernel) and with the peers:", ""]
    for sc in report["scenes"]:
        lines.append(f"- **{sc['name']}** ({sc['triangles']:,} tris, camera hit fraction "
                     f"{sc['hit_fraction']:.2f}): ours: {envelope_text(sc['best_by_rays_ours'])}; "
                     f"all: {envelope_text(sc['best_by_rays'])}")
    for skipped in report["skipped"]:
        lines.append(f"- {skipped['scene']}: skipped ({skipped['reason']})")
    lines += ["", COLUMN_NOTES]
    return "\n".join(lines) + "\n"


def fmt_rho(rho: float | None) -> str:
    return "-" if rho is None else f"{rho:+.2f}"


def correlation_lines(corr: dict) -> list[str]:
    """The table "which cost metric predicts the render time" and its verdict."""
    metrics = corr["metrics"]
    lines = ["", "## Which cost metric predicts the render time", "",
             "Spearman's rank correlation (ties as average ranks) between each metric and "
             "the measured render time (ordered traversal), over our trees of each scene "
             "(peers have no tree); +1: the metric orders the trees as their render times "
             "do. Render differences within the noise above reorder trees at random.", "",
             "| scene | trees | " + " | ".join(metrics.values()) + " |",
             "|---|---:|" + "---:|" * len(metrics)]
    for scene, rhos in corr["per_scene"].items():
        lines.append(f"| {scene} | {corr['trees'][scene]} | "
                     + " | ".join(fmt_rho(rhos[m]) for m in metrics) + " |")
    if corr["per_scene"]:
        lines.append(f"| **mean over {len(corr['per_scene'])} scene(s)** | | "
                     + " | ".join(f"**{fmt_rho(corr['mean'][m])}**" for m in metrics) + " |")
    lines.append("")
    lines.append(correlation_verdict(corr))
    return lines


def correlation_verdict(corr: dict) -> str:
    """Which metric ranked the trees best, from the numbers."""
    mean, metrics = corr["mean"], corr["metrics"]
    best_tree = corr["best_tree_metric"]
    if not best_tree:
        return "No metric could be ranked (fewer than 3 trees, or constant figures)."
    names = " and ".join(f"**{metrics[m]}**" for m in best_tree)
    tree_ranked = sorted((m for m in TREE_METRICS if mean[m] is not None), key=lambda m: -mean[m])
    order = ", ".join(f"{metrics[m]} {fmt_rho(mean[m])}" for m in tree_ranked)
    text = (f"Of the tree's cost metrics, {names} ranked the trees most like their render "
            f"times{' (tied)' if len(best_tree) > 1 else ''}: mean rho {order}.")
    counters = [m for m in METRICS if m not in TREE_METRICS and mean[m] is not None]
    if counters:
        top = max(counters, key=lambda m: mean[m])
        diff = mean[top] - mean[best_tree[0]]
        how = "better" if diff > 1e-9 else "worse" if diff < -1e-9 else "as well"
        text += (f" The render's own counters did {how}: best {metrics[top]} "
                 f"{fmt_rho(mean[top])}.")
    return text


def global_order_lines(rows: list[dict]) -> list[str]:
    """The table "ordered against global-order traversal", our trees only."""
    lines = ["", "## Ordered against global-order traversal", "",
             "The same tree and rays, traced depth first with the nearest child first "
             "(`order=\"ordered\"`, the default) and by the nearest pending node of all "
             "from a heap (`order=\"global\"`, Kay & Kajiya 1986), in the same render rounds. "
             "`global / ordered`: the ratio of nodes, triangles and time (median of the "
             "rounds' paired ratios); `same t`: fraction of rays with identical `t`; "
             "`overflow`: rays whose global-order heap overflowed (a pending node dropped: "
             "the hit may be wrong).", "",
             "| scene | builder | nodes/ray | tris/ray | Mrays/s | global nodes/ray "
             "| global tris/ray | global Mrays/s | nodes g/o | tris g/o | time g/o | same t "
             "| overflow |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        g = r["global_order"]
        if g is None:
            continue
        lines.append(
            f"| {r['scene']} | {r['builder']} | {fmt(r['nodes_per_ray'])} | {fmt(r['tris_per_ray'])} "
            f"| {r['rays_per_second'] / 1e6:.2f} | {fmt(g['nodes_per_ray'])} | {fmt(g['tris_per_ray'])} "
            f"| {g['rays_per_second'] / 1e6:.2f} | {fmt(g['nodes_ratio'])} | {fmt(g['tris_ratio'])} "
            f"| {fmt(g['time_ratio'])} | {g['same_t']:.4f} | {g['overflow_count']} |")
    return lines


def render_spread(rows: list[dict]) -> tuple[float, float]:
    """Median and largest (max - min) / median of the rows' render samples."""
    spreads = [(max(r["render"]["samples"]) - min(r["render"]["samples"])) / r["render_seconds"]
               for r in rows] or [0.0]
    return float(statistics.median(spreads)), float(max(spreads))


def envelope_text(segments: list[dict]) -> str:
    """``a up to 1.2M rays, then b up to 40M, then c``."""
    parts = [seg["builder"] + ("" if seg["to_rays"] is None else f" up to {fmt_rays(seg['to_rays'])} rays")
             for seg in segments]
    return ", then ".join(parts)


COLUMN_NOTES = f"""Columns: `build ms` host arrays to a tree on the device (peers: their own build,
Embree's scene commit; `(1x)`: built once, the budget cut the repeats; `median`, `midpoint`
and `sah` are host builds, their upload included); `render ms` closest hits of the primary rays (`lbvh.queries.traverse.intersect`,
transfers included; peers: their own traversal); `EPO`: end-point overlap (Aila, Karras & Laine
2013) from {EPO_SAMPLES // 1024}K surface samples (`lbvh.metrics.quality.tree_quality`; standard error in the
JSON); `ray cost`: ray-sampled cost of all the primary rays, inner nodes + leaf triangles their
segments up to the closest hit enter (`lbvh.verification.ray_cost.ray_sampled_cost`, the SAH
cost's units); `SAH / ref`, `trav / ref`: SAH cost and measured
nodes + triangles per ray over the reference's; `agree`: fraction of rays with the reference's
hit or miss, primitive and t (within 16 u (t + s) / max(|cos|, 1e-3)); `agree (ties)` also
accepts another primitive at the same t; break-even: `n → b`: past n rays, b (the faster
tracer) has the lower total time build + rays x time per ray, below n the faster build has;
`b always`: b is never more expensive; `-`: the row itself. `fastest` is the fastest build
among our trees."""


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Points not dominated in (x, y), both minimised, sorted by x."""
    front, best_y = [], math.inf
    for x, y in sorted(points):
        if y < best_y:
            front.append((x, y))
            best_y = y
    return front


PEER_LINES = ("-", "--", ":", "-.", (0, (5, 1, 1, 1)))


#: Colour and marker of the builders that are not LBVH variants.
HOST_STYLES = {"ploc": ("C8", "h"), "median": ("C5", "^"), "midpoint": ("C6", "v"),
               "sbvh": ("C9", "P"),
               REFERENCE: ("C3", "*"), f"{REFERENCE}+rays": ("C4", "*")}


def point_style(name: str, family: str) -> dict:
    """LBVH: colour by key width, circle, square with the leaf collapse, diamond with
    treelets (plus with treelets and collapse); ploc, median, midpoint, sah: a colour
    and a hexagon, triangle or star of their own."""
    if family == "lbvh":
        colour = {"30": "C0", "63": "C1", "auto": "C2"}.get(name.split("-")[-1].split("+")[0], "C7")
        marker = ("P" if "collapse" in name else "D") if "treelets" in name else \
            ("s" if "collapse" in name else "o")
    else:
        colour, marker = HOST_STYLES.get(name, ("C8", "X"))
    return {"color": colour, "marker": marker, "s": 110 if marker == "*" else 50, "zorder": 3}


def chart(report: dict, path: Path) -> str | None:
    """Speed against error in 2x2 panels, one point per builder (geometric means over the
    scenes); peers, whose trees are not visible, are vertical lines. Returns why no chart
    was written, or None."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib is not installed"
    agg = report["aggregate"]
    n_rays = report["settings"]["chart_rays"]
    xs = (("build_seconds", "build time (s)"),
          ("build_plus_render_seconds", f"build + render of {fmt_rays(n_rays)} rays (s)"))
    ys = (("sah_ratio", "SAH cost / SAH reference's"),
          ("traversal_ratio", "measured nodes + triangles per ray / reference's"))
    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    for (ykey, ylabel), ax_row in zip(ys, axes):
        for (xkey, xlabel), ax in zip(xs, ax_row):
            draw_panel(ax, agg, xkey, ykey)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=6, fontsize=8, frameon=False)
    scenes = ", ".join(s["name"] for s in report["scenes"])
    fig.suptitle(f"Speed against error, geometric means over {len(report['scenes'])} scene(s): "
                 f"{scenes}\n{report['machine']['cpu']}, {report['machine']['cores']} cores; "
                 f"peers (grey lines) have no visible tree", fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return None


def draw_panel(ax: Any, agg: dict, xkey: str, ykey: str) -> None:
    """Our builders as points with their Pareto front (both axes minimised), peers as lines."""
    points = []
    peers = 0
    for name, a in agg.items():
        if a[ykey] is not None:
            ax.scatter(a[xkey], a[ykey], label=name, **point_style(name, a["family"]))
            points.append((a[xkey], a[ykey]))
        elif a[xkey] is not None:
            ax.axvline(a[xkey], color="0.45", linewidth=1.2, label=name,
                       linestyle=PEER_LINES[peers % len(PEER_LINES)])
            peers += 1
    front = pareto_front(points)
    ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="C4",
            linewidth=2.0, alpha=0.5, label="Pareto front", zorder=2)
    ax.set_xscale("log")
    ax.grid(True, which="both", alpha=0.3)


# -- main ----------------------------------------------------------------------------

def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    scene_options = (QUICK_SCENES, FULL_SCENES, QUICK_RAYS, FULL_RAYS)
    add_scene_options(p, *scene_options)
    p.add_argument("--repeats", type=int, default=3, help="builds and renders per builder (median)")
    p.add_argument("--build-budget", type=float, default=20.0,
                   help="stop repeating a builder's builds after this many seconds (default 20)")
    p.add_argument("--chart-rays", type=int, default=CHART_RAYS,
                   help="ray count of the chart's build + render axis (default 1e7)")
    add_run_options(p)
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error("--repeats: at least 1")
    resolve_scenes(p, args, *scene_options)
    return args


def main(argv: list[str] | None = None) -> dict:
    """Run the bench; returns the report (also written as JSON, Markdown and PNG)."""
    args = parse_args(argv)
    started = time.perf_counter()
    command = command_line("bench_builders.py", argv)
    ctx = dev.get_context(args.device)
    peers, peer_status = load_peers(not args.no_peers)
    builders = {**{family: Ours(ctx) for family in OUR_FAMILIES}, **peers}
    variants = our_variants() + [v for peer in peers.values() for v in peer.variants()]
    settings = Settings(args.repeats, args.build_budget, args.build_budget)
    cameras = load_cameras()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    warm_up(ctx, variants)
    progress = Progress(len(args.scene_names) * steps_per_scene(args.repeats))
    scenes, rows, skipped = [], [], []
    def load(name: str) -> Scene | str:
        return load_bench_scene(name, args.size, cameras, args.shared)

    for scene in loaded_scenes(args.scene_names, load, progress, steps_per_scene(args.repeats),
                               skipped):
        contestants = [Contestant(v, builders[v.family]) for v in variants
                       if v.family != "sbvh" or len(scene.faces) <= SBVH_MAX_TRIANGLES]
        summary, scene_rows = bench_scene(scene, contestants, settings, progress, out / "views")
        scenes.append(summary)
        rows += scene_rows
    progress.close()
    report = {
        **report_start(command, ctx, peer_status),
        "settings": {"scenes": args.scene_names, "width": args.size[0], "height": args.size[1],
                     "repeats": args.repeats, "build_budget": args.build_budget,
                     "chart_rays": args.chart_rays, "quick": args.quick,
                     "c_node": C_NODE, "c_tri": C_TRI, "max_leaf_size": MAX_LEAF_SIZE,
                     "reference": REFERENCE,
                     "t_bound": AGREEMENT_T_BOUND},
        "scenes": scenes, "skipped": skipped, "rows": rows,
        "aggregate": aggregate(rows, args.chart_rays) if rows else {},
        "metric_correlation": metric_correlation(rows),
        "cpu_use": {what: geomean([r[what]["cpu_over_wall"] for r in rows if r["family"] == "lbvh"]) or 0.0
                    for what in ("build", "render")},
    }
    write_outputs(report, out, started)
    return report


def write_outputs(report: dict, out: Path, started: float) -> None:
    """The chart, then JSON and Markdown (also to stdout); the report records what was
    written and the run time up to here."""
    paths = {"json": out / "bench_builders.json", "markdown": out / "bench_builders.md",
             "chart": out / "bench_builders.png"}
    no_chart = chart(report, paths["chart"]) if report["rows"] else "no rows"
    report["outputs"] = {k: str(p) for k, p in paths.items() if k != "chart" or no_chart is None}
    report["chart_missing"] = no_chart
    report["duration_seconds"] = time.perf_counter() - started
    write_report(report, markdown(report), paths, out)


if __name__ == "__main__":
    main()
