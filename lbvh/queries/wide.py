"""Wide records for the traversal (kernels/wide.cl).

The traversal kernel reads a tree through records of up to ``width``
children (Wald, Benthin, Boulos 2008; Dammertz, Hanika, Keller 2008): a
record keeps its children's boxes as six rows of ``width`` floats (lower x,
upper x, lower y, upper y, lower z, upper z) and their references as two rows
of ``width`` int32 (``x``, ``y``: a leaf child's node words, or an internal
child's record index and 0), so that one vector slab test covers every child
of a node. A visit then reads one record where the binary tree needs up to
``width - 1`` of them, and the ray takes half as many or fewer steps down.

Records are made on the device from any tree of the layout, on its first
query (:func:`make_wide`), and cached by :class:`lbvh.BVH`
(``bvh.wide_records()``); a refit rewrites their boxes in one launch and
keeps their lanes (:func:`write_records`). Each
starts from a binary internal node and opens the internal child of largest
surface area until it has ``width`` children; every internal child left
becomes a record. The greedy opening is decided in float32 exactly as the
numpy twin (:func:`wide_numpy`) decides it, so both give the same records,
up to their numbering: the device hands out record indices level by level
with an atomic counter.

``width`` is 8 on a CPU (a row is one AVX vector; on the 2-core machine,
primary rays through ``bvh.intersect`` are 1.4-1.8x as fast as through
binary records of two children on the bunny, Sponza and a 1M-triangle
terrain, and 8 lanes beat 4 by about 10%) and 4 elsewhere (a GPU traces
one ray per work-item, so the lanes are scalar work; not measured, no GPU was
lent to this project yet).
"""
from __future__ import annotations

from dataclasses import dataclass
import numpy as np
import pyopencl as cl

from .. import device as dev
from ..metrics.cost import box_scale, scaled_half_area
from ..layout import is_leaf
from ..tree import Tree

KERNEL_FILE = "wide.cl"

#: Children per record that kernels/wide.cl and kernels/traverse.cl accept.
WIDTHS = (4, 8)

_NO_BAD_NODE = np.iinfo(np.int32).max


def lane_defines(ctx: dev.Context) -> dict[str, int]:
    """The -D defines every walk through wide records takes for its lanes
    (kernels/wide_rows.h): ``CLANG_MOVMSK``, the lanes' bit mask by one
    ``vmovmskps``, and ``CLANG_CTZ``, the lowest lane by clang's count of trailing
    zeros, both where the compiler is clang (PoCL). Measured, old / new, Zen 3:
    closest hits 1.06-1.10x (the mask) and 1.04-1.13x (the count); winding
    numbers 1.04-1.11x and closest points 1.03-1.07x (both, bunny, Sponza,
    terrain-1m, bench/README.md)."""
    clang = int(ctx.compiler_is_clang)
    return {"CLANG_MOVMSK": clang, "CLANG_CTZ": clang}


def width_for(ctx: dev.Context) -> int:
    """Children per record on this device: 8 on a CPU, 4 elsewhere."""
    return 8 if ctx.is_cpu else 4


def record_bytes(width: int) -> int:
    """Bytes of one record: 8 rows of ``width`` 32-bit words."""
    return 32 * width


@dataclass
class Wide:
    """A tree's wide records on the device (see the module docstring).

    ``buffer`` holds ``count`` records of :func:`record_bytes` each, or is the
    tree's own node buffer when ``packed`` is False (records that could exceed
    the device's largest buffer: the kernel then walks the binary nodes).
    ``record_node`` (``int32 (count,)`` on the device, or None) is the binary
    node each record starts from; ``lanes`` (``int32 (count, width)``, -1 for
    an empty lane) the binary node of each lane and ``base`` (``int32
    (count,)``) the index of each record's first internal child: with them a
    refit rewrites the boxes without making the records again
    (:func:`write_records`). ``stack_need`` is the most stack entries an
    ordered traversal of the records can hold: over every root-to-record path,
    the sum of each record's children minus one. ``root_x``, ``root_y``: the
    root's reference in the records' encoding.
    """
    buffer: cl.Buffer
    packed: bool
    width: int
    count: int
    record_node: cl.Buffer | None
    stack_need: int
    root_x: int
    root_y: int
    lanes: cl.Buffer | None = None
    base: cl.Buffer | None = None


