"""Whole device builds: valid trees on real and generated scenes, and the API around them."""
from __future__ import annotations

import gc
import os
import subprocess
import sys

import numpy as np
import pytest

import lbvh
from conftest import REPO, random_soup, shared_mesh, shipped_mesh
from lbvh import device as dev
from lbvh.layout import NODE_DTYPE, children_of, is_leaf, prim_range_of


@pytest.mark.parametrize("scene", ["stanford-bunny.obj", "crytek_sponza.obj", "conference.obj"])
@pytest.mark.parametrize("keys", [30, 63, "auto"])
def test_shared_scenes_build_valid_trees(scene, keys):
    v, f = shared_mesh(scene)
    bvh = lbvh.build(v, f, key_bits=keys)
    bvh.validate()
    rep = bvh.report()
    assert rep.num_triangles == len(f) and rep.num_leaves == len(f)
    assert rep.num_nodes == 2 * len(f) - 1
    # Karras trees are at most (key bits + index bits) deep
    assert rep.depth <= rep.key_bits + 32


def test_conference_zero_area_triangles_and_auto_keys():
    v, f = shared_mesh("conference.obj")
    tri = v[f].astype(np.float64)
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert (area2 == 0).sum() == 53627  # the scene as documented
    bvh = lbvh.build(v, f, key_bits="auto")
    rep = bvh.report()
    # many 30-bit codes collide in this scene: auto must move to 63 bits and say why
    assert rep.key_bits == 63 and "moved to 63 bits" in rep.key_choice
    assert f"of {len(f):,} 30-bit codes are duplicates" in rep.key_choice
    # 63 bits separate more of them, but the identical triangles of the scene still collide
    assert 0 < rep.duplicate_codes < int(rep.key_choice.split()[1].replace(",", ""))


def test_auto_keeps_30_bits_when_codes_separate_well():
    v, f = random_soup(5000, seed=11)
    rep = lbvh.build(v, f).report()
    assert rep.key_bits == 30 and "kept 30 bits" in rep.key_choice


GENERATED = {
    "all_identical": lambda: (np.tile(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), (20000, 1)),
                              np.arange(60000, dtype=np.uint32).reshape(-1, 3)),
    "one_point": lambda: (np.zeros((3000, 3), np.float32), np.arange(3000, dtype=np.uint32).reshape(-1, 3)),
    "flat_z": lambda: (random_soup(4000, 1)[0] * np.float32([1, 1, 0]), random_soup(4000)[1]),
    "line_y": lambda: (random_soup(4000, 2)[0] * np.float32([0, 1, 0]), random_soup(4000)[1]),
    "one_triangle": lambda: (np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.uint32([[0, 1, 2]])),
    "two_triangles": lambda: (np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]),
                              np.uint32([[0, 1, 2], [1, 3, 2]])),
    "pow2_plus_1": lambda: random_soup(4097, 3),
}


@pytest.mark.parametrize("name", sorted(GENERATED))
@pytest.mark.parametrize("keys", [30, 63])
def test_generated_cases_build_valid_trees(name, keys):
    v, f = GENERATED[name]()
    bvh = lbvh.build(v, f, key_bits=keys)
    bvh.validate()
    assert bvh.tree.num_nodes == 2 * len(f) - 1 and bvh.root == 0
    assert np.isfinite(bvh.nodes["lower"]).all() and np.isfinite(bvh.nodes["upper"]).all()
    if name == "all_identical":
        assert bvh.report().duplicate_codes == len(f) - 1


def test_views_follow_the_documented_layout():
    v, f = shipped_mesh("teapot.obj")
    bvh = lbvh.build(v, f)
    n = len(f)
    assert bvh.nodes.dtype == NODE_DTYPE and bvh.nodes.shape == (2 * n - 1,)
    assert bvh.nodes["lower"].dtype == np.float32 and bvh.nodes["lower"].shape == (2 * n - 1, 3)
    assert children_of(bvh.nodes).dtype == np.int32 and children_of(bvh.nodes).shape == (2 * n - 1, 2)
    assert (children_of(bvh.nodes)[n - 1:] == -1).all() and (children_of(bvh.nodes)[: n - 1] >= 0).all()
    assert np.array_equal(prim_range_of(bvh.nodes)[n - 1:], np.stack([np.arange(n), np.ones(n)], 1))
    assert bvh.tree.read("parent")[0] == -1 and bvh.prim_order.dtype == np.int32
    assert np.array_equal(np.sort(bvh.prim_order), np.arange(n))
    assert is_leaf(bvh.nodes).sum() == n
    with pytest.raises(ValueError):
        bvh.nodes["lower"][0] = 0  # views are read-only: the device copy is the truth


