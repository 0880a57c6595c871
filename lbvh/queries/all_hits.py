"""Every hit along each ray, and the hit counts (kernels/all_hits.cl).

``bvh.count_hits(origins, directions)`` answers how many times each ray
crosses the mesh in ``[tmin, tmax]``; ``bvh.all_hits(origins, directions,
max_hits=...)`` answers every hit, nearest first, as flat arrays with per-ray
offsets (:class:`AllHits`). Rays are checked as for
:func:`lbvh.queries.traverse.intersect` (:mod:`lbvh.queries.rays`).

Each hit is found by the same watertight test as the closest hit (Woop,
Benthin & Wald 2013, kernels/ray_triangle.h), with one rule more: a ray
through an edge or a vertex that several triangles share hits exactly one of
them where it crosses the surface, so the crossing counts once (the tie is
broken by moving the ray off the edge by an infinitesimal amount, a
simulation of simplicity; a ray that only touches the surface at a
silhouette edge counts it 0 or 2 times, which keeps the parity). The hits do
not depend on the tree, and their ``t, u, v`` are those the closest-hit
query reports for the same triangle.

On a CPU both passes walk their rays as streams (kernels/hit_streams.h,
:func:`stream_plan`): a work-item takes a chunk of rays through the wide records
together, each record read once for every ray of the chunk that entered it, where
the per-ray walk waits on each record's rows in turn. The counts and hits are the
per-ray walk's, ray for ray.

The twin is :func:`lbvh.verification.oracle.all_hits_brute`: the same test in
numpy over every triangle, equal to the kernel's hits bit for bit
(``dtype=np.float32``), and the float64 oracle, which differs from it only
for rays within rounding of an edge.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from .rays import Rays, check_invalid_rays, check_rays, is_device_array
from .options import QueryOptions, check_positive, query_options
from .target import QueryTarget, query_target
from .wide import lane_defines
from .traverse import FLAG_OVERFLOW, FLAG_VISIT_LIMIT, slab_pad, stack_bucket, stack_need

KERNEL_FILE = "all_hits.cl"

__all__ = ["AllHits", "count_hits", "all_hits", "segment_work", "wide_defines", "DEFAULT_BATCH",
           "stream_plan", "StreamPlan"]

#: Rays per kernel launch unless ``batch_size`` says otherwise.
DEFAULT_BATCH = 1 << 18

_WORK_GROUP = 64


@dataclass
class AllHits:
    """Every hit of each ray, nearest first, as flat arrays.

    The hits of ray ``i`` are ``t[offsets[i]:offsets[i + 1]]`` (and the same slice
    of ``prim``, ``u``, ``v``), in increasing ``t`` (equal ``t``: increasing ``prim``).

    Attributes:
        offsets: ``int64 (N + 1,)``.
        t: ``float32 (M,)`` distance along the ray's direction.
        prim: ``int32 (M,)`` triangle index in the caller's numbering.
        u, v: ``float32 (M,)`` barycentrics: the hit point is
            ``(1-u-v)*p0 + u*p1 + v*p2`` with ``p0, p1, p2 = vertices[faces[prim]]``.
        total: ``int64 (N,)`` hits of each ray in ``[tmin, tmax]``, before ``max_hits``
            (what :func:`count_hits` answers).
        overflow: ``bool (N,)`` the traversal's stack overflowed (the ray may have
            missed hits); ``overflow_count`` how many.
        invalid: ``bool (N,)`` the ray was bad and not traced (``invalid_rays="miss"``).
    """
    offsets: np.ndarray
    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    total: np.ndarray
    overflow: np.ndarray
    overflow_count: int
    invalid: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def counts(self) -> np.ndarray:
        """``int64 (N,)``: hits kept per ray (``total`` capped at ``max_hits``)."""
        return np.diff(self.offsets)

    @property
    def truncated(self) -> np.ndarray:
        """``bool (N,)``: the ray had more than ``max_hits`` hits (the nearest were kept)."""
        return self.total > self.counts

    @property
    def ray(self) -> np.ndarray:
        """``int64 (M,)``: the ray of each hit."""
        return np.repeat(np.arange(len(self), dtype=np.int64), self.counts)

    def of(self, i: int) -> slice:
        """The slice of ray ``i``'s hits in ``t``, ``prim``, ``u`` and ``v``."""
        return slice(int(self.offsets[i]), int(self.offsets[i + 1]))

    def locations(self, origins: Any, directions: Any) -> np.ndarray:
        """The hit points ``origin + t * direction`` of every hit, ``(M, 3)``, float64
        when either array is float64, else float32 (as the rays were traced)."""
        o, d = np.asarray(origins), np.asarray(directions)
        for name, a in (("origins", o), ("directions", d)):
            if a.shape != (len(self), 3):
                raise ValueError(f"{name}: shape {a.shape}, expected ({len(self)}, 3): the rays "
                                 "of this result")
        dtype = np.float64 if np.float64 in (o.dtype, d.dtype) else np.float32
        ray = self.ray
        return (o[ray].astype(dtype) + d[ray].astype(dtype) * self.t[:, None].astype(dtype))