def _levels(tree: Tree, width: int, capacity: int) -> tuple[int, int, dict[str, cl.Buffer]]:
    """Run ``wide_level`` until no record is added: (records, stack need, buffers)."""
    ctx, memory = tree.ctx, tree.ctx.memory
    bufs = {"node": memory.alloc(4 * capacity), "need": memory.alloc(4 * capacity),
            "base": memory.alloc(4 * capacity), "lanes": memory.alloc(4 * width * capacity),
            "counters": memory.alloc(12)}
    queue = ctx.queue
    cl.enqueue_copy(queue, bufs["node"], np.int32([tree.root]), is_blocking=True)
    cl.enqueue_copy(queue, bufs["need"], np.int32([0]), is_blocking=True)
    counters = np.int32([1, 0, _NO_BAD_NODE])
    cl.enqueue_copy(queue, bufs["counters"], counters, is_blocking=True)
    begin, end = 0, 1
    scale = area_scale(*tree.root_box())
    while begin < end:
        launch = ctx.launch(end - begin, min_per_item=256, gpu_per_item=1)
        dev.run(ctx, KERNEL_FILE, "wide_level", launch, tree.nodes, tree.num_nodes, begin, end,
                capacity, launch.per_item, scale, bufs["node"], bufs["need"], bufs["base"],
                bufs["lanes"], bufs["counters"], defines={"WIDTH": width})
        cl.enqueue_copy(queue, counters, bufs["counters"], is_blocking=True)
        if counters[2] != _NO_BAD_NODE:
            memory.free(*bufs.values())
            bad = int(counters[2])
            if counters[0] > capacity:
                raise ValueError(f"tree: more than {capacity} internal nodes are reachable from "
                                 f"the root (node {bad} is reached twice: a cycle or a shared "
                                 f"child); the tree cannot be traversed")
            raise ValueError(f"tree: node {bad} has a child index outside "
                             f"[0, {tree.num_nodes}); the tree cannot be traversed")
        begin, end = end, int(counters[0])
    return end, int(counters[1]), bufs


def make_wide(tree: Tree, width: int | None = None, max_bytes: int | None = None) -> Wide:
    """The tree's wide records, made on the device (:class:`lbvh.BVH` caches them).

    Where records could exceed ``max_bytes`` (default: the device's largest
    buffer; the bound is one record per internal node) none are made: the
    kernel then reads the tree's own nodes. ``width`` (4 or 8) defaults to
    :func:`width_for`. The caller holds ``ctx.lock`` and gives the records
    back with :func:`release_wide`.
    """
    ctx = tree.ctx
    width = width_for(ctx) if width is None else width
    if width not in WIDTHS:
        raise ValueError(f"width: {width!r}; expected one of {WIDTHS}")
    if max_bytes is None:
        max_bytes = int(ctx.device.max_mem_alloc_size)
    root_x, root_y = tree.root_words()
    if root_y < 0:   # the root is a leaf: no records
        return Wide(ctx.memory.alloc(4), True, width, 0, None, 0, root_x, root_y)
    capacity = max(tree.num_nodes - tree.num_leaves, 1)
    if capacity * record_bytes(width) > max_bytes:   # records could not fit: walk the nodes
        return Wide(tree.nodes, False, width, 0, None, 0, tree.root, 0)
    count, need, bufs = _levels(tree, width, capacity)
    records = ctx.memory.alloc(count * record_bytes(width), pooled=True)
    kept = {}   # the level pass's arrays, cut to the records made
    for name, size in (("node", 4 * count), ("base", 4 * count), ("lanes", 4 * width * count)):
        kept[name] = ctx.memory.alloc(size)
        cl.enqueue_copy(ctx.queue, kept[name], bufs[name], byte_count=size)
    wide = Wide(records, True, width, count, kept["node"], need, 0, 0, kept["lanes"], kept["base"])
    write_records(tree, wide)
    ctx.queue.finish()
    ctx.memory.free(*bufs.values())
    return wide


def write_records(tree: Tree, wide: Wide) -> cl.Event | None:
    """(Re)write the records' boxes from the tree's nodes, keeping their lanes: after
    a refit (same topology, new boxes) one launch (the lanes were chosen by the old
    boxes' areas, which changes the speed of a query, never its answer)."""
    if not (wide.packed and wide.count):
        return None
    launch = tree.ctx.launch(wide.count, min_per_item=1024, gpu_per_item=1)
    return dev.run(tree.ctx, KERNEL_FILE, "wide_records", launch, tree.nodes, wide.count,
                   launch.per_item, wide.base, wide.lanes, wide.buffer,
                   defines={"WIDTH": wide.width})


def wide_buffers(wide: Wide) -> list[cl.Buffer]:
    """The buffers the records hold (none of the tree's own)."""
    if not wide.packed:
        return []
    return [b for b in (wide.buffer, wide.record_node, wide.lanes, wide.base) if b is not None]


def release_wide(memory: dev.DeviceMemory, wide: Wide) -> None:
    """Give the records back; their buffer goes to the pool, where the next
    :func:`make_wide` of the same size finds it."""
    if wide.packed:
        memory.free(wide.buffer, to_pool=True)
        memory.free(wide.record_node, wide.lanes, wide.base)


