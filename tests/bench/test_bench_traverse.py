"""The traversal bench (bench/bench_traverse.py): its quick mode end to end with the
real kernels (and the peers when installed), the rays it makes and the arithmetic
of its comparisons."""
from __future__ import annotations

import importlib.util
import json
import math
import statistics
import sys

import numpy as np
import pytest

import lbvh
from conftest import REPO
from lbvh.rendering.camera import Camera
from lbvh.rendering.render import AO_DISTANCE, hit_points, scene_diagonal, triangle_normals


sys.path.insert(0, str(REPO / "bench"))   # bench/ is not a package
import bench_traverse as bench  # noqa: E402


def _importable(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def _finite_positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _expected_tracers() -> set[str]:
    ours = [bench.OURS, f"{bench.OURS}+collapse", bench.TREELETS]
    names = set(ours) | {bench.MOLLER}
    if bench.kernel_only_missing() is None:
        names |= {f"{n} (kernel only)" for n in ours}
    if _importable("embreex"):
        names |= {"embree-1t", "embree-2t"}
    if _importable("warp"):
        names.add("warp")
    return names


# -- the quick mode, end to end -------------------------------------------------------

@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_traverse")
    report = bench.main(["--quick", "--out", str(out)])
    return out, report


def test_quick_json_has_every_field_for_every_query_and_tracer(quick):
    out, report = quick
    data = json.loads((out / "bench_traverse.json").read_text())
    assert data["scenes"] and not data["skipped"]
    assert data["machine"]["cores"] >= 1 and data["machine"]["opencl_device"]
    expected = _expected_tracers()
    for scene in data["scenes"]:
        for query in bench.QUERIES:
            rows = [r for r in data["rows"] if r["scene"] == scene["name"] and r["query"] == query]
            assert {r["tracer"] for r in rows} == expected and len(rows) == len(expected)
    for row in data["rows"]:
        assert set(bench.ROW_FIELDS) <= set(row), set(bench.ROW_FIELDS) - set(row)
        for name in ("hit_fraction", "agreement", "overflow_count", "other_load"):
            if row[name] is None:
                assert row["null_reasons"].get(name), f"{row['tracer']}: {name} null without reason"
        for peer, ratio in row["vs"].items():
            if ratio is None:
                assert row["null_reasons"][f"vs {peer}"]
    assert set(data["cpu_use"]) and all(v > 0 for v in data["cpu_use"].values())


def test_quick_timings_are_medians_of_every_round(quick):
    _, report = quick
    repeats = report["settings"]["repeats"]
    for row in report["rows"]:
        who = f"{row['query']} {row['tracer']}"
        assert len(row["samples"]) == len(row["wall_samples"]) == repeats, who
        assert row["seconds"] == pytest.approx(statistics.median(row["samples"]))
        assert row["rays_per_second"] == pytest.approx(row["rays"] / row["seconds"])
        assert _finite_positive(row["rays_per_second"]) and row["spread"] >= 0, who
        assert 0 < row["cpu_over_wall"] <= report["machine"]["cores"] + 0.5, who
        if row["timing"] == "device":      # kernel only: part of the wall time of the call
            assert all(d <= w for d, w in zip(row["samples"], row["wall_samples"])), who


def test_quick_agreement_is_one_or_every_disagreement_is_judged_right(quick):
    _, report = quick
    reference = "embree-1t" if _importable("embreex") else bench.FALLBACK_REFERENCE
    for scene in report["scenes"]:
        for query, comparison in scene["comparisons"].items():
            assert comparison["reference"] == reference
            # quick mode judges every disagreement (fewer than --judge)
            assert comparison["judged_rays"] == comparison["disagreeing_rays"] <= report["settings"]["judge"]
    for row in report["rows"]:
        a = row["agreement"]
        if row["family"] == "kernel":
            assert a is None and row["hit_fraction"] is None
            continue
        who = f"{row['query']} {row['tracer']}"
        assert 0 <= a["fraction"] <= a["fraction_with_ties"] <= 1, who
        assert a["judged"] == a["disagree"], who
        if row["family"] in ("lbvh", "sah"):
            assert row["overflow_count"] == 0, who
            assert a["fraction_with_ties"] == 1.0 or (a["wrong"] == 0 and a["right"] == a["disagree"]), \
                f"{who}: {a['wrong']} rays wrong by the float64 oracle"
        if row["tracer"] == reference:
            assert a["fraction"] == 1.0 and a["disagree"] == 0
    ao = {r["tracer"]: r["hit_fraction"] for r in report["rows"] if r["query"] == "ao"}
    assert 0 < ao[bench.OURS] < 1        # AO rays are neither all blocked nor all free


def test_quick_ratios_and_targets(quick):
    _, report = quick
    rows = {(r["query"], r["tracer"]): r for r in report["rows"]}
    for query in bench.QUERIES:
        mine = rows[(query, bench.OURS)]
        for peer in ("embree-2t", "warp"):
            ratio = mine["vs"][peer]
            if (query, peer) not in rows:
                assert ratio is None
                continue
            want = rows[(query, peer)]["seconds"] / mine["seconds"]
            assert ratio["ratio"] == pytest.approx(want)
            assert ratio["round_min"] <= ratio["round_max"] and len(ratio["rounds"]) == report["settings"]["repeats"]
    statuses = {(t["peer"], t["status"].split(" (")[0]) for t in report["targets"]}
    assert all("caveat" in t for t in report["targets"])
    judged = set(bench.TARGET_TREES) - {"sah"}          # the SAH tree only with --sah
    assert {t["ours"] for t in report["targets"]} == judged
    for tree in judged:
        for peer, at_least in bench.TARGETS:
            t = next(t for t in report["targets"] if t["peer"] == peer and t["ours"] == tree)
            if (("closest", peer)) in rows:
                assert t["ratio"] == rows[("closest", tree)]["vs"][peer]["ratio"]
                assert t["status"] == ("MET" if t["ratio"] >= at_least else "NOT MET")
            else:
                assert (peer, "NOT MEASURED") in statuses


def test_quick_prices_watertightness_on_every_query(quick):
    """The default tree with Moller-Trumbore beside the watertight test, same rounds:
    a ratio for every query, from the rows' own samples."""
    _, report = quick
    rows = {(r["query"], r["tracer"]): r for r in report["rows"]}
    price = {w["query"]: w for w in report["watertight_price"]}
    assert set(price) == set(bench.QUERIES)
    for query, w in price.items():
        tight, fast = rows[(query, bench.OURS)], rows[(query, bench.MOLLER)]
        assert w["ratio"] == pytest.approx(tight["seconds"] / fast["seconds"])
        rounds = [a / b for a, b in zip(tight["samples"], fast["samples"])]
        assert (w["round_min"], w["round_max"]) == (min(rounds), max(rounds))
        assert len(rounds) == report["settings"]["repeats"]
        assert w["moller_agreement"] == fast["agreement"]
        assert w["watertight_agreement"] == tight["agreement"]


def test_quick_markdown_has_the_tables_and_targets(quick):
    out, report = quick
    text = (out / "bench_traverse.md").read_text()
    for heading in ("## Closest hit: ours against the peers", "## Targets", "## Every tracer, every query"):
        assert heading in text
    assert "## The price of watertightness" in text
    assert text.count(f"| {report['scenes'][0]['name']} | ") == (
        len(report["rows"]) + len(report["closest_ratios"]) + len(report["watertight_price"]))
    assert text.count("**MET**") + text.count("**NOT MET**") + text.count("NOT MEASURED") == len(report["targets"])


def test_without_peers_the_reference_is_ours_and_targets_are_not_measured(tmp_path):
    report = bench.main(["--quick", "--rays", "24x24", "--repeats", "1", "--no-peers",
                         "--out", str(tmp_path)])
    assert {r["family"] for r in report["rows"]} <= {"lbvh", "moller", "kernel"}
    assert report["scenes"][0]["comparisons"]["closest"]["reference"] == bench.FALLBACK_REFERENCE
    assert report["targets"] and all(t["status"].startswith("NOT MEASURED") for t in report["targets"])


def test_missing_scene_is_skipped_with_reason_and_bad_arguments_refused(tmp_path):
    report = bench.main(["--scenes", "bunny", "--shared", str(tmp_path / "absent"), "--no-peers",
                         "--out", str(tmp_path)])
    assert report["rows"] == [] and report["skipped"][0]["scene"] == "bunny"
    assert "not found" in report["skipped"][0]["reason"]
    for argv in (["--scenes", "no-such-scene"], ["--rays", "12by4"], ["--repeats", "0"],
                 ["--ao-samples", "0"]):
        with pytest.raises(SystemExit):
            bench.parse_args(argv)


# -- the rays ------------------------------------------------------------------------

def test_sponza_uses_the_atrium_camera():
    cameras = bench.common.load_cameras()
    assert bench.CAMERA_OF["sponza"] in cameras
    if not (bench.common.SHARED_SCENES / "crytek_sponza.obj").is_file():
        pytest.skip("shared scenes not present")
    scene = bench.load_scene("sponza", (8, 8), cameras, bench.common.SHARED_SCENES)
    assert scene.camera.as_dict()["position"] == cameras["sponza-atrium"]["position"]


def test_ao_rays_leave_the_visible_side_within_the_reach(ctx):
    v, f = bench.common.meshes.sphere(2000)
    bvh = lbvh.build(v, f, device=ctx)
    camera = Camera.from_dict({"position": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0],
                               "fov": 40}, size=(24, 24))
    o, d = camera.rays()
    hits = bvh.intersect(o, d)
    rays = bench.ao_rays(bvh, hits, d, samples=2)
    assert rays.query == "ao" and len(rays) == 2 * int(hits.hit.sum())
    assert rays.tmax == pytest.approx(AO_DISTANCE * scene_diagonal(v))
    # seen from outside a convex mesh, every AO ray leaves its triangle on the outer side
    # (the rays come one sample pass after the other, each over the hit pixels)
    normals = triangle_normals(v, f, hits.prim[hits.hit])
    normals *= np.sign(np.einsum("ij,ij->i", normals, hit_points(
        v, f, hits.prim[hits.hit], hits.u[hits.hit], hits.v[hits.hit])))[:, None]
    assert (np.einsum("ij,ij->i", np.tile(normals, (2, 1)), rays.directions) > 0).all()
    assert not bvh.occluded(rays.origins, rays.directions, tmax=rays.tmax).any()


