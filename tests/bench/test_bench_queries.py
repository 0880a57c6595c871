"""The query bench (bench/bench_queries.py): its quick mode end to end with the real
kernels (every query of lbvh, the peers skipped), its agreement checks, and the
points, rays and boxes it makes."""
from __future__ import annotations

import json
import sys

import numpy as np

from conftest import REPO

sys.path.insert(0, str(REPO / "bench"))   # bench/ is not a package
import bench_queries as bench  # noqa: E402
from lbvh.queries.all_hits import AllHits  # noqa: E402


def test_quick_mode_writes_every_query_and_agrees(tmp_path):
    assert bench.main(["--quick", "--no-peers", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "bench_queries.json").read_text())
    rows = report["rows"]
    assert {(r["query"], r["tracer"]) for r in rows} == \
        {(q, t) for q in bench.QUERIES for t in ("lbvh", "lbvh+collapse")}
    assert set(report["machine"]["peers"]) == set(bench.QUERY_PEERS)
    counts = {"points": bench.QUICK_POINTS, "rays": bench.QUICK_RAYS, "boxes": bench.QUICK_BOXES}
    for r in rows:
        kind = bench.INPUT[r["query"]]
        assert r["scene"] == "teapot" and r["count"] == counts[kind] and not r["subsample"]
        assert len(r["samples"]) == r["rounds"] == report["settings"]["repeats"] == 2
        assert r["seconds"] == bench.median(r["samples"]) and r["per_second"] > 0
        assert r["judged"] == (bench.QUICK_SAMPLE if kind == "points" else bench.QUICK_RAY_SAMPLE)
        # lbvh answers within its stated bounds on every judged point, ray and box of the teapot
        assert r["agree"] == 1.0, r
    by = {(r["query"], r["tracer"]): r for r in rows}
    for t in ("lbvh", "lbvh+collapse"):
        assert by[("closest", t)]["max_error_over_bound"] <= 1.0
        assert by[("signed_distance", t)]["sign_agrees"] == by[("signed_distance", t)]["within_bound"] == 1.0
        assert by[("winding_numbers", t)]["max_winding_error"] <= bench.WINDING_BOUND
        assert by[("count_hits", t)]["count_differs"] == 0
        assert by[("all_hits", t)]["same_count"] == 1.0
        assert by[("all_hits", t)]["max_t_error_over_bound"] <= 1.0
        assert by[("overlapping", t)]["count_differs"] == 0
        assert 0 < by[("contains", t)]["inside_fraction"] < 1      # some points inside the teapot
    (scene,) = report["scenes"]
    assert scene["scene"] == "teapot" and scene["boundary_edges"] > 0   # the teapot is open
    assert scene["mean_hits"] > 0 and scene["mean_overlaps"] > 0
    text = (tmp_path / "bench_queries.md").read_text()
    for q in bench.QUERIES:
        assert f"## {bench.TITLES[q]}" in text
    assert "| teapot | lbvh | 20,000 |" in text and "No peer ran" in text


def test_judge_counts_a_wrong_answer_as_a_disagreement():
    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.int32([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])            # a closed tetrahedron
    o = np.float32([[0.2, 0.2, -1], [5, 5, 5]])
    d = np.float32([[0, 0, 1], [1, 0, 0]])
    p = np.float32([[0.1, 0.1, 0.1], [2, 2, 2]])
    lo, hi = np.float32([[-1, -1, -1], [1.95, 1.95, 1.95]]), np.float32([[2, 2, 2], [2.05, 2.05, 2.05]])
    inputs = bench.Inputs(p, o, d, lo, hi, np.arange(2), np.arange(2), np.arange(2))
    ref = bench.References(v, f, inputs)
    assert np.array_equal(ref.winding > 0.5, [True, False])
    good = bench.judge("count_hits", np.int32([2, 0]), ref)
    assert good["agree"] == 1.0 and good["count_differs"] == 0
    assert bench.judge("count_hits", np.int32([1, 0]), ref)["agree"] == 0.5
    d_ref = ref.distance[0]
    assert bench.judge("closest", d_ref.astype(np.float32), ref)["agree"] == 1.0
    assert bench.judge("closest", (d_ref + 1e-3).astype(np.float32), ref)["agree"] == 0.0
    sd = bench.judge("signed_distance", np.float32([d_ref[0], d_ref[1]]), ref)   # the inside one positive
    assert sd["within_bound"] == 1.0 and sd["sign_agrees"] == 0.5 and sd["agree"] == 0.5
    assert bench.judge("contains", np.array([True, True]), ref)["agree"] == 0.5
    hits: AllHits = ref.hits[0]
    t = hits.t.copy()
    answer = (hits.offsets, t[::-1].copy(), hits.prim[::-1].copy())   # any order within a ray
    assert bench.judge("all_hits", answer, ref)["agree"] == 1.0
    t[-1] += 1e-3
    late = bench.judge("all_hits", (hits.offsets, t, hits.prim), ref)
    assert late["same_count"] == 1.0 and late["agree"] == 0.5
    boxes = ref.boxes                                        # every triangle, then none
    assert np.array_equal(boxes.offsets, [0, 4, 4]) and np.array_equal(boxes.prims, [0, 1, 2, 3])
    assert bench.judge("overlapping", (boxes.offsets, np.int32([3, 1, 2, 0])), ref)["agree"] == 1.0
    missing = bench.judge("overlapping", (np.int64([0, 3, 3]), np.int32([0, 1, 2])), ref)
    assert missing["agree"] == 0.5 and missing["count_differs"] == 1

def test_query_points_fill_the_grown_box_and_repeat():
    v = np.float32([[0, 0, 0], [2, 1, 4]])
    p = bench.query_points(v, 5000)
    assert np.array_equal(p, bench.query_points(v, 5000))
    lo, hi = v.min(0) - bench.GROWTH * (v.max(0) - v.min(0)), v.max(0) + bench.GROWTH * (v.max(0) - v.min(0))
    assert (p >= lo - 1e-6).all() and (p <= hi + 1e-6).all()
    assert (p < v.min(0)).any() and (p > v.max(0)).any()   # some outside the mesh's box


def test_rays_aim_at_the_surface_and_boxes_sit_on_it():
    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    f = np.int32([[0, 1, 2], [1, 3, 2]])                      # the unit square at z = 0
    o, d = bench.query_rays(v, f, 2000)
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-6)
    moving = np.abs(d[:, 2]) > 1e-3
    t = -o[moving, 2] / d[moving, 2]                          # where each ray meets z = 0
    hit = o[moving] + t[:, None] * d[moving]
    assert (t > 0).all() and (hit[:, :2] >= -1e-4).all() and (hit[:, :2] <= 1 + 1e-4).all()
    lo, hi = bench.query_boxes(v, f, 2000)
    side = bench.BOX_SIDE
    assert np.allclose(hi - lo, side, atol=1e-6)
    assert (lo[:, 2] <= 0).all() and (hi[:, 2] >= 0).all()   # every box meets the plane
    assert np.array_equal(lo, bench.query_boxes(v, f, 2000)[0])
