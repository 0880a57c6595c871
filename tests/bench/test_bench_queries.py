"""The point-query bench (bench/bench_queries.py): its quick mode end to end with the
real kernels, and the query points it makes."""
from __future__ import annotations

import json
import sys

import numpy as np

from conftest import REPO

sys.path.insert(0, str(REPO / "bench"))   # bench/ is not a package
import bench_queries as bench  # noqa: E402


def test_quick_mode_writes_every_field_and_agrees(tmp_path):
    assert bench.main(["--quick", "--no-peers", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "bench_queries.json").read_text())
    rows = report["rows"]
    assert {r["tracer"] for r in rows} == {"lbvh", "lbvh+collapse"}
    for r in rows:
        assert r["scene"] == "teapot" and r["points"] == bench.QUICK_POINTS
        assert len(r["samples"]) == report["settings"]["repeats"] == 2
        assert r["seconds"] == bench.median(r["samples"])
        assert r["points_per_second"] > 0 and r["judged"] == bench.QUICK_SAMPLE
        assert r["within_bound"] == 1.0 and r["max_error_over_bound"] <= 1.0
    text = (tmp_path / "bench_queries.md").read_text()
    assert "| teapot | 6,320 | lbvh |" in text and "within bound" in text


def test_query_points_fill_the_grown_box_and_repeat():
    v = np.float32([[0, 0, 0], [2, 1, 4]])
    p = bench.query_points(v, 5000)
    assert np.array_equal(p, bench.query_points(v, 5000))
    lo, hi = v.min(0) - bench.GROWTH * (v.max(0) - v.min(0)), v.max(0) + bench.GROWTH * (v.max(0) - v.min(0))
    assert (p >= lo - 1e-6).all() and (p <= hi + 1e-6).all()
    assert (p < v.min(0)).any() and (p > v.max(0)).any()   # some outside the mesh's box
