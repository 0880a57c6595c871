#!/usr/bin/env python
"""The tree study: would a PLOC tree pay for rays as lbvh's default?

    .venv/bin/python bench/bench_ploc.py [--scenes bunny sponza terrain-1m]
        [--rays 1024x1024] [--rounds 5] [--radius 8 16 32] [--out bench/out/ploc]

PLOC (Meister & Bittner 2018, "Parallel Locally-Ordered Clustering for Bounding
Volume Hierarchy Construction"; PLOC++, Benthin et al. 2022; H-PLOC, Benthin et
al. 2024) builds bottom up from the leaves in Morton order: each cluster finds,
among the ``radius`` clusters on either side, the one whose merged box has the
least surface area; mutual nearest neighbours merge; the survivors are compacted
in order and the step repeats until one cluster is left. Each step is three
data-parallel passes (nearest neighbour, merge, compaction), which is why the
family is the GPU's choice of near-SAH builders.

This script builds PLOC trees with a numpy implementation of that algorithm
(:func:`ploc_tree`, vectorised over the clusters of a step; ties go to the pair
of lower indices, which makes a mutual pair in every step), uploads them with
``lbvh.BVH.from_arrays`` and measures, on the same camera rays and in the same
rounds as the device LBVH default and the bench's best LBVH (treelets and
collapse, ``bench_traverse``'s `lbvh+treelets2+collapse`):

* the SAH cost (``lbvh.metrics.quality.sah_cost``) and its ratio to the
  serial sweep SAH tree's (``builder="sah"``), the reference of bench_builders;
* closest-hit rays per second through ``bvh.intersect`` (the median of
  ``--rounds`` interleaved rounds), and the answers' agreement with the default
  tree's (the same t bits, the same triangle: the walk's answers do not depend
  on the tree);
* the build time: the device builds as ``lbvh.build`` (after an untimed one that
  compiles); PLOC's is this numpy
  implementation's (two cores' worth of numpy, not a device build: the column
  says what a device PLOC would have to beat, not what it would take).

Writes ``bench_ploc.md`` and ``bench_ploc.json`` to ``--out``.
"""
from __future__ import annotations

import common  # noqa: F401  (sets the environment before numpy loads)

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import lbvh
from lbvh.builders.bounds import triangle_boxes_numpy
from lbvh.builders.morton import morton_codes_numpy
from lbvh.layout import make_nodes
from lbvh.metrics.quality import sah_cost

HERE = Path(__file__).resolve().parent


