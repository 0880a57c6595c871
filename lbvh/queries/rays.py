"""Rays as the traversal kernel reads them: checks, conversion to float32, upload.

``origins`` and ``directions`` are ``(N, 3)`` arrays (float32; float64 and
integers are converted to float32). Directions need not be unit length: ``t``
is measured in units of the direction's length, the hit point is
``origin + t * direction``. ``tmin`` and ``tmax`` are scalars or ``(N,)``
arrays; a hit counts when ``tmin <= t <= tmax``.

Bad rays are refused before anything runs on the device, with a ``ValueError``
naming the first bad ray: NaN or infinite origins and directions (also values
beyond the float32 range), zero-length directions (after the float32
conversion), NaN, negative or infinite ``tmin``, NaN ``tmax``, ``tmin > tmax``,
wrong shapes or dtypes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from .. import device as dev
from ..mesh import real_array


@dataclass
class Rays:
    """Checked rays, as the kernel reads them.

    ``origins``, ``directions``: ``float32 (N, 3)`` C-contiguous. ``tmin``,
    ``tmax``: ``float32``, each a 0-d array (one value for every ray) or ``(N,)``.
    """
    origins: np.ndarray
    directions: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray

    def __len__(self) -> int:
        return len(self.origins)

    def intervals(self) -> tuple[np.ndarray, np.ndarray]:
        """``tmin`` and ``tmax`` as ``float32 (N,)`` arrays."""
        n = len(self)
        return np.broadcast_to(self.tmin, (n,)), np.broadcast_to(self.tmax, (n,))

    def kernel_intervals(self) -> tuple[np.ndarray, np.ndarray, int]:
        """``(tmin, tmax, stride)`` as the kernel reads them: C-contiguous ``(N,)``
        arrays with stride 1 when either varies per ray, else one value each, stride 0."""
        if self.tmin.ndim == 1 or self.tmax.ndim == 1:
            lo, hi = self.intervals()
            return np.ascontiguousarray(lo), np.ascontiguousarray(hi), 1
        return self.tmin.reshape(1), self.tmax.reshape(1), 0


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _as_float32(name: str, arr: np.ndarray) -> np.ndarray:
    """C-contiguous float32; values beyond the float32 range become infinite (refused later)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.ascontiguousarray(arr, dtype=np.float32)


def _ray_vectors(name: str, value: Any, count: int | None) -> np.ndarray:
    """The caller's ``(N, 3)`` array, shape and dtype checked, as float32."""
    arr = real_array(name, value)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: shape {arr.shape}, expected (N, 3)")
    if count is not None and len(arr) != count:
        raise ValueError(f"{name}: {len(arr)} rays, but origins has {count}")
    return _as_float32(name, arr)


def _interval(name: str, value: Any, count: int) -> np.ndarray:
    """The caller's scalar or ``(N,)`` array, shape and dtype checked, as float32."""
    arr = real_array(name, value)
    if arr.ndim != 0 and arr.shape != (count,):
        raise ValueError(f"{name}: shape {arr.shape}, expected a scalar or ({count},)")
    return _as_float32(name, arr)


def _all_finite(a: np.ndarray) -> bool:
    """No NaN or infinity in ``a``: its minimum and maximum are finite (NaN propagates
    through both); two reductions without temporaries instead of an isfinite mask."""
    return a.size == 0 or bool(np.isfinite(a.min()) and np.isfinite(a.max()))


def _all_nonzero_rows(d: np.ndarray) -> bool:
    """Every row of float32 ``d`` has a nonzero component: the OR of the three bit
    patterns, sign bit dropped, is nonzero."""
    bits = d.view(np.uint32)
    return bool((((bits[:, 0] | bits[:, 1] | bits[:, 2]) << np.uint32(1)) != 0).all())


def _intervals_ok(lo: np.ndarray, hi: np.ndarray) -> bool:
    with np.errstate(invalid="ignore"):
        return bool(not np.isnan(hi).any() and (lo >= 0).all() and np.isfinite(lo).all()
                    and (lo <= hi).all())


def _raise_first_bad(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     given_o: np.ndarray, given_d: np.ndarray) -> None:
    """Name the first problem of converted rays (slow path, only after the fast checks failed)."""
    for name, vec, given in (("origins", o, given_o), ("directions", d, given_d)):
        bad = ~np.isfinite(vec).all(axis=1)
        if bad.any():
            i = _first_bad(bad)
            raise ValueError(f"{name}: ray {i} has a NaN, infinite or beyond-float32 component "
                             f"{given[i].tolist()}")
    zero = ~(d != 0).any(axis=1)
    if zero.any():
        raise ValueError(f"directions: ray {_first_bad(zero)} has a zero-length direction "
                         "(after conversion to float32)")
    lo, hi = np.broadcast_to(lo, (len(o),)), np.broadcast_to(hi, (len(o),))
    for name, col in (("tmin", lo), ("tmax", hi)):
        if np.isnan(col).any():
            raise ValueError(f"{name}: ray {_first_bad(np.isnan(col))} is NaN")
    checks = ((lo < 0, "tmin: ray {i} has a negative tmin {lo}"),
              (np.isinf(lo), "tmin: ray {i} has an infinite tmin"),
              (lo > hi, "tmin/tmax: ray {i} has tmin {lo} > tmax {hi}"))
    for bad, message in checks:
        if bad.any():
            i = _first_bad(bad)
            raise ValueError(message.format(i=i, lo=float(lo[i]), hi=float(hi[i])))


def check_rays(origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf) -> Rays:
    """Validate rays and convert them to the float32 arrays the kernel reads.

    Values are converted to float32 first and checked after (a float64 beyond the
    float32 range is refused). Raises ``ValueError`` naming the first bad ray (see
    the module docstring). Costs a few passes over the arrays (no copy when they
    are float32 and C-contiguous already).
    """
    given_o = real_array("origins", origins)
    o = _ray_vectors("origins", given_o, None)
    given_d = real_array("directions", directions)
    d = _ray_vectors("directions", given_d, len(o))
    n = len(o)
    lo, hi = _interval("tmin", tmin, n), _interval("tmax", tmax, n)
    ok = (n == 0 or (_all_finite(o) and _all_finite(d) and _all_nonzero_rows(d)
                     and _intervals_ok(lo, hi)))
    if not ok:
        _raise_first_bad(o, d, lo, hi, given_o, given_d)
    return Rays(o, d, lo, hi)


@dataclass
class DeviceRays:
    """Rays on the device (``count`` of them), as :func:`trace_buffers` reads them:
    ``origins``, ``directions`` float32 ``3 * count``; ``tmin``, ``tmax`` float32, one
    per ray (``interval_stride`` 1) or one for all (``interval_stride`` 0)."""
    count: int
    origins: cl.Buffer
    directions: cl.Buffer
    tmin: cl.Buffer
    tmax: cl.Buffer
    interval_stride: int

    def release(self) -> None:
        """Release the buffers now (their memory counts them out)."""
        for buf in (self.origins, self.directions, self.tmin, self.tmax):
            buf.release()


def upload_rays(ctx: dev.Context, rays: Rays) -> DeviceRays:
    """Copy rays to new device buffers (no checks beyond :func:`check_rays`' types:
    the caller decides what it uploads)."""
    lo, hi, stride = rays.kernel_intervals()
    up = ctx.memory.upload
    return DeviceRays(len(rays), up(rays.origins), up(rays.directions), up(lo), up(hi), stride)