def read_records(ctx: dev.Context, wide: Wide) -> tuple[np.ndarray, np.ndarray]:
    """The device's records as ``float32 (count, 8, width)`` (rows 6-7 hold int32
    bits) and ``int32 (count,)`` binary node of each record (tests, debugging)."""
    records = np.empty((wide.count, 8, wide.width), np.float32)
    nodes = np.empty(wide.count, np.int32)
    if wide.count:
        cl.enqueue_copy(ctx.queue, records, wide.buffer, is_blocking=True)
        cl.enqueue_copy(ctx.queue, nodes, wide.record_node, is_blocking=True)
    return records, nodes


# -- numpy twin -----------------------------------------------------------------

@dataclass
class WideTwin:
    """What :func:`wide_numpy` makes: ``records`` ``float32 (R, 8, width)`` as on
    the device, ``record_node`` ``int32 (R,)``, ``lanes`` ``int32 (R, width)``
    (the binary node of each lane, -1 for an empty lane) and ``stack_need``.
    Records are numbered breadth first, lanes in order."""
    records: np.ndarray
    record_node: np.ndarray
    lanes: np.ndarray
    stack_need: int


def area_scale(lower: np.ndarray, upper: np.ndarray) -> np.float32:
    """The power of two kernels/wide.cl scales every box by before its area: common.h
    box_scale of the root's box ``lower, upper`` (``float32 (3,)``)."""
    return box_scale(np.float32(lower)[None], np.float32(upper)[None])[0, 0]


def _half_areas(nodes: np.ndarray, scale: np.float32) -> np.ndarray:
    """float32, as kernels/wide.cl half_area."""
    return scaled_half_area(nodes["lower"], nodes["upper"], scale)


def _open_lanes(lanes: np.ndarray, a: np.ndarray, b: np.ndarray, internal: np.ndarray,
                area: np.ndarray) -> np.ndarray:
    """One greedy step for every row with room for a lane: the internal lane of
    largest area (the first of equal ones) replaced by its two children, the
    later lanes moved right."""
    rows, width = lanes.shape
    safe = np.maximum(lanes, 0)
    candidate = (lanes >= 0) & internal[safe] & (area[safe] > -1.0)
    pick = np.argmax(np.where(candidate, area[safe], -np.inf), axis=1)
    opens = candidate.any(axis=1) & (lanes[:, -1] < 0)
    cols = np.arange(width)[None, :]
    p = pick[:, None]
    opened = safe[np.arange(rows), pick][:, None]
    moved = np.take_along_axis(lanes, np.where(cols <= p, cols, cols - 1), axis=1)
    out = np.where(cols == p, a[opened], np.where(cols == p + 1, b[opened], moved))
    return np.where(opens[:, None], out, lanes)


def wide_numpy(nodes: np.ndarray, root: int, width: int) -> WideTwin:
    """The numpy twin of kernels/wide.cl for a tree given as ``NODE_DTYPE`` nodes."""
    a, b = nodes["a"], nodes["b"]
    internal = ~is_leaf(nodes)
    area = _half_areas(nodes, area_scale(nodes["lower"][root], nodes["upper"][root]))
    empty = np.zeros((0,), np.int32)
    if not internal[root]:
        return WideTwin(np.zeros((0, 8, width), np.float32), empty,
                        np.zeros((0, width), np.int32), 0)
    level, level_need = np.int32([root]), np.int32([0])
    all_nodes, all_lanes, need = [], [], 0
    while len(level):
        lanes = np.full((len(level), width), -1, np.int32)
        lanes[:, 0], lanes[:, 1] = a[level], b[level]
        for _ in range(width - 2):
            lanes = _open_lanes(lanes, a, b, internal, area)
        used = (lanes >= 0).sum(axis=1)
        row_need = level_need + used - 1
        need = max(need, int(row_need.max()))
        all_nodes.append(level)
        all_lanes.append(lanes)
        inner = (lanes >= 0) & internal[np.maximum(lanes, 0)]
        level = lanes[inner].astype(np.int32)
        level_need = np.repeat(row_need, inner.sum(axis=1)).astype(np.int32)
    record_node = np.concatenate(all_nodes)
    lanes = np.concatenate(all_lanes)
    index = np.full(len(nodes), -1, np.int32)
    index[record_node] = np.arange(len(record_node), dtype=np.int32)
    records = np.zeros((len(record_node), 8, width), np.float32)
    present = lanes >= 0
    child = np.maximum(lanes, 0)
    lo, hi = nodes["lower"][child], nodes["upper"][child]
    for axis in range(3):
        records[:, 2 * axis] = np.where(present, lo[..., axis], np.float32(np.inf))
        records[:, 2 * axis + 1] = np.where(present, hi[..., axis], np.float32(-np.inf))
    inner = present & internal[child]
    ref_x = np.where(inner, index[child], np.where(present, a[child], 0)).astype(np.int32)
    ref_y = np.where(inner, 0, np.where(present, b[child], 0)).astype(np.int32)
    records[:, 6] = ref_x.view(np.float32)
    records[:, 7] = ref_y.view(np.float32)
    return WideTwin(records, record_node, lanes, need)