def test_save_and_load_round_trip(tmp_path):
    v, f = shipped_mesh("suzanne.obj")
    bvh = lbvh.build(v, f)
    path = tmp_path / "suzanne_bvh.npz"
    bvh.save(path)
    with np.load(path) as data:  # a plain numpy container
        assert data["nodes"].dtype == NODE_DTYPE
    loaded = lbvh.load(path)
    loaded.validate()
    for name in ("nodes", "prim_order", "vertices", "faces"):
        assert np.array_equal(getattr(loaded, name), getattr(bvh, name)), name
    assert np.array_equal(loaded.tree.read("parent"), bvh.tree.read("parent"))
    loaded.refit(v * np.float32(2))
    loaded.validate()


def test_load_rejects_other_files(tmp_path):
    bad = tmp_path / "other.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(ValueError, match="not a saved lbvh BVH"):
        lbvh.load(bad)
    text = tmp_path / "text.npz"
    text.write_text("hello")
    with pytest.raises(ValueError, match="not a saved lbvh BVH"):
        lbvh.load(text)


def test_save_writes_the_path_given_and_load_reads_it_back(tmp_path):
    """Issue 19, item 4: no suffix is added behind the caller's back."""
    bvh = lbvh.build(*random_soup(300, seed=4))
    for name in ("noext", "tree.bvh", "tree.npz"):
        bvh.save(tmp_path / name)
        assert (tmp_path / name).is_file() and not (tmp_path / f"{name}.npz").exists()
        assert np.array_equal(lbvh.load(str(tmp_path / name)).nodes, bvh.nodes)


def test_loading_a_missing_file_is_a_file_not_found_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.npz: no such file"):
        lbvh.load(tmp_path / "absent.npz")
    with pytest.raises(ValueError, match="no such file"):   # still a ValueError too
        lbvh.load(tmp_path / "absent.npz")
    with pytest.raises(FileNotFoundError, match="a folder"):
        lbvh.load(tmp_path)


def test_refit_follows_moving_vertices():
    v, f = shipped_mesh("teapot.obj")
    bvh = lbvh.build(v, f)
    moved = v + np.float32([10, -3, 2])
    bvh.refit(moved)
    bvh.validate()
    fresh = lbvh.build(moved, f)
    assert np.allclose(bvh.nodes["lower"][bvh.root], fresh.nodes["lower"][fresh.root])
    assert np.array_equal(bvh.nodes["lower"][bvh.root], moved.min(axis=0))


def test_second_build_compiles_nothing(ctx):
    v, f = shipped_mesh("teapot.obj")
    lbvh.build(v, f, key_bits="auto")
    lbvh.build(v, f, key_bits=30)
    before = ctx.compiled_programs()
    v2, f2 = random_soup(3000, seed=9)
    lbvh.build(v2, f2, key_bits="auto")
    lbvh.build(v2, f2, key_bits=30)
    assert ctx.compiled_programs() == before


def test_report_has_phases_memory_and_device():
    v, f = shared_mesh("stanford-bunny.obj")
    bvh = lbvh.build(v, f)
    rep = bvh.report()
    assert set(rep.phase_seconds) == {"bounds", "morton", "sort", "emit", "refit"}
    assert all(t > 0 for t in rep.phase_seconds.values())
    # the device the tree was built on (PoCL unless LBVH_DEVICE names another)
    assert rep.device == bvh.ctx.name and bvh.ctx.device.platform.name.strip() in rep.device
    assert 0 < rep.bytes_per_triangle < 128
    d = rep.as_dict()
    assert d["depth"] == rep.depth and d["duplicate_codes"] == rep.duplicate_codes
    text = str(rep)
    for word in ("device:", "phases (ms)", "duplicate codes", "depth"):
        assert word in text


def test_device_chosen_by_environment_variable():
    code = ("import lbvh, numpy as np; b = lbvh.build(np.eye(3, dtype=np.float32), [[0, 1, 2]]);"
            "print(b.ctx.name)")
    # "pocl" names PoCL's device whatever PoCL calls it ("pthread-...", "cpu-...")
    env = dict(os.environ, LBVH_DEVICE="pocl")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("Portable Computing Language / ")
    env["LBVH_DEVICE"] = "no-such-device-xyz"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=REPO)
    assert out.returncode != 0 and "no OpenCL device matches" in out.stderr


def test_build_with_leaf_collapse():
    v, f = shipped_mesh("teapot.obj")
    plain = lbvh.build(v, f)
    bvh = lbvh.build(v, f, collapse=True, max_leaf_size=4)
    bvh.validate()
    sizes = prim_range_of(bvh.nodes)[is_leaf(bvh.nodes), 1]
    assert sizes.max() <= 4 and sizes.sum() == len(f) and bvh.tree.num_nodes < plain.tree.num_nodes
    assert lbvh.sah_cost(bvh) <= lbvh.sah_cost(plain)
    assert bvh.tree.builder == "lbvh+collapse"


