"""Stage 3: Morton codes of the triangle centroids (kernels/morton.cl).

Two widths: 30-bit codes (10 bits per axis) in ``uint32`` keys and 63-bit codes
(21 bits per axis) in ``uint64`` keys. ``"auto"`` starts with 30 bits and moves
to 63 when too many triangles share a code (see :func:`choose_key_bits`).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import pyopencl as cl

from ..device import Context, MemoryTracker, read_later, run

KERNEL_FILE = "morton.cl"
#: codes per vector in morton.cl (LANES): CPU chunks are whole multiples of it
LANES = 8

#: bits of code per axis for each key width
AXIS_BITS = {32: 10, 64: 21}
KEY_DTYPE = {32: np.dtype(np.uint32), 64: np.dtype(np.uint64)}

#: "auto" moves to 63-bit keys when more than this fraction of 30-bit codes are
#: duplicates. Measured on the shared scenes, bunny (5%), sphere and terrain
#: meshes (19-20%), Sibenik (33%) and Sponza (39%) build trees of the same SAH
#: cost with 30 and 63 bits; only heavy collisions such as Conference's (89%,
#: runs of up to 10,924 equal codes) call for the wider keys and their twice as
#: many sort passes.
AUTO_DUPLICATE_FRACTION = 0.5


def code_bits(key_bits: int) -> int:
    """Bits of Morton code held in a key of ``key_bits`` bits (30 or 63)."""
    return 3 * AXIS_BITS[key_bits]


def morton_codes(ctx: Context, mem: MemoryTracker, boxes: cl.Buffer,
                 centroid_box: cl.Buffer, n: int, key_bits: int, per_item: int | None = None
                 ) -> tuple[cl.Buffer, cl.Buffer, list[cl.Event]]:
    """Device keys (``uint32`` or ``uint64``) and values (triangle index) for ``n`` triangle boxes.

    ``per_item`` forces the chunk length (tests); by default the launch picks it.
    """
    keys = mem.alloc(n * KEY_DTYPE[key_bits].itemsize, scratch=True)
    values = mem.alloc(n * 4)
    launch = (ctx.launch(n, multiple=LANES) if per_item is None
              else ctx.launch_chunks(n, per_item))
    ev = run(ctx, KERNEL_FILE, "morton_codes", launch, boxes, centroid_box, n, launch.per_item,
             keys, values, defines={"KEY_BITS": key_bits})
    return keys, values, [ev]


def enqueue_count_duplicates(ctx: Context, mem: MemoryTracker, sorted_keys: cl.Buffer, n: int,
                             key_bits: int) -> tuple[Callable[[], int], list[cl.Event]]:
    """Queue the count of sorted keys equal to their predecessor and its read; the
    returned function waits for them and gives the count (it steers the build)."""
    launch = ctx.launch(n, gpu_per_item=-(-n // 4096))
    partial = mem.alloc(4 * launch.global_size, scratch=True)
    ev = run(ctx, KERNEL_FILE, "count_duplicates", launch, sorted_keys, n, launch.per_item,
             partial, defines={"KEY_BITS": key_bits})
    count = read_later(ctx, mem, partial, np.empty(launch.global_size, np.uint32), ev,
                       lambda c: int(c.sum(dtype=np.int64)))
    return count, [ev]


def count_duplicates(ctx: Context, mem: MemoryTracker, sorted_keys: cl.Buffer, n: int,
                     key_bits: int) -> tuple[int, list[cl.Event]]:
    """Number of sorted keys equal to their predecessor (read back: it steers the build)."""
    count, events = enqueue_count_duplicates(ctx, mem, sorted_keys, n, key_bits)
    return count(), events


def choose_key_bits(duplicates_30: int, n: int,
                    fraction: float = AUTO_DUPLICATE_FRACTION) -> tuple[int, str]:
    """The key width "auto" settles on after a 30-bit pass, and why."""
    limit = fraction * n
    if duplicates_30 > limit:
        return 64, (f"auto: {duplicates_30:,} of {n:,} 30-bit codes are duplicates, "
                    f"more than {fraction:.2%}; moved to 63 bits")
    return 32, (f"auto: {duplicates_30:,} of {n:,} 30-bit codes are duplicates, "
                f"at most {fraction:.2%}; kept 30 bits")


# -- numpy twins ----------------------------------------------------------------

def quantise_numpy(c: np.ndarray, lo: np.ndarray, hi: np.ndarray, axis_bits: int) -> np.ndarray:
    """Twin of quantise() in morton.cl: the same float32 operations, in numpy."""
    c, lo, hi = (np.asarray(x, np.float32) for x in (c, lo, hi))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        extent = hi - lo
        offset = c - lo
        huge = np.isinf(extent)
        half = np.float32(0.5)
        extent = np.where(huge, hi * half - lo * half, extent).astype(np.float32)
        offset = np.where(huge, c * half - lo * half, offset).astype(np.float32)
        safe = np.where(extent > 0, extent, np.float32(1))
        t = np.where(extent > 0, offset / safe, np.float32(0)).astype(np.float32)
        q = t * np.float32(1 << axis_bits)
        q = np.fmin(np.fmax(q, np.float32(0)), np.float32((1 << axis_bits) - 1))
    return q.astype(np.uint64)


def interleave_numpy(x: np.ndarray, y: np.ndarray, z: np.ndarray, axis_bits: int) -> np.ndarray:
    """Interleave bit by bit (x highest): a plain loop, independent of the kernel's magic masks."""
    code = np.zeros(len(x), np.uint64)
    for bit in range(axis_bits):
        for value, pos in ((x, 2), (y, 1), (z, 0)):
            code |= ((value >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + pos)
    return code


def morton_codes_numpy(centres: np.ndarray, bounds: np.ndarray, key_bits: int) -> np.ndarray:
    """Numpy twin of morton_codes: keys of dtype ``KEY_DTYPE[key_bits]``."""
    axis_bits = AXIS_BITS[key_bits]
    q = [quantise_numpy(centres[:, a], bounds[0, a], bounds[1, a], axis_bits) for a in range(3)]
    return interleave_numpy(*q, axis_bits).astype(KEY_DTYPE[key_bits])
