"""The float32 error bound on a hit's ``t``: one home for the checks, the tests and the benches.

The traversal kernel decides each hit exactly (kernels/ray_triangle.h) and
computes ``t`` in double from the float32 inputs, rounding it once to float32
(Woop, Benthin & Wald 2013, with the shear scaled by ``d_kz``); without doubles
(``NO_FP64``) all in float32. Each of its results carries a few roundings of
unit roundoff ``U = 2^-24`` at most (Higham 2002, ch. 3) on quantities of the
size of the coordinates it subtracts; dividing by the triangle's projected area
amplifies them by ``1 / |cos a|``, ``a`` the angle between the ray and the
triangle's normal. So, against the float64 oracle's ``t_ref`` for the same
triangle::

    |t - t_ref| <= T_BOUND * (t_ref + s) / max(|cos a|, cos_floor)

with ``T_BOUND = 16 U`` and ``s = (scene extent + largest origin component)
/ |d|``. ``cos_floor`` only keeps the quotient finite (``1e-30``); the
builders bench floors it at ``1e-3`` on purpose, a stricter agreement test
for grazing rays, and says so in its table.

Both sides scale with the scene: scaled by a power of two, ``t``, ``t_ref`` and
``s`` scale alike (the kernel's ``t`` bit for bit), so the bound holds at every
scale while ``t`` is a normal float32. Below float32's normal range rounding is absolute: :data:`UNDERFLOW` is the
floor the finer, per-pair analysis of :mod:`lbvh.verification.error_analysis`
adds (that analysis, which ``lbvh check`` judges by, uses the same ``T_BOUND``
with each pair's own size and conditioning: its module docstring says how the
two bounds relate).
"""
from __future__ import annotations

import numpy as np

#: Unit roundoff of float32.
U = 2.0 ** -24
#: Relative bound on ``t`` in units of ``(t_ref + s) / |cos a|``: 16 roundings.
T_BOUND_ULPS = 16
T_BOUND = T_BOUND_ULPS * U
#: Absolute error floor of float32 results that underflow (2^9 of the smallest denormal).
UNDERFLOW = 2.0 ** -140
#: The default floor of ``|cos a|``: only keeps the quotient finite.
COS_FLOOR = 1e-30


