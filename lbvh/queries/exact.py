"""Exact decisions of the ray/triangle test: twin of ``kernels/exact.h`` and of the
decision part of ``hit_triangle`` in ``kernels/ray_triangle.h``.

The kernel decides each sign (an edge function, the numerator of ``t``,
collinearity) in double where a rigorous error bound settles it and by exact
expansion arithmetic (Shewchuk 1997) where it does not. This module computes
the same double values with numpy (IEEE float64, the same operations in the
same order) and the exact signs with Python integers: every float32 is an
integer times ``2^-149``, so ``x * 2^149`` is an exact integer and a polynomial
of them is exact. Both are exact, so the signs are equal by construction, and
the double values (``t``, ``u``, ``v``) are equal bit for bit.

Error bounds of the double stage (``u = 2^-53``, ``Q`` the largest ``|p - o|`` of
the triangle's three corners, ``|ex|, |ey| <= |ez|`` since ``kz`` is the
dominant axis):

- ``q = p - o`` rounds once: ``|dq| <= u |q|``;
- a sheared coordinate ``x = q_x ez - q_z ex`` is off by at most
  ``3.01 u (|q_x| + |q_z|) |ez| <= 6.02 u |ez| Q``, and ``|x| <= 2 |ez| Q``;
- an edge function ``U = x_c y_b - y_c x_b`` by at most ``4 (6.02 u |ez| Q)
  (2 |ez| Q) + 16 u ez^2 Q^2 = 64.2 u ez^2 Q^2`` (plus ``O(u^2)``): the kernel
  takes ``2^-45 ez^2 Q^2``, four times that;
- ``T = U q_a,z + V q_b,z + W q_c,z`` (summed by :func:`sum3`) by at most
  ``3 (64.2 u ez^2 Q^2) Q + 3 u (8 ez^2 Q^3) + 2 u (24 ez^2 Q^3) < 2^-45 ez^2 Q^3``:
  the kernel takes ``2^-42 ez^2 Q^3``.

No step underflows or overflows in double for float32 inputs (products of up
to four float32 lie within ``2^-600 .. 2^520``), so the bounds hold at every
scale and the decisions do not depend on a power-of-two scaling of the scene.
"""
from __future__ import annotations

import numpy as np

__all__ = ["BOUND_EDGE", "BOUND_NUMERATOR", "sum3", "collinear", "edge_signs_exact",
           "numerator_signs_exact", "ruled_signs_exact", "to_int"]

#: Factor on ``ez^2 Q^2`` bounding the double edge functions' error (kernel: 0x1p-45).
BOUND_EDGE = 2.0 ** -45
#: Factor on ``ez^2 Q^3`` bounding the double numerator's error (kernel: 0x1p-42).
BOUND_NUMERATOR = 2.0 ** -42


