"""The ray-sampled cost of a tree: its cost weighed by the rays it will trace, not by area.

The SAH cost (:func:`lbvh.metrics.quality.sah_cost`) weighs every node by
the probability that a uniformly distributed ray meeting the root meets the
node, its area over the root's (MacDonald & Booth 1990). Camera rays are not
uniform, and a closest-hit ray stops at its hit; so the SAH can rank trees
unlike their render times (Aila, Karras & Laine 2013). The ray-sampled cost
(the simple form of Nabata et al. 2013's idea) weighs each node instead by the
fraction of sampled rays whose segment from ``tmin`` to the closest hit enters
it::

    C_rays = mean over the rays of (C_NODE * inner nodes entered + C_TRI * triangles
             in the leaves entered)

in the units of the SAH cost. Whatever its order, a closest-hit traversal
of the tree must enter every one of those nodes (each may hold a nearer
hit until it is opened), so this is the work the tree forces on those rays;
an ordered traversal adds only the nodes it opens before it finds the hit.

:func:`ray_sampled_cost` counts on the device (kernels/all_hits.cl with
``COUNTERS=1``, :func:`lbvh.queries.all_hits.segment_work`); its twin
:func:`segment_work_numpy` replays the kernel's float32 slab test over every
node in numpy, and the two agree exactly.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..metrics.cost import C_NODE, C_TRI
from ..layout import is_leaf, node_depths, parents_of, prim_range_of
from ..queries.all_hits import segment_work
from ..queries.rays import check_rays
from ..queries.traverse import slab_pad


@dataclass(frozen=True)
class RayCost:
    """What :func:`ray_sampled_cost` measured, per ray on average.

    Attributes:
        cost: ``c_node * inner + c_tri * triangles`` (the SAH cost's units).
        inner: internal nodes entered; ``leaves``: leaves entered;
        triangles: triangles in the leaves entered.
        rays: how many rays were sampled.
    """
    cost: float
    inner: float
    leaves: float
    triangles: float
    rays: int


def ray_sampled_cost(bvh: Any, origins: Any, directions: Any, tmin: Any = 0.0, *,
                     c_node: float = C_NODE, c_tri: float = C_TRI) -> RayCost:
    """The ray-sampled cost of ``bvh`` (an :class:`lbvh.BVH`) for these rays (see the
    module docstring); each ray's segment ends at its closest hit (``inf`` on a miss)."""
    hits = bvh.intersect(origins, directions, tmin)
    work = segment_work(bvh, origins, directions, tmin, hits.t).astype(np.float64)
    inner, leaves, tris = work.mean(axis=0) if len(work) else (0.0, 0.0, 0.0)
    return RayCost(float(c_node * inner + c_tri * tris), float(inner), float(leaves),
                   float(tris), len(work))


def segment_work_numpy(nodes: np.ndarray, root: int, origins: Any, directions: Any,
                       tmin: Any, tmax: Any, pad: float) -> np.ndarray:
    """The twin of :func:`lbvh.queries.all_hits.segment_work` for rays whose largest
    direction component lies in ``[2^-60, 2^60]`` (the kernel scales the others):
    ``int32 (N, 3)`` inner nodes, leaves and triangles entered, by the kernel's slab
    test in float32 (``pad`` its SLAB_PAD) over every node, a node entered only where
    its parent is."""
    rays = check_rays(origins, directions, tmin, tmax)
    o, d = rays.origins, rays.directions
    lo_t, hi_t = rays.intervals()
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        inv = (np.float32(1) / d).astype(np.float32)
        big = np.float32(np.finfo(np.float32).max)
        inv_near = np.where((d != 0) & np.isinf(inv), np.copysign(big, d), inv).astype(np.float32)
        neg = np.signbit(d)
        lower, upper = nodes["lower"], nodes["upper"]
        t0 = np.broadcast_to(lo_t[:, None], (len(o), len(nodes))).astype(np.float32)
        t1 = np.full((len(o), len(nodes)), np.inf, np.float32)
        for k in range(3):
            near = np.where(neg[:, k:k + 1], upper[None, :, k], lower[None, :, k])
            far = np.where(neg[:, k:k + 1], lower[None, :, k], upper[None, :, k])
            a = ((near - o[:, k:k + 1]) * inv_near[:, k:k + 1]).astype(np.float32)
            t0 = np.where(a > t0, a, t0)
            b = ((far - o[:, k:k + 1]) * inv[:, k:k + 1]).astype(np.float32)
            t1 = np.where(b < t1, b, t1)
        limit = np.where(t1 < hi_t[:, None], t1, hi_t[:, None]).astype(np.float32)
        passes = t0 <= (limit * np.float32(pad)).astype(np.float32)
    parent = parents_of(nodes, root)
    depth = node_depths(parent, root)
    entered = passes.copy()
    for level in range(1, int(depth.max()) + 1 if len(nodes) > 1 else 1):
        at = np.flatnonzero(depth == level)
        entered[:, at] &= entered[:, parent[at]]
    leaf = is_leaf(nodes)
    counts = prim_range_of(nodes)[:, 1]
    return np.stack([entered[:, ~leaf].sum(axis=1), entered[:, leaf].sum(axis=1),
                     (entered[:, leaf] * counts[leaf]).sum(axis=1)], axis=1).astype(np.int32)


def device_pad(bvh: Any) -> float:
    """The SLAB_PAD the device's kernels use (for :func:`segment_work_numpy`)."""
    return float.fromhex(slab_pad(bvh.ctx).rstrip("f"))
