"""Queries of two checkouts in the same run: this one against another (``--other``).

    .venv/bin/python bench/bench_ab.py --other /path/to/other/checkout
        [--scenes bunny sponza terrain-1m] [--rays 1024x1024] [--rounds 4] [--repeats 3]
        [--queries closest any winding one thousand] [--points 262144]

lbvh cannot be imported twice in one process, so each round runs one worker
process per checkout (in alternating order from round to round), each timing
``bvh.intersect`` (closest hit) and ``bvh.occluded`` (any hit) through the public
API on the default ``lbvh.build`` tree, on the bench camera's primary rays
(``lbvh/data/cameras.json``), the median of ``--repeats`` calls after one untimed
call. ``ao`` and ``ao-any`` time the same calls on bench_traverse's ambient-occlusion
rays (one per hit pixel, from the checkout's own primary hits): incoherent rays.
``winding`` times ``bvh.winding_numbers`` at ``--points`` points drawn
uniformly from the scene's box grown by a tenth each side (seed 0);
``closest-points`` and ``signed-distance`` time ``bvh.closest_points`` and
``bvh.signed_distance`` at the same points. ``one`` and
``thousand`` time ``bvh.intersect`` of 1 and 1,000 of the camera's rays picked
evenly over the image (the price of a call: the median of ``100 * --repeats``
calls after 20 untimed ones). The report gives each checkout's median over the
rounds and the ratio this / other (above 1: this checkout is slower), with the
answers' agreement: the fraction of rays with the same answer (closest hit,
one, thousand, closest points: the same triangle or miss; any hit: the same bool;
winding: the same side of 1/2; signed distance: the same sign) and with the same
bits (closest hit, one, thousand: ``t``; closest points: the distance; winding,
signed distance: the value).
"""
from __future__ import annotations

import common  # noqa: F401  (sets the environment before numpy loads)

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: The queries timed once a call (the others: 100 calls a repeat).
WHOLE_QUERIES = ("closest", "any", "ao", "ao-any", "winding", "closest-points", "signed-distance")

WORKER = r"""
import sys, json, time
sys.path.insert(0, sys.argv[1])
import numpy as np
import lbvh
sys.path.insert(0, sys.argv[2])
import common
scene = common.load_bench_scene(sys.argv[3], tuple(map(int, sys.argv[4].split("x"))),
                                common.load_cameras())
o, d = scene.camera.rays()
bvh = lbvh.build(scene.vertices, scene.faces)
lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
pts = (lo - 0.1 * (hi - lo) + 1.2 * (hi - lo) * np.random.default_rng(0).random(
    (int(sys.argv[8]), 3))).astype(np.float32)
few = {k: np.linspace(0, len(o) - 1, k).astype(np.int64) for k in (1, 1000)}
o1, d1 = o[few[1]], d[few[1]]
ok, dk = o[few[1000]], d[few[1000]]
ao = []


def ao_rays():
    if not ao:   # the AO rays of bench_traverse (one per hit pixel), made once
        import bench_traverse
        rs = bench_traverse.ao_rays(bvh, bvh.intersect(o, d), d, 1)
        ao.extend([rs.origins, rs.directions, rs.tmax])
    return ao


queries = {"closest": lambda: bvh.intersect(o, d), "any": lambda: bvh.occluded(o, d),
           "ao": lambda: bvh.intersect(ao_rays()[0], ao_rays()[1], tmax=ao_rays()[2]),
           "ao-any": lambda: bvh.occluded(ao_rays()[0], ao_rays()[1], tmax=ao_rays()[2]),
           "winding": lambda: bvh.winding_numbers(pts),
           "closest-points": lambda: bvh.closest_points(pts),
           "signed-distance": lambda: bvh.signed_distance(pts),
           "one": lambda: bvh.intersect(o1, d1), "thousand": lambda: bvh.intersect(ok, dk)}
out = {}
for name in sys.argv[7].split(","):
    fn = queries[name]
    whole = name in ("closest", "any", "winding", "ao", "ao-any", "closest-points",
                     "signed-distance")   # WHOLE_QUERIES
    for _ in range(1 if whole else 20):
        fn()
    times = []
    calls = int(sys.argv[5]) * (1 if whole else 100)
    for _ in range(calls):
        t0 = time.perf_counter(); r = fn(); times.append(time.perf_counter() - t0)
    out[name] = sorted(times)[len(times) // 2]
    res = {"closest-points": lambda r: r.distance}.get(name, lambda r: r if name in (
        "any", "ao-any", "winding", "signed-distance") else r.t)(r)
    np.save(sys.argv[6] + f"-{name}.npy", res)
    if name not in ("any", "ao-any", "winding", "signed-distance"):
        np.save(sys.argv[6] + f"-{name}-prim.npy", r.prim)
print(json.dumps(out))
"""


