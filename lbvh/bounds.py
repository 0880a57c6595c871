"""Stages 1-2: triangle boxes and the centroid bounds (kernels/bounds.cl).

The triangle box is recomputed by each stage that needs it (min/max of three
vertices is exact), so this stage only produces the bounds of the centroids,
by a two-level reduction on the device.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from .device import Context, MemoryTracker

KERNEL_FILE = "bounds.cl"


def centroid_bounds(ctx: Context, mem: MemoryTracker, vertices: cl.Buffer, faces: cl.Buffer,
                    n: int) -> tuple[cl.Buffer, list[cl.Event]]:
    """Device buffer of two float4 (min, max of the triangle box centres) and the events."""
    launch = ctx.launch(n, gpu_per_item=-(-n // 4096))
    partial = mem.alloc(32 * launch.global_size)
    out = mem.alloc(32)
    ev1 = ctx.kernel(KERNEL_FILE, "centroid_bounds_partial")(ctx.queue, (launch.global_size,), launch.local,
                                       vertices, faces, np.int32(n), np.int32(launch.per_item),
                                       partial)
    ev2 = ctx.kernel(KERNEL_FILE, "reduce_boxes")(ctx.queue, (1,), (1,), partial, np.int32(launch.global_size), out)
    mem.free(partial)
    return out, [ev1, ev2]


def triangle_centres_numpy(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Numpy twin: ``float32 (F, 3)`` centres of the triangle boxes, same float ops as the kernel."""
    tri = vertices[faces]
    lo = np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2])
    hi = np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2])
    half = np.float32(0.5)
    return lo * half + hi * half


def centroid_bounds_numpy(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Numpy twin: ``float32 (2, 3)``, min and max of the centres (exact)."""
    c = triangle_centres_numpy(vertices, faces)
    return np.stack([c.min(axis=0), c.max(axis=0)])