def _check_max_hits(max_hits: Any) -> int | None:
    if max_hits is None:
        return None
    if isinstance(max_hits, bool) or not isinstance(max_hits, (int, np.integer)) or max_hits < 0:
        raise ValueError(f"max_hits: {max_hits!r}; expected None or an integer >= 0")
    return int(max_hits)


def _rays(origins: Any, directions: Any, tmin: Any, tmax: Any, invalid_rays: str) -> Rays:
    check_invalid_rays(invalid_rays)
    # rays in pyopencl arrays are read back: this query's answer is read back anyway
    origins, directions, tmin, tmax = (x.get() if is_device_array(x) else x
                                       for x in (origins, directions, tmin, tmax))
    return check_rays(origins, directions, tmin, tmax, invalid_rays=invalid_rays)


@dev.serialised
def count_hits(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0,
               tmax: Any = np.inf, *, signed: bool = False, options: QueryOptions | None = None,
               **fields: Any) -> np.ndarray:
    """How many times each ray crosses the mesh in ``[tmin, tmax]``.

    Args:
        target: an :class:`lbvh.BVH`.
        origins, directions, tmin, tmax: as for :func:`lbvh.queries.traverse.intersect`.
        options: a :class:`lbvh.QueryOptions`, or its fields ``invalid_rays`` (an
            invalid ray with ``invalid_rays="miss"`` counts 0) and ``batch_size`` (rays
            per kernel launch; default :data:`DEFAULT_BATCH`) as keywords.
        signed: count each crossing +1 where the ray leaves a triangle by its front
            (``n . d > 0``, ``n = (b - a) x (c - a)``) and -1 where it enters by it:
            from ``tmin = 0`` to ``tmax = inf``, the winding number of the origin
            for a closed mesh (each edge, by its corners' coordinates, used as often
            one way as the other: :func:`lbvh.mesh.is_closed`); kernels/every_hit.h
            ``SIGNED``.

    Returns:
        ``int32 (N,)``.

    Raises:
        ValueError: a bad ray (named) or option; ``signed`` on a tree with spatial
            splits (``builder="sbvh"``).
        RuntimeError: the traversal stack overflowed (a tree deeper than 768 levels).
    """
    target = query_target(target)   # a BVH gives its query data
    opts = query_options("hits", options, fields)
    batch = opts.batch(DEFAULT_BATCH)
    if not isinstance(signed, (bool, np.bool_)):
        raise ValueError(f"signed: {signed!r}; expected True or False")
    rays = _rays(origins, directions, tmin, tmax, opts.invalid_rays)
    if target.tree.clipped_leaves:   # a triangle in several leaves: count it once
        if signed:
            raise ValueError("count_hits(signed=True): this tree has spatial splits "
                             "(builder='sbvh'); build another tree for signed counts")
        hits = _collect(target, rays, batch, None)
        raise_on_overflow(hits.overflow.astype(np.int32), "count_hits")
        return hits.total.astype(np.int32)
    counts, flags = _run(target, rays, batch, None, signed=bool(signed))[:2]
    raise_on_overflow(flags, "count_hits")
    return counts.astype(np.int32)


