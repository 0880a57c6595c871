#!/usr/bin/env python
"""Ray traversal against Embree, Open3D and warp on the same rays, in the same run
(issues 3 and 16).

    .venv/bin/python bench/bench_traverse.py [--quick] [--scenes sponza,bunny,terrain-1m]
        [--rays 1024x1024] [--repeats 3] [--ao-samples 1] [--sah] [--no-peers] [--out DIR]

For every scene, three ray sets, traced by every tracer:

* ``closest``: primary rays, one per pixel of the scene's camera in
  ``lbvh/data/cameras.json`` (Sponza uses ``sponza-atrium``: inside the open
  atrium, every pixel hits), closest hit;
* ``any``: the same rays, any hit (occlusion), ``tmax = inf``;
* ``ao``: ambient occlusion rays, ``--ao-samples`` cosine-weighted rays per
  pixel whose primary ray hits, made once (outside any timing) from the lbvh
  tree's primary hits by :func:`lbvh.rendering.render.ambient_occlusion` itself (the
  offsets, reach and sample pattern of ``lbvh render --mode ao``), any hit
  with ``tmax`` = the AO reach (``AO_DISTANCE`` times the scene diagonal).

Tracers (each ray set goes in ``--repeats`` rounds, every tracer once per
round, so that the machine's noise hits all alike):

* ours, through the public API ``bvh.intersect`` / ``bvh.occluded`` (ray
  validation, packing, transfers and read-back included: what users get), on
  the default ``lbvh.build`` tree (``lbvh``: key bits auto), the same with
  ``collapse=True`` (``lbvh+collapse``), the same with one round of 5-leaf
  treelets before the collapse (``lbvh+treelets1-5+collapse``: about a third of
  the work of a 7-leaf round), with three rounds of them, the second and third
  over the subtrees of at least 14 and 28 leaves (``lbvh+treelets3-5+collapse``),
  with two rounds of 7-leaf treelet
  restructuring before the collapse (``lbvh+treelets2+collapse``: a lower SAH
  cost for a longer build), the default tree again with Moller-Trumbore instead
  of the watertight test (``lbvh (moller)``: the price of watertightness, in a
  table of its own with both tests' disagreements, Moller's leaks among them)
  and, with ``--sah``, the serial SAH
  tree on scenes up to :data:`SAH_MAX_TRIANGLES` triangles;
* ours ``(kernel only)``: the traversal kernels' device time from OpenCL event
  profiling (:func:`lbvh.queries.traverse.trace_buffers` on rays already on the
  device: the packets' kernel and the single-ray walk of the rays it leaves),
  same trees: the API rows minus the host work;
* ``embree-1t``: embreex (Embree 4) ``scene.run`` on one thread (closest hit
  ``output=1``, any hit ``query='OCCLUDED'`` with ``dists = tmax``);
  ``embree-2t``: the same scene, the rays in :data:`EMBREE_CHUNKS` chunks
  pulled by two Python threads (embreex releases the GIL while it traces);
* ``open3d``: Open3D's ``o3d.t.geometry.RaycastingScene`` (:class:`common.Open3D`:
  Embree 4 inside, ``RTC_SCENE_FLAG_ROBUST``, one ``rtcIntersect1`` /
  ``rtcOccluded1`` per ray over a TBB arena) with ``nthreads=2``: closest hit
  ``cast_rays``, any hit ``test_occlusions(tnear=0, tfar=tmax)``;
* ``warp``: warp-lang on the CPU device (``wp.Mesh``, SAH constructor; a CPU
  launch runs on one thread): closest hit ``wp.mesh_query_ray``, any hit
  ``wp.mesh_query_ray_anyhit`` (closest hit with ``max_t`` where a warp
  version lacks it, said in the report).

Every peer is optional: one that is not importable (or ``--no-peers``) has no
rows, and the ratios and goals that need it say NOT MEASURED.

Each of our trees is also traced once more per ray set, outside the timing,
with ``counters=True`` (``bvh.intersect`` / ``bvh.occluded``): the mean nodes
visited and triangles tested per ray stand beside its speed (the kernel-only
rows share the API row's tree and kernel, hence its counts). Our build times
are the median of :data:`BUILD_REPEATS` builds after an untimed one that
compiles the kernels (the serial SAH tree: one build).

Error figures beside every speed: the spread of the timing samples
((max - min) / median) and the agreement with the reference tracer
(``embree-1t``; ``lbvh`` when Embree is not installed): for closest hits
:func:`common.agreement` (hit or miss, primitive, ``t`` within the float32
bound :func:`lbvh.metrics.error_bound.t_bound` with ``|cos a|`` floored at
:data:`common.AGREEMENT_COS_FLOOR`, as in the builders bench; ``with ties``
accepts another primitive at the same ``t``), for any hits the fraction with the same hit or miss. Rays on which
a tracer and the reference disagree are judged (up to ``--judge`` of them per
ray set) against the float64 oracle (:func:`lbvh.verification.oracle.brute_force`) with
:class:`lbvh.verification.rules.Judge`, which accepts any answer that float32 rounding can
give (edges, ties, grazing hits): each row says how many of its disagreements
were right and how many wrong. Our rows also count stack overflows.

Outputs in ``--out``: ``bench_traverse.json`` (every sample, the machine) and
``bench_traverse.md`` (also printed): issue 16's goal table with its verdict
(:func:`goal`: per scene, the default tree and the best tree built in under
:data:`GOAL_BUILD_FACTOR` times the default's build time, over ``open3d`` and
``embree-2t``), the closest-hit ratios, the targets of issue 3, each MET or NOT
MET, and every row. Progress goes to stderr.

The scenes and cameras, the peers' adapters (:class:`common.Embree`,
:class:`common.Open3D`, :class:`common.Warp`), the agreement and the timing
helpers are shared with the other benches in ``bench/common.py``.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# bench/common.py, beside this script; imported before numpy, for it sets
# OPENBLAS_NUM_THREADS (see there).
import common

import numpy as np

import lbvh
from lbvh import device as dev
from lbvh.queries import traverse
from lbvh.rendering.render import AO_DISTANCE, ambient_occlusion, scene_diagonal
from lbvh.verification.rules import Judge, Reference
from lbvh.metrics.error_bound import t_bound
from lbvh.verification.hard_cases import Case
from lbvh.verification.oracle import brute_force

FULL_SCENES = ("sponza", "bunny", "terrain-1m")
QUICK_SCENES = ("teapot",)
FULL_RAYS = (1024, 1024)
QUICK_RAYS = (96, 96)
#: Scenes whose camera is another entry of lbvh/data/cameras.json.
CAMERA_OF = {"sponza": "sponza-atrium"}
QUERIES = ("closest", "any", "ao")
#: ``--sah`` builds the serial SAH tree only up to this size (7 s on Sponza's 262K,
#: 27 s on terrain-1m in bench_builders).
SAH_MAX_TRIANGLES = 1_100_000
#: embree-2t hands out the rays in this many chunks, so that neither thread idles
#: while the other finishes an expensive part of the image.
EMBREE_CHUNKS = 16
REFERENCE = "embree-1t"
FALLBACK_REFERENCE = "lbvh"
#: The tree ``lbvh.build`` gives by default.
OURS = "lbvh"
#: Rounds of treelet restructuring of the better tree (``lbvh.build(treelet_rounds=...)``).
TREELET_ROUNDS = 2
#: Our best tree: the default build plus the restructuring (Karras & Aila 2013) and
#: the leaf collapse (bench_builders.py: the lowest SAH cost of our device builds).
TREELETS = f"{OURS}+treelets{TREELET_ROUNDS}+collapse"
#: A cheaper restructuring: one round of 5-leaf treelets (``treelet_leaves=5``), about
#: a third of the work of a 7-leaf round, before the collapse: a candidate for the best
#: tree built in under issue 16's build-time budget.
SMALL_TREELETS = f"{OURS}+treelets1-5+collapse"
#: Rounds of the 5-leaf restructuring of :data:`ROUNDS_TREELETS`.
SMALL_TREELET_ROUNDS = 3
#: Several rounds of 5-leaf treelets, the later ones only over the larger subtrees
#: (``treelet_min_leaves``, default): about the SAH cost of two 7-leaf rounds for
#: about half their build time (bench/README.md), another candidate for the best
#: tree built in under the budget.
ROUNDS_TREELETS = f"{OURS}+treelets{SMALL_TREELET_ROUNDS}-5+collapse"
#: The trees the targets are judged on, each on its own line (``sah``: with ``--sah``).
TARGET_TREES = (OURS, TREELETS, "sah")
#: The default tree traced with Moller-Trumbore instead of the watertight test.
MOLLER = f"{OURS} (moller)"
#: Issue 3's targets: closest hit, our throughput over the peer's, at least this much.
TARGETS = (("embree-2t", 0.3), ("warp", 1.5))
WARP_CONSTRUCTOR = "sah"
#: The peers of this bench: family -> adapter class (:func:`common.load_peers`).
TRACE_PEERS = {**common.PEERS, "open3d": common.Open3D}
#: Open3D's tracer (``RaycastingScene`` with ``nthreads`` = :attr:`common.Open3D.threads`).
OPEN3D = "open3d"
#: The peers every row gives its ratio to (``vs``).
VS_PEERS = ("embree-1t", "embree-2t", OPEN3D, "warp")
#: Issue 16's goal: through the API, our throughput over each of these peers' ...
GOAL_PEERS = (OPEN3D, "embree-2t")
#: ... at least this much for the default tree ...
GOAL_DEFAULT = 0.8
#: ... and at least this much for the best tree built in under
#: :data:`GOAL_BUILD_FACTOR` times the default tree's build time (judged on closest
#: hits; any hits and AO get the same test, reported beside it).
GOAL_BEST = 1.0
GOAL_BUILD_FACTOR = 5.0
#: Our trees that may be the goal's best tree (the fastest on closest hits among those
#: built fast enough; the default tree is one of them).
GOAL_CANDIDATES = (OURS, f"{OURS}+collapse", SMALL_TREELETS, ROUNDS_TREELETS, TREELETS, "sah")
#: Timed builds per device tree (after an untimed one: kernel compilation).
BUILD_REPEATS = 3

#: Batch sizes of the small-batch table (closest hit, the default tree through the API
#: against each peer): the price of one call, host work included, where a batch is too
#: small for the traversal's throughput to decide.
SMALL_BATCHES = (1, 1_000, 10_000)
#: Calls of every tracer per batch size (interleaved: one call of each per round).
SMALL_CALLS = 25


# -- rays ----------------------------------------------------------------------------

@dataclass
class RaySet:
    """One query's rays: ``float32 (N, 3)`` origins and directions, a scalar ``tmax``."""
    query: str
    origins: np.ndarray
    directions: np.ndarray
    tmax: float

    @property
    def closest(self) -> bool:
        return self.query == "closest"

    def __len__(self) -> int:
        return len(self.origins)

    def first(self) -> "RaySet":
        """The first ray alone (compiles kernels outside the timing)."""
        return RaySet(self.query, self.origins[:1], self.directions[:1], self.tmax)


