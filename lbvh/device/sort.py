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

from .context import Context, queued_together
from .launch import run
from .memory import MemoryTracker, read_later, to_device

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
    ev = run(ctx, KERNEL_FILE, "key_bits", launch, keys, n, launch.per_item, and_or,
             defines=kernel_defines(key_bits, ctx.is_cpu))
    mask = read_later(ctx, mem, and_or, np.empty((2, launch.global_size), dtype), ev,
                      lambda p: int(np.bitwise_and.reduce(p[0])) ^ int(np.bitwise_or.reduce(p[1])))
    return VaryingBits(mask, [ev], and_or, launch.global_size)


def kernel_defines(key_bits: int, is_cpu: bool, radix_bits: int = 8) -> dict[str, int]:
    """The -D defines kernels/sort.cl is compiled with for these keys and device kind."""
    return {"KEY_BITS": key_bits, "RADIX_BITS": radix_bits, "LOCAL_BITS": LOCAL_BITS,
            "SCRATCH_BYTES": SCRATCH_BYTES if is_cpu else 16}


#: Digit width of the in-cache passes of the CPU path: 10 bits measured best
#: against 6 and 8 on 1M Morton keys (two passes below an 11-bit MSD digit).
LOCAL_BITS = 10
#: Half of sort_buckets' private scratch on a CPU: buckets of up to 8192
#: 32-bit-key records sort there (the CPU path's two passes of 30-bit keys).
SCRATCH_BYTES = 1 << 16
#: Keys per work-item on a GPU, at least: each work-item keeps 2^RADIX_BITS
#: counters (4 bytes each), which one or two keys a work-item (as before) made
#: 512 bytes a key, 560 bytes a triangle in the bunny's build on an NVIDIA H200
#: (bench/results/device-nvidia-cuda-*); with 64, 16 bytes a key.
GPU_MIN_KEYS = 64
#: Fewer keys than this are sorted by plain LSD passes.
MSD_MIN_KEYS = 1 << 16


def msd_plan(mask: int, n: int, radix_bits: int, is_cpu: bool) -> tuple[int, list[int]] | None:
    """CPU path for long keys: the shift of one MSD digit over the highest varying
    bits, and the shifts of the in-cache LSD passes below it (kernels/sort.cl,
    scatter_records and sort_buckets); ``None`` where plain LSD passes are as
    good (a GPU, few keys, or one digit covering every varying bit)."""
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
               key_bits: int, *, radix_bits: int | None = None,
               mask: VaryingBits | None = None) -> SortResult:
    """Sort pairs stably by key. Returns the buffers holding the result (inputs or new ones).

    ``keys`` and ``values`` must be writable: the passes use them as scratch.
    The sort's own buffers and the inputs that do not hold the result are given
    back to ``mem``. ``radix_bits`` overrides the device's digit width
    (:func:`radix_bits_for`). ``mask``: where the caller has queued the
    varying-bits read already, what :func:`enqueue_varying_bits` returned;
    else the read is queued here.

    On the CPU path (:func:`msd_plan`) the passes for :func:`expected_mask` are
    queued before the host has read the real mask, and check it on the device:
    the host does not wait between key_bits and the passes. Where the mask is
    another, those passes do nothing and the plan for the real mask runs.
    """
    varying = mask or enqueue_varying_bits(ctx, mem, keys, n, key_bits)
    sort = _Sort(ctx, mem, keys, values, n, key_bits, radix_bits or radix_bits_for(ctx))
    events = list(varying.events)
    guess = expected_mask(key_bits)
    plan = msd_plan(guess, n, sort.radix_bits, ctx.is_cpu)
    if plan is not None:
        guard = (varying.partials, np.int32(varying.count), sort.key_type(guess))
        speculated = sort.enqueue_msd(plan, guard, events)
    # result() gives the partials back to the pool while the speculated passes
    # may still have to read them: safe on the in-order queue, which runs them
    # before any later command that reuses the buffer.
    bits = varying.result()
    if plan is not None and bits == guess:
        result = speculated
    else:   # the speculated passes, if any, did nothing
        shifts = digit_shifts(bits, key_bits, sort.radix_bits)
        plan = msd_plan(bits, n, sort.radix_bits, ctx.is_cpu)
        if plan is not None:
            result = sort.enqueue_msd(plan, (sort.counts, np.int32(0), sort.key_type(0)), events)
        elif shifts and n >= 2:
            result = sort.enqueue_lsd(shifts, events)
        else:
            result = SortResult(keys, values, 0, events)
    returned = {id(result.keys), id(result.values)}
    mem.free(*[buf for buf in sort.own if id(buf) not in returned])
    mem.free(*[buf for buf in (keys, values) if id(buf) not in returned])
    return result


