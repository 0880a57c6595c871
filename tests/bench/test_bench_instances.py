"""The instances bench (bench/bench_instances.py, issue 18): its quick mode end to end with
the real kernels (peers off), the placement, the camera and the agreement sample."""
from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest

import lbvh
from conftest import REPO
from lbvh.builders import pipeline

sys.path.insert(0, str(REPO / "bench"))   # bench/ is not a package
import bench_instances as bench  # noqa: E402


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _within_bound(a: dict) -> None:
    """The scene agrees with its reference within the bench's stated bound (and the
    quick scene, deterministic, gives 1.0)."""
    bound = bench.HIT_MISS_BOUND
    assert a["hit_miss_fraction"] <= bound, a
    assert a["fraction_with_ties"] >= 1.0 - bound, a
    assert a["any_hit_same"] >= 1.0 - bound, a
    assert a["max_t_error_over_bound"] <= 1.0 or a["t_out_of_bound"] <= bound * a["rays"], a


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_instances")
    report = bench.main(["--quick", "--no-peers", "--out", str(out)])
    return out, report


def test_quick_json_has_every_section_and_field(quick):
    out, report = quick
    data = json.loads((out / "bench_instances.json").read_text())
    assert data["command"].endswith("--quick --no-peers --out " + str(out))
    assert data["machine"]["opencl_device"] and data["machine"]["peers"] == \
        {"embree": "disabled (--no-peers)"}
    assert data["skipped"] is None
    assert data["mesh"]["name"] == "teapot" and data["mesh"]["triangles"] == len(lbvh.data.teapot()[1])
    assert _positive(data["mesh"]["build"]["seconds"])
    assert [k["instances"] for k in data["instances"]] == list(bench.QUICK_INSTANCES)
    w, h = bench.QUICK_RAYS
    for k in data["instances"]:
        assert k["world_triangles"] == k["instances"] * data["mesh"]["triangles"]
        assert k["rays"] == w * h and k["top_nodes"] == 2 * k["instances"] - 1
        build = k["build"]
        for name in ("Scene()", "set_transforms"):
            assert len(build[name]["samples"]) == bench.QUICK_REPEATS
            assert _positive(build[name]["seconds"])
        tracers = {bench.SCENE_TRACER} | ({bench.FLAT_TRACER} if k["flattened"] else set())
        assert {(r["tracer"], r["query"]) for r in k["rows"]} == \
            {(t, q) for t in tracers for q in bench.QUERIES}
        for r in k["rows"]:
            assert _positive(r["mrays_per_second"]) and r["rays"] == w * h
            assert len(r["samples"]) == bench.QUICK_REPEATS
            assert 0.3 < r["hit_fraction"] <= 1.0           # the camera sees the grid
            if r["query"] == "closest":
                assert r["nodes_per_ray"] >= 1 and r["tris_per_ray"] > 0
                assert r["overflow_count"] == 0
            assert set(r["speed_over"]) == tracers - {r["tracer"]}
        assert k["agreement"]
        for a in k["agreement"]:
            assert "skipped" not in a, a
            _within_bound(a)
    first, second = data["instances"]
    # the first quick count is flattened whole (every ray), the second is past
    # --flatten-max and goes through the tile sample
    assert first["flattened"] and first["flattened_skipped"] is None
    assert {"flatten (host)", "lbvh.build (flattened)"} <= set(first["build"])
    assert first["agreement"][0]["reference"] == bench.FLAT_TRACER
    assert first["agreement"][0]["rays"] == w * h
    assert not second["flattened"] and "--flatten-max" in second["flattened_skipped"]
    sample = second["agreement"][0]
    assert 0 < sample["sample_instances"] < second["instances"]
    # whole tiles, dropped from the last until the instances they cross fit --flatten-max
    assert 0 < sample["rays"] <= len(bench.tile_rays(bench.QUICK_RAYS))
    assert sample["rays"] % bench.TILE ** 2 == 0
    assert sample["sample_triangles"] <= data["settings"]["flatten_max"]


