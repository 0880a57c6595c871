"""Does the ray-sampled SAH pay? Trees costed by a camera's rays against the SAH (issue 20).

Usage::

    .venv/bin/python bench/bench_ray_sampled.py [--quick] [--scenes bunny,sponza ...] [--out DIR]

For each scene, the SAH reference (``builder="sah"``) and SAH trees whose splits
are costed by a grid of the bench camera's rays (``rays=camera.resized(W, H).rays()``,
:mod:`lbvh.builders.ray_sampled`; the grids of :data:`SAMPLES`, each ray ending at its
closest hit in the default LBVH, traced inside ``lbvh.build`` and counted in its
build time) are built (median of ``--build-repeats``) and then trace, in
interleaved rounds (median of ``--repeats``), three sets of closest-hit rays:

* **view**: the camera's primary rays at ``--rays`` (512x384): the view the sample
  was taken from, but not the sample's rays (pixel centres of a finer grid);
* **bounce**: one diffuse bounce from each point the view's rays hit (cosine
  directions about the face normal, turned towards the camera): the same frame's
  secondary rays, which the sample does not describe;
* **uniform**: as many rays with origins uniform in the scene's box and directions
  uniform on the sphere: the SAH's own assumption.

Beside each time: its ratio to the SAH tree's in the same rounds, the tree's SAH
cost and its ray-sampled cost on those rays (inner nodes + leaf triangles
entered per ray, :func:`lbvh.verification.ray_cost.ray_sampled_cost`), and the
error figure: the fraction of rays whose hit distance equals the SAH tree's
exactly (the same watertight triangle test in every tree: it must be 1).

Outputs ``bench_ray_sampled.json`` and ``bench_ray_sampled.md`` in ``--out``.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from common import (Progress, add_run_options, add_scene_options, command_line, header_lines,
                    load_bench_scene, load_cameras, loaded_scenes, median, report_start,
                    resolve_scenes, write_report)

import numpy as np

import lbvh
from lbvh import device as dev
from lbvh.metrics.cost import C_NODE, C_TRI, MAX_LEAF_SIZE
from lbvh.verification.ray_cost import ray_sampled_cost

FULL_SCENES = ("bunny", "sponza", "sibenik", "conference")
QUICK_SCENES = ("teapot",)
FULL_RAYS = (512, 384)
QUICK_RAYS = (64, 48)
#: Sample grids of the camera (width, height): 1/256, 1/64 and 1/16 of the view's rays.
SAMPLES = ((32, 24), (64, 48), (128, 96))
QUICK_SAMPLES = ((16, 12),)
RAY_SETS = ("view", "bounce", "uniform")
SAH_OPTIONS = {"c_node": C_NODE, "c_tri": C_TRI, "max_leaf_size": MAX_LEAF_SIZE}


def bounce_rays(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray,
                directions: np.ndarray, t: np.ndarray, prim: np.ndarray,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A cosine-distributed bounce off each hit, from just above the surface."""
    hit = np.isfinite(t)
    p = origins[hit].astype(np.float64) + t[hit, None] * directions[hit]
    tri = vertices[faces[prim[hit]]].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    n *= -np.sign(np.einsum("ij,ij->i", n, directions[hit]))[:, None]   # towards the viewer
    # a cosine-weighted direction: a uniform point on the unit sphere plus the normal
    s = rng.normal(size=n.shape)
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    d = n + s
    d[np.linalg.norm(d, axis=1) < 1e-9] = n[np.linalg.norm(d, axis=1) < 1e-9]
    scale = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    return (p + n * (1e-5 * scale)).astype(np.float32), d.astype(np.float32)


