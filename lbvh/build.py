"""The device LBVH build: the six stages in order, data kept on the device throughout.

    bounds -> morton -> sort -> emit -> refit [-> restructure (treelet_rounds)]

The host reads back only scalars that decide which kernels run next: the
varying key bits (which sort passes to skip) and, with ``key_bits="auto"``,
the number of duplicate 30-bit codes.
"""
from __future__ import annotations

import time
from typing import Any

import pyopencl as cl

from . import device as dev
from .bounds import triangle_bounds
from .bvh import BVH
from .emit import emit_hierarchy
from .geometry import as_mesh
from .morton import (AUTO_DUPLICATE_FRACTION, choose_key_bits, enqueue_count_duplicates,
                     morton_codes)
from .refit import refit_from_boxes
from .report import PHASES, BuildReport
from .restructure import check_rounds, restructure_treelets
from .sort import enqueue_varying_bits, radix_sort

KEY_CHOICES = {"auto": None, 30: 32, 63: 64, "30": 32, "63": 64}


def _key_bits_of(key_bits: Any) -> int | None:
    try:
        return KEY_CHOICES[key_bits]
    except (KeyError, TypeError):
        raise ValueError(f"key_bits: {key_bits!r}; expected 30, 63 or 'auto'") from None


BUILDERS = ("lbvh", "sah")


def build(vertices: Any, faces: Any = None, *, builder: str = "lbvh",
          key_bits: int | str = "auto", device: Any = None,
          auto_duplicate_fraction: float = AUTO_DUPLICATE_FRACTION, treelet_rounds: int = 0,
          collapse: bool = False, **options: Any) -> BVH:
    """Build a BVH over a triangle mesh: the device LBVH, or the serial SAH reference.

    Args:
        vertices: ``(V, 3)`` float coordinates, or a ``trimesh.Trimesh`` (then no ``faces``).
        faces: ``(F, 3)`` integer vertex indices.
        builder: ``"lbvh"`` (device, Karras 2012) or ``"sah"`` (serial full-sweep SAH on
            the host, the reference; ``options`` go to :func:`lbvh.sah.build_sah`).
        key_bits: ``30`` (``uint32`` keys), ``63`` (``uint64`` keys) or ``"auto"``:
            30 bits unless more than ``auto_duplicate_fraction`` of the 30-bit codes
            are duplicates.
        device: a device name (see :mod:`lbvh.device`), a ``pyopencl.Device``, or
            ``None`` for ``$LBVH_DEVICE`` / PoCL's CPU device.
        treelet_rounds: ``"lbvh"`` only: rounds of treelet restructuring after the
            refit (:mod:`lbvh.restructure`, Karras & Aila 2013): a tree of lower SAH
            cost, hence faster rays, for a longer build; 0 (the default) keeps the
            Karras 2012 tree.
        collapse: ``"lbvh"`` only: after the build, merge subtrees into leaves where the
            SAH says testing their triangles is cheaper (:func:`lbvh.collapse.collapse_leaves`,
            ``options``: ``c_node``, ``c_tri``, ``max_leaf_size``).

    Returns:
        :class:`lbvh.BVH` whose buffers stay on the device. ``bvh.report()``
        gives the phase timings and tree statistics.

    Raises:
        ValueError: bad mesh (NaN/inf, out-of-range indices, non-triangles, empty,
            wrong shape or dtype) or bad option; nothing is built.
    """
    if builder not in BUILDERS:
        raise ValueError(f"builder: {builder!r}; expected one of {', '.join(BUILDERS)}")
    wanted = _key_bits_of(key_bits)
    rounds = check_rounds(treelet_rounds)
    v, f = as_mesh(vertices, faces)
    if builder == "sah":
        if rounds:
            raise ValueError("treelet_rounds: only for builder='lbvh' (the SAH builder's tree "
                             "is the reference)")
        if collapse:
            raise ValueError("collapse: only for builder='lbvh' (the SAH builder already makes "
                             "multi-triangle leaves)")
        from .sah import build_sah
        return build_sah(v, f, device=device, **options)
    if options and not collapse:
        raise ValueError(f"unknown option(s) for the lbvh builder: {', '.join(sorted(options))}")
    if collapse:
        _check_collapse_options(**options)
    ctx = dev.get_context(device)
    _check_fits(ctx, len(f))
    with ctx.lock:   # one call's commands at a time on the context's queue
        return _build_lbvh(ctx, v, f, wanted, auto_duplicate_fraction, rounds, collapse, options)


