"""The ray-sampled cost (lbvh/verification/ray_cost.py): the device's counts of the nodes
each ray's segment enters against the numpy twin, and what the cost says of the trees."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from conftest import random_soup, shipped_mesh
from lbvh.queries.all_hits import segment_work
from lbvh.verification.ray_cost import device_pad, ray_sampled_cost, segment_work_numpy


def rays_at(v: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    o = lo + (hi - lo) * rng.uniform(-0.5, 1.5, (n, 3))
    return o.astype(np.float32), (v[rng.integers(0, len(v), n)] - o).astype(np.float32)


@pytest.mark.parametrize("builder", ["lbvh", "sah", "median", "midpoint"])
def test_segment_work_equals_its_twin(builder):
    v, f = random_soup(400, seed=3)
    bvh = lbvh.build(v, f, builder=builder)
    o, d = rays_at(v, 200, 1)
    t = bvh.intersect(o, d).t
    got = segment_work(bvh, o, d, 0.0, t)
    want = segment_work_numpy(bvh.nodes, bvh.root, o, d, 0.0, t, device_pad(bvh))
    assert np.array_equal(got, want)
    assert (got[:, 2] >= 1)[np.isfinite(t)].all()   # a hit's own leaf is entered
    # a whole ray enters at least what its segment to the hit does
    assert (segment_work(bvh, o, d) >= got).all()


def test_the_cost_of_the_trees():
    v, f = shipped_mesh("teapot.obj")
    o, d = rays_at(v, 3000, 2)
    costs = {b: ray_sampled_cost(lbvh.build(v, f, builder=b), o, d) for b in
             ("lbvh", "sah", "median")}
    for c in costs.values():
        assert c.rays == 3000 and c.cost == pytest.approx(c.inner + c.triangles)
        assert c.leaves > 0 and c.inner > 0
    # the SAH reference forces less work on these rays than the balanced median split
    assert costs["sah"].cost < costs["median"].cost
    # in other units: c_node and c_tri weigh the counts
    heavy = ray_sampled_cost(lbvh.build(v, f), o, d, c_node=2.0, c_tri=0.5)
    assert heavy.cost == pytest.approx(2 * costs["lbvh"].inner + 0.5 * costs["lbvh"].triangles)