# -- the arithmetic of the comparisons -------------------------------------------------

def test_chunks_cover_every_ray_once():
    for count, parts in ((10, 16), (1000, 16), (17, 4), (0, 3)):
        covered = np.concatenate([np.arange(count)[s] for s in bench.chunks(count, parts)] or [[]])
        assert covered.tolist() == list(range(count))


def test_differs_counts_hit_miss_and_t_beyond_the_bound_not_ties():
    ref = bench.Answer(np.array([True, True, False, True]), np.int32([0, 1, -1, 3]),
                       np.float32([1.0, 2.0, np.inf, 4.0]))
    got = bench.Answer(np.array([True, True, True, True]), np.int32([0, 7, 2, 3]),
                       np.float32([1.0, 2.0, 3.0, 4.5]))
    bound = np.full(4, 1e-3)
    assert bench.differs(got, ref, bound).tolist() == [False, False, True, True]   # ray 1: a tie
    assert bench.differs(got, ref, None).tolist() == [False, False, True, False]


def test_ratio_to_pairs_the_rounds():
    def contestant(name, samples):
        c = bench.Contestant(bench.common.Variant(name, "x"), None, None, "wall", 0.0)
        c.seconds["closest"] = samples
        return c
    ours, peer = contestant("ours", [2.0, 4.0, 3.0]), contestant("peer", [1.0, 1.0, 1.5])
    r = bench.ratio_to(ours, peer, "closest")
    assert r["ratio"] == pytest.approx(1.0 / 3.0)
    assert r["rounds"] == pytest.approx([0.5, 0.25, 0.5])
    assert (r["round_min"], r["round_max"]) == (0.25, 0.5)
    assert bench.ratio_to(ours, None, "closest") is None and bench.ratio_to(ours, ours, "closest") is None