def _build_lbvh(ctx: dev.Context, v: np.ndarray, f: np.ndarray, wanted: int | None,
                auto_duplicate_fraction: float, rounds: int, collapse: bool,
                options: dict) -> BVH:
    t0 = time.perf_counter()
    vbuf, fbuf = dev.to_device(ctx, v), dev.to_device(ctx, f)
    ctx.queue.finish()
    upload = time.perf_counter() - t0
    bvh = build_on_device(ctx, v, f, vbuf, fbuf, wanted, auto_duplicate_fraction, rounds)
    bvh.build_report.upload_seconds = upload
    if collapse:
        from .collapse import collapse_leaves
        bvh = collapse_leaves(bvh, **options)
    return bvh


def _check_fits(ctx: dev.Context, num_triangles: int) -> None:
    """Refuse, before any upload, a mesh whose node buffer exceeds the device's largest buffer."""
    node_bytes = 32 * (2 * num_triangles - 1)
    limit = int(ctx.device.max_mem_alloc_size)
    if node_bytes > limit:
        raise dev.DeviceError(
            f"lbvh: {num_triangles:,} triangles need a {node_bytes:,}-byte node buffer, more than "
            f"{ctx.name}'s largest allocation ({limit:,} bytes); split the mesh or pick another "
            "device")


def _check_collapse_options(c_node: float = 1.0, c_tri: float = 1.0, max_leaf_size: int = 8,
                            **unknown: Any) -> None:
    """Reject bad collapse options before anything is built."""
    from .quality import check_sah_constants

    if unknown:
        raise ValueError(f"unknown option(s) for the leaf collapse: {', '.join(sorted(unknown))}")
    check_sah_constants(c_node, c_tri, max_leaf_size)


def _codes_and_mask(ctx: dev.Context, mem: dev.MemoryTracker, boxes: cl.Buffer, box: cl.Buffer,
                    n: int, bits: int, events: dict[str, list]):
    """Queue the Morton codes and the varying-bits read: (keys, values, what
    radix_sort's ``mask`` takes)."""
    keys, values, evs = morton_codes(ctx, mem, boxes, box, n, bits)
    events["morton"] += evs
    return keys, values, enqueue_varying_bits(ctx, mem, keys, n, bits)


def _sort_and_count(ctx: dev.Context, mem: dev.MemoryTracker, keys: cl.Buffer, values: cl.Buffer,
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


def build_on_device(ctx: dev.Context, vertices, faces, vbuf: cl.Buffer, fbuf: cl.Buffer,
                    key_bits: int | None, auto_duplicate_fraction: float = AUTO_DUPLICATE_FRACTION,
                    treelet_rounds: int = 0) -> BVH:
    """Build from a mesh already on the device (host copies kept for validation and views)."""
    n = len(faces)
    mem = dev.MemoryTracker(ctx)
    events: dict[str, list] = {phase: [] for phase in PHASES}
    t0 = time.perf_counter()

    # The host waits for the device twice: for the varying key bits (which
    # sort passes run; on the CPU those it expects are queued before it
    # waits) and for the duplicate count (30 or 63 bits). The commands
    # between waits are queued together (dev.queued_together).
    with dev.queued_together(ctx):
        boxes, box, evs = triangle_bounds(ctx, mem, vbuf, fbuf, n)
        events["bounds"] += evs
        bits = key_bits or 32
        keys, values, mask = _codes_and_mask(ctx, mem, boxes, box, n, bits, events)
    result, duplicates = _sort_and_count(ctx, mem, keys, values, n, bits, mask, events)
    passes = result.passes
    choice = f"fixed: {'63' if bits == 64 else '30'} bits asked for"
    if key_bits is None:
        bits, choice = choose_key_bits(duplicates, n, auto_duplicate_fraction)
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
        events["refit"] += refit_from_boxes(ctx, boxes, prim_order, nodes, parent, None, n,
                                            2 * n - 1, karras_ranges=True)
        mem.free(boxes)
        if treelet_rounds:
            cost = mem.alloc(4 * (2 * n - 1), scratch=True)
            arrivals = mem.alloc(4 * (2 * n - 1), scratch=True)
            events["restructure"] = restructure_treelets(
                ctx, nodes, parent, cost, arrivals, 2 * n - 1, 0, treelet_rounds, n - 1, n)
            mem.free(cost, arrivals)
    ctx.queue.finish()
    wall = time.perf_counter() - t0
    mem.close()

    phase_seconds = {phase: dev.event_seconds(evs) for phase, evs in events.items()}
    builder = f"lbvh+treelets{treelet_rounds}" if treelet_rounds else "lbvh"
    report = BuildReport(device=ctx.name, builder=builder, num_triangles=n, key_bits=bits,
                         key_choice=choice, duplicate_codes=duplicates,
                         phase_seconds=phase_seconds, device_seconds=sum(phase_seconds.values()),
                         wall_seconds=wall, sort_passes=passes,
                         peak_device_bytes=mem.peak, input_bytes=vertices.nbytes + faces.nbytes)
    return BVH(ctx, vertices, faces, vbuf, fbuf, nodes, parent, prim_order, 2 * n - 1, 0,
               builder, report, pooled=True)
