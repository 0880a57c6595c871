"""Bad rays under ``invalid_rays="miss"`` (issue 19, item 7): reported as misses, flagged
and counted; every other ray's answer bit for bit the one it gets traced alone.

The default stays ``"raise"`` (tests/queries/test_traverse.py, test_bad_rays_*). The
rules are those of lbvh/queries/rays.py; :func:`mixed_rays` makes rays that break
each of them, and the ones beside them that only just pass (``-0.0`` tmin, a
denormal direction, ``tmin == tmax``, float32's largest value).
"""
from __future__ import annotations

import functools
import tracemalloc

import numpy as np
import pytest

import lbvh
from conftest import shipped_mesh
from lbvh.queries.rays import check_rays, invalid_mask

FMAX = float(np.finfo(np.float32).max)
DENORMAL = float(np.float32(1e-45))

#: (what, origin, direction, tmin, tmax, bad): one ray per rule, and its near misses.
CASES = [
    ("NaN origin", [np.nan, 0, 0], [1, 0, 0], 0.0, np.inf, True),
    ("inf origin", [0, -np.inf, 0], [1, 0, 0], 0.0, np.inf, True),
    ("NaN direction", [0, 0, 0], [0, 0, np.nan], 0.0, np.inf, True),
    ("inf direction", [0, 0, 0], [np.inf, 0, 0], 0.0, np.inf, True),
    ("zero direction", [0, 0, 0], [0, 0, 0], 0.0, np.inf, True),
    ("-0 direction", [0, 0, 0], [-0.0, 0, -0.0], 0.0, np.inf, True),
    ("NaN tmin", [0, 0, 0], [1, 0, 0], np.nan, np.inf, True),
    ("negative tmin", [0, 0, 0], [1, 0, 0], -1.0, np.inf, True),
    ("tiny negative tmin", [0, 0, 0], [1, 0, 0], -DENORMAL, np.inf, True),
    ("inf tmin", [0, 0, 0], [1, 0, 0], np.inf, np.inf, True),
    ("NaN tmax", [0, 0, 0], [1, 0, 0], 0.0, np.nan, True),
    ("tmin > tmax", [0, 0, 0], [1, 0, 0], 3.0, 2.0, True),
    ("denormal tmin > tmax", [0, 0, 0], [1, 0, 0], 2 * DENORMAL, DENORMAL, True),
    ("tmin > negative tmax", [0, 0, 0], [1, 0, 0], 0.0, -1.0, True),
    ("-0 tmin", [0, 0, 0], [1, 0, 0], -0.0, np.inf, False),
    ("zero tmin, -0 tmax", [0, 0, 0], [1, 0, 0], 0.0, -0.0, False),
    ("tmin == tmax", [0, 0, 0], [1, 0, 0], 1.5, 1.5, False),
    ("denormal direction", [0, 0, 0], [DENORMAL, 0, 0], 0.0, np.inf, False),
    ("largest float32 origin", [FMAX, 0, 0], [-1, 0, 0], 0.0, np.inf, False),
]


@functools.lru_cache(maxsize=None)
def teapot():
    v, f = shipped_mesh("teapot.obj")
    return lbvh.build(v, f)


def good_rays(n, seed=0):
    """Rays from around the teapot at points of its triangles: most of them hit."""
    bvh = teapot()
    rng = np.random.default_rng(seed)
    target = bvh.vertices[bvh.faces[rng.integers(0, bvh.mesh.num_prims, n)]].mean(axis=1)
    o = (target + rng.normal(size=target.shape) * 40).astype(np.float32)
    return o, (target - o).astype(np.float32)


def mixed_rays(n=600, seed=1):
    """``(o, d, tmin, tmax, bad)``: good rays with every case of :data:`CASES` placed
    among them at random (per-ray intervals), and which ones are bad."""
    o, d = good_rays(n, seed)
    rng = np.random.default_rng(seed)
    tmin, tmax = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    bad = np.zeros(n, bool)
    slots = rng.choice(n, 3 * len(CASES), replace=False).reshape(3, len(CASES))
    for row in slots:
        for i, (_, oi, di, lo, hi, is_bad) in zip(row, CASES):
            o[i], d[i], tmin[i], tmax[i], bad[i] = oi, di, lo, hi, is_bad
    return o, d, tmin, tmax, bad


@pytest.mark.parametrize("what, o, d, tmin, tmax, bad", CASES, ids=[c[0] for c in CASES])
def test_the_mask_is_exactly_what_the_default_refuses(what, o, d, tmin, tmax, bad):
    """invalid_mask (the slow path under "miss") and the raising checks agree ray by ray."""
    args = (np.float32([o]), np.float32([d]), np.float32([tmin]), np.float32([tmax]))
    if bad:
        with pytest.raises(ValueError):
            check_rays(*args)
    else:
        check_rays(*args)
    rays = check_rays(*args, invalid_rays="miss")
    assert invalid_mask(rays.origins, rays.directions, rays.tmin, rays.tmax).tolist() == [bad]
    assert (rays.invalid is not None) == bad


@pytest.mark.parametrize("what, o, d, tmin, tmax, bad", CASES, ids=[c[0] for c in CASES])
def test_the_small_call_path_passes_exactly_the_good_rays(what, o, d, tmin, tmax, bad):
    """check_rays' path for small float32 calls with scalar intervals (rays._plain_rays)
    passes exactly the good rays, as the arrays the general path makes; a bad ray goes on
    to the general path, which names it."""
    from lbvh.queries.rays import _plain_rays
    for lo, hi in ((tmin, tmax), (np.float64(tmin), np.float32(tmax)), (np.float32(tmin), tmax)):
        fast = _plain_rays(np.float32([o]), np.float32([d]), lo, hi)
        assert (fast is None) == bad
        if bad:
            with pytest.raises(ValueError):
                check_rays(np.float32([o]), np.float32([d]), lo, hi)
            continue
        general = check_rays(np.float64([o]), np.float64([d]), np.float64(lo), np.float64(hi))
        for name in ("origins", "directions", "tmin", "tmax"):
            a, b = getattr(fast, name), getattr(general, name)
            assert a.dtype == b.dtype == np.float32 and a.shape == b.shape
            assert a.tobytes() == b.tobytes(), name


