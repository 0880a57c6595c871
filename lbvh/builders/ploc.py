"""The device PLOC build (kernels/ploc.cl): bottom-up clustering in Morton order.

Meister & Bittner 2018, "Parallel Locally-Ordered Clustering for Bounding
Volume Hierarchy Construction" (IEEE TVCG 24(3)): the leaves, one triangle
each, start as clusters in Morton order; in each step every cluster finds its
nearest neighbour (the least surface area of the merged box) among the
``radius`` clusters on either side, mutual nearest neighbours merge into a new
node at the place of the lower one, and the survivors are compacted in order;
the steps repeat until one cluster, the root, is left. Each step is a handful
of data-parallel passes, so the whole build stays on the device:

    bounds -> morton (63-bit keys) -> sort -> leaves -> steps (nearest, count,
    scan, merge) until one cluster

The numbering (docs/pages/layout.md): the leaf of slot ``k`` is node ``F - 1 + k``
(as in the LBVH: :meth:`lbvh.tree.Tree.leaf_walks` needs no leaf list), the
``t``-th merge (pairs in increasing position within a step, steps in order)
makes internal node ``t``, the root is node ``F - 2`` (node 0 for one triangle).

The host reads back one small buffer (the cluster count) after a batch of
steps, not after each: the kernels read the count on the device and size their
chunks by it; the last steps, from a few thousand clusters on (on a CPU), run in
one work-item. :func:`ploc_numpy` is the twin: the same float32 operations in the
same order, so the same tree bit for bit (areas at the root box's
:func:`~lbvh.metrics.cost.box_scale`, as the treelet restructuring's).
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..device import Launch, run
from ..device.sort import radix_sort
from ..layout import NODE_DTYPE
from ..metrics.cost import box_scale, scaled_half_area
from ..report import BuildReport
from ..tree import Mesh, Tree
from . import bounds
from .morton import code_bits, enqueue_count_duplicates, morton_codes
from .options import PLOC_RADIUS, PLOCOptions

KERNEL_FILE = "ploc.cl"
#: Morton keys of the leaves' order: 63-bit codes (``uint64`` keys).
KEY_BITS = 64
#: Clusters per work-item of the nearest-neighbour pass on a CPU, at least (whole
#: groups of eight go in vectors; a chunk's last few one by one).
NEAREST_MIN_PER_ITEM = 256
#: Clusters per work-item of the count and merge passes on a CPU, at least.
MERGE_MIN_PER_ITEM = 2048
#: The cluster count's shrink per step the first batch of steps is sized by (0.81 to
#: 0.83 on the teapot, the bunny and a random soup at radius 16, after a first step
#: of about 0.6); later batches are sized by the rate seen (:func:`batch_steps`).
EXPECTED_RATE = 0.8
#: The most steps queued between two reads.
MAX_BATCH = 32
#: From this many clusters on, the last steps run in one work-item (kernel ploc_tail).
#: On a CPU the host queues a step's 4 launches in about 45 us, which the device waits
#: for (a queued_together block starts once queued), and the serial tail of 2048
#: clusters takes about 0.4 ms: on the teapot and the bunny, tails of 2048 and 4096
#: built fastest (256: 1.3-2x slower). A GPU's single work-item is slow.
TAIL_CLUSTERS = {"cpu": 2048, "gpu": 32}


#: Clusters per vector in ploc.cl's nearest-neighbour pass on a CPU (LANES); a GPU's
#: work-item takes one cluster.
LANES = 8


def kernel_defines(radius: int, is_cpu: bool, compiler_is_clang: bool) -> dict[str, int]:
    """The -D defines kernels/ploc.cl is compiled with: the search radius, eight
    clusters per vector on a CPU (PoCL does not vectorise a work-item's loop), one on
    a GPU (each work-item a SIMT lane already), and clang's prefetch where the
    compiler is clang (refit.cl's CLANG_PREFETCH)."""
    return {"RADIUS": int(radius), "LANES": LANES if is_cpu else 1,
            "CLANG_PREFETCH": int(compiler_is_clang)}


def tail_clusters(ctx: dev.Context) -> int:
    """The count from which the last steps run in one work-item (:data:`TAIL_CLUSTERS`)."""
    return TAIL_CLUSTERS["cpu" if ctx.is_cpu else "gpu"]


def builder_name(radius: int) -> str:
    """``"ploc"``, or ``"ploc-<radius>"`` for another radius than the default."""
    return "ploc" if radius == PLOC_RADIUS else f"ploc-{radius}"


def batch_steps(clusters: int, tail: int, rate: float = EXPECTED_RATE) -> int:
    """How many steps to queue from ``clusters`` clusters on: the steps down to ``tail``
    clusters if each step keeps ``rate`` of them (from at most ``tail`` on, one kernel
    does the rest), at most :data:`MAX_BATCH`; 0 from at most ``tail``."""
    if clusters <= tail:
        return 0
    rate = min(rate, 0.99)
    return max(1, min(MAX_BATCH, math.ceil(math.log(clusters / tail) / -math.log(rate))))


#: A step's launches: the nearest pass's and its least chunk, the count and merge
#: passes' and theirs.
StepLaunches = tuple[Launch, int, Launch, int]


def step_launches(ctx: dev.Context, m: int) -> StepLaunches:
    """The launches of the steps from ``m`` clusters on, with the least chunk each kernel
    takes (the kernels cut the work-items' chunks by the count they read: chunks shrink
    with the count)."""
    near = ctx.launch(m, min_per_item=NEAREST_MIN_PER_ITEM)
    merge = ctx.launch(m, min_per_item=MERGE_MIN_PER_ITEM, gpu_per_item=max(1, -(-m // 4096)))
    if ctx.is_cpu:
        return near, NEAREST_MIN_PER_ITEM, merge, MERGE_MIN_PER_ITEM
    return near, 1, merge, 1


def max_merge_items(ctx: dev.Context) -> int:
    """The most work-items of a count or merge launch (:func:`step_launches`) for any
    count: a CPU's few per core; on a GPU at most 4096 chunks, in groups of 64."""
    return ctx.work_items() if ctx.is_cpu else 4096 + 64


@dataclasses.dataclass
class _Steps:
    """The buffers of the clustering steps, and the events of their kernels."""
    ctx: dev.Context
    clusters: list[cl.Buffer]     # 7 planes of F entries (ploc.cl), in and out by turns
    nearest: cl.Buffer            # int32 per cluster
    counts: cl.Buffer             # int32 [m of side 0, m of side 1, stuck]
    chunk_counts: cl.Buffer       # int32 pairs per chunk of the merge launch
    root_box: cl.Buffer           # 2 float4
    nodes: cl.Buffer
    parent: cl.Buffer
    num_prims: int
    defines: dict[str, int]
    events: list[cl.Event] = dataclasses.field(default_factory=list)

    def queue(self, side: int, geometry: StepLaunches) -> None:
        """One step from the clusters of ``side`` (0 or 1) to the other side's."""
        ctx, d = self.ctx, self.defines
        near, near_min, merge, merge_min = geometry
        src, dst = self.clusters[side], self.clusters[1 - side]
        items = np.int32(merge.global_size)
        cap = np.int32(self.num_prims)
        self.events.append(run(ctx, KERNEL_FILE, "ploc_nearest", near, src, cap, self.counts,
                               side, near.global_size, near_min, self.root_box, self.nearest,
                               defines=d))
        self.events.append(run(ctx, KERNEL_FILE, "ploc_count", merge, self.nearest, self.counts,
                               side, items, merge_min, self.chunk_counts, defines=d))
        self.events.append(run(ctx, KERNEL_FILE, "ploc_scan", Launch(1, 1, 1, 1),
                               self.chunk_counts, self.counts, side, items, merge_min,
                               defines=d))
        self.events.append(run(ctx, KERNEL_FILE, "ploc_merge", merge, src, cap, self.nearest,
                               self.counts, side, items, merge_min, self.chunk_counts,
                               self.nodes, self.parent, dst, defines=d))

    def queue_tail(self, side: int, limit: int) -> None:
        """The last steps, in one work-item, in place on the clusters of ``side``, if at
        most ``limit`` are left by then."""
        self.events.append(run(self.ctx, KERNEL_FILE, "ploc_tail", Launch(1, 1, 1, 1),
                               self.clusters[side], np.int32(self.num_prims), self.counts, side,
                               limit, self.root_box, self.nearest, self.nodes, self.parent,
                               defines=self.defines))


def _leaves(steps: _Steps, mem: dev.Scope, boxes: cl.Buffer, prim_order: cl.Buffer) -> None:
    """Queue the leaves, the first clusters and the root box (kernel ploc_leaves, then
    bounds.cl's reduce_boxes over the chunks' boxes)."""
    ctx, n = steps.ctx, steps.num_prims
    launch = ctx.launch(n, min_per_item=4096, gpu_per_item=max(1, -(-n // 4096)))
    partial = mem.alloc(32 * launch.global_size, scratch=True)
    steps.events.append(run(ctx, KERNEL_FILE, "ploc_leaves", launch, boxes, prim_order, n,
                            launch.per_item, steps.nodes, steps.parent, steps.clusters[0],
                            steps.counts, partial, defines=steps.defines))
    steps.events.append(run(ctx, bounds.KERNEL_FILE, "reduce_boxes", Launch(1, 1, 1, 1), partial,
                            launch.global_size, steps.root_box))
    mem.free(partial)


def _queue_round(steps: _Steps, m: int, side: int, batch: int) -> int:
    """Queue ``batch`` steps from ``m`` clusters on the clusters of ``side``, then the
    tail; returns the side the count and clusters end on."""
    if batch:
        geometry = step_launches(steps.ctx, m)
        for _ in range(batch):
            steps.queue(side, geometry)
            side = 1 - side
    steps.queue_tail(side, tail_clusters(steps.ctx))
    return side


def _cluster(steps: _Steps, mem: dev.Scope, boxes: cl.Buffer, prim_order: cl.Buffer) -> None:
    """Queue the leaves, then rounds until the host reads a count of one cluster: each
    round a batch of steps sized to reach :func:`tail_clusters` (:func:`batch_steps`),
    then the tail (which does nothing while the count is above that). Raises
    ``RuntimeError`` if a step of two clusters or more merged nothing (which
    kernels/ploc.cl argues cannot happen: a guard against an endless loop)."""
    ctx = steps.ctx
    m, side = steps.num_prims, 0
    batch = batch_steps(m, tail_clusters(ctx))
    counts = np.zeros(3, np.int32)
    with dev.queued_together(ctx):
        _leaves(steps, mem, boxes, prim_order)
        mem.free(boxes)   # the in-order queue runs the leaves before any reuse
        if m > 1:
            side = _queue_round(steps, m, side, batch)
    while m > 1:
        cl.enqueue_copy(ctx.queue, counts, steps.counts, is_blocking=True)
        if counts[2] or counts[side] >= m:
            raise RuntimeError(f"lbvh: a PLOC step of {m:,} clusters or fewer merged nothing "
                               "(kernels/ploc.cl)")
        before, m = m, int(counts[side])
        if m > 1:
            rate = (m / before) ** (1.0 / max(batch, 1))
            batch = batch_steps(m, tail_clusters(ctx), rate)
            with dev.queued_together(ctx):
                side = _queue_round(steps, m, side, batch)


def build_tree(ctx: dev.Context, mesh: Mesh, options: PLOCOptions = PLOCOptions(),
               mem: dev.Scope | None = None) -> Tree:
    """Build a PLOC tree over a mesh already on the device; the caller holds ``ctx.lock``.

    ``mem``: the scope the build allocates in (default: a new one, closed at the end);
    the report's ``peak_device_bytes`` is its peak. The report's phases: ``bounds``,
    ``morton``, ``sort`` (as the LBVH's) and ``cluster`` (the leaves and every step).
    """
    own_scope = mem is None
    if own_scope:
        mem = dev.MemoryTracker(ctx)
    n = mesh.num_prims
    events: dict[str, list] = {"bounds": [], "morton": [], "sort": [], "cluster": []}
    t0 = time.perf_counter()
    with dev.queued_together(ctx):
        boxes, centroid_box, evs = bounds.triangle_bounds(ctx, mem, mesh.vertices_buf,
                                                          mesh.faces_buf, n)
        events["bounds"] += evs
        keys, values, evs = morton_codes(ctx, mem, boxes, centroid_box, n, KEY_BITS)
        events["morton"] += evs
    result = radix_sort(ctx, mem, keys, values, n, KEY_BITS)
    events["sort"] += result.events
    duplicates, evs = enqueue_count_duplicates(ctx, mem, result.keys, n, KEY_BITS)
    events["morton"] += evs
    mem.free(centroid_box, result.keys)
    prim_order = result.values
    num_nodes = 2 * n - 1
    steps = _Steps(ctx, [mem.alloc(28 * n, scratch=True), mem.alloc(28 * n, scratch=True)],
                   mem.alloc(4 * n, scratch=True), mem.alloc(16, scratch=True),
                   mem.alloc(8 * max_merge_items(ctx), scratch=True),
                   mem.alloc(32, scratch=True), mem.alloc(32 * num_nodes), mem.alloc(4 * num_nodes),
                   n, kernel_defines(options.radius, ctx.is_cpu, ctx.compiler_is_clang))
    _cluster(steps, mem, boxes, prim_order)
    events["cluster"] = steps.events
    mem.free(*steps.clusters, steps.nearest, steps.counts, steps.chunk_counts, steps.root_box)
    ctx.queue.finish()
    wall = time.perf_counter() - t0
    if own_scope:
        mem.close()
    tree = Tree(ctx, steps.nodes, steps.parent, prim_order, root=max(n - 2, 0),
                num_nodes=num_nodes, num_prims=n, builder=builder_name(options.radius))
    phase_seconds = {phase: dev.event_seconds(evs) for phase, evs in events.items()}
    report = BuildReport(device=ctx.name, builder=tree.builder, num_triangles=n,
                         key_bits=code_bits(KEY_BITS),
                         key_choice="fixed: 63 bits (the ploc builder's)",
                         duplicate_codes=duplicates(), phase_seconds=phase_seconds,
                         device_seconds=sum(phase_seconds.values()), wall_seconds=wall,
                         sort_passes=result.passes, peak_device_bytes=mem.peak,
                         input_bytes=mesh.vertices.nbytes + mesh.faces.nbytes)
    return dataclasses.replace(tree, report=report)


# -- numpy twin -------------------------------------------------------------------------

def root_scale(lo: np.ndarray, hi: np.ndarray) -> np.float32:
    """The area scale of the kernels: :func:`~lbvh.metrics.cost.box_scale` of the box of
    all the boxes ``lo``, ``hi`` (``float32 (F, 3)``)."""
    return box_scale(lo.min(axis=0)[None], hi.max(axis=0)[None])[0, 0]


def _pair_areas(c_lo: np.ndarray, c_hi: np.ndarray, k: int, scale: np.float32) -> np.ndarray:
    """``float32 (m - k,)``: the merged half area of clusters ``i`` and ``i + k`` (the lower
    position first, as ploc.cl's merged_area)."""
    m = len(c_lo)
    return scaled_half_area(np.minimum(c_lo[:m - k], c_lo[k:]), np.maximum(c_hi[:m - k], c_hi[k:]),
                            scale)


def _nearest(c_lo: np.ndarray, c_hi: np.ndarray, radius: int, scale: np.float32) -> np.ndarray:
    """``int64 (m,)``: each cluster's nearest neighbour (kernel ploc_nearest): the least
    area; among equal areas the nearer candidate, and at equal distance the right one
    for an even position, the left one for an odd position (a strict ``<`` over the
    candidates in that order)."""
    m = len(c_lo)
    r = min(radius, m - 1)
    best = np.full(m, np.inf, np.float32)
    nearest = np.full(m, -1, np.int64)
    index = np.arange(m)
    even = index % 2 == 0
    for k in range(1, r + 1):
        pair = _pair_areas(c_lo, c_hi, k, scale)     # clusters i and i + k
        right = np.full(m, np.inf, np.float32)       # candidate i + k (inf: none)
        right[:m - k] = pair
        left = np.full(m, np.inf, np.float32)        # candidate i - k
        left[k:] = pair
        for take_right in (even, ~even):             # the preferred side first
            area = np.where(take_right, right, left)
            j = np.where(take_right, index + k, index - k)
            exists = (j >= 0) & (j < m)
            better = exists & (area < best)
            best[better] = area[better]
            nearest[better] = j[better]
    return nearest


def ploc_numpy(lo: np.ndarray, hi: np.ndarray, order: np.ndarray, radius: int = PLOC_RADIUS,
               scale: float | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Twin of the device build's clustering: the PLOC tree over triangle boxes ``lo``,
    ``hi`` (``float32 (F, 3)``, in triangle order) whose slot ``k`` holds triangle
    ``order[k]`` (``int (F,)``, the Morton order), the same float32 operations in the
    same order as kernels/ploc.cl.

    ``scale``: the areas' scale (``float32``; default :func:`root_scale` of the boxes,
    as the device's). Returns ``nodes`` (:data:`~lbvh.layout.NODE_DTYPE` ``(2F - 1,)``),
    ``parent`` (``int32 (2F - 1,)``, -1 at the root) and the root. Raises
    ``RuntimeError`` if a step merges nothing (kernels/ploc.cl argues it cannot).
    """
    order = np.asarray(order, np.int64)
    f = len(order)
    total = 2 * f - 1
    if scale is None:
        scale = root_scale(lo, hi)
    scale = np.float32(scale)
    lower = np.empty((total, 3), np.float32)
    upper = np.empty((total, 3), np.float32)
    a = np.empty(total, np.int32)
    b = np.empty(total, np.int32)
    parent = np.full(total, -1, np.int32)
    zero = np.float32(0)
    lower[f - 1:] = lo[order] + zero    # +0.0 for -0.0, as ploc_leaves
    upper[f - 1:] = hi[order] + zero
    a[f - 1:], b[f - 1:] = np.arange(f), -1
    clusters = np.arange(f - 1, total)
    with np.errstate(over="ignore", under="ignore"):
        while len(clusters) > 1:
            m = len(clusters)
            nearest = _nearest(lower[clusters], upper[clusters], radius, scale)
            index = np.arange(m)
            mutual = (nearest >= 0) & (nearest[nearest] == index)
            pair = np.flatnonzero(mutual & (index < nearest))
            if not len(pair):
                raise RuntimeError(f"ploc_numpy: a step of {m} clusters merged nothing")
            new = (f - m) + np.arange(len(pair))
            left, right = clusters[pair], clusters[nearest[pair]]
            lower[new] = np.minimum(lower[left], lower[right])
            upper[new] = np.maximum(upper[left], upper[right])
            a[new], b[new] = left, right
            parent[left] = new
            parent[right] = new
            merged = clusters.copy()
            merged[pair] = new
            clusters = merged[~(mutual & (index > nearest))]
    nodes = np.zeros(total, NODE_DTYPE)
    nodes["lower"], nodes["upper"], nodes["a"], nodes["b"] = lower, upper, a, b
    return nodes, parent, int(clusters[0])
