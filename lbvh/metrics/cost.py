"""The SAH cost model: its constants and their checks, one home for every builder.

The surface area heuristic (Goldsmith & Salmon 1987; MacDonald & Booth 1990)
prices a tree as ``C_node`` per internal node a ray enters plus ``C_tri`` per
triangle it tests, each weighted by the probability ``A(node) / A(root)``
that a random ray through the root's box enters the node. The SAH reference
(:mod:`lbvh.builders.sah`), the treelet restructuring
(:mod:`lbvh.builders.restructure`), the leaf collapse
(:mod:`lbvh.builders.collapse`), the quality metrics
(:mod:`lbvh.metrics.quality`) and the benches all take their defaults
from here.
"""
from __future__ import annotations

import numpy as np

#: Default cost of one internal node visit (box test), relative to C_TRI.
C_NODE = 1.0
#: Default cost of one ray-triangle test.
C_TRI = 1.0
#: Default largest leaf of the SAH reference and of the collapse; bigger nodes are always split.
MAX_LEAF_SIZE = 8


def check_sah_constants(c_node: float, c_tri: float, max_leaf_size: int) -> None:
    """Raise ``ValueError`` naming a bad SAH constant or leaf size."""
    for name, value, positive in (("c_node", c_node, False), ("c_tri", c_tri, True)):
        try:
            x = float(value)
        except (TypeError, ValueError):
            x = float("nan")
        if isinstance(value, bool) or not np.isfinite(x) or x < 0 or (positive and x == 0):
            raise ValueError(f"{name}: {value!r}; expected a finite number {'>' if positive else '>='} 0")
    if isinstance(max_leaf_size, bool) or not isinstance(max_leaf_size, (int, np.integer)) \
            or not 1 <= max_leaf_size < 2**31:
        raise ValueError(f"max_leaf_size: {max_leaf_size!r}; expected an integer >= 1")


def box_area(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Surface area ``2 (dx dy + dy dz + dz dx)`` of boxes ``(..., 3)``, in float64.

    The same expression (same order of operations) is used by the SAH builder and
    the quality metrics, so costs computed by both are bit-identical.
    """
    d = np.asarray(upper, np.float64) - np.asarray(lower, np.float64)
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    return 2.0 * (dx * dy + dy * dz + dz * dx)


# -- the float32 areas the kernels compare (kernels/common.h box_scale, scaled_half_area)

def box_scale(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """float32 ``(n, 1)``: ``2**-e`` for the exponent ``e`` of each box's largest
    ``|coordinate|``, of boxes ``lo, hi`` ``(n, 3)`` (the twin of kernels/common.h
    box_scale). A box times its scale has coordinates below 2 in magnitude: its area
    neither underflows nor overflows float32, and the same box at any power-of-two scale
    gives the same scaled coordinates."""
    m = np.maximum(np.abs(lo), np.abs(hi)).max(axis=-1)
    e = np.clip(((np.asarray(m, np.float32).view(np.int32) >> 23) & 0xFF) - 126, -126, 126)
    return ((127 - e) << 23).astype(np.int32).view(np.float32)[..., None]


def scaled_half_area(lo: np.ndarray, hi: np.ndarray, s: np.ndarray) -> np.ndarray:
    """float32 ``(...)``: half the surface area of each box ``lo, hi`` ``(..., 3)`` with its
    coordinates times ``s`` (the twin of kernels/common.h scaled_half_area: the same
    operations in the same order, so the same bits)."""
    d = hi * s - lo * s
    return d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0]