@pytest.mark.parametrize("tmin, tmax", [(0.0, 1e300), (0, 2**62 + 1), (2**24 + 1, np.inf),
                                        (0.0, np.float64(FMAX) * (1 + 2**-30))])
def test_intervals_float32_does_not_hold_take_the_general_path(tmin, tmax):
    """Intervals beyond float32 (or an int it rounds) are converted as the general path
    converts them, without a warning, whichever path the call takes."""
    from lbvh.queries.rays import _plain_rays
    o, d = np.zeros((1, 3), np.float32), np.float32([[1, 0, 0]])
    general = check_rays(o.tolist(), d.tolist(), np.float64(tmin), np.float64(tmax))
    with np.errstate(all="raise"):
        got = check_rays(o, d, tmin, tmax)
    assert got.tmin.tobytes() == general.tmin.tobytes()
    assert got.tmax.tobytes() == general.tmax.tobytes()
    if np.isfinite(float(tmax)) and abs(float(tmax)) > FMAX:
        assert _plain_rays(o, d, tmin, tmax) is None


@pytest.mark.parametrize("query", ["intersect", "occluded"])
def test_bad_rays_are_misses_and_the_others_are_traced_as_alone(query):
    bvh = teapot()
    o, d, tmin, tmax, bad = mixed_rays()
    call = getattr(bvh, query)
    extra = {} if query == "intersect" else {"return_hits": True}
    with pytest.raises(ValueError, match="ray"):
        call(o, d, tmin, tmax, **extra)
    got = call(o, d, tmin, tmax, invalid_rays="miss", counters=True, **extra)
    good = ~bad
    alone = call(o[good], d[good], tmin[good], tmax[good], counters=True, **extra)
    assert got.invalid.dtype == bool and np.array_equal(got.invalid, bad)
    assert got.invalid_count == int(bad.sum()) > 0
    for name in ("t", "prim", "u", "v", "overflow", "nodes_visited", "tris_tested"):
        assert getattr(got, name)[good].tobytes() == getattr(alone, name).tobytes(), name
    assert got.overflow_count == alone.overflow_count
    assert np.isinf(got.t[bad]).all() and (got.prim[bad] == -1).all()
    assert (got.u[bad] == 0).all() and (got.v[bad] == 0).all() and not got.overflow[bad].any()
    assert (got.nodes_visited[bad] == 0).all() and (got.tris_tested[bad] == 0).all()
    assert not got.mask[bad].any() and got.mask[good].mean() > 0.5
    if query == "occluded":
        answer = bvh.occluded(o, d, tmin, tmax, invalid_rays="miss")
        assert answer.dtype == bool and np.array_equal(answer, got.hit)


def test_all_rays_bad_none_traced_and_good_rays_unflagged():
    bvh = teapot()
    o = np.full((5, 3), np.nan, np.float32)
    got = bvh.intersect(o, np.ones((5, 3)), invalid_rays="miss")
    assert got.invalid.all() and got.invalid_count == 5 and not got.hit.any()
    o, d = good_rays(50)
    plain, missed = bvh.intersect(o, d), bvh.intersect(o, d, invalid_rays="miss")
    assert missed.invalid_count == 0 and not missed.invalid.any() and missed.invalid.shape == (50,)
    assert plain.t.tobytes() == missed.t.tobytes() and plain.prim.tobytes() == missed.prim.tobytes()
    assert plain.invalid_count == 0 and not plain.invalid.any()


@pytest.mark.parametrize("bad, message", [
    (dict(origins=np.zeros((2, 2))), r"origins: shape \(2, 2\)"),
    (dict(directions=np.ones((3, 3))), "directions: 3 rays, but origins has 2"),
    (dict(tmax=np.ones(3)), r"tmax: shape \(3,\)"),
    (dict(origins=np.zeros((2, 3), complex)), "origins: dtype complex128"),
    (dict(invalid_rays="skip"), "invalid_rays: 'skip'"),
    (dict(invalid_rays=None), "invalid_rays: None"),
])
def test_shapes_dtypes_and_the_option_itself_still_raise(bad, message):
    args = dict(origins=np.zeros((2, 3)), directions=np.ones((2, 3)), tmax=np.inf,
                invalid_rays="miss")
    args.update(bad)
    for call in (teapot().intersect, teapot().occluded):
        with pytest.raises(ValueError, match=message):
            call(args["origins"], args["directions"], tmax=args["tmax"],
                 invalid_rays=args["invalid_rays"])


def test_good_rays_cost_no_more_memory_under_miss_than_under_raise():
    """The checks make no per-ray mask while every ray is good (the fast path)."""
    o, d = good_rays(1 << 18)
    peaks = {}
    for mode in ("raise", "miss", "raise"):
        tracemalloc.start()
        rays = check_rays(o, d, 0.0, np.inf, invalid_rays=mode)
        peaks[mode] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert rays.invalid is None and rays.origins is o and rays.directions is d
    assert peaks["miss"] <= peaks["raise"] + 4096
    o[7, 1] = np.nan   # a bad ray: the mask is made, and only then
    tracemalloc.start()
    rays = check_rays(o, d, 0.0, np.inf, invalid_rays="miss")
    slow = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert rays.invalid.sum() == 1 and slow > peaks["miss"] + len(o)
