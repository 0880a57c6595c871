"""Answers against rewritings of the same scene: the count of rays whose answer changes.

For each scene, builder and ray set (:func:`lbvh.verification.invariance.ray_sets`:
views, aimed, surface), each rewriting (corners rotated, winding flipped, faces
permuted, the scene scaled by powers of two from 2^-60 to 2^60 where float32
holds it) is built and traced, and the rays whose answer differs from the
scene as written are counted: closest hit (hit/miss, triangle, t exactly as
scaled), any hit, hit counts. The same rewritings of each scene are asked for
winding numbers at points in and about it and on and beside its faces
(:func:`lbvh.verification.invariance.winding_points`): the points whose winding
number is not the same bits (negated for the winding flipped), and whose side of
1/2 changed. Every count should be 0, but for the faces permuted, which make
another tree: its winding numbers are within the walk's bound of the first ones,
not the same bits.

    .venv/bin/python bench/bench_invariance.py [--scenes bunny teapot slivers]
        [--rays 4096] [--builders lbvh sah] [--out bench/results/invariance]
"""
from __future__ import annotations

import common  # noqa: F401  (sets the environment before numpy loads)

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import lbvh
from lbvh.files import load_mesh
from lbvh.verification import invariance

GENERATED = {"slivers": lambda: invariance.sliver_soup(4000, 0)}


def load(name: str):
    if name in GENERATED:
        return GENERATED[name]()
    path = common.scene_file(name)
    if not path.is_file():
        return None
    return load_mesh(path)


def measure(v: np.ndarray, f: np.ndarray, builder: str, rays: int) -> list[dict]:
    base = lbvh.build(v, f, builder=builder)
    sets = invariance.ray_sets(v, f, rays, 0, trace=base.intersect)
    order = np.random.default_rng(1).permutation(len(f))
    rows = []
    points = invariance.winding_points(v, f, rays, 0)
    all_o = np.concatenate([o for o, _ in sets.values()] + [points])
    for rewrite in invariance.rewrites(v, all_o):
        other = lbvh.build(rewrite.points(v), rewrite.faces(f, order), builder=builder)
        for name, (o, d) in sets.items():
            o2 = rewrite.points(o)
            got = invariance.differences(base.intersect(o, d), other.intersect(o2, d), rewrite,
                                         order)
            got["any"] = int((base.occluded(o, d) != other.occluded(o2, d)).sum())
            got["count"] = int((base.count_hits(o, d) != other.count_hits(o2, d)).sum())
            rows.append({"builder": builder, "rays": name, "count_rays": len(o),
                         "rewrite": rewrite.name, **got})
        if builder != "sbvh":       # spatial splits have no winding numbers
            sign = np.float32(-1 if rewrite.corners == (0, 2, 1) else 1)
            w = base.winding_numbers(points)
            w2 = sign * other.winding_numbers(rewrite.points(points))
            rows.append({"builder": builder, "rays": "points", "count_rays": len(points),
                         "rewrite": rewrite.name,
                         "winding": int((w.view(np.uint32) != w2.view(np.uint32)).sum()),
                         "inside": int(((w > 0.5) != (w2 > 0.5)).sum()),
                         "winding_max": float(np.abs(w - w2).max())})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["bunny", "teapot", "slivers"])
    p.add_argument("--rays", type=int, default=4096)
    p.add_argument("--builders", nargs="+", default=["lbvh", "sah"])
    p.add_argument("--out", type=Path, default=Path("bench/results/invariance"))
    args = p.parse_args(argv)
    start = time.perf_counter()
    report = {"command": common.command_line("bench_invariance.py", argv),
              "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                       text=True).stdout.strip(),
              "rows": []}
    lines = ["# Answers against rewritings of the scene", "",
             f"Command: `{report['command']}` at {report['commit']}  ", "",
             "Rays whose answer changed (closest hit: hit/miss, triangle, t not exactly as "
             "scaled; any hit; hit count); points whose winding number changed (bits; the "
             "side of 1/2; the largest change). 0 everywhere is the goal, but for the "
             "winding numbers of the faces permuted (another tree: within the bound).", "",
             "| scene | builder | rays | rewrite | hit | triangle | t | any hit | count | "
             "winding | inside | largest |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for scene in args.scenes:
        mesh = load(scene)
        if mesh is None:
            print(f"[bench] {scene}: not found, skipped", file=sys.stderr)
            continue
        v, f = mesh
        for builder in args.builders:
            for row in measure(v, f, builder, args.rays):
                row["scene"] = scene
                report["rows"].append(row)
                if row["rays"] == "points":
                    cells = (f"| | | | | {row['winding']} | {row['inside']} | "
                             f"{row['winding_max']:.2g} |")
                else:
                    cells = (f"| {row['hit']} | {row['prim']} | {row['t']} | {row['any']} | "
                             f"{row['count']} | | | |")
                lines.append(f"| {scene} | {builder} | {row['rays']} ({row['count_rays']}) | "
                             f"{row['rewrite']} {cells}")
                print(lines[-1], file=sys.stderr)
    report["duration_seconds"] = time.perf_counter() - start
    rays = [r for r in report["rows"] if r["rays"] != "points"]
    total = sum(r["hit"] + r["prim"] + r["t"] + r["any"] + r["count"] for r in rays)
    kept = [r for r in report["rows"] if r["rays"] == "points" and r["rewrite"] != "permute"]
    winding = sum(r["winding"] + r["inside"] for r in kept)
    lines += ["", f"Total changed ray answers: {total}; changed winding numbers and inside "
              f"tests (the faces permuted aside): {winding}. Run time "
              f"{report['duration_seconds']:.0f} s."]
    args.out.mkdir(parents=True, exist_ok=True)
    common.write_report(report, "\n".join(lines) + "\n",
                        {"markdown": args.out / "bench_invariance.md",
                         "json": args.out / "bench_invariance.json"},
                        args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