def ao_rays(bvh: lbvh.BVH, hits: lbvh.queries.traverse.Hits, directions: np.ndarray, samples: int,
            seed: int = 0) -> RaySet:
    """The rays :func:`lbvh.rendering.render.ambient_occlusion` casts for these primary hits,
    recorded instead of traced (its generator, not a copy of it)."""
    batches: list[tuple[np.ndarray, np.ndarray]] = []
    reach = [AO_DISTANCE * scene_diagonal(bvh.vertices)]

    def record(origins: np.ndarray, dirs: np.ndarray, tmax: float) -> np.ndarray:
        batches.append((origins, dirs))
        reach[0] = float(tmax)
        return np.zeros(len(origins), bool)

    ambient_occlusion(record, bvh.vertices, bvh.faces, (hits.prim, hits.u, hits.v), directions,
                      samples, seed=seed)
    if not batches:
        empty = np.zeros((0, 3), np.float32)
        return RaySet("ao", empty, empty, reach[0])
    return RaySet("ao", np.concatenate([b[0] for b in batches]),
                  np.concatenate([b[1] for b in batches]), reach[0])


# -- tracers -------------------------------------------------------------------------

@dataclass
class Answer:
    """What a tracer returned: ``hit bool (N,)``; ``prim int32`` and ``t float32 (N,)``
    of the closest hit (of the hit found, for our any hits) where the tracer gives them;
    ``overflow``: our rays whose stack overflowed."""
    hit: np.ndarray
    prim: np.ndarray | None = None
    t: np.ndarray | None = None
    overflow: int | None = None


class OurTree:
    """One of our trees through the public API (host work included), with the
    watertight triangle test or, for the price of watertightness, Moller-Trumbore."""

    def __init__(self, bvh: lbvh.BVH, triangle_test: str = "watertight") -> None:
        self.bvh = bvh
        self.triangle_test = triangle_test

    def trace(self, rays: RaySet) -> tuple[Answer, None]:
        if rays.closest:
            h = self.bvh.intersect(rays.origins, rays.directions, triangle_test=self.triangle_test)
        else:
            h = self.bvh.occluded(rays.origins, rays.directions, tmax=rays.tmax, return_hits=True,
                                  triangle_test=self.triangle_test)
        return Answer(h.hit, h.prim, h.t, int(h.overflow_count)), None

    def counters(self, rays: RaySet) -> tuple[float, float] | None:
        """Mean nodes visited and triangles tested per ray (``counters=True``: a kernel
        of its own, so never inside the timing); None for no rays."""
        return tree_counters(self.bvh, rays, self.triangle_test)

    def close(self) -> None:
        pass


def tree_counters(bvh: lbvh.BVH, rays: RaySet, triangle_test: str = "watertight"
                  ) -> tuple[float, float] | None:
    """``(nodes visited, triangles tested)`` per ray, means over the ray set, from
    ``bvh.intersect`` / ``bvh.occluded`` with ``counters=True``; None for no rays."""
    if not len(rays):
        return None
    if rays.closest:
        h = bvh.intersect(rays.origins, rays.directions, triangle_test=triangle_test, counters=True)
    else:
        h = bvh.occluded(rays.origins, rays.directions, tmax=rays.tmax, return_hits=True,
                         triangle_test=triangle_test, counters=True)
    return float(h.nodes_visited.mean()), float(h.tris_tested.mean())


#: The device-level entry points the kernel-only rows use.
KERNEL_API = ("check_rays", "upload_rays", "trace_buffers")


def kernel_only_missing() -> str | None:
    """Why kernel-only rows cannot be measured with this lbvh, or None."""
    missing = [name for name in KERNEL_API if not hasattr(traverse, name)]
    return f"lbvh.traverse has no {', '.join(missing)}" if missing else None


class OurKernel:
    """The traversal kernel alone (:func:`lbvh.queries.traverse.trace_buffers`) on rays uploaded
    once per ray set, into output buffers allocated once: device seconds from its event."""

    def __init__(self, bvh: lbvh.BVH) -> None:
        self.bvh = bvh
        # id(ray set) -> (the ray set, kept alive so that its id is not reused; its buffers)
        self._buffers: dict[int, tuple[RaySet, Any, Any, Any]] = {}

    def _on_device(self, rays: RaySet) -> tuple[RaySet, Any, Any, Any]:
        key = id(rays)
        if key not in self._buffers:
            ctx = self.bvh.ctx
            checked = traverse.check_rays(rays.origins, rays.directions, 0.0, rays.tmax)
            self._buffers[key] = (rays, traverse.upload_rays(ctx, checked),
                                  dev.empty(ctx, 16 * len(rays)), dev.empty(ctx, 4 * len(rays)))
        return self._buffers[key]

    def trace(self, rays: RaySet) -> tuple[None, float]:
        _, device_rays, hit_buf, flag_buf = self._on_device(rays)
        out = traverse.trace_buffers(self.bvh.query_data, device_rays, any_hit=not rays.closest,
                                     outputs=traverse.HitBuffers(hit_buf, flag_buf))
        return None, dev.event_seconds(out.kernels)   # the packets' kernel and the single-ray walk

    def counters(self, rays: RaySet) -> tuple[float, float] | None:
        """Those of the API row: the same tree and the same (watertight) kernel."""
        return tree_counters(self.bvh, rays)

    def close(self) -> None:
        for _, device_rays, hit_buf, flag_buf in self._buffers.values():
            device_rays.release()
            hit_buf.release()
            flag_buf.release()
        self._buffers.clear()


def chunks(count: int, parts: int) -> list[slice]:
    """``parts`` contiguous slices covering ``range(count)`` (empty ones dropped)."""
    edges = np.linspace(0, count, parts + 1).astype(int)
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


class EmbreeTracer:
    """embreex on ``threads`` Python threads (1: the calling thread), one shared scene."""

    def __init__(self, embree: common.Embree, built: Any, threads: int,
                 pool: ThreadPoolExecutor | None) -> None:
        self.embree, self.built, self.threads, self.pool = embree, built, threads, pool

    def _part(self, rays: RaySet, part: slice) -> tuple[np.ndarray, np.ndarray | None]:
        o, d = rays.origins[part], rays.directions[part]
        if rays.closest:
            t, prim = self.embree.trace(self.built, o, d)
            return prim, t
        return self.embree.occluded(self.built, o, d, rays.tmax), None

    def trace(self, rays: RaySet) -> tuple[Answer, None]:
        if self.threads == 1:
            parts = [self._part(rays, slice(None))]
        else:
            parts = list(self.pool.map(lambda s: self._part(rays, s),
                                       chunks(len(rays), EMBREE_CHUNKS)))
        if rays.closest:
            prim = np.concatenate([p[0] for p in parts])
            return Answer(prim >= 0, prim, np.concatenate([p[1] for p in parts])), None
        return Answer(np.concatenate([p[0] for p in parts])), None

    def close(self) -> None:
        pass


class Open3DTracer:
    """Open3D's ``RaycastingScene`` through :class:`common.Open3D` (its ``nthreads``):
    closest hit ``cast_rays``, any hit ``test_occlusions`` with ``tfar = tmax``."""

    def __init__(self, open3d: common.Open3D, scene: Any) -> None:
        self.open3d, self.scene = open3d, scene

    def trace(self, rays: RaySet) -> tuple[Answer, None]:
        if rays.closest:
            t, prim = self.open3d.cast_rays(self.scene, rays.origins, rays.directions)
            return Answer(prim >= 0, prim, t), None
        return Answer(self.open3d.test_occlusions(self.scene, rays.origins, rays.directions,
                                                  rays.tmax)), None

    def close(self) -> None:
        self.scene = None


