"""Spatial splits: the SBVH of Stich, Friedrich & Dietrich 2009, a host reference.

Top down over *references* (a triangle and a box holding the part of it that
the node owns; at the root every triangle's own box). At every node:

* the best object split: the full SAH sweep over the references sorted by
  the centres of their boxes, on each axis (as :mod:`lbvh.builders.sah`);
* if the two sides of that split overlap by more than ``alpha`` times the
  root's area (Stich et al., section 4.4), the best spatial split: on each
  axis ``bins`` equal slabs of the node's box; every reference is clipped to
  each slab it spans (the triangle's polygon cut by the slab's planes, its box
  met with the reference's), the slabs' boxes and the references entering and
  leaving them swept left to right as in section 4.3, and a plane between two
  slabs costed as ``A(L) |L| + A(R) |R|`` with a straddling reference counted
  on both sides;
* the cheaper of the two wins (the SAH of Wald 2007, eq. 2, with the cost
  constants of :mod:`lbvh.metrics.cost`), or a leaf where it is cheaper than
  both and holds at most ``max_leaf_size`` references; a spatial split sends a
  straddling reference to both sides, each with the box of its part.

A triangle may then sit in several leaves: ``prim_order`` holds one slot per
reference (longer than the mesh), and a leaf's box holds the parts of its
triangles, not their whole boxes (docs/pages/layout.md: "spatial splits"). The
boxes are computed in float64 and rounded outwards to float32, so every part
of every triangle lies in the box of a leaf that references it. The number of
references is kept below ``max_growth`` times the triangles (spatial splits
stop beyond it), and a split that sends every reference to both sides is
never taken, so the build ends.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from .. import device as dev
from ..layout import NODE_DTYPE, parents_of
from ..progress import bar as progress_bar
from ..report import BuildReport
from ..tree import Mesh, Tree, upload_tree
from ..layout import is_leaf
from .bounds import round_outward
from ..metrics.cost import box_area
from .options import SAHOptions, SBVHOptions
from .sah import sah_tree

#: Meshes from this size on show a progress bar by default.
PROGRESS_TRIANGLES = 50_000


def clip_to_slab(tri: np.ndarray, box_lo: np.ndarray, box_hi: np.ndarray, axis: int,
                 plane_lo: np.ndarray, plane_hi: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of the parts of triangles inside slabs, met with their reference boxes.

    Args:
        tri: ``float64 (m, 3, 3)`` the triangles' corners.
        box_lo, box_hi: ``float64 (m, 3)`` the references' boxes.
        axis: the slabs' axis; plane_lo, plane_hi: ``float64 (m,)`` their planes.

    Returns:
        ``(lo, hi, nonempty)``: the polygon of each triangle cut by its slab has as
        corners the triangle's corners inside the slab and the points where its edges
        cross the two planes; its box, met with the reference's box and the slab.
    """
    m = len(tri)
    inf = np.full((m, 3), np.inf)
    lo, hi = inf.copy(), -inf
    x = tri[:, :, axis]
    for k in range(3):
        inside = (x[:, k] >= plane_lo) & (x[:, k] <= plane_hi)
        lo = np.where(inside[:, None], np.minimum(lo, tri[:, k]), lo)
        hi = np.where(inside[:, None], np.maximum(hi, tri[:, k]), hi)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        pa, pb = tri[:, a], tri[:, b]
        xa, xb = x[:, a], x[:, b]
        for plane in (plane_lo, plane_hi):
            cross = (xa - plane) * (xb - plane) < 0
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(cross, (plane - xa) / np.where(cross, xb - xa, 1), 0)
            point = pa + s[:, None] * (pb - pa)
            point[:, axis] = plane
            lo = np.where(cross[:, None], np.minimum(lo, point), lo)
            hi = np.where(cross[:, None], np.maximum(hi, point), hi)
    # the cut points carry float64 rounding: widen by a few units of it, then meet the
    # reference's box and the slab (which hold the part exactly)
    with np.errstate(invalid="ignore"):
        pad = 8 * np.finfo(np.float64).eps * np.maximum(np.abs(lo), np.abs(hi))
        lo, hi = lo - pad, hi + pad
    lo, hi = np.maximum(lo, box_lo), np.minimum(hi, box_hi)
    lo[:, axis] = np.maximum(lo[:, axis], plane_lo)
    hi[:, axis] = np.minimum(hi[:, axis], plane_hi)
    return lo, hi, (lo <= hi).all(axis=1)


