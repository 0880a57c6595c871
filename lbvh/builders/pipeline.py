"""The device LBVH build: the stages in order, data kept on the device throughout.

    bounds -> morton -> sort -> emit -> refit [-> restructure (treelet_rounds)]

:func:`build_tree` takes a :class:`~lbvh.tree.Mesh` on the device and
returns a :class:`~lbvh.tree.Tree` (``lbvh.build(builder="lbvh")`` wraps it
in a :class:`lbvh.BVH`). The host reads back only scalars that decide which
kernels run next: the varying key bits (which sort passes to skip) and, with
``key_bits="auto"``, the number of duplicate 30-bit codes.
"""
from __future__ import annotations

import dataclasses
import time

import pyopencl as cl

from .. import device as dev
from ..device.sort import enqueue_varying_bits, radix_sort
from ..report import PHASES, BuildReport
from ..tree import Mesh, Tree
from .bounds import triangle_bounds
from .emit import emit_hierarchy
from .morton import choose_key_bits, code_bits, enqueue_count_duplicates, morton_codes
from .options import LBVHOptions
from .refit import refit_from_boxes
from .restructure import restructure


def max_triangles(ctx: dev.Context) -> int:
    """The most triangles whose node buffer (32 bytes x (2F - 1)) fits the device's
    largest allocation (read from the device)."""
    return (int(ctx.device.max_mem_alloc_size) // 32 + 1) // 2


def fits(ctx: dev.Context, num_triangles: int) -> bool:
    """Whether a mesh of ``num_triangles`` builds in one tree on ``ctx``'s device."""
    return num_triangles <= max_triangles(ctx)


def check_fits(ctx: dev.Context, num_triangles: int) -> None:
    """Refuse, before any upload, a mesh whose node buffer exceeds the device's largest buffer."""
    node_bytes = 32 * (2 * num_triangles - 1)
    limit = int(ctx.device.max_mem_alloc_size)
    if node_bytes > limit:
        raise dev.DeviceError(
            f"lbvh: {num_triangles:,} triangles need a {node_bytes:,}-byte node buffer, more than "
            f"{ctx.name}'s largest allocation ({limit:,} bytes); split the mesh or pick another "
            "device")


def _codes_and_mask(ctx: dev.Context, mem: dev.Scope, boxes: cl.Buffer, box: cl.Buffer,
                    n: int, bits: int, events: dict[str, list]):
    """Queue the Morton codes and the varying-bits read: (keys, values, what
    radix_sort's ``mask`` takes)."""
    keys, values, evs = morton_codes(ctx, mem, boxes, box, n, bits)
    events["morton"] += evs
    return keys, values, enqueue_varying_bits(ctx, mem, keys, n, bits)


def _sort_and_count(ctx: dev.Context, mem: dev.Scope, keys: cl.Buffer, values: cl.Buffer,
                    n: int, bits: int, mask, events: dict[str, list]):
    """Sort the codes and count their duplicates; waits for the count (``mask``: from
    :func:`_codes_and_mask`). Not one queued_together block: radix_sort queues
    its passes behind its own, which opens before it waits for the mask, so
    that on the CPU the speculated passes follow key_bits without a gap."""
    result = radix_sort(ctx, mem, keys, values, n, bits, mask=mask)
    count, evs = enqueue_count_duplicates(ctx, mem, result.keys, n, bits)
    events["sort"] += result.events
    events["morton"] += evs
    return result, count()


def build_tree(ctx: dev.Context, mesh: Mesh, options: LBVHOptions = LBVHOptions(),
               mem: dev.Scope | None = None) -> Tree:
    """Build over a mesh already on the device; the caller holds ``ctx.lock``.

    ``mem``: the scope the build allocates in (default: a new one, closed at
    the end); the report's ``peak_device_bytes`` is its peak.
    """
    own_scope = mem is None
    if own_scope:
        mem = dev.MemoryTracker(ctx)
    n = mesh.num_prims
    key_bits = options.wanted_bits
    events: dict[str, list] = {phase: [] for phase in PHASES}
    t0 = time.perf_counter()

    # The host waits for the device twice: for the varying key bits (which
    # sort passes run; on the CPU those it expects are queued before it
    # waits) and for the duplicate count (30 or 63 bits). The commands
    # between waits are queued together (dev.queued_together).
    with dev.queued_together(ctx):
        boxes, box, evs = triangle_bounds(ctx, mem, mesh.vertices_buf, mesh.faces_buf, n)
        events["bounds"] += evs
        bits = key_bits or 32
        keys, values, mask = _codes_and_mask(ctx, mem, boxes, box, n, bits, events)
    result, duplicates = _sort_and_count(ctx, mem, keys, values, n, bits, mask, events)
    passes = result.passes
    choice = f"fixed: {'63' if bits == 64 else '30'} bits asked for"
    if key_bits is None:
        bits, choice = choose_key_bits(duplicates, n, options.auto_duplicate_fraction)
        if bits == 64:
            mem.free(result.keys, result.values)
            with dev.queued_together(ctx):
                keys, values, mask = _codes_and_mask(ctx, mem, boxes, box, n, 64, events)
            result, duplicates = _sort_and_count(ctx, mem, keys, values, n, 64, mask, events)
            passes += result.passes
    mem.free(box)

    with dev.queued_together(ctx):
        nodes, parent, evs = emit_hierarchy(ctx, mem, result.keys, n, bits, write_leaves=False)
        events["emit"] += evs
        mem.free(result.keys)
        prim_order = result.values
        tree = Tree(ctx, nodes, parent, prim_order, root=0, num_nodes=2 * n - 1, num_prims=n,
                    builder="lbvh")
        events["refit"] += refit_from_boxes(tree, boxes, None, karras_ranges=True)
        mem.free(boxes)
        tree, evs = restructure(tree, options.treelet_rounds, mem,
                                leaves=options.treelet_leaves,
                                min_leaves=options.treelet_min_leaves)
        if evs:
            events["restructure"] = evs
    ctx.queue.finish()
    wall = time.perf_counter() - t0
    if own_scope:
        mem.close()

    phase_seconds = {phase: dev.event_seconds(evs) for phase, evs in events.items()}
    report = BuildReport(device=ctx.name, builder=tree.builder, num_triangles=n,
                         key_bits=code_bits(bits),
                         key_choice=choice, duplicate_codes=duplicates,
                         phase_seconds=phase_seconds, device_seconds=sum(phase_seconds.values()),
                         wall_seconds=wall, sort_passes=passes, peak_device_bytes=mem.peak,
                         input_bytes=mesh.vertices.nbytes + mesh.faces.nbytes)
    return dataclasses.replace(tree, report=report)