class WarpTracer:
    """warp-lang's CPU mesh queries through :class:`common.Warp`: closest hit
    ``wp.mesh_query_ray``, any hit ``wp.mesh_query_ray_anyhit`` (closest hit with
    ``max_t`` before it existed)."""

    def __init__(self, warp: common.Warp, mesh: Any) -> None:
        self.warp, self.mesh = warp, mesh

    def trace(self, rays: RaySet) -> tuple[Answer, None]:
        if rays.closest:
            t, prim = self.warp.trace(self.mesh, rays.origins, rays.directions)
            return Answer(prim >= 0, prim, t), None
        return Answer(self.warp.occluded(self.mesh, rays.origins, rays.directions, rays.tmax)), None

    def close(self) -> None:
        self.mesh = None


def machine_busy_seconds() -> float | None:
    """CPU seconds every process on the machine has spent busy so far (Linux
    ``/proc/stat``: user, nice, system, irq, softirq and steal time), or None."""
    try:
        fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]
    except (OSError, ValueError):
        return None
    user, nice, system, _idle, _iowait, irq, softirq, steal = fields
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


#: /proc/stat counts in ticks (10 ms): shorter samples get no other-load figure.
MIN_TICKS = 20


def other_load(busy_before: float | None, busy_after: float | None, own_cpu: float,
               wall: float) -> float | None:
    """Cores kept busy by other processes (or the hypervisor) during a sample: the
    machine's busy CPU seconds minus this process's, over the wall time (>= 0); None
    without /proc/stat or for a sample shorter than :data:`MIN_TICKS` ticks."""
    if busy_before is None or busy_after is None or wall < MIN_TICKS / os.sysconf("SC_CLK_TCK"):
        return None
    return max(0.0, (busy_after - busy_before - own_cpu) / wall)


@dataclass
class Contestant:
    """One tracer on one scene: its samples per query and its latest answers."""
    variant: common.Variant          # .name is what the report and the progress show
    tracer: Any
    threads: int | None
    timing: str                      # "wall" (the call) or "device" (kernel events)
    build_seconds: float
    build_samples: list[float] = field(default_factory=list)
    seconds: dict[str, list[float]] = field(default_factory=dict)
    wall: dict[str, list[float]] = field(default_factory=dict)
    cpu: dict[str, list[float]] = field(default_factory=dict)
    others: dict[str, list[float | None]] = field(default_factory=dict)
    answer: dict[str, Answer | None] = field(default_factory=dict)
    #: ours: ``(nodes visited, triangles tested)`` per ray, per query (untimed pass)
    counters: dict[str, tuple[float, float] | None] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.variant.name

    def run(self, rays: RaySet) -> None:
        b0, c0, t0 = machine_busy_seconds(), time.process_time(), time.perf_counter()
        answer, device_seconds = self.tracer.trace(rays)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        q = rays.query
        self.others.setdefault(q, []).append(other_load(b0, machine_busy_seconds(), cpu, wall))
        self.cpu.setdefault(q, []).append(cpu)
        self.wall.setdefault(q, []).append(wall)
        self.seconds.setdefault(q, []).append(wall if device_seconds is None else device_seconds)
        self.answer[q] = answer


# -- building the contestants of a scene ---------------------------------------------

def our_trees(scene: common.Scene, ctx: dev.Context, with_sah: bool) -> tuple[list[tuple[str, dict]], list[str]]:
    """``(name, lbvh.build options)`` of our trees for this scene, and notes on trees left out."""
    trees = [(OURS, {}), (f"{OURS}+collapse", {"collapse": True}),
             (SMALL_TREELETS, {"treelet_rounds": 1, "treelet_leaves": 5, "collapse": True}),
             (ROUNDS_TREELETS, {"treelet_rounds": SMALL_TREELET_ROUNDS, "treelet_leaves": 5,
                                "collapse": True}),
             (TREELETS, {"treelet_rounds": TREELET_ROUNDS, "collapse": True})]
    notes = []
    if with_sah:
        if len(scene.faces) <= SAH_MAX_TRIANGLES:
            trees.append(("sah", {"builder": "sah"}))
        else:
            notes.append(f"sah: not built on {len(scene.faces):,} triangles (--sah builds it up to "
                         f"{SAH_MAX_TRIANGLES:,}: the serial build is too slow)")
    return trees, notes


def timed_builds(v: np.ndarray, f: np.ndarray, ctx: dev.Context, options: dict,
                 repeats: int) -> tuple[list[float], lbvh.BVH]:
    """Wall seconds of ``repeats`` builds of ``lbvh.build(v, f, **options)`` and the
    last tree. With more than one, an untimed build first: it compiles the kernels
    (the first build of a process pays PoCL's compilation, which is not the build's)."""
    def build() -> lbvh.BVH:
        return lbvh.build(v, f, device=ctx, **options)
    if repeats > 1:
        build()
    samples, bvh = [], None
    for _ in range(repeats):
        seconds, bvh = common.timed(build)
        samples.append(seconds)
    return samples, bvh


def make_contestants(scene: common.Scene, ctx: dev.Context, peers: dict[str, Any],
                     pool: ThreadPoolExecutor, with_sah: bool) -> tuple[list[Contestant], list[str]]:
    """Build every tree (each once, timed for the record) and wrap it as contestants."""
    v, f = scene.vertices, scene.faces
    out: list[Contestant] = []
    trees, notes = our_trees(scene, ctx, with_sah)
    kernels = []
    no_kernel = kernel_only_missing()
    if no_kernel:
        notes.append(f"no kernel-only rows: {no_kernel}")
    for name, options in trees:
        samples, bvh = timed_builds(v, f, ctx, options, repeats=1 if name == "sah" else BUILD_REPEATS)
        seconds = float(statistics.median(samples))
        bvh.validate()
        family = "sah" if name == "sah" else "lbvh"
        out.append(Contestant(common.Variant(name, family, options), OurTree(bvh), None, "wall",
                              seconds, samples))
        if name == OURS:   # the same tree with the faster, leaky triangle test
            out.append(Contestant(common.Variant(MOLLER, "moller", options), OurTree(bvh, "moller"),
                                  None, "wall", seconds, samples))
        if not no_kernel:
            kernels.append(Contestant(common.Variant(f"{name} (kernel only)", "kernel", options),
                                      OurKernel(bvh), None, "device", seconds, samples))
    out += kernels
    if "embree" in peers:
        embree = peers["embree"]
        setup, build, built = embree.build(v, f)
        for threads in (1, 2):
            out.append(Contestant(common.Variant(f"embree-{threads}t", "embree"),
                                  EmbreeTracer(embree, built, threads, pool), threads, "wall",
                                  setup + build))
    if "open3d" in peers:
        o3d = peers["open3d"]
        setup, build, o3d_scene = o3d.build(v, f)
        out.append(Contestant(common.Variant(OPEN3D, "open3d", {"nthreads": o3d.threads}),
                              Open3DTracer(o3d, o3d_scene), o3d.threads, "wall", setup + build))
    if "warp" in peers:
        warp = peers["warp"]
        variant = common.Variant("warp", "warp", {"bvh_constructor": WARP_CONSTRUCTOR})
        setup, build, mesh = warp.build(v, f, **variant.options)
        tracer = WarpTracer(warp, mesh)
        out.append(Contestant(variant, tracer, 1, "wall", setup + build))
        notes.append(f"warp any hit: {warp.any_hit_note}")
    return out, notes


# -- comparing answers ------------------------------------------------------------------

def reference_of(contestants: list[Contestant]) -> Contestant:
    by_name = {c.name: c for c in contestants}
    return by_name.get(REFERENCE) or by_name[FALLBACK_REFERENCE]


def differs(a: Answer, ref: Answer, bound: np.ndarray | None) -> np.ndarray:
    """``bool (N,)``: rays not agreeing with the reference even counting ties (closest
    hits: hit or miss, or ``t`` beyond ``bound``; any hits: hit or miss)."""
    out = a.hit != ref.hit
    if bound is not None:
        both = a.hit & ref.hit
        with np.errstate(invalid="ignore"):
            out |= both & ~(np.abs(a.t.astype(np.float64) - ref.t) <= bound)
    return out


def agreement_figures(a: Answer, ref: Answer, bound: np.ndarray | None) -> dict:
    if bound is not None:
        return common.agreement(a.t, a.prim, ref.t, ref.prim, bound)
    same = a.hit == ref.hit
    n = max(len(same), 1)
    return {"fraction": float(same.sum() / n), "fraction_with_ties": float(same.sum() / n),
            "hit_miss_differ": int((~same).sum())}


