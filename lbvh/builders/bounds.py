"""Stages 1-2: triangle boxes and the centroid bounds (kernels/bounds.cl).

The boxes (min/max of three vertices, exact) are stored as two float4 per
triangle in the caller's order; the bounds of their centres come from a
two-level reduction on the device.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..device import Context, Launch, MemoryTracker, run

KERNEL_FILE = "bounds.cl"


def triangle_bounds(ctx: Context, mem: MemoryTracker, vertices: cl.Buffer, faces: cl.Buffer,
                    n: int) -> tuple[cl.Buffer, cl.Buffer, list[cl.Event]]:
    """Device triangle boxes (``2n`` float4: lo, hi), the centroid box (2 float4) and the events."""
    launch = ctx.launch(n, gpu_per_item=-(-n // 4096))
    boxes = mem.alloc(32 * n, scratch=True)
    partial = mem.alloc(32 * launch.global_size, scratch=True)
    out = mem.alloc(32, scratch=True)
    ev1 = run(ctx, KERNEL_FILE, "triangle_bounds", launch, vertices, faces, n, launch.per_item,
              boxes, partial)
    ev2 = run(ctx, KERNEL_FILE, "reduce_boxes", Launch(1, 1, 1, 1), partial, launch.global_size,
              out)
    mem.free(partial)
    return boxes, out, [ev1, ev2]


def triangle_boxes_numpy(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin: ``float32 (F, 3)`` min and max corners of each triangle (exact)."""
    tri = vertices[faces]
    lo = np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2])
    hi = np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2])
    return lo, hi


def triangle_centres_numpy(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Numpy twin: ``float32 (F, 3)`` centres of the triangle boxes, same float ops as the kernel."""
    lo, hi = triangle_boxes_numpy(vertices, faces)
    half = np.float32(0.5)
    return lo * half + hi * half


def centroid_bounds_numpy(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Numpy twin: ``float32 (2, 3)``, min and max of the centres (exact)."""
    c = triangle_centres_numpy(vertices, faces)
    return np.stack([c.min(axis=0), c.max(axis=0)])


def round_outward(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float64 boxes rounded outwards to float32 (each corner to the nearest float32 on
    the outside), so that the float32 box holds the float64 one."""
    with np.errstate(over="ignore"):   # only where used: no finite float32 is beyond FLT_MAX
        lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
        lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
        hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32