def _object_split(lo: np.ndarray, hi: np.ndarray) -> tuple[float, int, np.ndarray, np.ndarray,
                                                          np.ndarray]:
    """The best object split: (cost sum, axis, order, left box, right box) where the first
    ``k`` of ``order`` go left; ``k`` is returned through the order's split index."""
    n = len(lo)
    centre = 0.5 * (lo + hi)
    best = (np.inf, 0, None, 0)
    for axis in range(3):
        order = np.argsort(centre[:, axis], kind="stable")
        l_lo = np.minimum.accumulate(lo[order], axis=0)
        l_hi = np.maximum.accumulate(hi[order], axis=0)
        r_lo = np.minimum.accumulate(lo[order][::-1], axis=0)[::-1]
        r_hi = np.maximum.accumulate(hi[order][::-1], axis=0)[::-1]
        k = np.arange(1, n)
        cost = box_area(l_lo[:-1], l_hi[:-1]) * k + box_area(r_lo[1:], r_hi[1:]) * (n - k)
        i = int(np.argmin(cost + 1e-12 * np.abs(k - n / 2) * cost.max(initial=0)))
        if cost[i] < best[0]:
            best = (float(cost[i]), axis, order, i + 1)
    cost, axis, order, k = best
    return cost, k, order, np.stack([lo[order[:k]].min(0), hi[order[:k]].max(0)]), \
        np.stack([lo[order[k:]].min(0), hi[order[k:]].max(0)])


def _spatial_split(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray, node_lo: np.ndarray,
                   node_hi: np.ndarray, bins: int) -> tuple[float, int, float]:
    """The best spatial split: (cost sum, axis, plane); cost ``inf`` if none divides."""
    n = len(lo)
    best = (np.inf, 0, 0.0)
    for axis in range(3):
        a, b = node_lo[axis], node_hi[axis]
        if not b > a:
            continue
        width = (b - a) / bins
        first = np.clip(((lo[:, axis] - a) / width).astype(np.int64), 0, bins - 1)
        last = np.clip(((hi[:, axis] - a) / width).astype(np.int64), 0, bins - 1)
        span = last - first + 1
        ref = np.repeat(np.arange(n), span)
        slab = first[ref] + (np.arange(len(ref)) - np.repeat(np.cumsum(span) - span, span))
        plane_lo = a + slab * width
        plane_hi = np.where(slab == bins - 1, b, a + (slab + 1) * width)
        plo, phi, ok = clip_to_slab(tri[ref], lo[ref], hi[ref], axis, plane_lo, plane_hi)
        bin_lo = np.full((bins, 3), np.inf)
        bin_hi = np.full((bins, 3), -np.inf)
        np.minimum.at(bin_lo, slab[ok], plo[ok])
        np.maximum.at(bin_hi, slab[ok], phi[ok])
        enter = np.bincount(first, minlength=bins)
        leave = np.bincount(last, minlength=bins)
        l_lo = np.minimum.accumulate(bin_lo, axis=0)[:-1]
        l_hi = np.maximum.accumulate(bin_hi, axis=0)[:-1]
        r_lo = np.minimum.accumulate(bin_lo[::-1], axis=0)[::-1][1:]
        r_hi = np.maximum.accumulate(bin_hi[::-1], axis=0)[::-1][1:]
        n_left = np.cumsum(enter)[:-1]
        n_right = np.cumsum(leave[::-1])[::-1][1:]
        valid = (n_left > 0) & (n_right > 0) & ~((n_left == n) & (n_right == n))
        with np.errstate(invalid="ignore"):
            cost = np.where(valid, box_area(l_lo, l_hi) * n_left + box_area(r_lo, r_hi) * n_right,
                            np.inf)
        j = int(np.argmin(cost))
        if cost[j] < best[0]:
            best = (float(cost[j]), axis, float(a + (j + 1) * width))
    return best