@dev.serialised
def all_hits(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0,
             tmax: Any = np.inf, *, max_hits: int | None = None,
             options: QueryOptions | None = None, **fields: Any) -> AllHits:
    """Every hit of each ray in ``[tmin, tmax]``, nearest first.

    Args:
        target: an :class:`lbvh.BVH`.
        origins, directions, tmin, tmax: as for :func:`lbvh.queries.traverse.intersect`.
        max_hits: keep at most this many hits per ray, the nearest (``None``: all);
            ``AllHits.total`` still counts all of them.
        options: a :class:`lbvh.QueryOptions`, or its fields ``invalid_rays`` (an
            invalid ray with ``invalid_rays="miss"`` has no hits) and ``batch_size``
            (rays per kernel launch; default :data:`DEFAULT_BATCH`) as keywords.

    Returns:
        :class:`AllHits`.

    Raises:
        ValueError: a bad ray (named) or option.
        lbvh.DeviceError: a batch's hits would not fit the device's largest buffer
            (a smaller ``batch_size`` or a ``max_hits`` makes them fit).
    """
    target = query_target(target)   # a BVH gives its query data
    cap = _check_max_hits(max_hits)
    opts = query_options("hits", options, fields)
    rays = _rays(origins, directions, tmin, tmax, opts.invalid_rays)
    return _collect(target, rays, opts.batch(DEFAULT_BATCH), cap)


def _collect(target: QueryTarget, rays: Rays, batch: int, cap: int | None) -> AllHits:
    """The hits of checked rays as :class:`AllHits` (:func:`assemble`)."""
    dedupe = target.tree.clipped_leaves
    total, flags, kept = _run(target, rays, batch, -1 if dedupe or cap is None else cap)
    return AllHits(*assemble(rays, total, flags, kept, cap, dedupe)[:-1])


def assemble(rays: Rays, total: np.ndarray, flags: np.ndarray, kept: tuple[np.ndarray, ...],
             cap: int | None, dedupe: bool) -> tuple:
    """:class:`AllHits`' fields, then the instance of each hit (``None`` without), from
    what :func:`run_passes` collected (``kept``: ``(t, prim, u, v)`` or ``(t, prim, u, v,
    instance)``, in ray order and, within a ray, by ``t``, then instance, then triangle, as
    the kernels sort them). With ``dedupe`` (a tree with spatial splits: a triangle may be found in
    several leaves, with the same t, u, v, the same test of the same ray and triangle)
    every hit but the first of each (ray, instance, triangle) is dropped, and
    ``max_hits`` (``cap``) applied after."""
    counts = np.minimum(total, cap) if cap is not None and not dedupe else total
    t, prim, u, v = kept[:4]
    inst = kept[4] if len(kept) > 4 else None
    ray = np.repeat(np.arange(len(rays)), counts)
    # in ray order already, and the kernels sort each ray's hits (sort_kept)
    cols = [t, prim, u, v] + ([inst] if inst is not None else [])
    if dedupe:
        rows = np.stack([ray, cols[1]] + ([cols[4]] if inst is not None else []), axis=1)
        keep = np.zeros(len(ray), bool)
        keep[np.unique(rows, axis=0, return_index=True)[1]] = True
        total = np.bincount(ray[keep], minlength=len(rays)).astype(np.int64)
        rank = np.arange(int(keep.sum())) - np.repeat(np.cumsum(total) - total, total)
        within = rank < cap if cap is not None else np.ones(len(rank), bool)
        cols = [c[keep][within] for c in cols]
        counts = np.bincount(ray[keep][within], minlength=len(rays))
    offsets = _offsets(counts)
    overflow = (flags & (FLAG_OVERFLOW | FLAG_VISIT_LIMIT)) != 0
    invalid = rays.invalid if rays.invalid is not None else np.zeros(len(rays), bool)
    return (offsets, cols[0], cols[1], cols[2], cols[3], total.astype(np.int64), overflow,
            int(overflow.sum()), invalid, cols[4] if inst is not None else None)


@dev.serialised
def segment_work(target: QueryTarget, origins: Any, directions: Any, tmin: Any = 0.0,
                 tmax: Any = np.inf, *, batch_size: int = DEFAULT_BATCH) -> np.ndarray:
    """``int32 (N, 3)``: for each ray, the internal nodes and the leaves whose boxes its
    segment ``[tmin, tmax]`` enters (the slab test of the traversal) and the triangles of
    those leaves. With ``tmax`` at the closest hit this is the work every traversal of
    this tree must do for the ray, whatever its order: what the ray-sampled cost
    (:func:`lbvh.metrics.quality.ray_sampled_cost`) weighs."""
    target = query_target(target)   # a BVH gives its query data
    batch = check_positive("batch_size", batch_size)
    rays = _rays(origins, directions, tmin, tmax, "raise")
    work = np.zeros((len(rays), 4), np.int32)
    flags = _run(target, rays, batch, None, work)[1]
    raise_on_overflow(flags, "segment_work")
    return work[:, :3].copy()


