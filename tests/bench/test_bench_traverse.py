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
from lbvh.camera import Camera
from lbvh.rendering.render import AO_DISTANCE, hit_points, scene_diagonal, triangle_normals


sys.path.insert(0, str(REPO / "bench"))   # bench/ is not a package
import bench_traverse as bench  # noqa: E402


def _importable(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def _finite_positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _expected_tracers() -> set[str]:
    ours = [bench.OURS, f"{bench.OURS}+collapse", bench.SMALL_TREELETS, bench.ROUNDS_TREELETS,
            bench.TREELETS]
    names = set(ours) | {bench.MOLLER}
    if bench.kernel_only_missing() is None:
        names |= {f"{n} (kernel only)" for n in ours}
    if _importable("embreex"):
        names |= {"embree-1t", "embree-2t"}
    if _importable("warp"):
        names.add("warp")
    if _importable("open3d"):
        names.add(bench.OPEN3D)
    return names


#: The row families of our trees (their rows carry the traversal counters).
OUR_FAMILIES = ("lbvh", "sah", "moller", "kernel")


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
        for name in ("hit_fraction", "agreement", "overflow_count", "other_load", "nodes_per_ray",
                     "tris_per_ray"):
            if row[name] is None:
                assert row["null_reasons"].get(name), f"{row['tracer']}: {name} null without reason"
        for peer, ratio in row["vs"].items():
            if ratio is None:
                assert row["null_reasons"][f"vs {peer}"]
    assert set(data["cpu_use"]) and all(v > 0 for v in data["cpu_use"].values())


def test_quick_every_tree_row_counts_nodes_and_triangles_per_ray(quick):
    """Every row of our trees (API, Moller, kernel only; closest, any, AO) has the mean
    nodes visited and triangles tested per ray; the kernel-only row has its API row's."""
    _, report = quick
    rows = {(r["query"], r["tracer"]): r for r in report["rows"]}
    for (query, tracer), row in rows.items():
        who = f"{query} {tracer}"
        if row["family"] not in OUR_FAMILIES:
            assert row["nodes_per_ray"] is None and row["tris_per_ray"] is None, who
            continue
        assert _finite_positive(row["nodes_per_ray"]) and row["nodes_per_ray"] >= 1, who  # the root
        assert _finite_positive(row["tris_per_ray"]), who
        n = report["scenes"][0]["triangles"]       # at most every node, every triangle
        assert row["nodes_per_ray"] < 2 * n and row["tris_per_ray"] <= n, who
        if query == "closest" and row["family"] != "kernel":   # a hit tested at least its triangle
            assert row["tris_per_ray"] >= row["hit_fraction"], who
        if row["family"] == "kernel":
            api = rows[(query, tracer.removesuffix(" (kernel only)"))]
            assert (row["nodes_per_ray"], row["tris_per_ray"]) == (api["nodes_per_ray"], api["tris_per_ray"])
    for r in report["closest_ratios"]:
        row = rows[("closest", r["tracer"])]
        assert (r["nodes_per_ray"], r["tris_per_ray"]) == (row["nodes_per_ray"], row["tris_per_ray"])


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
        if row["tracer"] == bench.OPEN3D:     # Embree inside, robust: near the reference
            assert a["fraction_with_ties"] >= 0.99, who
    ao = {r["tracer"]: r["hit_fraction"] for r in report["rows"] if r["query"] == "ao"}
    assert 0 < ao[bench.OURS] < 1        # AO rays are neither all blocked nor all free


def test_quick_ratios_and_targets(quick):
    _, report = quick
    rows = {(r["query"], r["tracer"]): r for r in report["rows"]}
    for query in bench.QUERIES:
        mine = rows[(query, bench.OURS)]
        for peer in ("embree-2t", bench.OPEN3D, "warp"):
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


def test_quick_goal_has_the_default_and_the_best_tree_against_open3d_and_embree(quick):
    """Issue 16's goal: per scene the default tree and the fastest tree built in under
    5x its build time, their ratios those of the rows, the status from the numbers."""
    _, report = quick
    rows = {(r["scene"], r["query"], r["tracer"]): r for r in report["rows"]}
    for sc in report["scenes"]:
        mine = [e for e in report["goal"] if e["scene"] == sc["name"]]
        entries = {e["role"]: e for e in mine}
        assert [e["role"] for e in mine].count("best") == 1 and {e["role"] for e in mine} <= {
            "default", "best", "other"}
        assert entries["default"]["tree"] == bench.OURS and entries["default"]["build_factor"] == 1.0
        build = sc["build_seconds"]
        assert all(len(sc["build_samples"][t]) == bench.BUILD_REPEATS for t in build
                   if t in bench.GOAL_CANDIDATES and t != "sah")
        candidates = [t for t in bench.GOAL_CANDIDATES if (sc["name"], "closest", t) in rows]
        eligible = [t for t in candidates if build[t] < bench.GOAL_BUILD_FACTOR * build[bench.OURS]]
        speed = {t: rows[(sc["name"], "closest", t)]["rays_per_second"] for t in candidates}
        assert entries["best"]["tree"] == max(eligible, key=speed.get)
        others = [e["tree"] for e in mine if e["role"] == "other"]
        assert sorted(others) == sorted(set(candidates) - {bench.OURS, entries["best"]["tree"]})
        for e in mine:
            role = e["role"]
            assert e["build_factor"] == pytest.approx(build[e["tree"]] / build[bench.OURS])
            assert set(e["queries"]) == set(bench.QUERIES)
            for query, q in e["queries"].items():
                row = rows[(sc["name"], query, e["tree"])]
                assert q["rays_per_second"] == row["rays_per_second"]
                assert q["nodes_per_ray"] == row["nodes_per_ray"] and q["tris_per_ray"] == row["tris_per_ray"]
                for peer in bench.GOAL_PEERS:
                    assert q["vs"][peer] == row["vs"][peer]
            if role == "other":
                assert e["at_least"] is None and e["status"] is None and e["not_judged"]
                continue
            assert e["at_least"] == (bench.GOAL_DEFAULT if role == "default" else bench.GOAL_BEST)
            vs = e["queries"]["closest"]["vs"]
            if any(vs[p] is None for p in bench.GOAL_PEERS):
                assert e["status"] == "NOT MEASURED"
            else:
                assert e["status"] == ("MET" if all(vs[p]["ratio"] >= e["at_least"]
                                                    for p in bench.GOAL_PEERS) else "NOT MET")
    judged = [e["status"] for e in report["goal"] if e["at_least"] is not None]
    want = ("NOT MEASURED" if "NOT MEASURED" in judged else "NOT MET" if "NOT MET" in judged else "MET")
    assert report["goal_verdict"]["closest"]["status"] == want
    assert set(report["goal_verdict"]) == set(bench.QUERIES)


def test_goal_judges_from_the_numbers():
    """The goal on made-up rows: the best tree is the fastest built fast enough, each
    status follows from the ratios, a missing peer makes it NOT MEASURED."""
    def row(tracer, query, mrays, vs):
        return {"scene": "s", "query": query, "tracer": tracer, "threads": None, "cpu_over_wall": 2.0,
                "other_load": 0.0, "rays_per_second": mrays * 1e6, "nodes_per_ray": 10.0,
                "tris_per_ray": 3.0, "vs": {p: (None if r is None else
                                                {"ratio": r, "round_min": r, "round_max": r})
                                            for p, r in vs.items()}}
    build = {bench.OURS: 1.0, f"{bench.OURS}+collapse": 2.0, bench.TREELETS: 4.0, "sah": 50.0}
    speeds = {bench.OURS: (1.0, 0.9, 0.85), f"{bench.OURS}+collapse": (1.1, 1.0, 1.0),
              bench.TREELETS: (1.3, 1.2, 1.05), "sah": (1.5, 1.4, 1.3)}
    rows = [row(t, q, 3.0 * s[0], {bench.OPEN3D: s[1], "embree-2t": s[2]})
            for t, s in speeds.items() for q in bench.QUERIES]
    scenes = [{"name": "s", "build_seconds": build}]
    entries = bench.goal(rows, scenes)
    by_tree = {(e["role"], e["tree"]): e for e in entries}
    assert by_tree[("default", bench.OURS)]["status"] == "MET"
    assert by_tree[("best", bench.TREELETS)]["status"] == "MET"
    assert "slower" in by_tree[("other", f"{bench.OURS}+collapse")]["not_judged"]
    assert "50.0x" in by_tree[("other", "sah")]["not_judged"]
    assert by_tree[("other", "sah")]["status"] is None and len(entries) == 4
    assert bench.goal_verdict(entries)["closest"]["status"] == "MET"
    # the default tree the fastest: judged twice, at 0.8x and at 1.0x (1.05x open3d, 0.9x embree-2t)
    fast_default = [dict(r, rays_per_second=1e9, vs={bench.OPEN3D: {"ratio": 1.05, "round_min": 1, "round_max": 1},
                                                   "embree-2t": {"ratio": 0.9, "round_min": 1, "round_max": 1}})
                    if r["tracer"] == bench.OURS else r for r in rows]
    entries = bench.goal(fast_default, scenes)
    assert [(e["role"], e["tree"], e["status"]) for e in entries][:2] == [
        ("default", bench.OURS, "MET"), ("best", bench.OURS, "NOT MET")]
    # the best tree 0.95x embree-2t: NOT MET, said in the verdict
    rows = [dict(r, vs={**r["vs"], "embree-2t": {"ratio": 0.95, "round_min": 0.9, "round_max": 1.0}})
            if r["tracer"] == bench.TREELETS else r for r in rows]
    entries = bench.goal(rows, scenes)
    verdict = bench.goal_verdict(entries)["closest"]
    assert verdict["status"] == "NOT MET" and verdict["met"] == 1 and verdict["judged"] == 2
    assert "0.95x embree-2t" in verdict["why"][0]
    # no Open3D: not measured
    rows = [dict(r, vs={**r["vs"], bench.OPEN3D: None}) for r in rows]
    verdict = bench.goal_verdict(bench.goal(rows, scenes))["closest"]
    assert verdict["status"] == "NOT MEASURED" and verdict["why"] == [f"{bench.OPEN3D} not in this run"]


def test_gap_splits_the_ratio_into_host_tree_and_walk():
    """The gap table on made-up rates: gap = host x tree x walk, the top tree the fastest
    kernel of any build time, rows only where the kernel and the peer were measured."""
    def row(tracer, family, mrays):
        return {"scene": "s", "query": "closest", "tracer": tracer, "family": family,
                "rays_per_second": mrays * 1e6, "nodes_per_ray": 9.0, "tris_per_ray": 2.0}
    best = bench.SMALL_TREELETS
    rows = [row(best, "lbvh", 4.0), row(f"{best} (kernel only)", "kernel", 5.0),
            row(f"{bench.TREELETS} (kernel only)", "kernel", 6.0),
            row(f"{bench.OURS} (kernel only)", "kernel", 3.0),
            row("embree-2t", "embree", 9.0), row(bench.OPEN3D, "open3d", 3.0)]
    entries = [{"scene": "s", "role": "best", "tree": best},
               {"scene": "s", "role": "default", "tree": bench.OURS}]
    out = {g["peer"]: g for g in bench.gap(rows, entries)}
    assert set(out) == {"embree-2t", bench.OPEN3D}
    e = out["embree-2t"]
    assert e["top_tree"] == bench.TREELETS
    assert (e["gap"], e["host"], e["tree_quality"], e["walk"]) == pytest.approx((2.25, 1.25, 1.2, 1.5))
    assert e["gap"] == pytest.approx(e["host"] * e["tree_quality"] * e["walk"])
    assert out[bench.OPEN3D]["gap"] == pytest.approx(0.75)
    text = "\n".join(bench.gap_markdown(list(out.values())))
    assert "## Where the gap is" in text and "| s | closest | " in text
    # no kernel-only row of the best tree: nothing to split
    assert bench.gap([r for r in rows if r["tracer"] != f"{best} (kernel only)"], entries) == []
    assert bench.gap_markdown([]) == []


def test_quick_markdown_has_the_tables_and_targets(quick):
    out, report = quick
    text = (out / "bench_traverse.md").read_text()
    for heading in ("## Goal (issue 16", "## Closest hit: ours against the peers", "## Targets",
                    "## Every tracer, every query"):
        assert heading in text
    assert "## The price of watertightness" in text
    assert text.count(f"| {report['scenes'][0]['name']} | ") == (
        len(report["rows"]) + len(report["closest_ratios"]) + len(report["watertight_price"])
        + len(report["goal"]) + len(report["scenes"][0]["small_batches"]) + len(report["gap"])
        + len(report["rays_goal"]))
    assert "## Goal (rays ahead of Embree and Open3D" in text
    assert "## Small batches" in text
    verdict = [line for line in text.splitlines() if line.startswith("**Verdict, closest hit: ")]
    assert len(verdict) == 1 and report["goal_verdict"]["closest"]["status"] + "**" in verdict[0]
    targets = text.split("## Targets", 1)[1].split("\n## ", 1)[0]
    assert targets.count("**MET**") + targets.count("**NOT MET**") + targets.count("NOT MEASURED") == len(report["targets"])
    header = next(line for line in text.splitlines() if line.startswith("| scene | query | tracer |"))
    for column in ("nodes/ray", "tris/ray", "/ open3d"):
        assert f"| {column} |" in header


def test_quick_small_batches_time_every_tracer_on_the_same_calls(quick):
    """The small-batch table: every size that the quick run's rays hold, our default
    tree and every peer timed, ours / peer the median of the per-round time ratios."""
    _, report = quick
    scene = report["scenes"][0]
    n_rays = scene["rays"]["closest"]
    small = scene["small_batches"]
    assert [e["rays"] for e in small] == [n for n in bench.SMALL_BATCHES if n <= n_rays]
    peers = {n for n in _expected_tracers()
             if n.startswith(("embree", "warp")) or n == bench.OPEN3D}
    for e in small:
        assert e["calls"] == report["settings"]["small_calls"] == 3
        assert set(e["seconds"]) == {bench.OURS} | peers
        assert all(_finite_positive(v) for v in e["seconds"].values())
        assert set(e["ours_over"]) == peers
        assert all(len(v) == 3 for v in e["samples"].values())
        for name, v in e["samples"].items():
            assert e["seconds"][name] == statistics.median(v)
        ours = np.array(e["samples"][bench.OURS])
        for peer, ratio in e["ours_over"].items():
            assert ratio == float(np.median(np.array(e["samples"][peer]) / ours))


def test_small_batches_off(tmp_path):
    report = bench.main(["--quick", "--no-peers", "--small-calls", "0", "--out", str(tmp_path)])
    assert report["scenes"][0]["small_batches"] == []
    assert "## Small batches" not in (tmp_path / "bench_traverse.md").read_text()


def test_without_peers_the_reference_is_ours_and_targets_are_not_measured(tmp_path):
    report = bench.main(["--quick", "--rays", "24x24", "--repeats", "1", "--no-peers",
                         "--out", str(tmp_path)])
    assert {r["family"] for r in report["rows"]} <= {"lbvh", "moller", "kernel"}
    assert report["scenes"][0]["comparisons"]["closest"]["reference"] == bench.FALLBACK_REFERENCE
    assert report["targets"] and all(t["status"].startswith("NOT MEASURED") for t in report["targets"])
    assert report["goal_verdict"]["closest"]["status"] == "NOT MEASURED"
    assert all(r["nodes_per_ray"] is not None for r in report["rows"])


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


def test_rays_goal_judges_each_check_from_the_report():
    """The rays' goal: per query ours over each goal peer against RAYS_GOAL, the call of
    1,000 rays over Open3D, one ray's time; a missing figure is not judged."""
    vs = {bench.OPEN3D: {"ratio": 1.4}, "embree-2t": {"ratio": 1.2}}
    entry = {"scene": "s", "role": "default",
             "queries": {"closest": {"vs": vs}, "any": {"vs": vs},
                         "ao": {"vs": {bench.OPEN3D: {"ratio": 1.0}, "embree-2t": None}}}}
    small = [{"rays": 1, "seconds": {bench.OURS: 25e-6}, "ours_over": {}},
             {"rays": 1000, "seconds": {}, "ours_over": {bench.OPEN3D: 1.1}}]
    report = {"goal": [entry, {**entry, "role": "best"}],
              "scenes": [{"name": "s", "small_batches": small}]}
    rows = bench.rays_goal(report)
    assert len(rows) == 1
    met = {c["what"]: c["met"] for c in rows[0]["checks"]}
    assert met == {f"closest / {bench.OPEN3D}": True, "closest / embree-2t": False,
                   f"any / {bench.OPEN3D}": True, "any / embree-2t": False,
                   f"ao / {bench.OPEN3D}": True, "ao / embree-2t": None,
                   f"1,000 rays / {bench.OPEN3D}": True, "one ray (us)": False}
    text = "\n".join(bench.rays_goal_markdown(rows))
    assert "**4 of 7 checks met.**" in text and "| s | 1.40 | 1.20* |" in text