def judge(scene: common.Scene, rays: RaySet, ray_ids: np.ndarray, answers: dict[str, Answer]
          ) -> tuple[dict[str, np.ndarray], float]:
    """Which answers on rays ``ray_ids`` are right by the float64 oracle, within float32
    rounding (:class:`lbvh.verification.rules.Judge`); tracers that give only hit or miss are compared
    with the oracle's hit or miss. Returns ``{name: bool (len(ray_ids),)}`` and seconds."""
    t0 = time.perf_counter()
    o, d = rays.origins[ray_ids], rays.directions[ray_ids]
    k = len(ray_ids)
    oracle = brute_force(scene.vertices, scene.faces, o, d, 0.0, rays.tmax)
    case = Case(f"{scene.name}-{rays.query}", scene.vertices, scene.faces,
                "rays on which a tracer and the reference disagree", o, d,
                np.zeros(k, np.float32), np.full(k, rays.tmax, np.float32))
    j = Judge(case, Reference(oracle.prim, oracle.t.astype(np.float64), exact=False))
    right = {}
    with np.errstate(all="ignore"):
        for name, a in answers.items():
            if a.prim is None:
                right[name] = a.hit[ray_ids] == oracle.hit
            else:
                right[name] = j.right_answers(np.arange(k), a.prim[ray_ids],
                                              a.t[ray_ids].astype(np.float64), rays.closest)
    return right, time.perf_counter() - t0


def compare(scene: common.Scene, rays: RaySet, contestants: list[Contestant], judge_max: int) -> dict:
    """Agreement with the reference and oracle verdicts on disagreements, per tracer name."""
    ref = reference_of(contestants).answer[rays.query]
    bound = (t_bound(scene.vertices, scene.faces, rays.origins, rays.directions, ref.t, ref.prim,
                     cos_floor=common.AGREEMENT_COS_FLOOR)
             if rays.closest else None)
    answers = {c.name: c.answer[rays.query] for c in contestants if c.answer.get(rays.query) is not None}
    own = {name: differs(a, ref, bound) for name, a in answers.items()}
    union = np.flatnonzero(np.logical_or.reduce(list(own.values())))
    picked = union
    if len(union) > judge_max:
        picked = union[np.linspace(0, len(union) - 1, judge_max).astype(int)]
    right, seconds = judge(scene, rays, picked, answers) if len(picked) else ({}, 0.0)
    out = {"reference": reference_of(contestants).name, "disagreeing_rays": int(len(union)),
           "judged_rays": int(len(picked)), "judge_seconds": seconds, "tracers": {}}
    for name, a in answers.items():
        mine = own[name][picked]
        ok = right.get(name, np.zeros(0, bool))
        out["tracers"][name] = {
            **agreement_figures(a, ref, bound),
            "disagree": int(own[name].sum()), "judged": int(mine.sum()),
            "right": int((mine & ok).sum()), "wrong": int((mine & ~ok).sum()),
            "wrong_on_judged_rays": int((~ok).sum()),
            "judged_by": "lbvh.verification.rules.Judge" if a.prim is not None else "hit or miss vs the oracle",
        }
    return out


# -- rows -----------------------------------------------------------------------------

ROW_FIELDS = ("scene", "query", "tracer", "family", "threads", "timing", "rays", "seconds",
              "samples", "wall_samples", "cpu_over_wall", "other_load", "rays_per_second", "spread",
              "hit_fraction", "overflow_count", "nodes_per_ray", "tris_per_ray", "agreement", "vs",
              "null_reasons")


def spread(samples: list[float]) -> float:
    """(max - min) / median: how far the repeats scatter."""
    return float((max(samples) - min(samples)) / statistics.median(samples))