def uniform_rays(vertices: np.ndarray, count: int, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    o = lo + rng.random((count, 3)) * (hi - lo)
    d = rng.normal(size=(count, 3))
    return o.astype(np.float32), d.astype(np.float32)


def bench_scene(scene, ctx: dev.Context, samples, repeats: int, build_repeats: int,
                progress: Progress) -> dict:
    v, f, camera = scene.vertices, scene.faces, scene.camera
    rng = np.random.default_rng(0)
    lbvh.build(v, f, device=ctx).intersect(*camera.resized(4, 4).rays())   # compile, once
    trees = {"sah": {"options": {}}}
    for w, h in samples:
        trees[f"sah+rays {w}x{h}"] = {"options": {"rays": camera.resized(w, h).rays()},
                                      "sample": [w, h]}
    for name, tree in trees.items():
        seconds = []
        for r in range(build_repeats):
            progress.note(f"{name} build {r + 1}/{build_repeats}")
            tree["bvh"] = None
            t0 = time.perf_counter()
            tree["bvh"] = lbvh.build(v, f, builder="sah", device=ctx, **SAH_OPTIONS,
                                     **tree["options"])
            seconds.append(time.perf_counter() - t0)
        tree["build_seconds"] = median(seconds)
        tree["build_samples"] = seconds
    reference = trees["sah"]["bvh"]
    o, d = camera.rays()
    view = reference.intersect(o, d)
    rays = {"view": (o, d)}
    rays["bounce"] = bounce_rays(v, f, o, d, view.t, view.prim, rng)
    rays["uniform"] = uniform_rays(v, len(o), rng)
    for tree in trees.values():      # warm up: the kernels compiled, the caches filled
        tree["bvh"].intersect(*rays["view"])
    times = {name: {k: [] for k in rays} for name in trees}
    for r in range(repeats):
        progress.note(f"render round {r + 1}/{repeats}")
        for kind, (ro, rd) in rays.items():
            for name, tree in trees.items():
                t0 = time.perf_counter()
                tree["bvh"].intersect(ro, rd)
                times[name][kind].append(time.perf_counter() - t0)
    want = {kind: reference.intersect(ro, rd).t for kind, (ro, rd) in rays.items()}
    rows = []
    for name, tree in trees.items():
        bvh = tree["bvh"]
        row = {"tree": name, "sample": tree.get("sample"),
               "build_seconds": tree["build_seconds"], "build_samples": tree["build_samples"],
               "sah_cost": lbvh.sah_cost(bvh), "num_nodes": bvh.tree.num_nodes}
        for kind, (ro, rd) in rays.items():
            ratios = [a / b for a, b in zip(times[name][kind], times["sah"][kind])]
            got = bvh.intersect(ro, rd).t
            same = (got == want[kind]) | (np.isinf(got) & np.isinf(want[kind]))
            row[kind] = {"seconds": median(times[name][kind]), "samples": times[name][kind],
                         "ratio_to_sah": median(ratios),
                         "ray_cost": ray_sampled_cost(bvh, ro, rd).cost,
                         "same_t": float(same.mean())}
        rows.append(row)
        progress.advance()
    return {"scene": scene.name, "triangles": len(f), "rays": {k: len(r[0]) for k, r in rays.items()},
            "view_hit_fraction": float(np.isfinite(view.t).mean()), "rows": rows}


def markdown(report: dict) -> str:
    lines = ["# Does the ray-sampled SAH pay? (bench/bench_ray_sampled.py)", "",
             *header_lines(report), "",
             "Time of each ray set through each tree: median ms of the rounds, and (in "
             "brackets) the median ratio to the SAH tree's time in the same round (below 1: "
             "faster). Cost: the ray-sampled cost on those rays (inner nodes + leaf triangles "
             "entered per ray). Same t: fraction of rays with the SAH tree's hit distance, "
             "exactly.", "",
             "| scene | tree | build ms | SAH cost | " + " | ".join(
                 f"{k} ms (x SAH) | {k} cost" for k in RAY_SETS) + " | same t |",
             "|---|---|---:|---:|" + "---:|---:|" * len(RAY_SETS) + "---:|"]
    for sc in report["scenes"]:
        for row in sc["rows"]:
            cells = []
            for k in RAY_SETS:
                x = row[k]
                cells.append(f"{x['seconds'] * 1e3:.1f} ({x['ratio_to_sah']:.2f}) | "
                             f"{x['ray_cost']:.1f}")
            same = min(row[k]["same_t"] for k in RAY_SETS)
            lines.append(f"| {sc['scene']} | {row['tree']} | {row['build_seconds'] * 1e3:.0f} | "
                         f"{row['sah_cost']:.2f} | " + " | ".join(cells) + f" | {same:.4f} |")
    lines += ["", "Per scene, the best sampled tree on the view against the SAH tree:", ""]
    for sc in report["scenes"]:
        sampled = [r for r in sc["rows"] if r["sample"]]
        if not sampled:
            continue
        best = min(sampled, key=lambda r: r["view"]["ratio_to_sah"])
        ref = sc["rows"][0]
        lines.append(f"- **{sc['scene']}** ({sc['triangles']:,} tris, {sc['view_hit_fraction']:.0%} "
                     f"of the view's rays hit): {best['tree']} traces the view in "
                     f"{best['view']['ratio_to_sah']:.2f}x the SAH tree's time, the bounce rays in "
                     f"{best['bounce']['ratio_to_sah']:.2f}x, the uniform rays in "
                     f"{best['uniform']['ratio_to_sah']:.2f}x; it builds in "
                     f"{best['build_seconds'] / ref['build_seconds']:.2f}x the SAH's time, for an "
                     f"SAH cost {best['sah_cost'] / ref['sah_cost']:.2f}x the SAH tree's.")
    for s in report["skipped"]:
        lines.append(f"- {s['scene']}: skipped, {s['reason']}")
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_options(p, QUICK_SCENES, FULL_SCENES, QUICK_RAYS, FULL_RAYS)
    add_run_options(p)
    p.add_argument("--repeats", type=int, default=5, help="render rounds (median)")
    p.add_argument("--build-repeats", type=int, default=2, help="builds per tree (median)")
    args = p.parse_args(argv)
    resolve_scenes(p, args, QUICK_SCENES, FULL_SCENES, QUICK_RAYS, FULL_RAYS)
    if args.quick:
        args.repeats, args.build_repeats = min(args.repeats, 2), 1
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    ctx = dev.get_context(args.device)
    samples = QUICK_SAMPLES if args.quick else SAMPLES
    started = time.perf_counter()
    report = report_start(command_line("bench_ray_sampled.py", argv), ctx,
                          {"none": "none (our trees only)"})
    report.update(samples=[list(s) for s in samples], repeats=args.repeats,
                  build_repeats=args.build_repeats, scenes=[], skipped=[])
    cameras = load_cameras()
    progress = Progress(len(args.scene_names) * (len(samples) + 1))
    for scene in loaded_scenes(args.scene_names,
                               lambda name: load_bench_scene(name, args.size, cameras, args.shared),
                               progress, len(samples) + 1, report["skipped"]):
        report["scenes"].append(bench_scene(scene, ctx, samples, args.repeats,
                                            args.build_repeats, progress))
    progress.close()
    report["duration_seconds"] = time.perf_counter() - started
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "bench_ray_sampled.json", "markdown": out / "bench_ray_sampled.md"}
    write_report(report, markdown(report), paths, out)
    return report


if __name__ == "__main__":
    main()
