"""Property-based fuzzing of the builders, the refit and the traversal (issue 5).

Hypothesis draws small meshes built to be awkward: vertices from a pool of
special values (0, -0.0, denormals, 1e-30, 1e30, 3e38, a 1e7 offset) mixed
with ordinary ones; faces that repeat an index (zero area), collinear
triangles, duplicated triangles, triangles flattened onto one plane; and rays
whose direction components include 0, -0.0 and tiny values, aimed at vertices
and edge midpoints or drawn anywhere. Properties:

* every builder's tree passes the validator, without NaN or infinite boxes;
* the device LBVH tree and the serial SAH tree give the same answers: same hit
  or miss, the same ``t`` bit for bit (the kernel computes each triangle's ``t``
  the same way whatever the tree), and a different triangle only where it is
  hit at that same ``t`` (a tie); any-hit agrees too;
* after moving the vertices, the device refit equals ``lbvh.refit.refit_numpy``
  bit for bit (-0.0 and +0.0 taken as one value: see ``_bits``), for every
  builder's topology;
* every answer of the kernel is right by the rules of ``lbvh check`` (the
  float64 oracle, float32 ambiguities judged by the kernel's error bounds),
  for rays whose origin and direction components stay below 1e30 (see
  ``test_a_far_hit_along_a_huge_direction_is_found`` in tests/test_hard_cases.py).

Runs: the "ci" profile (the default) is derandomized with a fixed example
budget, so CI is repeatable; a longer random run is one command::

    LBVH_FUZZ_PROFILE=long .venv/bin/python -m pytest tests/test_fuzz.py

("long": 2000 examples per property, random seeds, failures saved to
.hypothesis/ and replayed first next time; ``LBVH_FUZZ_EXAMPLES=n`` overrides
the count of either profile). The fuzzer found the false hit of
``test_an_underflowing_edge_function_gives_no_false_hit``, the lost hit of
``test_a_far_hit_along_a_huge_direction_is_found`` and the hit on a zero-area
triangle of ``test_a_zero_area_triangle_with_overflowing_edges_is_never_hit``
(tests/test_hard_cases.py); a long run may meet the last one again until it is fixed.
"""
from __future__ import annotations

import os

import numpy as np
from hypothesis import HealthCheck, Phase, assume, given, settings, strategies as st

import lbvh
from lbvh import check
from lbvh.hard_cases import make_case
from lbvh.refit import refit_numpy

_COMMON = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                     HealthCheck.data_too_large])
# CI: a fixed budget, repeatable, no shrinking (a failure shows its first example at once)
settings.register_profile("ci", max_examples=50, derandomize=True, database=None,
                          phases=[Phase.explicit, Phase.reuse, Phase.generate], **_COMMON)
settings.register_profile("long", max_examples=2000, **_COMMON)
_PROFILE = settings.get_profile(os.environ.get("LBVH_FUZZ_PROFILE", "ci"))
FUZZ = settings(_PROFILE, max_examples=int(os.environ.get("LBVH_FUZZ_EXAMPLES",
                                                          _PROFILE.max_examples)))

BUILDERS = list(check.BUILDERS)
FLOAT32_MAX = float(np.finfo(np.float32).max)

SPECIAL = [0.0, -0.0, 1.0, -1.0, 0.5, 1e-45, -1e-45, 1e-38, 1e-30, -1e-30, 1e30, -1e30,
           3e38, -3e38, 1e7, 1e7 + 1, -1e7]
MODERATE = [0.0, -0.0, 1.0, -1.0, 0.5, 0.25, 1e-3, -1e-3, 1e3, 1e6, 1e6 + 0.5, -1e6]


def _coordinate(extreme: bool):
    special = st.sampled_from(SPECIAL if extreme else MODERATE)
    ordinary = st.floats(-10, 10, width=32)
    if extreme:
        anything = st.floats(width=32, allow_nan=False, allow_infinity=False)
        return st.one_of(special, ordinary, anything)
    return st.one_of(special, ordinary, st.floats(-1e6, 1e6, width=32).filter(
        lambda x: x == 0 or abs(x) >= 1e-15))


@st.composite
def meshes(draw, extreme: bool = True, max_triangles: int = 40):
    """(vertices float32 (V, 3), faces uint32 (F, 3)) with degenerate, duplicated,
    coplanar and extreme triangles."""
    coord = _coordinate(extreme)
    num_vertices = draw(st.integers(1, 24))
    v = np.array(draw(st.lists(st.tuples(coord, coord, coord), min_size=num_vertices,
                               max_size=num_vertices)), np.float32).reshape(-1, 3)
    index = st.integers(0, num_vertices - 1)
    f = np.array(draw(st.lists(st.tuples(index, index, index), min_size=1,
                               max_size=max_triangles)), np.int64).reshape(-1, 3)
    if draw(st.booleans()):  # collinear: a midpoint vertex per triangle of a subset
        k = draw(st.integers(1, len(f)))
        mid = (v[f[:k, 0]].astype(np.float64) + v[f[:k, 1]]) / 2
        f[:k, 2] = len(v) + np.arange(k)
        v = np.concatenate([v, np.clip(mid, -FLOAT32_MAX, FLOAT32_MAX).astype(np.float32)])
    if draw(st.booleans()):  # coplanar: flatten some vertices onto z = one value
        plane = np.float32(draw(coord))
        flat = np.array(draw(st.lists(st.booleans(), min_size=len(v), max_size=len(v))))
        v[flat, 2] = plane
    copies = draw(st.integers(0, 3))  # duplicated triangles
    f = np.concatenate([f] + [f[: draw(st.integers(1, len(f)))]] * copies)
    return v, f.astype(np.uint32)


