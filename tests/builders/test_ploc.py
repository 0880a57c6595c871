"""The device PLOC builder (Meister & Bittner 2018): bit-exact against its numpy twin,
valid trees, the default LBVH's ray answers, a lower SAH cost, and its options."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import random_soup
from lbvh.layout import node_depths
from lbvh.builders import ploc
from lbvh.builders.bounds import triangle_boxes_numpy, triangle_centres_numpy
from lbvh.builders.morton import morton_codes_numpy
from lbvh.builders.ploc import ploc_numpy


def _soup(n: int, seed: int):
    return random_soup(n, seed=seed)


def _identical():
    # 60 copies of one triangle: every merged area ties, ties go to the lower position
    return np.eye(3, dtype=np.float32), np.zeros((60, 3), np.uint32) + [0, 1, 2]


def _few(n: int):
    return _soup(n, seed=n)


def _scaled(seed: int, factor: float):
    v, f = _soup(1500, seed=seed)
    return v * np.float32(factor), f


MESHES = {
    "teapot": lbvh.data.teapot,
    "soup": lambda: _soup(3000, seed=2),
    "one": lambda: _few(1),
    "two": lambda: _few(2),
    "three": lambda: _few(3),
    "identical": _identical,
    "huge": lambda: _scaled(5, 1e30),     # areas overflow float32 without box_scale
    "tiny": lambda: _scaled(6, 1e-30),    # and underflow
}


def _twin_of(bvh: lbvh.BVH, radius: int):
    """The twin's tree over the mesh of ``bvh``, from the device's slot order."""
    lo, hi = triangle_boxes_numpy(bvh.vertices, bvh.faces)
    return ploc_numpy(lo, hi, bvh.tree.read("prim_order"), radius)


def _assert_same_as_twin(bvh: lbvh.BVH, radius: int) -> None:
    nodes, parent, root = _twin_of(bvh, radius)
    device_nodes = bvh.tree.read("nodes")
    assert device_nodes.dtype == nodes.dtype and len(device_nodes) == len(nodes)
    differ = np.flatnonzero(device_nodes.view(np.uint8).reshape(-1, 32)
                            != nodes.view(np.uint8).reshape(-1, 32))
    assert not len(differ), f"node records differ from byte {differ[0]} on"
    assert np.array_equal(bvh.tree.read("parent"), parent)
    assert bvh.root == root == max(len(bvh.faces) - 2, 0)


@pytest.mark.parametrize("name", sorted(MESHES))
def test_device_ploc_matches_twin_bit_for_bit(name):
    v, f = MESHES[name]()
    bvh = lbvh.build(v, f, builder="ploc")
    _assert_same_as_twin(bvh, 16)
    bvh.validate()
    # the leaves: slot k is node F - 1 + k (the Karras numbering), in Morton order
    n = len(f)
    leaves = bvh.tree.read("nodes")[n - 1:]
    assert np.array_equal(leaves["a"], np.arange(n)) and (leaves["b"] == -1).all()
    centres = triangle_centres_numpy(v, f)
    codes = morton_codes_numpy(centres, np.stack([centres.min(0), centres.max(0)]), 64)
    assert np.array_equal(bvh.tree.read("prim_order"), np.argsort(codes, kind="stable"))


@pytest.mark.parametrize("radius", [1, 16, 64])
@pytest.mark.parametrize("name", ["teapot", "soup"])
def test_every_radius_matches_twin(name, radius):
    v, f = MESHES[name]()
    bvh = lbvh.build(v, f, builder="ploc", radius=radius)
    _assert_same_as_twin(bvh, radius)
    bvh.validate()
    assert bvh.tree.builder == ("ploc" if radius == 16 else f"ploc-{radius}")


@pytest.mark.parametrize("tail", [1, 10 ** 9])
def test_parallel_steps_and_tail_alone_give_the_same_tree(monkeypatch, tail):
    """Every step in the parallel kernels (small chunks: many chunk boundaries, lanes at
    the list's ends one by one), or every step in the one-work-item tail."""
    v, f = MESHES["soup"]()
    monkeypatch.setitem(ploc.TAIL_CLUSTERS, "cpu", tail)
    monkeypatch.setitem(ploc.TAIL_CLUSTERS, "gpu", tail)
    monkeypatch.setattr(ploc, "NEAREST_MIN_PER_ITEM", 37)
    monkeypatch.setattr(ploc, "MERGE_MIN_PER_ITEM", 53)
    parallel_steps = []
    queue = ploc._Steps.queue

    def counted(self, side, geometry):
        parallel_steps.append(side)
        queue(self, side, geometry)

    monkeypatch.setattr(ploc._Steps, "queue", counted)
    bvh = lbvh.build(v, f, builder="ploc", radius=5)
    _assert_same_as_twin(bvh, 5)
    assert (not parallel_steps) if tail > len(f) else len(parallel_steps) > 10


def _rays(v: np.ndarray, n: int, seed: int):
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
    centre, size = (lo + hi) / 2, float((hi - lo).max())
    out = rng.normal(size=(n, 3))
    o = centre + out / np.linalg.norm(out, axis=1, keepdims=True) * 2 * size
    d = lo + rng.random((n, 3)) * (hi - lo) - o
    return o.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("name", ["teapot", "soup", "identical"])
def test_closest_hits_equal_the_default_lbvh_bit_for_bit(name):
    v, f = MESHES[name]()
    o, d = _rays(v, 3000, seed=4)
    ours, default = lbvh.build(v, f, builder="ploc"), lbvh.build(v, f)
    got, ref = ours.intersect(o, d), default.intersect(o, d)
    assert 0.2 < ref.mask.mean() <= 1
    assert np.array_equal(got.t.view(np.int32), ref.t.view(np.int32))
    assert np.array_equal(got.prim, ref.prim)
    assert got.overflow_count == 0


def test_sah_cost_below_the_default_lbvh_on_the_teapot():
    v, f = lbvh.data.teapot()
    ours, default = lbvh.build(v, f, builder="ploc"), lbvh.build(v, f)
    assert lbvh.sah_cost(ours) < 0.97 * lbvh.sah_cost(default)


def test_report_and_refit():
    v, f = MESHES["soup"]()
    bvh = lbvh.build(v, f, builder="ploc")
    report = bvh.report()
    assert report.builder == "ploc" and report.key_bits == 63
    assert set(report.phase_seconds) == {"bounds", "morton", "sort", "cluster"}
    assert all(t > 0 for t in report.phase_seconds.values())
    assert report.wall_seconds > 0 and report.peak_device_bytes > 0
    assert report.num_leaves == len(f) and report.num_nodes == 2 * len(f) - 1
    # the leaves are the Karras block: a refit (bottom-up walks from it) keeps the tree valid
    moved = v * np.float32(1.5) + np.float32(0.25)
    bvh.refit(moved)
    bvh.validate()
    o, d = _rays(moved, 500, seed=1)
    assert np.array_equal(bvh.intersect(o, d).t.view(np.int32),
                          lbvh.build(moved, f).intersect(o, d).t.view(np.int32))


@pytest.mark.parametrize("radius", [0, -1, True, "8", 8.0, 257, None])
def test_bad_radius_is_refused_by_name(radius):
    v, f = _few(3)
    with pytest.raises(ValueError, match="radius"):
        lbvh.build(v, f, builder="ploc", radius=radius)
    with pytest.raises(ValueError, match="radius"):
        lbvh.PLOCOptions(radius=radius)


def test_options_as_data_or_keywords_give_the_same_tree():
    v, f = lbvh.data.teapot()
    a = lbvh.build(v, f, builder="ploc", radius=8)
    b = lbvh.build(v, f, builder="ploc", options=lbvh.PLOCOptions(radius=8))
    assert a.nodes.tobytes() == b.nodes.tobytes()
    assert np.array_equal(a.tree.read("parent"), b.tree.read("parent")) and a.root == b.root
    assert np.array_equal(a.prim_order, b.prim_order)
    default = lbvh.build(v, f, builder="ploc")
    assert default.nodes.tobytes() != a.nodes.tobytes()     # the radius is used
    assert lbvh.PLOCOptions().radius == 16
    with pytest.raises(ValueError, match="radius: given both"):
        lbvh.build(v, f, builder="ploc", radius=8, options=lbvh.PLOCOptions(radius=8))
    with pytest.raises(ValueError, match="takes PLOCOptions"):
        lbvh.build(v, f, builder="ploc", options=lbvh.LBVHOptions())


def test_other_builders_options_are_refused():
    v, f = _few(3)
    with pytest.raises(ValueError, match="collapse"):
        lbvh.build(v, f, builder="ploc", collapse=True)
    with pytest.raises(ValueError, match="key_bits"):
        lbvh.build(v, f, builder="ploc", key_bits=30)
    with pytest.raises(ValueError, match="treelet_rounds"):
        lbvh.build(v, f, builder="ploc", treelet_rounds=1)
    with pytest.raises(ValueError, match="unknown option.*c_node"):
        lbvh.build(v, f, builder="ploc", c_node=1.0)
    # the LBVH's defaults (as the command line passes them) are accepted and dropped
    bvh = lbvh.build(v, f, builder="ploc", key_bits="auto", treelet_rounds=0)
    assert bvh.tree.builder == "ploc"


def test_twin_refuses_a_step_without_merges_and_batches_reach_the_tail():
    # the twin's guard: no pair can form without candidates (radius 0 is refused
    # by the options; the twin is called directly here)
    lo = np.zeros((4, 3), np.float32)
    hi = np.ones((4, 3), np.float32)
    with pytest.raises(RuntimeError, match="merged nothing"):
        ploc_numpy(lo, hi, np.arange(4), radius=0)
    assert ploc.batch_steps(100, 2048) == 0
    assert ploc.batch_steps(2049, 2048) == 1
    assert ploc.batch_steps(10 ** 6, 2048, rate=0.5) == 9       # 2^-9 * 1e6 < 2048
    assert ploc.batch_steps(10 ** 9, 2, rate=0.999) == ploc.MAX_BATCH


def test_a_run_of_identical_boxes_halves_at_every_step():
    """Equal areas go to the nearer cluster, the side by the position's parity: 4,096
    identical triangles pair up (2i, 2i + 1) at every step, a balanced tree of depth
    12, where ties to the lower index merged one pair per step (depth 4,095). The
    device's tree is the twin's."""
    n = 4096
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    f = np.tile(np.arange(3, dtype=np.uint32), (n, 1))
    bvh = lbvh.build(v, f, builder="ploc")
    _assert_same_as_twin(bvh, 16)
    depth = int(node_depths(bvh.tree.read("parent"), bvh.root).max())
    assert depth == 12
    # with other boxes around the run, the run still halves: depth near log2
    rng = np.random.default_rng(5)
    soup_v = rng.random((300, 3)).astype(np.float32) * 10
    mixed_v = np.concatenate([v, soup_v])
    mixed_f = np.concatenate([f, np.arange(3, 303, dtype=np.uint32).reshape(100, 3)])
    mixed = lbvh.build(mixed_v, mixed_f, builder="ploc")
    mixed.validate()
    _assert_same_as_twin(mixed, 16)
    assert int(node_depths(mixed.tree.read("parent"), mixed.root).max()) <= 30