def test_scratch_pool_holds_one_build_and_is_reused(ctx):
    v, f = random_soup(20000, seed=21)
    first = lbvh.build(v, f, key_bits=30)
    held = ctx.memory.pooled_bytes()
    assert held >= 32 * len(f)  # at least the triangle boxes stay pooled
    second = lbvh.build(v, f, key_bits=30)
    assert ctx.memory.pooled_bytes() == held  # the same buffers went round again
    assert np.array_equal(first.nodes, second.nodes)
    ctx.memory.trim()
    assert ctx.memory.pooled_bytes() == 0
    lbvh.build(v, f, key_bits=30).validate()


def test_a_dropped_trees_buffers_serve_the_next_build(ctx):
    """Rebuilding every frame: the last dropped tree's output buffers are reused (no
    fresh pages), never while the tree lives, and only one dropped tree is kept."""
    v, f = random_soup(5000, seed=22)
    ctx.memory.trim()
    first = lbvh.build(v, f, key_bits=30)
    expected, ptr = first.nodes.copy(), first.tree.nodes.int_ptr
    second = lbvh.build(v, f, key_bits=30)
    assert second.tree.nodes.int_ptr != ptr            # first is alive: not shared
    last = second.tree.nodes.int_ptr
    del first, second                                  # second is the last dropped
    gc.collect()
    held = ctx.memory.pooled_bytes()
    third = lbvh.build(v, f, key_bits=30)
    assert third.tree.nodes.int_ptr == last
    assert ctx.memory.pooled_bytes() < held                  # the outputs came from the pool
    assert np.array_equal(third.nodes, expected)
    third.validate()
    del third
    gc.collect()
    lbvh.build(*random_soup(300, seed=1)).validate()   # other sizes: fresh buffers
    ctx.memory.trim()
    assert ctx.memory.pooled_bytes() == 0


def test_a_collapsed_rebuild_takes_its_buffers_from_the_pool(ctx):
    """Rebuilding a collapsed tree: the collapse's scratch stays pooled for the next
    build (its per-node statistics, 16 bytes a node, at least), and the new tree's
    nodes are the last dropped tree's buffer (no fresh pages: lbvh.builders.collapse)."""
    v, f = random_soup(5000, seed=23)
    ctx.memory.trim()
    first = lbvh.build(v, f, key_bits=30, collapse=True)
    assert ctx.memory.pooled_bytes() >= 16 * (2 * len(f) - 1)
    expected, last = first.nodes.copy(), first.tree.nodes.int_ptr
    del first
    gc.collect()
    second = lbvh.build(v, f, key_bits=30, collapse=True)
    assert second.tree.nodes.int_ptr == last
    assert np.array_equal(second.nodes, expected)
    second.validate()
    del second
    gc.collect()
    ctx.memory.trim()
    assert ctx.memory.pooled_bytes() == 0


def test_the_pool_hands_out_a_buffer_only_with_its_own_flags(ctx):
    """A read-only buffer in the pool (a dropped tree's upload) never serves a request
    for a buffer the kernels write: Oclgrind reported such writes (the collapse's
    leaf list) before the pool matched flags."""
    import pyopencl as cl
    ctx.memory.trim()
    ro = ctx.memory.alloc(4096 * 7, flags=cl.mem_flags.READ_ONLY)
    ctx.memory.free(ro, to_pool=True)
    rw = ctx.memory.alloc(4096 * 7, pooled=True)
    assert rw.int_ptr != ro.int_ptr and rw.mem_flags == cl.mem_flags.READ_WRITE
    again = ctx.memory.alloc(4096 * 7, pooled=True, flags=cl.mem_flags.READ_ONLY)
    assert again.int_ptr == ro.int_ptr
    ctx.memory.free(rw, again)
    ctx.memory.trim()
    assert ctx.memory.pooled_bytes() == 0


def test_free_to_pool_hands_a_buffer_to_the_next_allocation(ctx):
    ctx.memory.trim()
    mem = dev.MemoryTracker(ctx)
    kept, dropped = mem.alloc(4096 * 3), mem.alloc(4096 * 5)
    mem.free(kept, to_pool=True)
    mem.free(dropped)
    assert mem.live == 0
    again = dev.MemoryTracker(ctx)
    assert again.alloc(4096 * 3).int_ptr == kept.int_ptr      # the same buffer, pages mapped
    assert ctx.memory.pooled_bytes() == 0                     # the other released, not pooled
    ctx.memory.trim()