@st.composite
def rays_for(draw, v: np.ndarray, extreme: bool = True, max_rays: int = 24):
    """(origins, directions) float32: aimed at vertices and edge midpoints, or anywhere,
    with zero, -0.0 and tiny direction components."""
    coord = _coordinate(extreme)
    tiny = [1e-30, -1e-38] if extreme else []
    component = st.one_of(st.sampled_from([0.0, -0.0, 1.0, -1.0] + tiny),
                          st.floats(-1, 1, width=32).filter(
                              lambda x: extreme or x == 0 or abs(x) >= 1e-6))
    n = draw(st.integers(1, max_rays))
    origins, directions = [], []
    for _ in range(n):
        o = np.array(draw(st.tuples(coord, coord, coord)), np.float64)
        kind = draw(st.sampled_from(["vertex", "midpoint", "free", "axis"]))
        if kind in ("vertex", "midpoint"):
            a = v[draw(st.integers(0, len(v) - 1))].astype(np.float64)
            b = v[draw(st.integers(0, len(v) - 1))].astype(np.float64)
            target = a if kind == "vertex" else (a + b) / 2
            d = target - o
        elif kind == "axis":
            d = np.zeros(3)
            d[draw(st.integers(0, 2))] = draw(st.sampled_from([1.0, -1.0]))
            d = np.where(d == 0, draw(st.sampled_from([0.0, -0.0])), d)
        else:
            d = np.array(draw(st.tuples(component, component, component)), np.float64)
        with np.errstate(over="ignore"):
            d32 = d.astype(np.float32)
        if np.isfinite(d32).all() and (d32 != 0).any():
            origins.append(o)
            directions.append(d32)
    assume(origins)
    return np.array(origins, np.float32), np.array(directions, np.float32)


def _build(v, f, builder):
    return lbvh.build(v, f, **check.BUILDERS[builder])


# -- properties ---------------------------------------------------------------------

@FUZZ
@given(mesh=meshes())
def test_every_builder_makes_a_valid_tree(mesh):
    v, f = mesh
    for builder in BUILDERS:
        bvh = _build(v, f, builder)
        bvh.validate()
        assert np.isfinite(bvh.lower).all() and np.isfinite(bvh.upper).all(), builder


def _same_answers(a, b, v, f, o, d):
    """Hits of two trees: same hit/miss and t bit for bit; another triangle only on a
    tie (each tree's triangle is a possible hit at that t, by lbvh.check's bounds)."""
    assert (a.hit == b.hit).all()
    assert np.array_equal(a.t, b.t)
    other = np.flatnonzero(a.prim != b.prim)
    if len(other):
        case = make_case("fuzz", v, f, "fuzz", o, d)
        judge = check.Judge(case, check.Reference(a.prim, a.t.astype(np.float64), exact=False))
        for hits in (a, b):
            g = judge.geometry(other, hits.prim[other])
            assert (g.possible & check.t_agrees(g, hits.t[other])).all()


@FUZZ
@given(data=st.data())
def test_device_and_serial_trees_give_the_same_hits(data):
    v, f = data.draw(meshes())
    o, d = data.draw(rays_for(v))
    serial = _build(v, f, "sah")
    expected = serial.intersect(o, d)
    expected_any = serial.occluded(o, d)
    assert expected.overflow_count == 0
    for builder in ("lbvh30", "lbvh63", "lbvh-auto-collapse"):
        device = _build(v, f, builder)
        got = device.intersect(o, d)
        assert got.overflow_count == 0
        _same_answers(got, expected, v, f, o, d)
        assert (device.occluded(o, d) == expected_any).all()


@FUZZ
@given(data=st.data())
def test_device_refit_equals_numpy_refit_bit_for_bit(data):
    v, f = data.draw(meshes())
    moved = np.array(data.draw(st.lists(st.tuples(*[_coordinate(True)] * 3), min_size=len(v),
                                        max_size=len(v))), np.float32).reshape(-1, 3)
    for builder in BUILDERS:
        bvh = _build(v, f, builder)
        bvh.refit(moved)
        lower, upper = refit_numpy(bvh.nodes, bvh.parent, bvh.root, bvh.prim_order, moved, f)
        assert np.array_equal(_bits(bvh.lower), _bits(lower)), builder
        assert np.array_equal(_bits(bvh.upper), _bits(upper)), builder
        bvh.validate()


def _bits(x: np.ndarray) -> np.ndarray:
    """The float32 bit patterns, with -0.0 read as +0.0: min and max of two equal
    zeros may return either one (IEEE 754, OpenCL fmin, numpy.minimum), and the
    device refit combines siblings in arrival order."""
    return (np.asarray(x, np.float32) + np.float32(0.0)).view(np.uint32)


@FUZZ
@given(data=st.data())
def test_kernel_answers_are_right(data):
    v, f = data.draw(meshes())
    o, d = data.draw(rays_for(v))
    # not yet: hits ~1.7e38 from the origin along directions longer than 2^60
    # (test_a_far_hit_along_a_huge_direction_is_found in tests/test_hard_cases.py)
    keep = (np.abs(o) < 1e30).all(axis=1) & (np.abs(d) < 1e30).all(axis=1)
    assume(keep.any())
    o, d = o[keep], d[keep]
    case = make_case("fuzz", v, f, "fuzz", o, d)
    judge = check.Judge(case, check.reference(case))
    for builder in ("lbvh-auto", "sah"):
        bvh = _build(v, f, builder)
        hits = bvh.intersect(o, d)
        agreement = check.compare_closest(judge, hits.prim, hits.t, hits.overflow)
        assert not agreement.wrong.any(), agreement.first
        any_hit = bvh.occluded(o, d, return_hits=True)
        assert not check.compare_any(judge, any_hit.prim, any_hit.t, any_hit.overflow).any()
