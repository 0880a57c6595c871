"""The ray-sampled SAH bench (bench/bench_ray_sampled.py): its quick mode end to end
(every tree gives the SAH tree's hits) and the bounce rays it traces."""
from __future__ import annotations

import json
import math

import numpy as np

import lbvh
from conftest import load_bench, shipped_mesh

bench = load_bench("bench_ray_sampled")


def test_quick_mode_writes_every_tree_with_the_sah_trees_hits(tmp_path):
    report = bench.main(["--quick", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "bench_ray_sampled.json").read_text())
    assert saved["scenes"][0]["scene"] == "teapot"
    rows = saved["scenes"][0]["rows"]
    assert [r["tree"] for r in rows] == ["sah"] + [f"sah+rays {w}x{h}" for w, h in bench.QUICK_SAMPLES]
    for row in rows:
        assert row["build_seconds"] > 0 and row["sah_cost"] > 0
        for kind in bench.RAY_SETS:
            x = row[kind]
            assert x["same_t"] == 1.0, (row["tree"], kind)
            assert math.isfinite(x["ratio_to_sah"]) and x["ratio_to_sah"] > 0
            assert x["ray_cost"] > 0
    assert rows[0]["view"]["ratio_to_sah"] == 1.0
    assert "sah+rays 16x12 traces the view" in (tmp_path / "bench_ray_sampled.md").read_text()
    assert report["duration_seconds"] > 0


def test_bounce_rays_leave_the_hit_surface_on_the_viewers_side():
    v, f = shipped_mesh("teapot.obj")
    camera = lbvh.camera.frame_bounds(v.min(axis=0), v.max(axis=0), 32, 24)
    o, d = camera.rays()
    hits = lbvh.build(v, f).intersect(o, d)
    bo, bd = bench.bounce_rays(v, f, o, d, hits.t, hits.prim, np.random.default_rng(1))
    assert len(bo) == int(hits.mask.sum()) > 0
    tri = v[f[hits.prim[hits.mask]]].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    towards_viewer = -np.sign(np.einsum("ij,ij->i", n, d[hits.mask]))
    # every bounce leaves on the side the view's ray came from (the cosine lobe's hemisphere)
    assert (np.einsum("ij,ij->i", n, bd) * towards_viewer >= 0).all()
