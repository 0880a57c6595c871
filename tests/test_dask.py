"""lbvh.dask on a dask.distributed LocalCluster of two worker processes: the same hits as
one in-process call, for a BVH and a scene (each pickled to the workers, uploaded to
their own devices)."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

import lbvh
from conftest import shipped_mesh

da = pytest.importorskip("dask.array")
distributed = pytest.importorskip("dask.distributed")
lbvh_dask = pytest.importorskip("lbvh.dask")


def rays(v: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    o = (lo + (hi - lo) * rng.uniform(-0.5, 1.5, (n, 3))).astype(np.float32)
    return o, (v[rng.integers(0, len(v), n)] - o).astype(np.float32)


def test_pickled_trees_answer_as_the_originals():
    bvh = lbvh.build(*shipped_mesh("teapot.obj"), collapse=True)
    o, d = rays(bvh.vertices, 500, 1)
    again = pickle.loads(pickle.dumps(bvh))
    assert again.tree.builder == bvh.tree.builder and np.array_equal(again.nodes, bvh.nodes)
    got, want = again.intersect(o, d), bvh.intersect(o, d)
    assert np.array_equal(got.t, want.t) and np.array_equal(got.prim, want.prim)
    scene = lbvh.Scene([bvh], [0, 0], np.stack([np.eye(3, 4), np.eye(3, 4) * 2]), ids=[7, 9])
    copy = pickle.loads(pickle.dumps(scene))
    assert copy.names == scene.names and np.array_equal(copy.ids, scene.ids)
    assert np.array_equal(copy.intersect(o, d).t, scene.intersect(o, d).t)


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as c:
        yield c


def test_rays_over_two_worker_processes(client):
    bvh = lbvh.build(*shipped_mesh("teapot.obj"))
    o, d = rays(bvh.vertices, 20_000, 2)
    hits = lbvh_dask.intersect(bvh, da.from_array(o, chunks=(2_500, 3)),
                               da.from_array(d, chunks=(4_000, 3)))   # rechunked to origins'
    got = hits.compute()
    want = bvh.intersect(o, d)
    for name in ("t", "prim", "u", "v"):
        assert np.array_equal(got[name], getattr(want, name)), name
    blocked = lbvh_dask.occluded(bvh, da.from_array(o, chunks=5_000), da.from_array(d, chunks=5_000),
                                 tmax=0.5).compute()
    assert np.array_equal(blocked, bvh.occluded(o, d, tmax=0.5))
    # both workers answered blocks
    assert len(client.scheduler_info()["workers"]) == 2


def test_a_scene_over_the_workers(client):
    bvh = lbvh.build(*shipped_mesh("teapot.obj"))
    moves = np.tile(np.eye(3, 4), (3, 1, 1))
    moves[:, :, 3] = [[0, 0, 0], [8, 0, 0], [0, 8, 0]]
    scene = lbvh.Scene([bvh], [0, 0, 0], moves)
    v, f, _ = scene.flattened()
    o, d = rays(v, 10_000, 3)
    got = lbvh_dask.intersect(scene, da.from_array(o, chunks=3_000),
                              da.from_array(d, chunks=3_000)).compute()
    want = scene.intersect(o, d)
    for name in ("t", "prim", "instance"):
        assert np.array_equal(got[name], getattr(want, name)), name


def test_bad_input():
    with pytest.raises(ValueError, match="expected an lbvh.BVH"):
        lbvh_dask.intersect("mesh.obj", da.zeros((3, 3)), da.zeros((3, 3)))
    bvh = lbvh.build(*shipped_mesh("teapot.obj"))
    with pytest.raises(ValueError, match=r"shape \(3, 2\)"):
        lbvh_dask.intersect(bvh, da.zeros((3, 2)), da.zeros((3, 3)))
