#!/usr/bin/env python
"""Point-query bench of issue 17: closest points against the peers, speed beside error.

For each scene, the same query points (uniform in the mesh's box grown by a
fifth on each side, seeded) go to every tracer in interleaved rounds, so that
ratios share the machine's noise:

* lbvh's ``bvh.closest_points`` on the default tree and the collapsed tree
  (kernels/closest.cl; the build is not timed);
* warp's ``wp.mesh_query_point_no_sign`` on the CPU device (one thread), when
  warp-lang is installed (bench/common.py's adapter).

Agreement: on a sample of the points, each tracer's distance against the
float64 brute force (:func:`lbvh.queries.closest.closest_points_numpy`),
within the bound of :func:`lbvh.verification.error_bound.closest_distance_bound`
(``4 u s``). The signed distance, inside, hit-count and box queries of the
issue are not in lbvh yet, so they are not here either.

    .venv/bin/python bench/bench_queries.py                # bunny, sponza, terrain-1m, 1M points
    .venv/bin/python bench/bench_queries.py --quick        # CI: teapot, 20K points
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# bench/common.py, beside this script; imported before numpy, for it sets
# OPENBLAS_NUM_THREADS (see there).
from common import (GENERATED_SCENES, FILE_SCENES, Progress, command_line, header_lines,
                    known_scenes, load_peers, median, report_start, scene_file, write_report)

import numpy as np

import lbvh
from lbvh import device as dev
from lbvh.queries.closest import closest_points_numpy
from lbvh.rendering.scene import load_mesh
from lbvh.verification.error_bound import CLOSEST_BOUND_ULPS, closest_distance_bound

FULL_SCENES = ("bunny", "sponza", "terrain-1m")
QUICK_SCENES = ("teapot",)
FULL_POINTS, QUICK_POINTS = 1 << 20, 20_000
FULL_SAMPLE, QUICK_SAMPLE = 300, 60
#: The query points fill the mesh's box grown by this fraction of it on each side.
GROWTH = 0.2


def query_points(vertices: np.ndarray, count: int, seed: int = 17) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    ext = hi - lo
    return (lo + ext * rng.uniform(-GROWTH, 1 + GROWTH, (count, 3))).astype(np.float32)


def load_scene_mesh(name: str, shared: Path) -> tuple[np.ndarray, np.ndarray] | str:
    if name in GENERATED_SCENES:
        return GENERATED_SCENES[name]()
    path = scene_file(name, shared)
    if not path.is_file():
        return f"{path} not found"
    return load_mesh(path)


def tracers(v: np.ndarray, f: np.ndarray, device, peers: dict) -> dict:
    """name -> function(points) -> distances (float32); builds are done here, untimed."""
    out = {}
    for name, options in (("lbvh", {}), ("lbvh+collapse", {"collapse": True})):
        bvh = lbvh.build(v, f, device=device, **options)
        out[name] = lambda p, b=bvh: b.closest_points(p).distance
    if "warp" in peers:
        warp = peers["warp"]
        _, _, mesh = warp.build(v, f)
        out["warp"] = lambda p, m=mesh: warp.closest_points(m, p)[0]
    return out


def bench_scene(name: str, v: np.ndarray, f: np.ndarray, args: argparse.Namespace,
                peers: dict, progress: Progress) -> list[dict]:
    points = query_points(v, args.points)
    run = tracers(v, f, args.device, peers)
    for fn in run.values():                      # compile and warm up on a few points
        fn(points[:64])
    seconds = {k: [] for k in run}
    for r in range(args.repeats):
        for k, fn in run.items():
            progress.note(f"{k} {r + 1}/{args.repeats}")
            t0 = time.perf_counter()
            fn(points)
            seconds[k].append(time.perf_counter() - t0)
        progress.advance()
    sample = np.random.default_rng(5).choice(len(points), min(args.sample, len(points)),
                                             replace=False)
    ref, _, _ = closest_points_numpy(v, f, points[sample])
    bound = closest_distance_bound(v, points[sample])
    rows = []
    for k, fn in run.items():
        d = fn(points[sample]).astype(np.float64)
        err = np.abs(d - ref) / bound
        med = median(seconds[k])
        rows.append({"scene": name, "triangles": int(len(f)), "tracer": k, "points": len(points),
                     "seconds": med, "samples": seconds[k],
                     "points_per_second": len(points) / med,
                     "judged": int(len(sample)),
                     "within_bound": float(np.mean(err <= 1.0)),
                     "max_error_over_bound": float(err.max())})
    return rows


def markdown(report: dict) -> str:
    lines = ["# Point queries: closest points", "", *header_lines(report), "",
             f"{report['settings']['points']:,} points per scene, uniform in the mesh's box grown "
             f"by {GROWTH:.0%} on each side; medians of {report['settings']['repeats']} "
             "interleaved rounds. Agreement: the distance of "
             f"{report['settings']['sample']} of the points against the float64 brute force, "
             f"bound {CLOSEST_BOUND_ULPS} u s (u = 2^-24, s = |p| + max |vertex|).", "",
             "| scene | tris | tracer | Mpoints/s | ms | vs lbvh | within bound | max err / bound |",
             "|---|---:|---|---:|---:|---:|---:|---:|"]
    base = {r["scene"]: r["points_per_second"] for r in report["rows"] if r["tracer"] == "lbvh"}
    for r in report["rows"]:
        lines.append(f"| {r['scene']} | {r['triangles']:,} | {r['tracer']} | "
                     f"{r['points_per_second'] / 1e6:.3f} | {r['seconds'] * 1e3:.1f} | "
                     f"{r['points_per_second'] / base[r['scene']]:.2f} | {r['within_bound']:.3f} | "
                     f"{r['max_error_over_bound']:.2f} |")
    for s in report["skipped"]:
        lines.append(f"\nskipped {s['scene']}: {s['reason']}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true",
                   help=f"CI mode: {', '.join(QUICK_SCENES)}, {QUICK_POINTS:,} points")
    p.add_argument("--scenes", nargs="+", metavar="NAME",
                   help=f"from {', '.join(known_scenes())}; default {','.join(FULL_SCENES)}")
    p.add_argument("--points", type=int, help=f"query points per scene (default {FULL_POINTS:,})")
    p.add_argument("--sample", type=int, help="points judged against the brute force")
    p.add_argument("--repeats", type=int, default=None, help="interleaved rounds (median)")
    p.add_argument("--no-peers", action="store_true", help="skip warp")
    p.add_argument("--device", default=None, help="OpenCL device (default: $LBVH_DEVICE or PoCL)")
    p.add_argument("--shared", type=Path, default=FILE_SCENES["bunny"][0],
                   help="folder of the shared scenes")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "out")
    args = p.parse_args(argv)
    names = [n for item in (args.scenes or []) for n in item.split(",") if n] or \
        list(QUICK_SCENES if args.quick else FULL_SCENES)
    unknown = [n for n in names if n not in known_scenes()]
    if unknown:
        p.error(f"--scenes: unknown scene {unknown[0]!r}; known: {', '.join(known_scenes())}")
    args.points = args.points or (QUICK_POINTS if args.quick else FULL_POINTS)
    args.sample = args.sample or (QUICK_SAMPLE if args.quick else FULL_SAMPLE)
    args.repeats = args.repeats or (2 if args.quick else 5)
    peers, status = load_peers(not args.no_peers)
    peers = {k: v for k, v in peers.items() if k == "warp"}
    ctx = dev.get_context(args.device)
    start = time.perf_counter()
    report = report_start(command_line("bench_queries.py", argv), ctx, status)
    report.update(settings={"points": args.points, "sample": args.sample, "repeats": args.repeats,
                            "scenes": names, "growth": GROWTH}, rows=[], skipped=[])
    progress = Progress(len(names) * args.repeats)
    for name in names:
        progress.begin(f"{name}:")
        mesh = load_scene_mesh(name, args.shared)
        if isinstance(mesh, str):
            report["skipped"].append({"scene": name, "reason": mesh})
            progress.skip(args.repeats)
            continue
        report["rows"] += bench_scene(name, *mesh, args, peers, progress)
    progress.close()
    report["duration_seconds"] = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": args.out / "bench_queries.md", "json": args.out / "bench_queries.json"}
    write_report(report, markdown(report), paths, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