class _Sort:
    """The buffers and kernels of one radix_sort call."""

    def __init__(self, ctx: Context, mem: MemoryTracker, keys: cl.Buffer, values: cl.Buffer,
                 n: int, key_bits: int, radix_bits: int) -> None:
        self.ctx, self.mem, self.keys, self.values, self.n = ctx, mem, keys, values, n
        self.key_bits, self.radix_bits = key_bits, radix_bits
        self.key_type = np.uint64 if key_bits == 64 else np.uint32
        defines = kernel_defines(key_bits, ctx.is_cpu, radix_bits)
        self.kernels = {name: ctx.kernel(KERNEL_FILE, name, defines) for name in
                        ("digit_histogram", "scan_counts", "scatter", "scatter_records",
                         "sort_buckets")}
        self.launch = ctx.launch(n, min_per_item=4096,
                                 gpu_per_item=max(GPU_MIN_KEYS, -(-n // 65536)))
        self.counts = mem.alloc(4 * (1 << radix_bits) * self.launch.global_size, scratch=True)
        self.totals = mem.alloc(4 * (1 << radix_bits), scratch=True)
        #: every buffer this sort allocated
        self.own = [self.counts, self.totals]

    def alloc(self, nbytes: int, scratch: bool = True) -> cl.Buffer:
        buf = self.mem.alloc(nbytes, scratch=scratch)
        self.own.append(buf)
        return buf

    def _count_and_scan(self, keys: cl.Buffer, shift: int, guard: tuple, events: list) -> None:
        """Queue the digit histogram of each chunk and their scan."""
        chunks, launch = self.launch.global_size, self.launch
        events.append(self.kernels["digit_histogram"](
            self.ctx.queue, (chunks,), launch.local, keys, np.int32(self.n),
            np.int32(launch.per_item), np.int32(shift), np.int32(chunks), self.counts, *guard))
        events.append(self.kernels["scan_counts"](
            self.ctx.queue, (1 << self.radix_bits,), None if self.ctx.is_cpu else (64,),
            self.counts, np.int32(chunks), self.totals))

    def enqueue_msd(self, plan: tuple[int, list[int]], guard: tuple, events: list) -> SortResult:
        """Queue the CPU path (kernels/sort.cl): one MSD pass into records, then
        sort_buckets back into the input buffers; ``guard``: (partials, count,
        expected mask) that the kernels check, count 0 for none."""
        top, local_shifts = plan
        chunks, launch, n = self.launch.global_size, self.launch, np.int32(self.n)
        record_bytes = 8 if self.key_bits == 32 else 16
        records = self.alloc(self.n * record_bytes)
        # The bucket passes' shifts are copied when the buffer is made: no command.
        local = to_device(self.ctx, np.int32(local_shifts))
        with queued_together(self.ctx):
            self._count_and_scan(self.keys, top, guard, events)
            events.append(self.kernels["scatter_records"](
                self.ctx.queue, (chunks,), launch.local, self.keys, self.values, records, n,
                np.int32(launch.per_item), np.int32(top), np.int32(chunks), self.counts,
                self.totals, *guard))
            events.append(self.kernels["sort_buckets"](
                self.ctx.queue, (chunks,), launch.local, records, self.keys, self.values, n,
                np.int32(launch.per_item), self.totals, local, np.int32(len(local_shifts)),
                *guard))
        local.release()   # the runtime keeps it until the kernel is done
        return SortResult(self.keys, self.values, 1 + len(local_shifts), events)

    def enqueue_lsd(self, shifts: list[int], events: list) -> SortResult:
        """Queue one LSD pass per shift, alternating between the inputs and a second pair."""
        chunks, launch, n = self.launch.global_size, self.launch, np.int32(self.n)
        itemsize = 8 if self.key_bits == 64 else 4
        src = (self.keys, self.values)
        dst = (self.alloc(self.n * itemsize), self.alloc(self.n * 4, scratch=False))
        no_guard = (self.counts, np.int32(0), self.key_type(0))
        with queued_together(self.ctx):
            for shift in shifts:
                self._count_and_scan(src[0], shift, no_guard, events)
                events.append(self.kernels["scatter"](
                    self.ctx.queue, (chunks,), launch.local, src[0], src[1], dst[0], dst[1], n,
                    np.int32(launch.per_item), np.int32(shift), np.int32(chunks), self.counts,
                    self.totals))
                src, dst = dst, src
        return SortResult(src[0], src[1], len(shifts), events)


def radix_sort_numpy(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin: a stable sort of the pairs by key."""
    order = np.argsort(keys, kind="stable")
    return keys[order], values[order]