def sum3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``a + b + c`` as ``sum3`` of ``kernels/ray_triangle.h``: the two smallest in
    magnitude first, or exactly the smallest where the two largest cancel; the
    same for any order of the three, negated exactly with them (float64)."""
    x, y, z = (np.asarray(q, np.float64).copy() for q in (a, b, c))
    for first, second in ((x, y), (y, z), (x, y)):
        swap = np.abs(first) > np.abs(second)
        first[swap], second[swap] = second[swap], first[swap].copy()
    return np.where(y == -z, x, (x + y) + z)


def to_int(x) -> int:
    """A float32 value times ``2^149``: an exact Python integer."""
    return int(np.ldexp(np.float64(np.float32(x)), 149))


def _det3(x, y, z) -> int:
    return (x[0] * (y[1] * z[2] - y[2] * z[1]) - x[1] * (y[0] * z[2] - y[2] * z[0])
            + x[2] * (y[0] * z[1] - y[1] * z[0]))


def _sign(n: int) -> int:
    return (n > 0) - (n < 0)


def _distinct_rows(*arrays) -> tuple[list[list[int]], np.ndarray]:
    """The rows of the float32 ``(N, 3)`` arrays side by side, once each distinct row
    (bit for bit), as lists of exact integers times ``2^149`` (:func:`to_int`), and
    ``int (N,)``: which distinct row each row is. The exact signs below are taken once
    per distinct input: a scene of identical triangles asks the same question many
    times."""
    rows = np.ascontiguousarray(np.concatenate(
        [np.asarray(a, np.float32).reshape(len(arrays[0]), -1) for a in arrays], axis=1))
    _, first, inverse = np.unique(rows.view(np.uint32), axis=0, return_index=True,
                                  return_inverse=True)
    # float32 -> float64 -> times 2^149 is exact, and so is int() of that float
    scaled = np.ldexp(rows[first].astype(np.float64), 149).tolist()
    return [[int(x) for x in row] for row in scaled], inverse.reshape(-1)


def edge_signs_exact(e, o, p, r) -> np.ndarray:
    """``int (N,)``: the exact sign of the edge function ``x_p y_r - y_p x_r`` of corners
    ``p`` and ``r`` for shear ``e = (ex, ey, ez)`` and origin ``o`` (all float32
    ``(N, 3)`` in the ray's axis order kx, ky, kz): ``sign(ez) sign(e . ((p - o) x
    (r - o)))``, as ``exact_edge_sign``."""
    if len(e) == 0:
        return np.zeros(0, np.int64)
    rows, inverse = _distinct_rows(e, o, p, r)
    out = np.zeros(len(rows), np.int64)
    for k, row in enumerate(rows):
        ei, oi, pi, ri = row[0:3], row[3:6], row[6:9], row[9:12]
        q = [pi[j] - oi[j] for j in range(3)]
        s = [ri[j] - oi[j] for j in range(3)]
        out[k] = _sign(_det3(ei, q, s)) * (1 if ei[2] >= 0 else -1)
    return out[inverse]


def numerator_signs_exact(o, a, b, c) -> np.ndarray:
    """``int (N,)``: the exact sign of ``T = -ez^2 det[a - o, b - o, c - o]`` (float32
    ``(N, 3)`` inputs in the ray's axis order), as ``exact_numerator_sign``."""
    if len(o) == 0:
        return np.zeros(0, np.int64)
    rows, inverse = _distinct_rows(o, a, b, c)
    out = np.zeros(len(rows), np.int64)
    for k, row in enumerate(rows):
        oi = row[0:3]
        qa, qb, qc = ([row[3 * m + j] - oi[j] for j in range(3)] for m in (1, 2, 3))
        out[k] = -_sign(_det3(qa, qb, qc))
    return out[inverse]


def ruled_signs_exact(f: np.ndarray, e, p, r) -> np.ndarray:
    """EDGE_RULE's sign of an edge function ``f`` (exact signs) of corners ``p``, ``r``:
    ``f``, or where it is 0 the exact sign of ``y_p - y_r``, then of ``x_r - x_p``,
    as ``exact_ruled_sign``."""
    out = np.asarray(f, np.int64).copy()
    zero = np.flatnonzero(out == 0)
    if len(zero) == 0:
        return out
    rows, inverse = _distinct_rows(*(np.asarray(x, np.float32)[zero] for x in (e, p, r)))
    signs = np.zeros(len(rows), np.int64)
    for k, row in enumerate(rows):
        (ex, ey, ez), pi, ri = row[0:3], row[3:6], row[6:9]
        sy = _sign(ez * (pi[1] - ri[1]) - ey * (pi[2] - ri[2]))
        signs[k] = sy if sy != 0 else _sign(ez * (ri[0] - pi[0]) - ex * (ri[2] - pi[2]))
    out[zero] = signs[inverse]
    return out


def _orient_zero(ax, ay, bx, by, cx, cy) -> np.ndarray:
    """``bool``: the exact 2D orientation of float32 points is zero. The six products of
    two float32 are exact in float64; their sum is zero exactly where the sum of an
    exact expansion of them is (Grow-Expansion, Two-Sum in float64, as exact.h)."""
    terms = [bx * cy, -(bx * ay), -(ax * cy), -(by * cx), by * ax, ay * cx]
    h: list[np.ndarray] = []
    for x in terms:
        q = x
        out = []
        for hj in h:
            s = q + hj
            bv = s - q
            err = (q - (s - bv)) + (hj - bv)
            q = s
            out.append(err)
        out.append(q)
        h = out
    return np.all([c == 0 for c in h], axis=0)


def collinear(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``bool (F,)``: triangles whose three corners lie exactly on a line (repeated
    corners included): ``(b - a) x (c - a) = 0`` exactly, ``degenerate()`` of
    ``kernels/ray_triangle.h`` on a device with doubles. Depends on the triangle
    as a set of points only."""
    p = np.asarray(vertices, np.float32)[np.asarray(faces, np.int64)].astype(np.float64)
    if len(p) == 0:
        return np.zeros(0, bool)
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    out = np.ones(len(p), bool)
    with np.errstate(over="ignore", invalid="ignore"):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            out &= _orient_zero(a[:, i], a[:, j], b[:, i], b[:, j], c[:, i], c[:, j])
    return out
