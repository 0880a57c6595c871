"""Stage 4: stable LSD radix sort of (key, value) pairs on the device (kernels/sort.cl).

Usable on its own: :func:`radix_sort` sorts ``uint32`` or ``uint64`` keys with
``uint32`` values already on the device, skipping every digit pass whose bits
are the same in all keys.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import pyopencl as cl

from .device import Context, MemoryTracker, queued_together, read_later, to_device

KERNEL_FILE = "sort.cl"


def radix_bits_for(ctx: Context) -> int:
    """Digit width: 11 bits on a CPU (3 passes for 30-bit keys, 6 for 63-bit; a
    chunk's 2048 counters fit in its core's cache), 8 bits on a GPU (256
    counters per work-item stay in fast memory)."""
    return 11 if ctx.is_cpu else 8


@dataclass
class SortResult:
    keys: cl.Buffer
    values: cl.Buffer
    passes: int
    events: list


@dataclass
class VaryingBits:
    """The queued key_bits kernel: ``result()`` waits for the read of its partial
    ANDs and ORs and gives the mask of the bits that vary; ``partials`` holds
    ``count`` ANDs then ``count`` ORs on the device (read by speculative passes)."""
    result: Callable[[], int]
    events: list
    partials: cl.Buffer
    count: int


def enqueue_varying_bits(ctx: Context, mem: MemoryTracker, keys: cl.Buffer, n: int,
                         key_bits: int) -> VaryingBits:
    """Queue the key_bits kernel and the read of its partial ANDs and ORs."""
    dtype = np.uint64 if key_bits == 64 else np.uint32
    launch = ctx.launch(n, gpu_per_item=-(-n // 4096))
    and_or = mem.alloc(2 * launch.global_size * np.dtype(dtype).itemsize, scratch=True)
    ev = ctx.kernel(KERNEL_FILE, "key_bits", _defines(key_bits))(
        ctx.queue, (launch.global_size,), launch.local, keys, np.int32(n),
        np.int32(launch.per_item), and_or)
    mask = read_later(ctx, mem, and_or, np.empty((2, launch.global_size), dtype), ev,
                      lambda p: int(np.bitwise_and.reduce(p[0])) ^ int(np.bitwise_or.reduce(p[1])))
    return VaryingBits(mask, [ev], and_or, launch.global_size)


def _defines(key_bits: int, radix_bits: int = 8) -> dict[str, int]:
    return {"KEY_BITS": key_bits, "RADIX_BITS": radix_bits, "LOCAL_BITS": LOCAL_BITS}


#: Digit width of the in-cache passes of the CPU path: 10 bits measured best
#: against 6 and 8 on 1M Morton keys (two passes below an 11-bit MSD digit).
LOCAL_BITS = 10
#: Fewer keys than this are sorted by plain LSD passes.
MSD_MIN_KEYS = 1 << 16


def msd_plan(mask: int, n: int, radix_bits: int, is_cpu: bool) -> tuple[int, list[int]] | None:
    """CPU path for long keys: the shift of one MSD digit over the highest varying
    bits, and the shifts of the in-cache LSD passes below it (kernels/sort.cl,
    sort_buckets); ``None`` where plain LSD passes are as good (a GPU, few keys,
    or one digit covering every varying bit)."""
    if not is_cpu or n < MSD_MIN_KEYS:
        return None
    top = max(mask.bit_length() - radix_bits, 0)
    below = mask & ((1 << top) - 1)
    if not below:
        return None
    local_mask = (1 << LOCAL_BITS) - 1
    return top, [s for s in range(0, top, LOCAL_BITS) if (below >> s) & local_mask]


def digit_shifts(mask: int, key_bits: int, radix_bits: int) -> list[int]:
    """Shifts of the digit passes that must run: those whose digit bits vary."""
    digit = (1 << radix_bits) - 1
    return [s for s in range(0, key_bits, radix_bits) if (mask >> s) & digit]


def expected_mask(key_bits: int) -> int:
    """The varying bits that the sort speculates on: all bits of a 30-bit
    (``uint32`` keys) or 63-bit (``uint64``) Morton code, as in any mesh of
    more than a few triangles."""
    return (1 << (63 if key_bits == 64 else 30)) - 1


def radix_sort(ctx: Context, mem: MemoryTracker, keys: cl.Buffer, values: cl.Buffer, n: int,
               key_bits: int, free_inputs: bool = True, radix_bits: int | None = None,
               mask: VaryingBits | None = None) -> SortResult:
    """Sort pairs stably by key. Returns the buffers holding the result (inputs or new ones).

    ``keys`` and ``values`` must be writable: the passes use them as scratch.
    With ``free_inputs`` the buffers not returned are released as soon as the
    sort no longer needs them. ``radix_bits`` overrides the device's digit width
    (:func:`radix_bits_for`). ``mask``: where the caller has queued the
    varying-bits read already, what :func:`enqueue_varying_bits` returned;
    else the read is queued here.

    On the CPU path (:func:`msd_plan`) the passes for :func:`expected_mask` are
    queued before the host has read the real mask, and check it on the device:
    the host does not wait between key_bits and the passes. Where the mask is
    another, those passes do nothing and the plan for the real mask runs.
    """
    varying = mask or enqueue_varying_bits(ctx, mem, keys, n, key_bits)
    radix_bits = radix_bits or radix_bits_for(ctx)
    defines = _defines(key_bits, radix_bits)
    kernels = [ctx.kernel(KERNEL_FILE, name, defines)
               for name in ("digit_histogram", "scan_counts", "scatter", "sort_buckets")]
    itemsize = 8 if key_bits == 64 else 4
    key_type = np.uint64 if key_bits == 64 else np.uint32
    launch = ctx.launch(n, min_per_item=4096, gpu_per_item=max(1, -(-n // 65536)))
    counts = mem.alloc(4 * (1 << radix_bits) * launch.global_size, scratch=True)
    totals = mem.alloc(4 * (1 << radix_bits), scratch=True)
    pair = (keys, values), (mem.alloc(n * itemsize, scratch=True), mem.alloc(n * 4))
    events = list(varying.events)
    guess = expected_mask(key_bits)
    plan = msd_plan(guess, n, radix_bits, ctx.is_cpu)
    if plan is not None:
        guard = (varying.partials, np.int32(varying.count), key_type(guess))
        speculated = _enqueue_plan(ctx, kernels, radix_bits, launch, n, plan, [], pair, counts,
                                   totals, guard, events)
    # result() gives the partials back to the pool while the speculated passes
    # may still have to read them: safe on the in-order queue, which runs them
    # before any later command that reuses the buffer.
    bits = varying.result()
    if plan is not None and bits == guess:
        (src, dst), passes = speculated, 1 + len(plan[1])
    else:
        shifts = digit_shifts(bits, key_bits, radix_bits)
        if not shifts or n < 2:
            mem.free(counts, totals, *pair[1])
            return SortResult(keys, values, 0, events)
        plan = msd_plan(bits, n, radix_bits, ctx.is_cpu)
        guard = (counts, np.int32(0), key_type(0))   # no check
        src, dst = _enqueue_plan(ctx, kernels, radix_bits, launch, n, plan, shifts, pair, counts,
                                 totals, guard, events)
        passes = len(shifts) if plan is None else 1 + len(plan[1])
    mem.free(counts, totals)
    if free_inputs:
        mem.free(*dst)
    return SortResult(src[0], src[1], passes, events)


def _enqueue_plan(ctx: Context, kernels: list[cl.Kernel], radix_bits: int, launch, n: int,
                  plan: tuple[int, list[int]] | None, shifts: list[int], pair, counts: cl.Buffer,
                  totals: cl.Buffer, guard: tuple, events: list[cl.Event]):
    """Queue the passes of ``plan`` (:func:`msd_plan`), or the LSD passes at
    ``shifts`` where it is ``None``, behind one barrier; ``guard``: (partials,
    count, expected mask) that the kernels check, count 0 for none."""
    # The bucket passes' shifts are copied when the buffer is made: no command.
    local = None if plan is None else to_device(ctx, np.int32(plan[1]))
    with queued_together(ctx):
        src_dst = _enqueue_passes(ctx, kernels, radix_bits, launch, n,
                                  shifts if plan is None else [plan[0]],
                                  None if plan is None else len(plan[1]),
                                  pair, counts, totals, local, guard, events)
    if local is not None:
        local.release()   # the runtime keeps it until the kernel is done
    return src_dst


def _enqueue_passes(ctx: Context, kernels: list[cl.Kernel], radix_bits: int, launch, n: int,
                    shifts: list[int], num_local: int | None, pair, counts: cl.Buffer,
                    totals: cl.Buffer, local: cl.Buffer | None, guard: tuple,
                    events: list[cl.Event]):
    """Queue the digit passes at ``shifts`` and, with ``num_local``, the bucket
    passes of the CPU path; returns ((keys, values) holding the result, the other pair)."""
    chunks = launch.global_size
    radix = 1 << radix_bits
    hist_k, scan_k, scatter_k, buckets_k = kernels
    scan_local = None if ctx.is_cpu else (64,)
    src, dst = pair
    for shift in shifts:
        events.append(hist_k(ctx.queue, (chunks,), launch.local, src[0], np.int32(n),
                             np.int32(launch.per_item), np.int32(shift), np.int32(chunks), counts,
                             *guard))
        events.append(scan_k(ctx.queue, (radix,), scan_local, counts, np.int32(chunks), totals))
        events.append(scatter_k(ctx.queue, (chunks,), launch.local, src[0], src[1], dst[0], dst[1],
                                np.int32(n), np.int32(launch.per_item), np.int32(shift),
                                np.int32(chunks), counts, totals, *guard))
        src, dst = dst, src
    if num_local is not None:
        events.append(buckets_k(
            ctx.queue, (chunks,), launch.local, src[0], src[1], dst[0], dst[1], np.int32(n),
            np.int32(launch.per_item), totals, local, np.int32(num_local), *guard))
        if num_local % 2:
            src, dst = dst, src
    return src, dst


def radix_sort_numpy(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin: a stable sort of the pairs by key."""
    order = np.argsort(keys, kind="stable")
    return keys[order], values[order]