def raise_on_overflow(flags: np.ndarray, name: str) -> None:
    """A ``RuntimeError`` naming how many rays' traversal overflowed its stack, and the
    first, if any did: a count is never silently short."""
    bad = (flags & (FLAG_OVERFLOW | FLAG_VISIT_LIMIT)) != 0
    if bad.any():
        raise RuntimeError(f"{name}: the traversal stack overflowed for {int(bad.sum())} rays "
                           f"(first: ray {int(np.flatnonzero(bad)[0])}); the tree is deeper than "
                           "the kernel's stack")


def _run(target: QueryTarget, rays: Rays, batch: int, cap: int | None,
         work: np.ndarray | None = None, signed: bool = False):
    """:func:`run_passes` of kernels/all_hits.cl over the target's tree (``signed``:
    counting, kernels/every_hit.h ``SIGNED``)."""
    tree = target.tree
    wide = target.wide_records()
    sign = {"SIGNED": 1} if signed else {}
    if wide.packed and work is None:   # the counters count binary nodes (segment_work)
        walk = HitWalk(KERNEL_FILE, "all_hits", wide_head(target), stack_need(target),
                       defines={**wide_defines(target.ctx, wide.width), **sign},
                       streams=stream_records(target.ctx, wide.count))
        return run_passes(target.ctx, walk, rays, batch, cap)
    head = (tree.nodes, tree.nodes, tree.prim_order, target.mesh.vertices_buf,
            target.slot_faces(), tree.root, tree.root, 0, tree.num_nodes)
    walk = HitWalk(KERNEL_FILE, "all_hits", head, target.traversal_depth(), defines=sign)
    return run_passes(target.ctx, walk, rays, batch, cap, work=work)


def wide_defines(ctx: dev.Context, width: int) -> dict[str, int]:
    """The -D defines of all_hits.cl's walk through wide records of ``width`` lanes:
    clang's builtins for the lanes' bit mask, its lowest bit and the prefetch of the
    records pushed, where the compiler is clang (kernels/wide_rows.h; with the walk
    that pushes no leaf, count_hits measured 1.10-1.16x on the bunny, Sponza and
    terrain-1m, kernels/every_hit.h), and the triangles read in slot order
    (``SLOT_TRIANGLES``: :func:`wide_head` passes them), and the room the streams
    give a ray (``RAY_BYTES``)."""
    return {"WIDE": 1, "WIDTH": width, **lane_defines(ctx),
            "CLANG_PREFETCH": int(ctx.compiler_is_clang), "SLOT_TRIANGLES": 1,
            "RAY_BYTES": RAY_BYTES}


#: Bytes of the room the streams give one ray's ``Ray`` (kernels/ray_triangle.h,
#: 164 bytes; the kernel's build fails where it is larger: hit_streams.h).
RAY_BYTES = 192
#: List entries a stream's work-item has per ray of its chunk (kernels/hit_streams.h):
#: a record takes WIDTH entries for each ray of its list until its subtree is done;
#: where they run out its rays go on one by one (the same counts).
STREAM_WORDS = 32
#: The rays of a stream: from a quarter of the records' count, rounded up to a power of
#: two, within these (see :func:`stream_plan`).
STREAM_CHUNK = (4096, 32768)


def stream_records(ctx: dev.Context, records: int) -> int:
    """Whether the passes walk their rays as streams (kernels/hit_streams.h):
    the records' count on a CPU, where a work-item is a loop on a core and the per-ray
    walk waits on each record's rows; 0 elsewhere (a GPU hides that wait with other
    work-items). Measured, streams / per-ray walk, count_hits of the queries bench's
    262,144 rays, 2 cores (bench/README.md): 1.5x (bunny), 1.2x (Sponza), 2.8x
    (terrain-1m)."""
    return int(records) if ctx.is_cpu else 0


