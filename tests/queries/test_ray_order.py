"""Ray ordering: keys exactly as the numpy twin, a stable sort, and the same answers in any order."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
import lbvh.queries.traverse as traverse
from conftest import random_soup, shipped_mesh
from lbvh import device as dev
from lbvh.queries.ray_order import MIN_NODES, MIN_RAYS, ray_keys_numpy, ray_order, worth_ordering


def _rays(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-0.5, 1.5, (n, 3)).astype(np.float32)
    directions = rng.normal(size=(n, 3)).astype(np.float32)
    directions[::7, 1] = -0.0        # signed zeros
    directions[::11, 0] = 0.0
    directions[::13] *= np.float32(1e-30)   # tiny and huge directions keep their cell
    directions[::17] *= np.float32(1e30)
    return origins, directions


def _device_order(origins, directions, lower, upper):
    ctx = dev.get_context(None)
    o, d = dev.to_device(ctx, origins), dev.to_device(ctx, directions)
    order, _ = ray_order(ctx, o, d, len(origins), np.asarray(lower, np.float32),
                         np.asarray(upper, np.float32))
    out = dev.from_device(ctx, order, np.int32, (len(origins),))
    order.release()
    return out


@pytest.mark.parametrize("box", [
    ([0, 0, 0], [1, 1, 1]),
    ([0, 0, 0], [1, 0, 1]),                       # a flat scene: no cells on y
    ([-3e38, -1, -1], [3e38, 1, 1]),              # an extent that overflows float32
    ([1e-30, 1e-30, 1e-30], [2e-30, 2e-30, 2e-30]),
])
def test_device_order_is_the_stable_sort_of_the_twins_keys(box):
    origins, directions = _rays(5000, seed=1)
    keys = ray_keys_numpy(origins, directions, *box)
    assert keys.max() < 1 << 30
    expected = np.argsort(keys, kind="stable").astype(np.int32)
    assert np.array_equal(_device_order(origins, directions, *box), expected)


def test_keys_group_rays_by_origin_then_direction():
    origins = np.float32([[0.1, 0.1, 0.1], [0.9, 0.9, 0.9], [0.1, 0.1, 0.1]])
    directions = np.float32([[1, 0, 0], [1, 0, 0], [-1, 0, 0]])
    keys = ray_keys_numpy(origins, directions, [0, 0, 0], [1, 1, 1])
    assert keys[0] >> 15 == keys[2] >> 15 != keys[1] >> 15
    assert keys[0] & 0x7FFF == keys[1] & 0x7FFF != keys[2] & 0x7FFF


def test_only_large_batches_over_large_trees_are_ordered():
    assert worth_ordering(MIN_RAYS, MIN_NODES)
    assert not worth_ordering(MIN_RAYS - 1, MIN_NODES)
    assert not worth_ordering(MIN_RAYS, MIN_NODES - 1)


@pytest.mark.parametrize("mesh", ["teapot", "soup"])
def test_same_answers_whether_the_rays_are_ordered_or_not(monkeypatch, mesh):
    v, f = shipped_mesh("teapot.obj") if mesh == "teapot" else random_soup(3000, seed=3)
    bvh = lbvh.build(v, f)
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    origins, directions = _rays(20000, seed=2)
    origins = (centre + (origins - 0.5) * (v.max(axis=0) - v.min(axis=0)) * 2).astype(np.float32)
    targets = v[f[np.random.default_rng(4).integers(0, len(f), len(origins)), 0]]
    aimed = np.arange(len(origins)) % 3 != 0          # two rays in three aim at a vertex
    directions[aimed] = targets[aimed] - origins[aimed]
    answers = {}
    for ordered in (False, True):
        monkeypatch.setattr(traverse, "worth_ordering", lambda rays, nodes, on=ordered: on)
        hits = bvh.intersect(origins, directions, counters=True, batch_size=7000)
        blocked = bvh.occluded(origins, directions, tmax=0.5)
        answers[ordered] = (hits, blocked)
    (a, blocked_a), (b, blocked_b) = answers[False], answers[True]
    assert (a.prim >= 0).sum() > 1000
    for field in ("t", "u", "v", "prim", "nodes_visited", "tris_tested", "overflow"):
        assert np.array_equal(getattr(a, field), getattr(b, field)), field
    assert np.array_equal(blocked_a, blocked_b)


def test_gathered_points_are_the_points_in_their_order():
    """kernels/ray_order.cl gather_points against its numpy twin, points[order], exactly
    (a copy), over a batch that spans several work-items."""
    from lbvh.queries.ray_order import gather_points, point_order
    ctx = dev.get_context(None)
    rng = np.random.default_rng(5)
    p = rng.normal(size=(20_011, 3)).astype(np.float32)
    p[::101] = np.float32([-0.0, np.inf, 1e-40])      # signed zero, inf, a denormal: copied
    buf = dev.to_device(ctx, p)
    order, evs = point_order(ctx, buf, len(p), np.full(3, -3, np.float32),
                             np.full(3, 3, np.float32))
    out, ev = gather_points(ctx, buf, order, len(p), wait_for=evs)
    ev.wait()
    perm = dev.from_device(ctx, order, np.int32, (len(p),))
    got = dev.from_device(ctx, out, np.float32, p.shape)
    ctx.memory.free(order, out)
    assert sorted(perm.tolist()) == list(range(len(p)))
    assert np.array_equal(got.view(np.uint32), p[perm].view(np.uint32))
