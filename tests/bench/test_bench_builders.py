"""The builders bench (bench/bench_builders.py): its quick mode end to end, its
break-even, agreement and rank-correlation arithmetic, and the claim its agreement
column rests on: every builder's tree, traced by the same kernel, returns the same hits."""
from __future__ import annotations

import importlib.util
import json
import math
import sys

import numpy as np
import pytest

from conftest import REPO, load_bench, shipped_mesh
from lbvh.verification.oracle import hits_on
from lbvh.queries.traverse import intersect


sys.path.insert(0, str(REPO / "bench"))   # bench/ is not a package: the script imports common
import common  # noqa: E402  (bench/common.py)

bench = load_bench("bench_builders")


def _importable(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


# -- the quick mode, end to end -------------------------------------------------------

@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_builders")
    report = bench.main(["--quick", "--out", str(out)])
    return out, report


def _finite_positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def test_quick_json_has_every_field_for_every_scene_and_builder(quick):
    out, report = quick
    data = json.loads((out / "bench_builders.json").read_text())
    assert data["rows"] and data["scenes"] and not data["skipped"]
    machine = data["machine"]
    assert machine["cpu"] and machine["cores"] >= 1 and machine["opencl_device"]
    expected = {v.name for v in bench.our_variants()}
    assert {"median", "midpoint", bench.REFERENCE} <= expected
    if _importable("embreex"):
        expected.add("embree")
    if _importable("warp"):
        expected |= {f"warp-{c}" for c in common.Warp.CONSTRUCTORS}
    for scene in data["scenes"]:
        rows = [r for r in data["rows"] if r["scene"] == scene["name"]]
        assert {r["builder"] for r in rows} == expected
        assert len(rows) == len(expected)
        assert 0.5 <= scene["hit_fraction"] <= 1      # the camera sees the scene
    for row in data["rows"]:
        assert set(bench.ROW_FIELDS) <= set(row), set(bench.ROW_FIELDS) - set(row)
        for name in bench.ROW_FIELDS:
            if row[name] is None:
                assert row["null_reasons"].get(name), f"{row['builder']}: {name} is null without reason"


def test_quick_numbers_are_finite_and_sane(quick):
    _, report = quick
    for row in report["rows"]:
        who = f"{row['scene']} {row['builder']}"
        for name in ("build_seconds", "render_seconds", "rays_per_second", "seconds_per_ray"):
            assert _finite_positive(row[name]), (who, name, row[name])
        assert row["rays_per_second"] == pytest.approx(row["rays"] / row["render_seconds"])
        assert row["build_seconds"] == pytest.approx(float(np.median(row["build"]["samples"])))
        assert 0 <= row["hit_fraction"] <= 1
        a = row["agreement"]
        assert 0 <= a["fraction"] <= a["fraction_with_ties"] <= 1
        if row["family"] in bench.OUR_FAMILIES:
            for name in ("sah_cost", "sah_ratio", "epo", "ray_cost", "traversal_cost_per_ray",
                         "traversal_ratio"):
                assert _finite_positive(row[name]), (who, name, row[name])
            assert row["tree"]["epo"] == row["epo"] and row["tree"]["epo_stderr"] >= 0
            assert row["tree"]["ray_cost"]["rays"] == row["rays"]
            assert row["ray_cost"] >= row["tree"]["ray_cost"]["inner"] > 0
            assert row["nodes_per_ray"] >= 1 and row["tris_per_ray"] >= 0
            assert row["overflow_count"] == 0
            assert row["tree"]["num_nodes"] >= 1 and row["tree"]["depth"] >= 0
            assert row["tree"]["key_bits"] in (30, 63, None)
            # same kernel, same triangle tests: the same closest hits up to ties
            assert a["fraction_with_ties"] == 1.0 and a["hit_miss_differ"] == 0
    families = {r["builder"]: r["family"] for r in report["rows"]}
    assert families["median"] == families["midpoint"] == "topdown"
    for ref in (r for r in report["rows"] if r["builder"] == bench.REFERENCE):
        assert ref["sah_ratio"] == 1.0 and ref["traversal_ratio"] == 1.0
        assert ref["agreement"]["fraction"] == 1.0


def test_quick_break_even_is_a_number_or_null_with_reason(quick):
    _, report = quick
    for row in report["rows"]:
        builders = {r["builder"] for r in report["rows"] if r["scene"] == row["scene"]}
        for name in ("break_even_vs_fastest", "break_even_vs_reference"):
            b = row[name]
            assert b["against"] in builders
            if b["rays"] is None:
                assert isinstance(b["reason"], str) and b["reason"]
            else:
                assert _finite_positive(b["rays"]) and b["reason"] is None
                assert {b["cheaper_before"], b["cheaper_after"]} == {row["builder"], b["against"]}
    for scene in report["scenes"]:
        for key in ("best_by_rays", "best_by_rays_ours"):
            segments = scene[key]
            assert segments[0]["from_rays"] == 0 and segments[-1]["to_rays"] is None
            for before, after in zip(segments, segments[1:]):
                assert before["to_rays"] == after["from_rays"]


def test_quick_global_order_agrees_with_the_ordered_traversal(quick):
    _, report = quick
    for row in report["rows"]:
        g = row["global_order"]
        if row["family"] not in bench.OUR_FAMILIES:
            assert g is None and row["null_reasons"]["global_order"]
            continue
        for name in ("render_seconds", "rays_per_second", "time_ratio", "nodes_per_ray",
                     "nodes_ratio"):
            assert _finite_positive(g[name]), (row["builder"], name, g[name])
        assert len(g["samples"]) == len(row["render"]["samples"])
        assert g["tris_per_ray"] >= 0
        # the teapot's trees are shallow: no heap overflows, the same t on every ray
        assert g["overflow_count"] == 0 and g["same_t"] == 1.0, row["builder"]


def test_quick_correlation_table_ranks_every_metric(quick):
    out, report = quick
    corr = report["metric_correlation"]
    scene = report["scenes"][0]["name"]
    assert set(corr["metrics"]) == set(bench.METRICS)
    assert corr["trees"][scene] == sum(r["family"] in bench.OUR_FAMILIES for r in report["rows"])
    for metric in bench.METRICS:
        for rho in (corr["per_scene"][scene][metric], corr["mean"][metric]):
            assert rho is not None and -1 <= rho <= 1, (metric, rho)
    assert corr["best_tree_metric"] and set(corr["best_tree_metric"]) <= set(bench.TREE_METRICS)
    top = max(corr["mean"][m] for m in bench.TREE_METRICS)
    assert all(corr["mean"][m] == pytest.approx(top) for m in corr["best_tree_metric"])
    text = (out / "bench_builders.md").read_text()
    table = _section(text, "## Which cost metric predicts the render time")
    rows = [line for line in table.splitlines() if line.startswith(f"| {scene} |")]
    assert len(rows) == 1
    values = [float(cell) for cell in rows[0].strip("|").split("|")[2:]]
    assert len(values) == len(bench.METRICS) and all(-1 <= v <= 1 for v in values)
    names = " and ".join(f"**{corr['metrics'][m]}**" for m in corr["best_tree_metric"])
    assert f"{names} ranked the trees" in table   # one metric, or the tied ones


def _section(text: str, heading: str) -> str:
    """The Markdown from ``heading`` to the next heading of its level."""
    start = text.index(heading + "\n")
    end = text.find("\n## ", start + len(heading))
    return text[start:end if end >= 0 else len(text)]


def test_quick_writes_markdown_chart_and_view(quick):
    out, report = quick
    text = (out / "bench_builders.md").read_text()
    assert "| scene | tris | builder | build ms |" in text
    scene = report["scenes"][0]["name"]
    main_table = text[:text.index("\n## ")]
    assert main_table.count(f"| {scene} |") == len(report["rows"])
    ours = [r for r in report["rows"] if r["family"] in bench.OUR_FAMILIES]
    order_table = _section(text, "## Ordered against global-order traversal")
    assert order_table.count(f"| {scene} |") == len(ours)
    for builder in ("median", "midpoint"):
        assert f"| {scene} | {builder} |" in order_table
        line = next(x for x in main_table.splitlines() if f"| {builder} |" in x)
        epo, ray_cost = line.strip("|").split("|")[8:10]
        assert float(epo) > 0 and float(ray_cost) > 0, line
    assert (out / "views" / f"{report['scenes'][0]['name']}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if not _importable("matplotlib"):
        assert report["chart_missing"]
        pytest.skip("matplotlib is not installed: no chart")
    assert report["chart_missing"] is None
    assert (out / "bench_builders.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_missing_scene_is_skipped_with_reason_and_bad_names_refused(tmp_path):
    report = bench.main(["--scenes", "bunny", "--shared", str(tmp_path / "absent"), "--no-peers",
                         "--out", str(tmp_path)])
    assert report["rows"] == [] and report["skipped"][0]["scene"] == "bunny"
    assert "not found" in report["skipped"][0]["reason"]
    with pytest.raises(SystemExit):
        bench.parse_args(["--scenes", "no-such-scene"])
    with pytest.raises(SystemExit):
        bench.parse_args(["--rays", "12by4"])


# -- the arithmetic of the comparisons -------------------------------------------------

def _line(name, build, per_ray):
    return {"builder": name, "build_seconds": build, "seconds_per_ray": per_ray}


def test_break_even_solves_build_a_plus_n_cost_a_equals_build_b_plus_n_cost_b():
    fast, good = _line("fast", 1.0, 4e-6), _line("good", 3.0, 1e-6)
    b = bench.crossing(good, fast)
    assert b["rays"] == pytest.approx(2.0 / 3e-6)      # 1 + 4e-6 n = 3 + 1e-6 n
    assert (b["cheaper_before"], b["cheaper_after"]) == ("fast", "good")
    assert bench.crossing(fast, good)["rays"] == pytest.approx(b["rays"])
    worse = _line("worse", 2.0, 5e-6)                  # slower build, slower trace
    never = bench.crossing(worse, fast)
    assert never["rays"] is None and never["cheaper_after"] == "fast" and never["reason"]
    assert bench.crossing(fast, worse)["cheaper_before"] == "fast"
    assert bench.crossing(fast, fast)["rays"] is None


def test_lower_envelope_picks_the_cheapest_builder_at_every_ray_count():
    lines = [_line("a", 1.0, 4e-6), _line("b", 3.0, 1e-6), _line("c", 2.0, 3.9e-6),
             _line("d", 10.0, 0.5e-6)]
    segments = bench.lower_envelope(lines)
    assert [s["builder"] for s in segments] == ["a", "b", "d"]
    for s in segments:                       # check against brute force inside each segment
        upper = s["to_rays"] if s["to_rays"] is not None else 2 * s["from_rays"] + 1e9
        for n in np.linspace(s["from_rays"], upper, 7)[1:-1]:
            best = min(lines, key=lambda r: r["build_seconds"] + n * r["seconds_per_ray"])
            assert best["builder"] == s["builder"], n


def test_average_ranks_share_ties_and_spearman_matches_hand_values():
    assert bench.average_ranks([3.0, 1.0, 2.0]).tolist() == [3, 1, 2]
    assert bench.average_ranks([5, 1, 5, 5, 0]).tolist() == [4, 2, 4, 4, 1]
    assert bench.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert bench.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    # ties: ranks x (1, 2.5, 2.5, 4), y (1, 3, 2, 4): 4.5 / sqrt(4.5 * 5)
    assert bench.spearman([1, 2, 2, 3], [1, 3, 2, 4]) == pytest.approx(4.5 / math.sqrt(22.5))
    # without ties: 1 - 6 sum d^2 / (n (n^2 - 1))
    rng = np.random.default_rng(3)
    x, y = rng.permutation(9), rng.permutation(9)
    d2 = float(((x - y) ** 2).sum())
    assert bench.spearman(x, y) == pytest.approx(1 - 6 * d2 / (9 * 80))
    assert bench.spearman([1, 1, 1], [1, 2, 3]) is None       # a constant metric ranks nothing
    assert bench.spearman([1, 2], [1, 2]) is None


def test_metric_correlation_names_the_metric_that_orders_the_renders():
    def row(builder, render, sah, epo, family="lbvh", scene="s"):
        return {"scene": scene, "builder": builder, "family": family, "render_seconds": render,
                "sah_cost": sah, "epo": epo, "ray_cost": None if sah is None else -sah,
                "nodes_per_ray": 1.0,
                "tris_per_ray": render, "traversal_cost_per_ray": 1.0 + render}
    rows = [row("a", 1.0, 10, 3), row("b", 2.0, 20, 1), row("c", 3.0, 30, 2),
            row("d", 4.0, 40, 4, family="sah"),
            row("peer", 0.1, None, None, family="embree")]       # no tree: left out
    corr = bench.metric_correlation(rows)
    assert corr["trees"] == {"s": 4}
    rho = corr["per_scene"]["s"]
    assert rho["sah_cost"] == pytest.approx(1) and rho["ray_cost"] == pytest.approx(-1)
    assert rho["epo"] == pytest.approx(0.4) and rho["nodes_per_ray"] is None
    assert corr["best_tree_metric"] == ["sah_cost"]
    assert corr["best"] == ["sah_cost", "tris_per_ray", "traversal_cost_per_ray"]   # tied at +1
    verdict = bench.correlation_verdict(corr)
    assert "**SAH cost** ranked the trees" in verdict and "as well" in verdict


def test_chart_gives_every_builder_its_own_point_style():
    styles = {v.name: bench.point_style(v.name, v.family) for v in bench.our_variants()}
    keys = {(s["color"], s["marker"]) for s in styles.values()}
    assert len(keys) == len(styles)
    assert styles["median"]["marker"] != styles["midpoint"]["marker"]


def test_agreement_counts_ties_misses_and_t_errors():
    t_ref = np.float32([1.0, 2.0, np.inf, 4.0, 5.0])
    p_ref = np.int32([0, 1, -1, 3, 4])
    t = np.float32([1.0, 2.0, 3.0, 4.0, 5.5])
    prim = np.int32([0, 7, 2, 3, 4])                  # a tie, a false hit, a t off by far
    bound = np.full(5, 1e-3)
    a = bench.agreement(t, prim, t_ref, p_ref, bound)
    assert a["fraction"] == pytest.approx(2 / 5) and a["fraction_with_ties"] == pytest.approx(3 / 5)
    assert (a["ties"], a["hit_miss_differ"], a["t_out_of_bound"]) == (1, 1, 1)


# -- every builder, one kernel, the same hits -----------------------------------------

def _rays(v, camera_name, rng, n_random=1500):
    """The bench camera's rays plus rays from a sphere around the scene towards its box."""
    camera = common.Camera.from_dict(common.load_cameras()[camera_name], size=(64, 48))
    o_cam, d_cam = camera.rays()
    lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
    centre, ext = (lo + hi) / 2, float((hi - lo).max())
    around = rng.normal(size=(n_random, 3))
    o = centre + around / np.linalg.norm(around, axis=1, keepdims=True) * 2 * ext
    d = lo + rng.random((n_random, 3)) * (hi - lo) - o
    return (np.concatenate([o_cam, o.astype(np.float32)]),
            np.concatenate([d_cam, d.astype(np.float32)]))


@pytest.mark.parametrize("name", ["teapot", "suzanne"])
def test_every_builder_returns_the_same_hits_through_the_same_kernel(name, ctx):
    v, f = shipped_mesh(f"{name}.obj")
    o, d = _rays(v, name, np.random.default_rng(7))
    trees = {variant.name: bench.build_tree(variant, v, f, ctx) for variant in bench.our_variants()}
    ref = intersect(trees[bench.REFERENCE], o, d)
    assert 0.2 < ref.hit.mean() < 1
    bound = bench.t_bound(v, f, o, d, ref.t, ref.prim, cos_floor=bench.AGREEMENT_COS_FLOOR)
    for builder, bvh in trees.items():
        bvh.validate()
        got = intersect(bvh, o, d)
        assert got.overflow_count == 0, builder
        assert (got.hit == ref.hit).all(), f"{builder}: hit/miss differs on ray {np.flatnonzero(got.hit != ref.hit)[0]}"
        hit = np.flatnonzero(ref.hit)
        err = np.abs(got.t[hit].astype(np.float64) - ref.t[hit])
        assert (err <= bound[hit]).all(), f"{builder}: t off by {err.max():.3g}"
        # another primitive only where it is a tie: the ray meets it at the same t
        other = hit[got.prim[hit] != ref.prim[hit]]
        if len(other):
            t_other, _, _ = hits_on(v, f, o[other], d[other], got.prim[other])
            assert (np.abs(t_other - ref.t[other]) <= bound[other]).all(), builder