def half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half the surface area of boxes, in float64."""
    e = (hi - lo).astype(np.float64)
    return e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]


def ploc_tree(lo: np.ndarray, hi: np.ndarray, order: np.ndarray, radius: int = 16
              ) -> tuple[np.ndarray, np.ndarray, int]:
    """A PLOC tree over primitive boxes ``lo``, ``hi`` (``float32 (F, 3)``) whose leaves
    (one primitive each) start in ``order`` (``int (F,)``, the Morton order).

    Returns ``nodes`` (``NODE_DTYPE``: leaves 0..F-1 in slot order, then the merged
    nodes in the order they are made), ``prim_order`` and the root. A step: each
    cluster's nearest neighbour (least merged half area; equal areas: the lower
    index) among the ``radius`` on either side; each mutual pair merges into a new
    node at the place of its lower member; the others stay, in order.
    """
    f = len(order)
    total = 2 * f - 1
    lower = np.empty((total, 3), np.float32)
    upper = np.empty((total, 3), np.float32)
    children = np.full((total, 2), -1, np.int64)
    ranges = np.zeros((total, 2), np.int64)
    lower[:f], upper[:f] = lo[order], hi[order]
    ranges[:f, 0], ranges[:f, 1] = np.arange(f), 1
    clusters = np.arange(f)
    made = f
    while len(clusters) > 1:
        m = len(clusters)
        r = min(radius, m - 1)
        c_lo, c_hi = lower[clusters], upper[clusters]
        best = np.full(m, np.inf)
        nearest = np.full(m, -1, np.int64)
        index = np.arange(m)
        # candidates in increasing index (i - r .. i - 1, then i + 1 .. i + r): a strict
        # comparison keeps the lower index among equal areas
        for k in range(r, 0, -1):   # j = i - k, for i = k .. m-1
            a = half_area(np.minimum(c_lo[k:], c_lo[:m - k]), np.maximum(c_hi[k:], c_hi[:m - k]))
            better = a < best[k:]
            best[k:][better] = a[better]
            nearest[k:][better] = index[:m - k][better]
        for k in range(1, r + 1):   # j = i + k, for i = 0 .. m-k-1
            a = half_area(np.minimum(c_lo[:m - k], c_lo[k:]), np.maximum(c_hi[:m - k], c_hi[k:]))
            better = a < best[:m - k]
            best[:m - k][better] = a[better]
            nearest[:m - k][better] = index[k:][better]
        mutual = nearest[nearest] == index
        first = mutual & (index < nearest)
        pair = np.flatnonzero(first)
        new = made + np.arange(len(pair))
        made += len(pair)
        left, right = clusters[pair], clusters[nearest[pair]]
        children[new, 0], children[new, 1] = left, right
        lower[new] = np.minimum(lower[left], lower[right])
        upper[new] = np.maximum(upper[left], upper[right])
        merged = clusters.copy()
        merged[pair] = new
        clusters = merged[~(mutual & (index > nearest))]
    nodes = make_nodes(lower, upper, children, ranges)
    return nodes, np.asarray(order, np.int32), int(clusters[0])


def ploc_bvh(vertices: np.ndarray, faces: np.ndarray, radius: int) -> tuple[lbvh.BVH, float]:
    """A PLOC tree uploaded as a BVH, and the seconds its numpy build took."""
    t0 = time.perf_counter()
    lo, hi = triangle_boxes_numpy(vertices, faces)
    centres = lo * np.float32(0.5) + hi * np.float32(0.5)
    bounds = np.stack([centres.min(axis=0), centres.max(axis=0)])
    codes = morton_codes_numpy(centres, bounds, 64)   # 21 bits per axis
    order = np.argsort(codes, kind="stable")
    nodes, prim_order, root = ploc_tree(lo, hi, order, radius)
    seconds = time.perf_counter() - t0
    return lbvh.BVH.from_arrays(nodes, prim_order, root, vertices, faces,
                                builder=f"ploc{radius}"), seconds


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["bunny", "sponza", "terrain-1m"])
    p.add_argument("--rays", default="1024x1024")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--radius", type=int, nargs="+", default=[8, 16])
    p.add_argument("--out", type=Path, default=HERE / "out" / "ploc")
    args = p.parse_args(argv)
    size = common.parse_rays(args.rays)
    cameras = common.load_cameras()
    lines = ["# The tree study: PLOC trees against lbvh's default and best trees", "",
             f"Command: `{common.command_line('bench_ploc.py', argv)}`", "",
             "| scene | tree | build s | SAH cost | / sweep SAH | closest Mrays/s | "
             "/ default | same t bits | same triangle |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    report = []
    for name in args.scenes:
        scene = common.load_bench_scene(name, size, cameras)
        if isinstance(scene, str):
            print(f"{name}: skipped ({scene})", file=sys.stderr)
            continue
        v, f = scene.vertices, scene.faces
        o, d = scene.camera.rays()
        trees, build = {}, {}
        lbvh.build(v, f, treelet_rounds=2, collapse=True)   # compiles the device builds' kernels
        t0 = time.perf_counter()
        trees["lbvh (default)"] = lbvh.build(v, f)
        build["lbvh (default)"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        trees["lbvh+treelets2+collapse"] = lbvh.build(v, f, treelet_rounds=2, collapse=True)
        build["lbvh+treelets2+collapse"] = time.perf_counter() - t0
        for radius in args.radius:
            trees[f"ploc r={radius}"], build[f"ploc r={radius}"] = ploc_bvh(v, f, radius)
            trees[f"ploc r={radius}+collapse"] = lbvh.api.collapse_leaves(trees[f"ploc r={radius}"])
            build[f"ploc r={radius}+collapse"] = build[f"ploc r={radius}"]
        t0 = time.perf_counter()
        reference = lbvh.build(v, f, builder="sah")
        build["sweep sah"] = time.perf_counter() - t0
        trees["sweep sah"] = reference
        ref_cost = sah_cost(reference)
        for bvh in trees.values():   # compile and warm outside the rounds
            bvh.intersect(o[:64], d[:64])
        times: dict[str, list[float]] = {k: [] for k in trees}
        answers = {}
        for r in range(args.rounds):
            names = list(trees) if r % 2 == 0 else list(trees)[::-1]
            for k in names:
                t0 = time.perf_counter()
                answers[k] = trees[k].intersect(o, d)
                times[k].append(time.perf_counter() - t0)
        base = answers["lbvh (default)"]
        rate0 = len(o) / float(np.median(times["lbvh (default)"]))
        for k, bvh in trees.items():
            rate = len(o) / float(np.median(times[k]))
            cost = sah_cost(bvh)
            same_t = float(np.mean(answers[k].t.view(np.int32) == base.t.view(np.int32)))
            same_prim = float(np.mean(answers[k].prim == base.prim))
            report.append({"scene": name, "tree": k, "build_seconds": build[k], "sah_cost": cost,
                           "sah_ratio": cost / ref_cost, "rays_per_second": rate,
                           "speed_ratio": rate / rate0, "same_t_bits": same_t,
                           "same_triangle": same_prim, "times": times[k]})
            lines.append(f"| {name} | {k} | {build[k]:.3f} | {cost:.1f} | {cost / ref_cost:.3f} "
                         f"| {rate / 1e6:.2f} | {rate / rate0:.2f} | {same_t:.5f} "
                         f"| {same_prim:.5f} |")
            print(lines[-1], file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    common.write_report({"rows": report}, "\n".join(lines) + "\n",
                        {"markdown": args.out / "bench_ploc.md", "json": args.out / "bench_ploc.json"},
                        args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