def test_quick_device_limits_and_parts(quick, ctx):
    _, report = quick
    dl = report["device_limits"]
    assert dl["max_mem_alloc_size"] == ctx.device.max_mem_alloc_size
    assert dl["global_mem_size"] == ctx.device.global_mem_size
    assert dl["max_triangles_one_tree"] == pipeline.max_triangles(ctx)
    assert dl["max_triangles_by_global_memory"] > 0 and "build_parts" in dl["meaning"]
    p = report["parts"]
    assert p["parts"] == bench.PARTS and p["part_triangles"] * bench.PARTS >= p["triangles"]
    assert {(r["tracer"], r["query"]) for r in p["rows"]} == \
        {(t, q) for t in (bench.ONE_TREE, bench.PARTS_TREE) for q in bench.QUERIES}
    for name in (bench.ONE_TREE, bench.PARTS_TREE):
        assert _positive(p["build"][name]["seconds"])
    _within_bound(p["agreement"])


def test_quick_markdown_has_every_table(quick):
    out, report = quick
    text = (out / "bench_instances.md").read_text()
    for heading in ("# Scenes of many instances (issue 18)", "## Build", "## Rays", "## Agreement",
                    "## The largest mesh the device takes", "## One mesh in parts"):
        assert heading in text
    assert "Command: `" in text and "Run time:" in text and "Peers:" in text
    assert bench.EMBREE_NOTE in text
    assert text.count("| closest | lbvh.Scene |") == len(bench.QUICK_INSTANCES)
    assert "no flattened copy" in text
    assert report["duration_seconds"] < 60


def test_a_missing_mesh_is_skipped_with_its_reason(tmp_path):
    report = bench.main(["--mesh", "bunny", "--shared", str(tmp_path / "none"), "--no-peers",
                         "--parts-triangles", "0", "--repeats", "1", "--out", str(tmp_path)])
    assert "not found" in report["skipped"] and report["instances"] == []
    text = (tmp_path / "bench_instances.md").read_text()
    assert "skipped" in text and "## The largest mesh the device takes" in text


def test_placement_stands_every_instance_on_its_cell():
    v, f = lbvh.data.teapot()
    t, grid = bench.placement(v, 10)
    assert t.shape == (10, 3, 4) and (grid.cols, grid.rows) == (4, 3)
    a = t[:, :, :3]
    scale = a[:, 1, 1]
    assert ((scale >= bench.SCALES[0]) & (scale <= bench.SCALES[1])).all()
    # a turn about y times a scale: A^T A = s^2 I, y maps to y
    assert np.allclose(np.einsum("ikj,ikl->ijl", a, a), scale[:, None, None] ** 2 * np.eye(3))
    assert np.allclose(a[:, 1], np.stack([np.zeros(10), scale, np.zeros(10)], 1))
    world = np.einsum("ijk,vk->ivj", a, v.astype(np.float64)) + t[:, None, :, 3]
    assert np.allclose(world[:, :, 1].min(axis=1), 0.0, atol=1e-9)   # standing on y = 0
    # same seed, same scene; moved() shifts every instance a little in the ground plane
    assert np.array_equal(bench.placement(v, 10)[0], t)
    m = bench.moved(t, grid)
    shift = m[:, :, 3] - t[:, :, 3]
    assert np.allclose(shift[:, 1], 0) and np.allclose(np.hypot(shift[:, 0], shift[:, 2]),
                                                       bench.MOVE * grid.spacing)
    assert np.array_equal(m[:, :, :3], a)


def test_crossed_boxes_is_a_slab_test():
    rng = np.random.default_rng(3)
    lo = rng.uniform(-5, 5, (50, 3))
    hi = lo + rng.uniform(0.1, 1.0, (50, 3))
    o = rng.uniform(-8, 8, (40, 3)).astype(np.float32)
    d = rng.normal(size=(40, 3)).astype(np.float32)
    got = set(bench.crossed_boxes(o, d, lo, hi).tolist())
    # brute force: points along each ray (dense), inside which box
    s = np.linspace(0, 30, 30001)
    p = o[:, None, :].astype(np.float64) + s[None, :, None] * d[:, None, :]
    inside = ((p[:, :, None, :] >= lo) & (p[:, :, None, :] <= hi)).all(axis=3).any(axis=(0, 1))
    assert set(np.flatnonzero(inside).tolist()) <= got
    assert got and got != set(range(50))


def test_tile_rays_are_pixels_of_the_tiles():
    rays = bench.tile_rays((128, 96))
    assert len(rays) == len(bench.TILE_CENTRES) * bench.TILE ** 2   # no two tiles overlap
    assert rays.min() >= 0 and rays.max() < 128 * 96 and np.array_equal(rays, np.unique(rays))