def median_or_none(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return float(statistics.median(known)) if known else None


def ratio_to(c: Contestant, peer: Contestant | None, query: str) -> dict | None:
    """This tracer's throughput over the peer's: the ratio of medians, and the range of
    the per-round ratios (both ran in the same round: the same noise)."""
    if peer is None or peer is c:
        return None
    mine, theirs = c.seconds[query], peer.seconds[query]
    rounds = [b / a for a, b in zip(mine, theirs)]
    return {"ratio": statistics.median(theirs) / statistics.median(mine),
            "round_min": min(rounds), "round_max": max(rounds), "rounds": rounds}


def make_rows(scene: common.Scene, rays: RaySet, contestants: list[Contestant], figures: dict) -> list[dict]:
    by_name = {c.name: c for c in contestants}
    rows = []
    for c in contestants:
        q = rays.query
        seconds = statistics.median(c.seconds[q])
        a = c.answer[q]
        row = dict.fromkeys(ROW_FIELDS)
        row.update(scene=scene.name, query=q, tracer=c.name, family=c.variant.family,
                   threads=c.threads, timing=c.timing, rays=len(rays), seconds=seconds,
                   samples=c.seconds[q], wall_samples=c.wall[q],
                   cpu_over_wall=common.cores_used(c.cpu[q], c.wall[q]),
                   other_load=median_or_none(c.others[q]),
                   rays_per_second=len(rays) / seconds, spread=spread(c.seconds[q]),
                   vs={peer: ratio_to(c, by_name.get(peer), q) for peer in VS_PEERS},
                   null_reasons={})
        counts = c.counters.get(q)
        if counts is not None:
            row["nodes_per_ray"], row["tris_per_ray"] = counts
        else:
            why = ("peer: no traversal counters" if not hasattr(c.tracer, "counters")
                   else "no rays in this ray set")
            row["null_reasons"].update(nodes_per_ray=why, tris_per_ray=why)
        if a is None:
            row["null_reasons"].update(
                hit_fraction="kernel only: nothing read back (the API row has the hits)",
                agreement="kernel only: same tree and kernel as the API row",
                overflow_count="kernel only: see the API row")
        else:
            row.update(hit_fraction=float(a.hit.mean()) if len(a.hit) else 0.0,
                       agreement=figures["tracers"][c.name])
            if a.overflow is None:
                row["null_reasons"]["overflow_count"] = "peer: no stack to overflow is reported"
            else:
                row["overflow_count"] = a.overflow
        if row["other_load"] is None:
            row["null_reasons"]["other_load"] = (f"no /proc/stat, or samples shorter than "
                                                 f"{MIN_TICKS} of its ticks")
        for peer, r in row["vs"].items():
            if r is None:
                row["null_reasons"][f"vs {peer}"] = ("itself" if peer == c.name
                                                     else f"{peer} not in this run")
        rows.append(row)
    return rows


# -- one scene ---------------------------------------------------------------------------

def steps_per_scene(repeats: int) -> int:
    return 1 + len(QUERIES) * repeats + 1


def count_nodes_and_triangles(contestants: list[Contestant], ray_sets: list[RaySet],
                              progress: common.Progress) -> None:
    """Each of our contestants' nodes visited and triangles tested per ray, per ray set:
    one untimed ``counters=True`` pass per tree, triangle test and ray set (the
    kernel-only rows share their API row's pass)."""
    done: dict[tuple[int, str, str], tuple[float, float] | None] = {}
    for rays in ray_sets:
        for c in contestants:
            if not hasattr(c.tracer, "counters"):
                continue
            key = (id(c.tracer.bvh), getattr(c.tracer, "triangle_test", "watertight"), rays.query)
            if key not in done:
                progress.note(f"{c.name} counters {rays.query}")
                done[key] = c.tracer.counters(rays)
            c.counters[rays.query] = done[key]


def bench_scene(scene: common.Scene, ctx: dev.Context, peers: dict[str, Any], pool: ThreadPoolExecutor,
                args: argparse.Namespace, progress: common.Progress) -> tuple[dict, list[dict]]:
    """Build, make the rays, trace them in interleaved rounds, compare; the scene's
    summary and rows."""
    progress.note("building")
    contestants, notes = make_contestants(scene, ctx, peers, pool, args.sah)
    ours = contestants[0].tracer.bvh
    origins, directions = scene.camera.rays()
    primary = ours.intersect(origins, directions)
    ray_sets = [RaySet("closest", origins, directions, float("inf")),
                RaySet("any", origins, directions, float("inf")),
                ao_rays(ours, primary, directions, args.ao_samples)]
    for rays in ray_sets:
        for c in contestants:
            progress.note(f"{c.name} warm-up {rays.query}")
            c.tracer.trace(rays.first())
    progress.advance()
    for rays in ray_sets:
        common.interleaved_rounds(contestants, args.repeats, args.budget,
                              lambda c, q=rays.query: sum(c.wall.get(q, [])),
                              lambda c, r=rays: c.run(r), progress, rays.query)
    count_nodes_and_triangles(contestants, ray_sets, progress)
    progress.note("small batches")
    small = small_batches(contestants, origins, directions, args.small_calls)
    rows, comparisons = [], {}
    for rays in ray_sets:
        progress.note(f"judging {rays.query}")
        figures = compare(scene, rays, contestants, args.judge)
        rows += make_rows(scene, rays, contestants, figures)
        comparisons[rays.query] = {k: v for k, v in figures.items() if k != "tracers"}
    progress.advance()
    if args.views is not None:
        common.save_view(args.views / f"{scene.name}.png", scene, directions, primary.t, primary.prim)
    for c in contestants:
        c.tracer.close()
    summary = {"name": scene.name, "source": scene.source, "triangles": len(scene.faces),
               "vertices": len(scene.vertices), "camera": scene.camera.as_dict(),
               "camera_entry": CAMERA_OF.get(scene.name, scene.name),
               "rays": {r.query: len(r) for r in ray_sets},
               "tmax": {r.query: (None if np.isinf(r.tmax) else r.tmax) for r in ray_sets},
               "primary_hit_fraction": float(primary.hit.mean()),
               "build_seconds": {c.name: c.build_seconds for c in contestants if c.timing == "wall"},
               "build_samples": {c.name: c.build_samples for c in contestants
                                 if c.timing == "wall" and c.build_samples},
               "comparisons": comparisons, "small_batches": small, "notes": notes}
    return summary, rows


def small_batches(contestants: list[Contestant], origins: np.ndarray, directions: np.ndarray,
                  calls: int) -> list[dict]:
    """Per size of :data:`SMALL_BATCHES`: the median wall seconds of one closest-hit
    call by our default tree through the API and by each peer, on the same rays (that
    many of the camera's, spread evenly over the image), ``calls`` rounds of one call
    of every tracer after an untimed one; and ours over each peer, the median of the
    per-round ratios of their times (above 1: ours is faster)."""
    tracers = [c for c in contestants
               if c.name == OURS or c.variant.family in ("embree", "open3d", "warp")]
    if not calls or not any(c.name == OURS for c in tracers):
        return []
    out = []
    for n in SMALL_BATCHES:
        if n > len(origins):
            continue
        pick = (np.arange(n, dtype=np.int64) * len(origins)) // n
        rays = RaySet("closest", np.ascontiguousarray(origins[pick]),
                      np.ascontiguousarray(directions[pick]), float("inf"))
        samples: dict[str, list[float]] = {c.name: [] for c in tracers}
        for c in tracers:
            c.tracer.trace(rays)
        for _ in range(calls):
            for c in tracers:
                t0 = time.perf_counter()
                c.tracer.trace(rays)
                samples[c.name].append(time.perf_counter() - t0)
        ours = np.array(samples[OURS])
        out.append({"rays": n, "calls": calls, "samples": samples,
                    "seconds": {k: float(statistics.median(v)) for k, v in samples.items()},
                    "ours_over": {k: float(np.median(np.array(v) / ours))
                                  for k, v in samples.items() if k != OURS}})
    return out


# -- summary, targets, Markdown -------------------------------------------------------

def closest_ratios(rows: list[dict]) -> list[dict]:
    """Per scene and per tracer of ours (API and kernel only): closest-hit throughput
    and its ratios to the peers."""
    out = []
    closest = [r for r in rows if r["query"] == "closest"]
    for r in closest:
        if r["family"] not in ("lbvh", "sah", "kernel"):
            continue
        peers = {p["tracer"]: p["rays_per_second"] for p in closest
                 if p["scene"] == r["scene"] and p["family"] in ("embree", "open3d", "warp")}
        out.append({"scene": r["scene"], "tracer": r["tracer"], "timing": r["timing"],
                    "rays_per_second": r["rays_per_second"], "spread": r["spread"],
                    "nodes_per_ray": r["nodes_per_ray"], "tris_per_ray": r["tris_per_ray"],
                    "peers_rays_per_second": peers, "vs": r["vs"]})
    return out


#: Below this CPU use a two-thread tracer did not get both cores of the 2-core machine.
BOTH_CORES = 1.5


def caveat(mine: dict, *theirs: dict | None) -> str | None:
    """Why a ratio of ours to a peer (or peers) may not be what the target means: a
    tracer that should use both cores got fewer (other processes took them)."""
    starved = [f"{r['tracer']} used {r['cpu_over_wall']:.2f} cores (other load "
               f"{fmt_or_dash(r['other_load'], '.2f')})"
               for r in (mine, *theirs) if r is not None and (r["threads"] or 2) >= 2
               and r["cpu_over_wall"] < BOTH_CORES]
    return "; ".join(starved) + ": not both cores" if starved else None


def targets(rows: list[dict], scene_names: list[str]) -> list[dict]:
    """Issue 3's targets per scene, for each of :data:`TARGET_TREES` through the API:
    MET, NOT MET, or not measured (peer missing), with a caveat where a tracer did not
    get both cores."""
    out = []
    for scene in scene_names:
        closest = {r["tracer"]: r for r in rows if r["scene"] == scene and r["query"] == "closest"}
        for tree in TARGET_TREES:
            if tree not in closest:
                continue
            mine = closest[tree]
            for peer, at_least in TARGETS:
                r = mine["vs"].get(peer)
                entry = {"scene": scene, "query": "closest", "ours": tree, "peer": peer,
                         "at_least": at_least, "ratio": None, "round_min": None,
                         "round_max": None, "caveat": caveat(mine, closest.get(peer))}
                if r is None:
                    entry["status"] = f"NOT MEASURED ({peer} not in this run)"
                else:
                    entry.update(ratio=r["ratio"], round_min=r["round_min"],
                                 round_max=r["round_max"],
                                 status="MET" if r["ratio"] >= at_least else "NOT MET")
                out.append(entry)
    return out


#: The rays' goal (the default tree through the API, the same rays and rounds): our
#: throughput over each of :data:`GOAL_PEERS` at least this much per query ...
RAYS_GOAL = {"closest": 1.3, "any": 1.3, "ao": 1.0}
#: ... a call of 1,000 rays at least as fast as Open3D's, and one ray in at most this
#: many seconds.
RAYS_GOAL_THOUSAND = 1.0
RAYS_GOAL_ONE_SECONDS = 20e-6


def rays_goal(report: dict) -> list[dict]:
    """The rays' goal per scene: the default tree's ratios per query against
    :data:`GOAL_PEERS` (:data:`RAYS_GOAL`), the small calls' (1,000 rays over Open3D,
    one ray's seconds); each with MET / NOT MET / NOT MEASURED."""
    out = []
    small = {sc["name"]: {e["rays"]: e for e in sc.get("small_batches", [])}
             for sc in report["scenes"]}
    for e in report["goal"]:
        if e["role"] != "default":
            continue
        row = {"scene": e["scene"], "checks": []}
        for q, need in RAYS_GOAL.items():
            for p in GOAL_PEERS:
                r = e["queries"].get(q, {}).get("vs", {}).get(p)
                value = None if r is None else r["ratio"]
                row["checks"].append({"what": f"{q} / {p}", "value": value, "needs": f">= {need:g}",
                                      "met": None if value is None else value >= need})
        calls = small.get(e["scene"], {})
        thousand = calls.get(1000, {}).get("ours_over", {}).get(OPEN3D)
        row["checks"].append({"what": f"1,000 rays / {OPEN3D}", "value": thousand,
                              "needs": f">= {RAYS_GOAL_THOUSAND:g}",
                              "met": None if thousand is None else thousand >= RAYS_GOAL_THOUSAND})
        one = calls.get(1, {}).get("seconds", {}).get(OURS)
        row["checks"].append({"what": "one ray (us)", "value": None if one is None else one * 1e6,
                              "needs": f"<= {RAYS_GOAL_ONE_SECONDS * 1e6:g}",
                              "met": None if one is None else one <= RAYS_GOAL_ONE_SECONDS})
        out.append(row)
    return out


def rays_goal_markdown(rows: list[dict]) -> list[str]:
    """The section of :func:`rays_goal`: one row per scene, a column per check."""
    if not rows:
        return []
    names = [c["what"] for c in rows[0]["checks"]]
    needs = [c["needs"] for c in rows[0]["checks"]]
    met = sum(c["met"] is True for r in rows for c in r["checks"])
    judged = sum(c["met"] is not None for r in rows for c in r["checks"])
    lines = ["", "## Goal (rays ahead of Embree and Open3D: the default tree through the API, "
             "same rays and rounds)", "",
             f"**{met} of {judged} checks met.** Each cell: ours over the peer (above 1 ours is "
             "faster), or one ray's time; `*` marks a check that is not met.", "",
             "| scene | " + " | ".join(f"{n} ({w})" for n, w in zip(names, needs)) + " |",
             "|---|" + "---:|" * len(names)]
    for r in rows:
        cells = [("-" if c["value"] is None else f"{c['value']:.2f}" if "us" not in c["what"]
                  else f"{c['value']:.0f}") + ("*" if c["met"] is False else "")
                 for c in r["checks"]]
        lines.append(f"| {r['scene']} | " + " | ".join(cells) + " |")
    return lines


def goal_status(ratios: dict[str, dict | None], at_least: float) -> tuple[str, list[str]]:
    """MET / NOT MET / NOT MEASURED for one tree and query against :data:`GOAL_PEERS`,
    and what falls short (``"0.69x embree-2t"``) or is missing."""
    missing = [p for p in GOAL_PEERS if ratios.get(p) is None]
    if missing:
        return "NOT MEASURED", [f"{p} not in this run" for p in missing]
    short = [f"{ratios[p]['ratio']:.2f}x {p}" for p in GOAL_PEERS if ratios[p]["ratio"] < at_least]
    return ("NOT MET" if short else "MET"), short


def goal(rows: list[dict], scenes: list[dict]) -> list[dict]:
    """Issue 16's goal per scene, through the API: the default tree (``role`` default,
    at least :data:`GOAL_DEFAULT` times each of :data:`GOAL_PEERS`) and the best tree
    (``best``: the fastest closest-hit tree of :data:`GOAL_CANDIDATES` built in under
    :data:`GOAL_BUILD_FACTOR` times the default's build time, at least :data:`GOAL_BEST`;
    it may be the default tree itself, then judged twice); the other candidates built
    here are listed too (``other``, not judged, with why). ``status`` judges the closest
    hits, ``status_by_query`` every query alike."""
    out = []
    for sc in scenes:
        by = {(r["query"], r["tracer"]): r for r in rows if r["scene"] == sc["name"]}
        build = sc["build_seconds"]
        if ("closest", OURS) not in by:
            continue
        default_build = build[OURS]
        candidates = [t for t in GOAL_CANDIDATES if ("closest", t) in by]
        factor = {t: build[t] / default_build for t in candidates}
        eligible = [t for t in candidates if factor[t] < GOAL_BUILD_FACTOR]
        speed = {t: by[("closest", t)]["rays_per_second"] for t in candidates}
        best = max(eligible, key=speed.get)
        roles = [("default", OURS, GOAL_DEFAULT, None)]
        for tree in candidates:
            if tree == best:
                roles.append(("best", tree, GOAL_BEST, None))
            elif tree != OURS:
                roles.append(("other", tree, None,
                              f"slower than `{best}`" if tree in eligible else
                              f"built in {factor[tree]:.1f}x the default's time (the goal allows "
                              f"under {GOAL_BUILD_FACTOR:g}x)"))
        for role, tree, at_least, not_judged in roles:
            queries = {}
            for q in QUERIES:
                r = by.get((q, tree))
                if r is None:
                    continue
                queries[q] = {"rays_per_second": r["rays_per_second"],
                              "nodes_per_ray": r["nodes_per_ray"], "tris_per_ray": r["tris_per_ray"],
                              "vs": {p: r["vs"].get(p) for p in GOAL_PEERS},
                              "caveat": caveat(r, *(by.get((q, p)) for p in GOAL_PEERS))}
            entry = {"scene": sc["name"], "role": role, "tree": tree,
                     "build_seconds": build[tree], "build_factor": factor[tree],
                     "at_least": at_least, "queries": queries}
            if at_least is not None:
                by_query = {q: goal_status(v["vs"], at_least) for q, v in queries.items()}
                entry.update(status=by_query["closest"][0], short=by_query["closest"][1],
                             status_by_query={q: v[0] for q, v in by_query.items()},
                             short_by_query={q: v[1] for q, v in by_query.items()})
            else:
                entry.update(status=None, short=[], status_by_query={}, short_by_query={},
                             not_judged=not_judged)
            out.append(entry)
    return out


def gap(rows: list[dict], entries: list[dict]) -> list[dict]:
    """Where the best tree's gap to each of :data:`GOAL_PEERS` lies, per scene and query,
    from the rates of this run: ``gap`` = peer / ours through the API, the product of
    ``host`` (our kernel-only rate over the API's: the host work of a call), ``tree``
    (the fastest kernel-only rate of any tree built here, whatever its build time, over
    the best tree's: what tree quality alone would still give) and ``walk`` (the peer
    over that fastest kernel: what is left with the best tree we build and no host
    work, the cost of our traversal itself). Rows only where the kernel-only and the
    peer's rates were measured."""
    by = {(r["scene"], r["query"], r["tracer"]): r for r in rows}
    out = []
    for e in entries:
        if e["role"] != "best":
            continue
        for q in QUERIES:
            api, kernel = by.get((e["scene"], q, e["tree"])), by.get((e["scene"], q, f"{e['tree']} (kernel only)"))
            ours = [r for r in rows if r["scene"] == e["scene"] and r["query"] == q
                    and r["family"] == "kernel" and r["rays_per_second"]]
            if api is None or kernel is None or not ours or not api["rays_per_second"] \
                    or not kernel["rays_per_second"]:
                continue
            top = max(ours, key=lambda r: r["rays_per_second"])
            for peer in GOAL_PEERS:
                theirs = by.get((e["scene"], q, peer))
                if theirs is None or not theirs["rays_per_second"]:
                    continue
                rate = {"api": api["rays_per_second"], "kernel": kernel["rays_per_second"],
                        "top": top["rays_per_second"], "peer": theirs["rays_per_second"]}
                out.append({"scene": e["scene"], "query": q, "tree": e["tree"], "peer": peer,
                            "top_tree": top["tracer"].removesuffix(" (kernel only)"),
                            "top_nodes_per_ray": top["nodes_per_ray"],
                            "top_tris_per_ray": top["tris_per_ray"], "rays_per_second": rate,
                            "gap": rate["peer"] / rate["api"],
                            "host": rate["kernel"] / rate["api"],
                            "tree_quality": rate["top"] / rate["kernel"],
                            "walk": rate["peer"] / rate["top"]})
    return out


def gap_markdown(entries: list[dict]) -> list[str]:
    """The section of :func:`gap`: one row per scene, query and peer."""
    if not entries:
        return []
    lines = ["", "## Where the gap is (the best tree, from this run's rates)", "",
             "`gap` = peer / ours through the API = `host` x `tree` x `walk`: `host` our "
             "kernel-only rate over the API's (the host work of a call); `tree` the fastest "
             "kernel-only rate of any tree built here (`top tree`, whatever its build time) "
             "over the best tree's (what tree quality alone still gives); `walk` the peer over "
             "that fastest kernel (what is left with our best tree and no host work: the "
             "traversal's own cost, and any edge of the peer's own tree over ours). Above 1: "
             "ours slower by that factor; ratios of medians, so noisy as the rates are.", "",
             "| scene | query | best tree | peer | peer Mrays/s | ours Mrays/s | gap | host "
             "| tree | walk | top tree | its nodes/ray, tris/ray |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for g in entries:
        r = g["rays_per_second"]
        lines.append(f"| {g['scene']} | {g['query']} | {g['tree']} | {g['peer']} "
                     f"| {fmt_mrays(r['peer'])} | {fmt_mrays(r['api'])} | {g['gap']:.2f} "
                     f"| {g['host']:.2f} | {g['tree_quality']:.2f} | {g['walk']:.2f} "
                     f"| {g['top_tree']} | {fmt_or_dash(g['top_nodes_per_ray'], '.1f')}, "
                     f"{fmt_or_dash(g['top_tris_per_ray'], '.1f')} |")
    return lines


def goal_verdict(entries: list[dict]) -> dict[str, dict]:
    """Per query: MET where every judged entry is MET, NOT MEASURED where a peer is
    missing, else NOT MET; with the entries that fall short, in words."""
    out = {}
    for q in QUERIES:
        judged = [e for e in entries if e["at_least"] is not None and q in e["status_by_query"]]
        if not judged:
            out[q] = {"status": "NOT MEASURED", "why": ["no scene measured"]}
            continue
        statuses = {e["status_by_query"][q] for e in judged}
        status = ("NOT MEASURED" if "NOT MEASURED" in statuses
                  else "NOT MET" if "NOT MET" in statuses else "MET")
        why = sorted({s for e in judged if e["status_by_query"][q] == "NOT MEASURED"
                      for s in e["short_by_query"][q]})
        if status == "NOT MET":
            why = [f"{e['scene']} {e['role']} `{e['tree']}`: {', '.join(e['short_by_query'][q])} "
                   f"(needs {e['at_least']:.1f}x)"
                   for e in judged if e["status_by_query"][q] == "NOT MET"]
        out[q] = {"status": status, "why": why,
                  "met": sum(e["status_by_query"][q] == "MET" for e in judged),
                  "judged": len(judged)}
    return out


def watertight_price(rows: list[dict]) -> list[dict]:
    """Per scene and query: the default tree's throughput with the watertight test
    and with Moller-Trumbore (same tree, same rays, same rounds), Moller over
    watertight as the ratio of the medians and the range of the per-round ratios,
    and each one's disagreements with the reference (Moller's leaks among them)."""
    out = []
    by = {(r["scene"], r["query"], r["tracer"]): r for r in rows}
    for (scene, query, tracer), tight in by.items():
        fast = by.get((scene, query, MOLLER))
        if tracer != OURS or fast is None:
            continue
        rounds = [a / b for a, b in zip(tight["samples"], fast["samples"])]
        out.append({"scene": scene, "query": query,
                    "watertight_rays_per_second": tight["rays_per_second"],
                    "moller_rays_per_second": fast["rays_per_second"],
                    "ratio": fast["rays_per_second"] / tight["rays_per_second"],
                    "round_min": min(rounds), "round_max": max(rounds),
                    "watertight_agreement": tight["agreement"],
                    "moller_agreement": fast["agreement"]})
    return out


def cpu_use(rows: list[dict]) -> dict[str, float]:
    """Median CPU use per tracer kind (tree names dropped: ``lbvh+collapse`` counts as ``lbvh``)."""
    kinds: dict[str, list[float]] = {}
    for r in rows:
        kind = {"lbvh": "ours", "sah": "ours", "moller": "ours",
                "kernel": "ours (kernel only)"}.get(r["family"], r["tracer"])
        kinds.setdefault(kind, []).append(r["cpu_over_wall"])
    return {k: float(statistics.median(v)) for k, v in kinds.items()}


def cpu_use_text(use: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.2f}" for k, v in use.items()) or "-"


def fmt_ratio(r: dict | None) -> str:
    if r is None:
        return "-"
    return f"{r['ratio']:.2f} ({r['round_min']:.2f}–{r['round_max']:.2f})"


def fmt_agreement(row: dict) -> tuple[str, str, str]:
    """``agree``, ``agree (ties)``, ``differ: right/wrong`` cells."""
    a = row["agreement"]
    if a is None:
        return "-", "-", "-"
    judged = f"{a['disagree']}"
    if a["disagree"]:
        judged += f" ({a['judged']} judged: {a['right']} right, {a['wrong']} wrong)"
    return f"{a['fraction']:.5f}", f"{a['fraction_with_ties']:.5f}", judged


def fmt_or_dash(x: Any, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def fmt_mrays(rays_per_second: float | None) -> str:
    return fmt_or_dash(None if rays_per_second is None else rays_per_second / 1e6, ".2f")


def markdown(report: dict) -> str:
    m, s = report["machine"], report["settings"]
    lines = [
        "# Traversal: closest hit, any hit and ambient occlusion against Embree, Open3D and warp", "",
        *common.header_lines(report),
        f"Code: commit {str(report['source']['commit'])[:10]}"
        + (f" with uncommitted changes to {', '.join(report['source']['modified'])}"
           if report["source"]["modified"] else "")
        + (" **The code changed during the run.**" if report["source"]["changed_during_run"] else "")
        + "  ",
        f"Rays: {s['width']}x{s['height']} primary rays per scene (closest hit, then any hit on the "
        f"same rays), {s['ao_samples']} AO ray(s) per hit pixel; medians of {s['repeats']} rounds, "
        f"every tracer once per round. Reference of the agreement columns: `{REFERENCE}` "
        f"(`{FALLBACK_REFERENCE}` without Embree).  ",
        f"CPU use (process CPU seconds over wall seconds, median over a tracer's rows): "
        f"{cpu_use_text(report['cpu_use'])} of {m['cores']} cores; less than a tracer can use "
        f"(2 for ours, embree-2t and open3d) means other load on the machine. Other processes kept "
        f"{fmt_or_dash(report['other_load']['median'], '.2f')} cores busy during the median row's "
        f"samples ({fmt_or_dash(report['other_load']['max'], '.2f')} in the worst row).", "",
    ]
    for sc in report["scenes"]:
        rays = ", ".join(f"{q} {n:,}" for q, n in sc["rays"].items())
        lines.append(f"- **{sc['name']}**: {sc['triangles']:,} triangles, camera "
                     f"`{sc['camera_entry']}`, primary hit fraction {sc['primary_hit_fraction']:.4f}; "
                     f"rays: {rays}; AO reach {fmt_or_dash(sc['tmax']['ao'], '.4g')}."
                     + "".join(f" {n}." for n in sc["notes"]))
    for skipped in report["skipped"]:
        lines.append(f"- {skipped['scene']}: skipped ({skipped['reason']})")
    lines += rays_goal_markdown(report.get("rays_goal", []))
    lines += goal_markdown(report["goal"], report["goal_verdict"])
    lines += gap_markdown(report.get("gap", []))
    lines += ["", "## Closest hit: ours against the peers (same run)", "",
              "| scene | ours | Mrays/s | nodes/ray | tris/ray | spread | embree-1t | embree-2t "
              "| ours / embree-2t | open3d | ours / open3d | warp | ours / warp |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in report["closest_ratios"]:
        p = r["peers_rays_per_second"]
        lines.append(
            f"| {r['scene']} | {r['tracer']} | {r['rays_per_second'] / 1e6:.2f} "
            f"| {fmt_or_dash(r['nodes_per_ray'], '.1f')} | {fmt_or_dash(r['tris_per_ray'], '.1f')} "
            f"| {r['spread']:.0%} "
            f"| {fmt_mrays(p.get('embree-1t'))} | {fmt_mrays(p.get('embree-2t'))} "
            f"| {fmt_ratio(r['vs'].get('embree-2t'))} "
            f"| {fmt_mrays(p.get(OPEN3D))} | {fmt_ratio(r['vs'].get(OPEN3D))} "
            f"| {fmt_mrays(p.get('warp'))} | {fmt_ratio(r['vs'].get('warp'))} |")
    lines += small_batches_markdown(report["scenes"])
    lines += ["", "## Targets (issue 3, closest hit through the API: the default `lbvh.build` "
              f"tree, `{TREELETS}` and, with `--sah`, the serial SAH reference tree)", ""]
    for t in report["targets"]:
        measured = "" if t["ratio"] is None else (
            f": {t['ratio']:.2f}x (rounds {t['round_min']:.2f}–{t['round_max']:.2f})")
        lines.append(f"- {t['scene']}, {t['ours']}: >= {t['at_least']}x {t['peer']}{measured} "
                     f"— **{t['status']}**"
                     + (f" (caveat: {t['caveat']})" if t["caveat"] else ""))
    lines += ["", f"## The price of watertightness (`{OURS}` tree through the API: the watertight "
              "test of Woop et al. 2013 against Moller-Trumbore, same rays, same rounds)", "",
              "| scene | query | watertight Mrays/s | Moller Mrays/s | Moller / watertight "
              "| watertight disagree (oracle) | Moller disagree (oracle) |",
              "|---|---|---:|---:|---:|---|---|"]
    for w in report["watertight_price"]:
        tight = fmt_agreement({"agreement": w["watertight_agreement"]})[2]
        fast = fmt_agreement({"agreement": w["moller_agreement"]})[2]
        lines.append(
            f"| {w['scene']} | {w['query']} | {w['watertight_rays_per_second'] / 1e6:.2f} "
            f"| {w['moller_rays_per_second'] / 1e6:.2f} | {fmt_ratio(w)} | {tight} | {fast} |")
    lines += ["", "## Every tracer, every query", "",
              "| scene | query | tracer | Mrays/s | ms | nodes/ray | tris/ray | spread | CPU use "
              "| other load | / embree-2t | / open3d | / warp | agree | agree (ties) "
              "| disagree (oracle) | overflow |",
              "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for r in report["rows"]:
        agree, ties, judged = fmt_agreement(r)
        lines.append(
            f"| {r['scene']} | {r['query']} | {r['tracer']} | {r['rays_per_second'] / 1e6:.2f} "
            f"| {r['seconds'] * 1e3:.1f} | {fmt_or_dash(r['nodes_per_ray'], '.1f')} "
            f"| {fmt_or_dash(r['tris_per_ray'], '.1f')} | {r['spread']:.0%} "
            f"| {r['cpu_over_wall']:.2f} | {fmt_or_dash(r['other_load'], '.2f')} "
            f"| {fmt_ratio(r['vs']['embree-2t'])} | {fmt_ratio(r['vs'][OPEN3D])} "
            f"| {fmt_ratio(r['vs']['warp'])} | {agree} | {ties} "
            f"| {judged} | {fmt_or_dash(r['overflow_count'], 'd')} |")
    lines += ["", COLUMN_NOTES]
    return "\n".join(lines) + "\n"


def small_batches_markdown(scenes: list[dict]) -> list[str]:
    """The small-batch table: microseconds per call, and ours over each peer."""
    entries = [(sc["name"], e) for sc in scenes for e in sc.get("small_batches", [])]
    if not entries:
        return []
    peers = sorted({k for _, e in entries for k in e["ours_over"]})
    calls = entries[0][1]["calls"]
    lines = ["", f"## Small batches (closest hit, the `{OURS}` tree through the API: one call's "
             f"wall time in microseconds, host work included; medians of {calls} interleaved "
             "calls; ours / peer: the median of the per-round ratios, above 1 ours is faster)",
             "", f"| scene | rays | {OURS} us | " + " | ".join(f"{p} us" for p in peers) + " | "
             + " | ".join(f"ours / {p}" for p in peers) + " |",
             "|---|---:|---:|" + "---:|" * (2 * len(peers))]
    for name, e in entries:
        sec = e["seconds"]
        lines.append(f"| {name} | {e['rays']:,} | {sec[OURS] * 1e6:.0f} | "
                     + " | ".join(fmt_or_dash(None if p not in sec else sec[p] * 1e6, ".0f")
                                  for p in peers) + " | "
                     + " | ".join(fmt_or_dash(e["ours_over"].get(p), ".2f") for p in peers) + " |")
    return lines


def goal_markdown(entries: list[dict], verdict: dict[str, dict]) -> list[str]:
    """The section of issue 16's goal: the verdict lines and the table."""
    needs = (f"the default tree at least {GOAL_DEFAULT:.1f}x, the best tree built in under "
             f"{GOAL_BUILD_FACTOR:g}x the default's build time at least {GOAL_BEST:.1f}x "
             f"{' and '.join(f'`{p}`' for p in GOAL_PEERS)}")
    lines = ["", f"## Goal (issue 16, through the API, same rays and rounds): {needs}", ""]
    v = verdict["closest"]
    counted = (f" ({v['met']} of {v['judged']} judged trees meet it)"
               if v["status"] != "NOT MEASURED" else "")
    lines.append(f"**Verdict, closest hit: {v['status']}**{counted}"
                 + (f": {'; '.join(v['why'])}." if v["why"] else "."))
    others = []
    for q in QUERIES[1:]:
        w = verdict[q]
        counted = f", {w['met']} of {w['judged']}" if w["status"] != "NOT MEASURED" else ""
        others.append(f"{q} {w['status']}{counted}")
    lines += ["", f"The same test on the other queries (reported, not the goal's): "
              f"{'; '.join(others)}.", "",
              "| scene | role | tree | build ms | build / default | closest Mrays/s "
              + "".join(f"| {q} / {p} " for q in QUERIES for p in GOAL_PEERS)
              + "| needs | closest hit |",
              "|---|---|---|---:|---:|---:|" + "---:|" * (len(QUERIES) * len(GOAL_PEERS)) + "---:|---|"]
    for e in entries:
        qs = e["queries"]
        ratios = "".join(f"| {fmt_ratio(qs[q]['vs'].get(p)) if q in qs else '-'} "
                         for q in QUERIES for p in GOAL_PEERS)
        if e["at_least"] is None:
            status = f"not judged: {e['not_judged']}"
        else:
            status = e["status"] + (f" ({', '.join(e['short'])})" if e["short"] else "")
            cav = qs.get("closest", {}).get("caveat")
            if cav:
                status += f" (caveat: {cav})"
        lines.append(
            f"| {e['scene']} | {e['role']} | {e['tree']} | {e['build_seconds'] * 1e3:.1f} "
            f"| {e['build_factor']:.2f} | {fmt_mrays(qs.get('closest', {}).get('rays_per_second'))} "
            f"{ratios}| {fmt_or_dash(e['at_least'], '.1f')} | {status} |")
    lines += ["", GOAL_NOTES]
    return lines


GOAL_NOTES = f"""`role`: `default` the default `lbvh.build` tree; `best` the fastest on
closest hits of {', '.join(f'`{t}`' for t in GOAL_CANDIDATES)} (those built here) among those built in under
{GOAL_BUILD_FACTOR:g}x the default's build time; `other` the other trees (not judged: slower, or built too slowly).
`build ms`: median of {BUILD_REPEATS} builds after one that compiles the kernels (the serial SAH
tree: one build). Ratios: our throughput over the peer's, ratio of the medians and, in brackets,
the range of the per-round ratios. The verdict judges closest hits on every scene; `NOT MEASURED`
where a peer is not installed."""


COLUMN_NOTES = """Columns: `Mrays/s` rays over the median time (`ms`): ours through
`bvh.intersect` / `bvh.occluded` (validation, packing, transfers, read-back included), `(kernel
only)` the traversal kernel's device time from OpenCL events on rays already on the device;
peers: their query call (embreex `scene.run`, Open3D `cast_rays` / `test_occlusions` with
`nthreads=2` and the tensor wrapping, warp `wp.launch` with the array copies). `nodes/ray`,
`tris/ray`: ours, mean nodes visited (the root plus every node descended into or popped) and
triangles tested per ray, from an untimed pass with `counters=True` (kernel-only rows: their API
row's tree and kernel). `spread`:
(max - min) / median of the samples: differences below it are noise. `CPU use`: process CPU
seconds over wall seconds of the calls (PoCL's and Embree's threads included): about the cores
busy; `other load`: cores other processes kept busy meanwhile (machine-wide busy CPU
time from /proc/stat minus this process's, over the wall time; median of the samples). `/ embree-2t`,
`/ open3d`, `/ warp`: this row's throughput over the peer's, ratio of the medians and,
in brackets, the range of the per-round ratios (same round, same noise). `agree`: fraction of rays
with the reference's hit or miss, primitive and t (within 16 u (t + s) / max(|cos|, 1e-3));
`agree (ties)` also accepts another primitive at the same t; any hits: the same hit or miss.
`disagree (oracle)`: rays not agreeing even with ties, and of those judged against the float64
oracle (lbvh.verification.rules.Judge: any answer float32 rounding can give is right) how many this tracer
got right or wrong. `overflow`: our rays whose traversal stack overflowed."""


# -- main ----------------------------------------------------------------------------

def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    scene_options = (QUICK_SCENES, FULL_SCENES, QUICK_RAYS, FULL_RAYS)
    common.add_scene_options(p, *scene_options)
    p.add_argument("--repeats", type=int, default=3, help="rounds per ray set (median)")
    p.add_argument("--budget", type=float, default=60.0,
                   help="a tracer stops repeating a ray set after this many seconds (default 60)")
    p.add_argument("--ao-samples", type=int, default=1, help="AO rays per hit pixel (default 1)")
    p.add_argument("--judge", type=int, default=200,
                   help="rays judged against the float64 oracle per ray set, at most (default 200)")
    p.add_argument("--sah", action="store_true",
                   help=f"also the serial SAH tree, on scenes up to {SAH_MAX_TRIANGLES:,} triangles")
    p.add_argument("--views", type=Path, default=None, help="also write what each camera sees here")
    p.add_argument("--small-calls", type=int, default=None,
                   help=f"calls per tracer and batch size of the small-batch table (default "
                        f"{SMALL_CALLS}, 3 with --quick; 0 leaves the table out)")
    common.add_run_options(p)
    p._option_string_actions["--no-peers"].help = "skip Embree, Open3D and warp"
    args = p.parse_args(argv)
    for name in ("repeats", "ao_samples"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')}: at least 1")
    if args.judge < 0:
        p.error("--judge: at least 0")
    if args.small_calls is None:
        args.small_calls = 3 if args.quick else SMALL_CALLS
    if args.small_calls < 0:
        p.error("--small-calls: at least 0")
    common.resolve_scenes(p, args, *scene_options)
    return args


def source_state() -> dict:
    """The commit measured and the library files that differ from it (the kernels and
    the traversal change under active tuning: a figure must say which code it timed)."""
    def git(*argv: str) -> str:
        try:
            return subprocess.run(["git", *argv], cwd=common.REPO, capture_output=True, text=True,
                                  timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""
    return {"commit": git("rev-parse", "HEAD") or None,
            "modified": git("diff", "--name-only", "HEAD", "--", "lbvh", "kernels").split()}


def load_scene(name: str, size: tuple[int, int], cameras: dict[str, dict], shared: Path) -> common.Scene | str:
    """The scene with its camera (``CAMERA_OF`` picks another entry), or why it is skipped."""
    entry = CAMERA_OF.get(name, name)
    if entry not in cameras:
        return f"no camera {entry!r} in {common.CAMERAS.name}"
    return common.load_bench_scene(name, size, {**cameras, name: cameras[entry]}, shared)


def main(argv: list[str] | None = None) -> dict:
    """Run the bench; returns the report (also written as JSON and Markdown)."""
    args = parse_args(argv)
    started = time.perf_counter()
    command = common.command_line("bench_traverse.py", argv)
    source = source_state()
    ctx = dev.get_context(args.device)
    peers, peer_status = common.load_peers(not args.no_peers, TRACE_PEERS)
    cameras = common.load_cameras()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    progress = common.Progress(len(args.scene_names) * steps_per_scene(args.repeats))
    scenes, rows, skipped = [], [], []
    with ThreadPoolExecutor(max_workers=2) as pool:
        def load(name: str) -> common.Scene | str:
            return load_scene(name, args.size, cameras, args.shared)

        for scene in common.loaded_scenes(args.scene_names, load, progress,
                                      steps_per_scene(args.repeats), skipped):
            summary, scene_rows = bench_scene(scene, ctx, peers, pool, args, progress)
            scenes.append(summary)
            rows += scene_rows
    progress.close()
    report = {
        **common.report_start(command, ctx, peer_status),
        "source": {**source, "changed_during_run": source_state() != source},
        "settings": {"scenes": args.scene_names, "width": args.size[0], "height": args.size[1],
                     "repeats": args.repeats, "budget": args.budget, "ao_samples": args.ao_samples,
                     "ao_distance": AO_DISTANCE, "judge": args.judge, "sah": args.sah,
                     "quick": args.quick, "reference": REFERENCE,
                     "fallback_reference": FALLBACK_REFERENCE, "embree_chunks": EMBREE_CHUNKS,
                     "warp_constructor": WARP_CONSTRUCTOR, "build_repeats": BUILD_REPEATS,
                     "small_batches": list(SMALL_BATCHES), "small_calls": args.small_calls,
                     "goal": {"peers": list(GOAL_PEERS), "default_at_least": GOAL_DEFAULT,
                              "best_at_least": GOAL_BEST, "build_factor": GOAL_BUILD_FACTOR,
                              "candidates": list(GOAL_CANDIDATES), "judged_query": "closest"},
                     "t_bound": common.AGREEMENT_T_BOUND},
        "scenes": scenes, "skipped": skipped, "rows": rows,
        "closest_ratios": closest_ratios(rows),
        "targets": targets(rows, [s["name"] for s in scenes]),
        "goal": goal(rows, scenes),
        "watertight_price": watertight_price(rows),
        "cpu_use": cpu_use(rows),
        "other_load": {"median": median_or_none([r["other_load"] for r in rows]),
                       "max": max((r["other_load"] for r in rows if r["other_load"] is not None),
                                  default=None)},
    }
    report["goal_verdict"] = goal_verdict(report["goal"])
    report["gap"] = gap(rows, report["goal"])
    report["rays_goal"] = rays_goal(report)
    write_outputs(report, out, started)
    return report


def write_outputs(report: dict, out: Path, started: float) -> None:
    report["duration_seconds"] = time.perf_counter() - started
    paths = {"json": out / "bench_traverse.json", "markdown": out / "bench_traverse.md"}
    report["outputs"] = {k: str(p) for k, p in paths.items()}
    common.write_report(report, markdown(report), paths, out)


if __name__ == "__main__":
    main()