def t_bound(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray, directions: np.ndarray,
            t_ref: np.ndarray, prim_ref: np.ndarray, cos_floor: float = COS_FLOOR) -> np.ndarray:
    """``float64 (N,)``: the bound of the module docstring on ``|t - t_ref|`` per ray.

    ``prim_ref`` is the triangle the bound is for (the oracle's, ``-1`` on a
    miss: the bound is then computed for triangle 0 and meaningless);
    ``t_ref`` its ``t`` (non-finite values count as 0).
    """
    d = np.asarray(directions, np.float64)
    dn = np.linalg.norm(d, axis=1)
    extent = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    s = (extent + np.abs(origins).max(axis=1)) / dn
    tri = vertices[faces[np.maximum(prim_ref, 0)]].astype(np.float64)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nn = np.linalg.norm(normal, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs((normal * d).sum(axis=1)) / np.maximum(nn * dn, 1e-300)
    t = np.where(np.isfinite(t_ref), t_ref, 0.0)
    return T_BOUND * (t + s) / np.maximum(cos, cos_floor)


#: Bound on a closest-point distance (:mod:`lbvh.queries.closest`) in units of
#: ``U * s``, ``s = |p|_inf + max |vertex|_inf``: the kernel works in double
#: (cl_khr_fp64) from the float32 inputs, so its only float32 rounding is the
#: answer's (half a unit of ``d <= s``, and of each coordinate of the point);
#: the rest is double rounding, far below. Measured on the hard cases
#: (slivers, zero-area triangles, coordinates from 1e-40 to 1e38): at most
#: 1.2. Without doubles (``NO_FP64``) the float32 arithmetic holds it only on
#: well-conditioned triangles of moderate coordinates: see docs/pages/stability.md.
CLOSEST_BOUND_ULPS = 4


def closest_distance_bound(vertices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``float64 (N,)``: the bound on ``|d - d_ref|`` of each query point's distance."""
    p = np.abs(np.asarray(points, np.float64))
    s = (p.max(axis=1) if p.size else np.zeros(len(p))) + float(np.abs(vertices).max())
    return CLOSEST_BOUND_ULPS * U * s


#: The scene's term of a closest-point distance through :class:`lbvh.Scene`
#: (kernels/instance_closest.cl), in units of ``U * max |vertex|_inf`` of the flattened
#: scene's vertices: the kernel moves the float32 mesh vertices to world space in double
#: with the float64 transform (to 2^-48: a float32 pair per entry), so its answer is the
#: exactly placed mesh's within :data:`CLOSEST_BOUND_ULPS`; the flattened copy the
#: float64 brute force reads rounds each world coordinate to float32 (half a unit of its
#: size, so a vertex moves by at most ``sqrt(3) / 2 U max |vertex|_inf``), and a distance
#: to a triangle moves no more than its vertices. Double rounding of the transform adds
#: ``2^-52 (|A| |v| + |b|)``, far below this unless a placement cancels by 2^28.
SCENE_CLOSEST_BOUND_ULPS = 1


def scene_closest_distance_bound(vertices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``float64 (N,)``: the bound on ``|d - d_ref|`` of each query point's distance
    through a scene, ``vertices`` the flattened scene's (:meth:`lbvh.Scene.flattened`)
    and ``d_ref`` the float64 brute force over its triangles:
    :func:`closest_distance_bound` plus :data:`SCENE_CLOSEST_BOUND_ULPS`."""
    extent = float(np.abs(vertices).max()) if len(vertices) else 0.0
    return closest_distance_bound(vertices, points) + SCENE_CLOSEST_BOUND_ULPS * U * extent


#: Generalised winding numbers (kernels/winding.cl) against the exact float64 sum, at the
#: default ``beta = 1.4`` with the second-order expansion: ``|w - w_exact| <=
#: WINDING_BOUND``. Through the restructured copy of the tree that the walk takes
#: (:data:`lbvh.queries.winding.WINDING_TREELET_ROUNDS`), over the bench's 1M points per
#: scene against the walk at ``beta = 4``: 0.022 on the bunny, 0.043 on Sponza and 0.026
#: on terrain-1m; 0.028, 0.049 and 0.029 at 1.35, the default until then (too close to
#: the bound on Sponza). Not a proof but a measured bound with room. Before the copy:
#: the largest error over the tests' meshes (a faceted sphere, an icosphere, a box, the
#: teapot, a soup; 1,500 points each, the default and the SAH tree) was 0.023 at
#: ``beta = 1.3``, and over 1,048,576 points in the box grown by a fifth of each of the
#: bench's scenes, against the walk at ``beta = 4`` (itself within 0.002), 0.025 on the
#: bunny, 0.042 on Sponza and 0.031 on a 1M-triangle terrain at 1.35. At ``beta = 1.3``
#: these were 0.033, 0.058 and
#: 0.039 on the trees of 2026-12-04 (past the bound on one Sponza point: six small nodes
#: at 1.31-1.36 radii, each off by 0.007-0.015, all of one sign), 0.031, 0.048 and 0.037
#: on those of the commit that set it, and 0.031, 0.062 and 0.042 before far nodes had
#: to be far for their area too (:data:`lbvh.queries.winding_moments.NODE_ERROR`, which
#: alone does not mend the first: 0.02 instead of 0.04 left it at 0.057). The error is that of the
#: expansion of the far nodes (Barill et al. 2018), about ``(1 / beta)^3`` of their
#: contribution, and the float32 sums add 1e-5. On a closed mesh ``w_exact`` is 0 or 1
#: off the surface, so ``contains`` (``w > 1/2``) is exact wherever the float32 solid
#: angles are, which the tests check down to points :data:`INSIDE_TOLERANCE` (relative
#: to the mesh's extent) from the surface.
WINDING_BOUND = 0.05
#: Relative distance from the surface of a closed mesh beyond which ``contains`` is right.
INSIDE_TOLERANCE = 1e-5