def sbvh_tree(vertices: np.ndarray, faces: np.ndarray, options: SBVHOptions = SBVHOptions(),
              progress: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Build the SBVH over a mesh (see the module docstring).

    Returns:
        ``nodes`` (``NODE_DTYPE``, root 0) and ``prim_order`` (``int32 (R,)``, a
        triangle per reference slot, ``R >= F``); leaves hold contiguous slots.
    """
    tri_all = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    n_tris = len(tri_all)
    lo0, hi0 = tri_all.min(axis=1), tri_all.max(axis=1)
    root_area = float(box_area(lo0.min(0), hi0.max(0)))
    budget = int(options.max_growth * n_tris)
    c_node, c_tri = float(options.c_node), float(options.c_tri)
    records: list[Any] = []          # per node: (lower, a, upper, b), NODE_DTYPE's order
    slots: list[np.ndarray] = []
    used = [0, n_tris]               # slots written, references alive
    stack = [(0, np.arange(n_tris), lo0, hi0)]
    records.append(None)
    while stack:
        node, refs, lo, hi = stack.pop()
        n = len(refs)
        node_lo, node_hi = lo.min(0), hi.max(0)
        area = float(box_area(node_lo, node_hi))
        rlo, rhi = round_outward(node_lo, node_hi)
        if n <= options.object_below or area <= options.alpha * root_area:
            # No spatial split worth its cost below (a node's overlap is at most its area):
            # the rest of the subtree is the SAH reference's, over the references' boxes.
            sub, order = sah_tree(*round_outward(lo, hi), SAHOptions(
                c_node=c_node, c_tri=c_tri, max_leaf_size=int(options.max_leaf_size)))
            base = len(records)
            inner = ~is_leaf(sub)
            sub["a"] = np.where(inner, sub["a"] + base - 1, sub["a"] + used[0])
            sub["b"] = np.where(inner, sub["b"] + base - 1, sub["b"])
            records[node] = sub[0]
            records.extend(sub[1:])
            slots.append(refs[order])
            used[0] += n
            if progress is not None:
                progress.update(n)
            continue
        cost_obj, k, order, box_l, box_r = _object_split(lo, hi)
        split = ("object", cost_obj)
        overlap_lo, overlap_hi = np.maximum(box_l[0], box_r[0]), np.minimum(box_l[1], box_r[1])
        overlap = float(box_area(overlap_lo, overlap_hi)) if (overlap_lo <= overlap_hi).all() else 0.0
        if overlap > options.alpha * root_area and used[1] < budget:
            cost_sp, axis, plane = _spatial_split(tri_all[refs], lo, hi, node_lo, node_hi,
                                                  int(options.bins))
            if cost_sp < cost_obj:
                split = ("spatial", cost_sp)
        leaf_cost = c_tri * n * area
        split_cost = c_node * area + c_tri * split[1]
        if n <= options.max_leaf_size and leaf_cost <= split_cost:
            records[node] = (rlo, used[0], rhi, -n)
            slots.append(refs)
            used[0] += n
            if progress is not None:
                progress.update(n)
            continue
        if split[0] == "object":
            left = (refs[order[:k]], lo[order[:k]], hi[order[:k]])
            right = (refs[order[k:]], lo[order[k:]], hi[order[k:]])
        else:
            left_only = hi[:, axis] <= plane
            right_only = (lo[:, axis] >= plane) & ~left_only   # a flat one at the plane: left
            both = ~left_only & ~right_only
            sides = []
            for keep, a, b in ((left_only, node_lo[axis], plane),
                               (right_only, plane, node_hi[axis])):
                b_idx = np.flatnonzero(both)
                plo, phi, ok = clip_to_slab(tri_all[refs[b_idx]], lo[b_idx], hi[b_idx], axis,
                                            np.full(len(b_idx), a), np.full(len(b_idx), b))
                idx = np.concatenate([np.flatnonzero(keep), b_idx[ok]])
                side_lo = np.concatenate([lo[keep], plo[ok]])
                side_hi = np.concatenate([hi[keep], phi[ok]])
                order_in = np.argsort(idx, kind="stable")
                sides.append((refs[idx][order_in], side_lo[order_in], side_hi[order_in]))
            left, right = sides
            if len(left[0]) == 0 or len(right[0]) == 0:   # rounding emptied a side
                left = (refs[order[:k]], lo[order[:k]], hi[order[:k]])
                right = (refs[order[k:]], lo[order[k:]], hi[order[k:]])
            used[1] += len(left[0]) + len(right[0]) - n
        a_id, b_id = len(records), len(records) + 1
        records.extend([None, None])
        records[node] = (rlo, a_id, rhi, b_id)
        stack.append((b_id, *right))
        stack.append((a_id, *left))
    nodes = np.zeros(len(records), NODE_DTYPE)
    for i, r in enumerate(records):
        nodes[i] = r
    return nodes, np.concatenate(slots).astype(np.int32)


def build_tree(ctx: dev.Context, mesh: Mesh, options: SBVHOptions = SBVHOptions(),
               progress: bool | None = None) -> Tree:
    """Build the SBVH on the host and upload it (``lbvh.build(builder="sbvh")``); the
    caller holds ``ctx.lock``."""
    t0 = time.perf_counter()
    if progress is None and mesh.num_prims < PROGRESS_TRIANGLES:
        progress = False
    with progress_bar(mesh.num_prims, "SBVH build", "tri", progress) as placed:
        nodes, prim_order = sbvh_tree(mesh.vertices, mesh.faces, options, placed)
    wall = time.perf_counter() - t0
    report = BuildReport(device=ctx.name, builder="sbvh", num_triangles=mesh.num_prims,
                         wall_seconds=wall, input_bytes=mesh.vertices.nbytes + mesh.faces.nbytes)
    t1 = time.perf_counter()
    tree = upload_tree(ctx, nodes, parents_of(nodes, 0), prim_order, 0, "sbvh", report,
                       clipped_leaves=True)
    ctx.queue.finish()
    report.upload_seconds = time.perf_counter() - t1
    return tree