def run(checkout: Path, scene: str, rays: str, repeats: int, stem: str, queries: list[str],
        points: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    # each checkout with its own bench helpers (common, bench_traverse): they follow
    # its package's module paths
    out = subprocess.run([sys.executable, "-c", WORKER, str(checkout), str(checkout / "bench"),
                          scene, rays, str(repeats), stem, ",".join(queries), str(points)],
                         capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--other", type=Path, required=True)
    p.add_argument("--scenes", nargs="+", default=["bunny", "sponza", "terrain-1m"])
    p.add_argument("--rays", default="1024x1024")
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--queries", nargs="+", default=["closest", "any"],
                   choices=["closest", "any", "ao", "ao-any", "winding", "closest-points",
                            "signed-distance", "one", "thousand"])
    p.add_argument("--points", type=int, default=1 << 18)
    p.add_argument("--out", type=Path, default=HERE / "out" / "ab")
    args = p.parse_args(argv)
    this = HERE.parent
    lines = [f"# This checkout against {args.other}", "",
             f"Command: `{common.command_line('bench_ab.py', argv)}`", "",
             "| scene | query | this (ms) | other (ms) | this / other | same answers | "
             "same bits |", "|---|---|---:|---:|---:|---:|---:|"]
    report = []
    tmp = Path(tempfile.mkdtemp())
    for scene in args.scenes:
        times = {who: {q: [] for q in args.queries} for who in ("this", "other")}
        for r in range(args.rounds):
            order = [("this", this), ("other", args.other)]
            for who, path in (order if r % 2 == 0 else order[::-1]):
                got = run(path, scene, args.rays, args.repeats, str(tmp / who), args.queries,
                          args.points)
                for q in got:
                    times[who][q].append(got[q])
        for q in args.queries:
            a, b = np.load(tmp / f"this-{q}.npy"), np.load(tmp / f"other-{q}.npy")
            if q in ("any", "ao-any"):
                same = bits = float(np.mean(a == b))
            elif q in ("winding", "signed-distance"):   # the same side; the same bits
                side = 0.5 if q == "winding" else 0.0
                same = float(np.mean((a > side) == (b > side)))
                bits = float(np.mean(a.view(np.uint32) == b.view(np.uint32)))
            else:   # the same triangle (or miss); and t bit for bit
                same = float(np.mean(np.load(tmp / f"this-{q}-prim.npy")
                                     == np.load(tmp / f"other-{q}-prim.npy")))
                bits = float(np.mean(a.view(np.uint32) == b.view(np.uint32)))
            ta, tb = statistics.median(times["this"][q]), statistics.median(times["other"][q])
            report.append({"scene": scene, "query": q, "this_s": ta, "other_s": tb,
                           "ratio": ta / tb, "same_answers": same, "same_bits": bits,
                           "rounds": {k: times[k][q] for k in times}})
            digits = 1 if q in WHOLE_QUERIES else 3
            lines.append(f"| {scene} | {q} | {1e3 * ta:.{digits}f} | {1e3 * tb:.{digits}f} | "
                         f"{ta / tb:.3f} | "
                         f"{same:.5f} | {bits:.5f} |")
            print(lines[-1], file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    common.write_report({"rows": report}, "\n".join(lines) + "\n",
                        {"markdown": args.out / "bench_ab.md",
                         "json": args.out / "bench_ab.json"},
                        args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