@dataclass(frozen=True)
class StreamPlan:
    """stream_hits_kernel's launch and room (kernels/all_hits.cl): ``items`` work-items,
    each taking chunks of ``per_chunk`` rays in turn, with ``scratch_words`` list
    entries of its own."""
    per_chunk: int
    items: int
    scratch_words: int

    def launch(self) -> dev.Launch:
        return dev.Launch(self.items, 1, self.items, 1)

    def buffers(self) -> dict[str, int]:
        """Bytes of each buffer the kernel needs: Rays, slab constants, lists."""
        rays = self.items * self.per_chunk
        return {"rays": RAY_BYTES * rays, "slabs": 48 * rays,
                "scratch": 4 * self.items * self.scratch_words}


def stream_plan(ctx: dev.Context, rays: int, records: int) -> StreamPlan:
    """The streams of a pass of ``rays`` rays through ``records`` wide
    records. A chunk's rays share a record's reads where several of them enter it:
    the more records, the more rays a chunk needs for that (a quarter of the
    records, within STREAM_CHUNK: measured best on the bunny, 21,791 records, at
    4,096-8,192 rays; terrain-1m, 303,914, at 32,768-65,536); but no fewer than
    two chunks a compute unit where the rays allow, so that every core has work.
    Two work-items a compute unit, each with its own room; no buffer past the
    device's largest allocation, and all of them within an eighth of its memory
    (the room then shrinks: fewer shared reads, the same hits)."""
    low, high = STREAM_CHUNK
    per_chunk = min(high, max(low, 1 << max(0, int(records) // 4 - 1).bit_length()))
    units = ctx.compute_units
    per_chunk = max(1, min(per_chunk, -(-rays // (2 * units))))
    chunks = -(-rays // per_chunk)
    items = max(1, min(chunks, 2 * units))
    words = STREAM_WORDS * per_chunk
    largest = ctx.memory.max_alloc
    budget = int(ctx.device.global_mem_size) // 8

    def too_big() -> bool:
        plan = StreamPlan(per_chunk, items, words).buffers()
        return max(plan.values()) > largest or sum(plan.values()) > budget

    while items > 1 and too_big():
        items -= 1
    while per_chunk > 1 and too_big():
        per_chunk //= 2
        words = STREAM_WORDS * per_chunk
    return StreamPlan(per_chunk, items, words)


def wide_head(target: QueryTarget) -> tuple:
    """all_hits.cl's arguments before the rays for the walk through the target's wide
    records (:func:`wide_defines`): the triangles' corners in slot order
    (``target.slot_triangles()``) where the kernel's ``vertices`` go."""
    target = query_target(target)   # a BVH gives its query data
    tree, wide = target.tree, target.wide_records()
    return (tree.nodes, wide.buffer, tree.prim_order, target.slot_triangles(),
            target.slot_faces(), tree.root, wide.root_x, wide.root_y, tree.num_nodes)


#: Hit slots per ray of all_hits' collecting pass, for batches too small to sample
#: (:func:`first_slots`): the pass keeps a ray's hits and counts them; only the rays with
#: more hits than slots are traced again, with room for all of theirs, where a counting
#: pass and a collecting pass traced every ray twice.
FIRST_SLOTS = 8
#: Larger batches count the hits of a sample of their rays first (one in SAMPLE_EVERY),
#: and give every ray the slots that SLOT_QUANTILE of the sample's rays need, within
#: SLOT_RANGE (16 bytes a slot: 256 MB for 64 slots of the default 262,144 rays) and
#: within the device's largest allocation for all the columns together. Only the kept
#: hits are read back (:func:`move_runs`), so a slot left empty costs memory, not time.
SAMPLE_EVERY = 64
SLOT_QUANTILE = 0.97
SLOT_RANGE = (4, 64)


@dataclass(frozen=True)
class HitWalk:
    """The kernel :func:`run_passes` walks the rays with: ``kernel`` of ``kernel_file``,
    one of all_hits.cl's arguments (``head``: those before the rays;
    kernels/instance_hits.cl has them too, with an instance column after the triangle's
    when ``instances``). ``depth``: the deepest tree walked (the stack's size).
    ``defines``: more of the kernel's compile-time choices (all_hits.cl's ``WIDE``).
    ``streams``: the wide records' count where the passes walk the rays as streams
    (``stream_hits_kernel``, :func:`stream_records`), else 0."""
    kernel_file: str
    kernel: str
    head: tuple
    depth: int
    instances: bool = False
    defines: dict | None = None
    streams: int = 0


def run_passes(ctx: dev.Context, walk: HitWalk, rays: Rays, batch: int, cap: int | None, *,
               work: np.ndarray | None = None):
    """Count (``cap`` None) or collect (``cap`` -1: all, else at most ``cap`` per ray)
    the hits of every good ray, batch by batch, with the kernel of ``walk``. Returns
    ``(total, flags)`` and, when collecting, ``(t, prim, u, v)`` (and ``instance``) in
    ray order (each ray's sorted by the kernel). ``work`` (``int32 (N, 4)``, counting
    only, all_hits.cl) receives its counters.

    Collecting: one pass gives each ray :func:`first_slots` slots and counts its hits;
    the rays with more hits to keep than slots are traced again in a pass that has room
    for all they keep (their counts known)."""
    n = len(rays)
    total = np.zeros(n, np.int64)
    flags = np.zeros(n, np.int32)
    pieces: list[tuple[np.ndarray, ...]] = []
    good = np.arange(n) if rays.invalid is None else np.flatnonzero(~rays.invalid)
    if rays.invalid is not None:
        rays = rays.take(good)
    base = {"STACK_SIZE": stack_bucket(walk.depth + 1), "SLAB_PAD": slab_pad(ctx),
            **(walk.defines or {})}
    # the kernel's columns: t, u, v, prim (and instance); returned as t, prim, u, v, ...
    dtypes = ((np.float32, np.float32, np.float32, np.int32)
              + ((np.int32,) if walk.instances else ()))
    pass_ = _Pass(ctx, walk.kernel_file, walk.kernel, walk.head, base, dtypes, walk.streams)
    lo, hi, stride = rays.kernel_intervals()
    m_all = len(rays)
    for start in range(0, m_all, batch):
        stop = min(m_all, start + batch)
        part = Rays(rays.origins[start:stop], rays.directions[start:stop],
                    lo[start:stop] if stride else lo, hi[start:stop] if stride else hi)
        slots = None if cap is None or cap == 0 else first_slots(pass_, part, cap)
        if not slots:   # counting (or max_hits=0): one counting pass
            counts, part_flags, part_work, _ = pass_.run(part, None, work is not None)
            if work is not None:
                work[good[start:stop]] = part_work
            if cap is not None:   # max_hits=0: nothing kept
                pieces.append(tuple(np.zeros(0, t) for t in _returned(dtypes)))
        else:
            m = stop - start
            # all hits (or more than the slots): a ray past its slots is traced again,
            # so the first pass only fills them (SLOTS_ONLY); a max_hits within them:
            # every ray done in this pass, the nearest kept
            counts, part_flags, _, slot_cols = pass_.run(
                part, np.arange(m + 1, dtype=np.int64) * slots, slots_only=cap < 0 or cap > slots)
            mem = ctx.memory
            flat: list[cl.Buffer] = []
            sub_cols: list[cl.Buffer] = []
            try:
                keep = counts.astype(np.int64) if cap < 0 else np.minimum(counts, cap)
                offsets = _offsets(keep)
                flat = [mem.alloc(4 * max(int(offsets[-1]), 1)) for _ in dtypes]
                # the rays whose hits all fit their slots: moved from them on the device
                done = np.flatnonzero((keep <= slots) & (keep > 0))
                move_runs(ctx, slot_cols, flat, done * slots, offsets[done], keep[done])
                mem.free(*slot_cols)
                slot_cols = []
                # the others, traced again with room for all they keep
                again = np.flatnonzero(keep > slots)
                if len(again):
                    need = keep[again]
                    sub_offsets = _offsets(need)
                    _, sub_flags, _, sub_cols = pass_.run(_pick(part, again), sub_offsets)
                    part_flags[again] |= sub_flags
                    move_runs(ctx, sub_cols, flat, sub_offsets[:-1], offsets[again], need)
                out = tuple(dev.from_device(ctx, buf, t, (int(offsets[-1]),))
                            for buf, t in zip(flat, dtypes))
            finally:
                mem.free(*slot_cols, *sub_cols, *flat)
            pieces.append((out[0], out[3], out[1], out[2], *out[4:]))
        total[good[start:stop]] = counts
        flags[good[start:stop]] = part_flags
    if cap is None:
        return total, flags, None
    if pieces:
        kept = tuple(np.concatenate(c) for c in zip(*pieces))
    else:
        kept = tuple(np.zeros(0, t) for t in _returned(dtypes))
    return total, flags, kept


def first_slots(pass_: "_Pass", rays: Rays, cap: int) -> int:
    """Hit slots per ray for the collecting pass of ``rays`` (``cap``: the rays' hits
    kept, -1 for all): :data:`FIRST_SLOTS` for a batch of fewer than ``64
    SAMPLE_EVERY`` rays, else the :data:`SLOT_QUANTILE` quantile of the hit counts of
    one ray in :data:`SAMPLE_EVERY` (a counting pass over them) within
    :data:`SLOT_RANGE`; never more than ``cap``.

    Measured through ``bvh.all_hits`` against ``bvh.count_hits`` in the same process
    (262,144 rays from the box towards the surface, as the queries bench's, Zen 3): a
    counting and a collecting pass over every ray took 2.1-2.5 times a count on the
    bunny, Sponza and terrain-1m; 8 slots for every ray 1.3, 2.3 and 2.0 times (Sponza's
    rays have 16 hits on average, terrain-1m's 9); 16 slots 1.5, 1.9, 1.5; the sampled
    slots 1.4-1.5, 1.5-1.7, 1.3-1.4. ``all_hits`` against the two passes (e0142d1),
    alternating processes: 606, 630 -> 346, 336 ms on the bunny, 2954, 2181 -> 1352,
    1529 ms on Sponza, 3779, 3580 -> 2487, 2745 ms on terrain-1m, the same hits. Once
    only the kept hits were read back (:func:`move_runs`), the 0.97 quantile within 4
    to 64 slots against the 0.9 within 4 to 32: 1.07, 1.09, 1.10 (bunny, Sponza,
    terrain-1m; 7 rounds in one process; the 0.99 quantile 1.06, 1.07, 1.16): the
    rays traced again are the ones with the most hits, and the longest walks."""
    m = len(rays)
    if m < 64 * SAMPLE_EVERY:
        slots = FIRST_SLOTS
    else:
        counts = pass_.run(_pick(rays, np.arange(0, m, SAMPLE_EVERY)), None)[0]
        need = int(np.ceil(np.quantile(counts, SLOT_QUANTILE)))
        slots = int(np.clip(need, *SLOT_RANGE))
    # every column's slots within one of the device's largest buffers
    fit = pass_.ctx.memory.max_alloc // (4 * len(pass_.dtypes) * max(m, 1))
    slots = max(1, min(slots, fit))
    return slots if cap < 0 else min(slots, cap)


def _offsets(counts: np.ndarray) -> np.ndarray:
    """``int64 (len(counts) + 1,)``: where each ray's run of hits starts, and the end."""
    offsets = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    return offsets


def move_runs(ctx: dev.Context, src: list[cl.Buffer], dst: list[cl.Buffer],
              src_first: np.ndarray, dst_first: np.ndarray, count: np.ndarray) -> None:
    """Copy run k of every column, ``count[k]`` 32-bit words from ``src_first[k]`` of
    ``src[c]`` to ``dst_first[k]`` of ``dst[c]``, on the device (all_hits.cl
    move_runs; twin: :func:`move_runs_numpy`): the kept hits gathered from their slots
    into the flat arrays, so that only they are read back. Queued on the context's
    in-order queue; the caller reads ``dst`` after it."""
    runs = len(count)
    if runs == 0:
        return
    mem = ctx.memory
    bufs = [mem.upload(np.ascontiguousarray(src_first, np.int64)),
            mem.upload(np.ascontiguousarray(dst_first, np.int64)),
            mem.upload(np.ascontiguousarray(count, np.int32))]
    try:
        launch = ctx.launch(runs, min_per_item=1024)
        for s, d in zip(src, dst):
            dev.run(ctx, KERNEL_FILE, "move_runs", launch, s, d, *bufs, runs, launch.per_item,
                    defines={})
    finally:   # the in-order queue runs the moves before any later use of these buffers
        mem.free(*bufs)


def move_runs_numpy(src: np.ndarray, dst: np.ndarray, src_first: np.ndarray,
                    dst_first: np.ndarray, count: np.ndarray) -> None:
    """Twin of :func:`move_runs` for one column: ``dst`` written in place."""
    for a, b, n in zip(src_first, dst_first, count):
        dst[b:b + n] = src[a:a + n]


def _pick(rays: Rays, index: np.ndarray) -> Rays:
    """The rays ``index`` names (copies; one interval for all stays one)."""
    lo, hi, stride = rays.kernel_intervals()
    return Rays(rays.origins[index], rays.directions[index], lo[index] if stride else lo,
                hi[index] if stride else hi)


def _returned(dtypes: tuple) -> tuple:
    """The types of the columns run_passes returns (t, prim, u, v, ...) from the
    kernel's (t, u, v, prim, ...)."""
    return (dtypes[0], dtypes[3], dtypes[1], dtypes[2], *dtypes[4:])


@dataclass
class _Pass:
    """One kernel of all_hits.cl's arguments over a batch of checked rays."""
    ctx: dev.Context
    kernel_file: str
    kernel: str
    head: tuple
    defines: dict
    dtypes: tuple
    streams: int = 0   # the records' count where counting goes by streams, else 0

    def run(self, rays: Rays, offsets: np.ndarray | None, counters: bool = False,
            slots_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                               list[cl.Buffer]]:
        """Trace ``rays``: counting (``offsets`` None) or keeping ray i's nearest hits
        in slots ``[offsets[i], offsets[i + 1])``. Returns every ray's hit count, its
        flags, the counters (``counters``, counting only) and the kept columns (t, u, v,
        prim, ...: the kernel's order) as device buffers of ``offsets[-1]`` words,
        which the caller gives back to ``ctx.memory`` (none when counting)."""
        ctx, mem = self.ctx, self.ctx.memory
        m = len(rays)
        lo, hi, stride = rays.kernel_intervals()
        bufs = {"o": mem.upload(rays.origins), "d": mem.upload(rays.directions),
                "lo": mem.upload(np.ascontiguousarray(lo)),
                "hi": mem.upload(np.ascontiguousarray(hi)),
                "counts": mem.alloc(4 * m), "flags": mem.alloc(4 * m),
                "offsets": (mem.alloc(8) if offsets is None else mem.upload(offsets))}
        if counters:
            bufs["work"] = mem.alloc(16 * m)
        size = 0 if offsets is None else int(offsets[-1])
        out: list[cl.Buffer] = []
        launch = dev.Launch(m, 1, -(-m // _WORK_GROUP) * _WORK_GROUP, _WORK_GROUP)
        args = (*self.head, bufs["o"], bufs["d"], bufs["lo"], bufs["hi"], stride, m,
                bufs["offsets"], bufs["counts"])
        try:
            if offsets is not None:   # the kept hits' columns; counting writes none
                out = [mem.alloc(4 * max(size, 1)) for _ in self.dtypes]
            columns = out or [bufs["flags"]] * len(self.dtypes)
            defines = {**self.defines, "COUNT": int(offsets is None),
                       **({"COUNTERS": 1} if counters else {}),
                       **({"SLOTS_ONLY": 1} if slots_only else {})}
            if self.streams and not counters:   # either pass, as streams
                plan = stream_plan(ctx, m, self.streams)
                for name, nbytes in plan.buffers().items():
                    bufs[name] = mem.alloc(nbytes)
                dev.run(ctx, self.kernel_file, "stream_hits_kernel", plan.launch(), *args,
                        *columns, bufs["flags"], plan.per_chunk, bufs["rays"], bufs["slabs"],
                        bufs["scratch"], plan.scratch_words, defines=defines)
            else:
                dev.run(ctx, self.kernel_file, self.kernel, launch, *args, *columns,
                        bufs["flags"], bufs.get("work", bufs["flags"]), defines=defines)
            counts = dev.from_device(ctx, bufs["counts"], np.int32, (m,))
            flags = dev.from_device(ctx, bufs["flags"], np.int32, (m,))
            work = (dev.from_device(ctx, bufs["work"], np.int32, (m, 4)) if counters else None)
            kept, out = out, []
            return counts, flags, work, kept
        finally:
            mem.free(*out, *bufs.values())
