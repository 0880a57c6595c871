"""What a query's :class:`lbvh.Hits` offers beyond t, prim, u, v (issue 19, item 10):
``mask``, ``locations(origins, directions)`` and ``normals``, NaN rows for misses."""
from __future__ import annotations

import numpy as np
import pytest

import lbvh
from lbvh.queries.traverse import Hits, geometric_normals
from test_invalid_rays import good_rays, teapot

# One triangle in the z = 0 plane, counter-clockwise seen from +z, and the same
# triangle wound the other way (offset in x so that rays pick one).
V = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0], [2, 1, 0]])
F = np.uint32([[0, 1, 2], [3, 5, 4]])


def test_mask_is_hit():
    o, d = good_rays(300)
    o[::3] += 1000   # these miss
    hits = teapot().intersect(o, d)
    assert hits.mask.dtype == bool and np.array_equal(hits.mask, hits.prim >= 0)
    assert np.array_equal(hits.mask, hits.hit) and 0 < hits.mask.mean() < 1


def test_normals_follow_the_winding_and_misses_are_nan():
    bvh = lbvh.build(V, F)
    o = np.float32([[0.2, 0.2, 1], [2.2, 0.2, 1], [0.2, 0.2, -1], [9, 9, 1]])
    d = np.float32([[0, 0, -1], [0, 0, -1], [0, 0, 2], [0, 0, -1]])
    hits = bvh.intersect(o, d)
    assert hits.prim.tolist() == [0, 1, 0, -1]
    n = hits.normals
    assert n.dtype == np.float32 and n.shape == (4, 3)
    assert n[:3].tolist() == [[0, 0, 1], [0, 0, -1], [0, 0, 1]]   # whichever side the ray comes from
    assert np.isnan(n[3]).all()
    loc = hits.locations(o, d)
    assert loc.dtype == np.float32
    assert np.allclose(loc[:3], [[0.2, 0.2, 0], [2.2, 0.2, 0], [0.2, 0.2, 0]], atol=1e-6)
    assert np.isnan(loc[3]).all()


def test_normals_and_locations_on_a_real_mesh():
    bvh = teapot()
    o, d = good_rays(500, seed=3)
    o[::4] += 1000
    hits = bvh.intersect(o, d)
    h = hits.mask
    n = hits.normals
    assert np.isnan(n[~h]).all() and not np.isnan(n[h]).any()
    assert np.allclose(np.linalg.norm(n[h], axis=1), 1, atol=1e-6)
    tri = bvh.vertices[bvh.faces[hits.prim[h]]].astype(np.float64)
    ref = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.allclose(n[h], ref / np.linalg.norm(ref, axis=1, keepdims=True), atol=1e-6)
    # the hit point by t agrees with the hit point by barycentrics
    loc = hits.locations(o, d)
    uu, vv = hits.u[h, None], hits.v[h, None]
    on_triangle = (1 - uu - vv) * tri[:, 0] + uu * tri[:, 1] + vv * tri[:, 2]
    scale = float(np.abs(o).max())
    assert np.allclose(loc[h], on_triangle, atol=1e-5 * scale)
    assert np.isnan(loc[~h]).all()
    wide = hits.locations(o.astype(np.float64), d)
    assert wide.dtype == np.float64
    assert np.allclose(wide[h], loc[h], atol=1e-5 * scale) and np.isnan(wide[~h]).all()
    # any-hit results carry the mesh too
    any_hit = bvh.occluded(o, d, return_hits=True)
    assert np.array_equal(np.isnan(any_hit.normals[:, 0]), ~any_hit.hit)


def test_the_mesh_is_kept_by_reference_and_survives_a_refit():
    v, f = V.copy(), F
    bvh = lbvh.build(v, f)
    o, d = np.float32([[0.2, 0.2, 1]]), np.float32([[0, 0, -1]])
    before = bvh.intersect(o, d)
    assert before.geometry[0] is bvh.vertices and before.geometry[1] is bvh.faces
    flipped = v.copy()
    flipped[:, 2] = flipped[:, 0]   # tilt the triangles: another normal
    bvh.refit(flipped)
    after = bvh.intersect(o + np.float32([0, 0, 5]), d)
    assert before.normals.tolist() == [[0, 0, 1]]       # the mesh it was traced against
    assert np.allclose(after.normals, [[-np.sqrt(0.5), 0, np.sqrt(0.5)]])


def test_locations_check_their_rays_and_normals_need_a_mesh():
    hits = teapot().intersect(*good_rays(10))
    o, d = good_rays(10)
    with pytest.raises(ValueError, match=r"origins: shape \(9, 3\), expected \(10, 3\)"):
        hits.locations(o[:9], d)
    with pytest.raises(ValueError, match=r"directions: shape \(10,\)"):
        hits.locations(o, d[:, 0])
    bare = Hits(hits.t, hits.prim, hits.u, hits.v, hits.overflow, 0)
    with pytest.raises(ValueError, match="holds no mesh"):
        bare.normals
    assert np.array_equal(geometric_normals(teapot().vertices, teapot().faces, hits.prim),
                          hits.normals, equal_nan=True)
    assert bare.invalid.shape == (10,) and bare.invalid_count == 0
