"""Answers against rewritings of the same scene: the count of rays whose answer changes.

For each scene, builder and ray set (:func:`lbvh.verification.invariance.ray_sets`:
views, aimed, surface), each rewriting (corners rotated, winding flipped, faces
permuted, the scene scaled by powers of two from 2^-60 to 2^60 where float32
holds it) is built and traced, and the rays whose answer differs from the
scene as written are counted: closest hit (hit/miss, triangle, t exactly as
scaled), any hit, hit counts. Every count should be 0.

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
from lbvh.rendering.scene import load_mesh
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
    all_o = np.concatenate([o for o, _ in sets.values()])
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
             "scaled; any hit; hit count). 0 everywhere is the goal.", "",
             "| scene | builder | rays | rewrite | hit | triangle | t | any hit | count |",
             "|---|---|---|---|---:|---:|---:|---:|---:|"]
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
                lines.append(f"| {scene} | {builder} | {row['rays']} ({row['count_rays']}) | "
                             f"{row['rewrite']} | {row['hit']} | {row['prim']} | {row['t']} | "
                             f"{row['any']} | {row['count']} |")
                print(lines[-1], file=sys.stderr)
    report["duration_seconds"] = time.perf_counter() - start
    total = sum(r["hit"] + r["prim"] + r["t"] + r["any"] + r["count"] for r in report["rows"])
    lines += ["", f"Total changed answers: {total}. Run time {report['duration_seconds']:.0f} s."]
    args.out.mkdir(parents=True, exist_ok=True)
    common.write_report(report, "\n".join(lines) + "\n",
                        {"markdown": args.out / "bench_invariance.md",
                         "json": args.out / "bench_invariance.json"},
                        args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
