"""Ray queries over dask arrays: batches of rays spread over a cluster's workers.

When the rays of a job outgrow one machine (preprocessing thousands of
meshes, lidar simulation, offline rendering), a Python user reaches for Dask
(or Ray), not for a scheduler of lbvh's. This module maps lbvh's queries
over the blocks of dask arrays of rays::

    import dask.array as da, lbvh, lbvh.dask
    from dask.distributed import Client
    client = Client(n_workers=4)                   # or a cluster's address
    bvh = lbvh.build(vertices, faces)              # or an lbvh.Scene
    origins = da.from_array(o, chunks=(1 << 20, 3))
    directions = da.from_array(d, chunks=(1 << 20, 3))
    hits = lbvh.dask.intersect(bvh, origins, directions)   # lazy dask arrays
    t, prim = da.compute(hits.t, hits.prim)

The tree travels once: ``bvh`` enters the graph as one ``dask.delayed``
value, pickled (its arrays, not its device buffers: :meth:`lbvh.BVH.__reduce__`)
to the workers that need it, where it is uploaded to each worker's own
default device. Each block of rays is one call of ``bvh.intersect`` (or
``occluded``) on a worker, with its answers those of one in-process call.
``directions`` is rechunked to ``origins``' blocks. Dask is an optional
dependency (``pip install 'lbvh-opencl[dask]'``), imported only here.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import dask
import dask.array as da
import numpy as np

from .bvh import BVH
from .scene import Scene

__all__ = ["DaskHits", "intersect", "occluded"]


@dataclass
class DaskHits:
    """Lazy results of :func:`intersect`, one entry per ray (dask arrays).

    ``t`` (``float32``, ``inf`` on a miss), ``prim`` (``int32``, ``-1``), ``u``, ``v``
    (``float32``) as :class:`lbvh.Hits`; for a scene also ``instance`` (``int32``).
    """
    t: da.Array
    prim: da.Array
    u: da.Array
    v: da.Array
    instance: da.Array | None = None

    def compute(self) -> dict[str, np.ndarray]:
        """Every field computed at once (one pass over the blocks)."""
        names = ["t", "prim", "u", "v"] + (["instance"] if self.instance is not None else [])
        return dict(zip(names, dask.compute(*(getattr(self, n) for n in names))))


def _rays(target: Any, origins: Any, directions: Any) -> tuple[da.Array, da.Array]:
    if not isinstance(target, (BVH, Scene)):
        raise ValueError(f"target: a {type(target).__name__}; expected an lbvh.BVH or an "
                         "lbvh.Scene")
    o, d = da.asarray(origins), da.asarray(directions)
    for name, a in (("origins", o), ("directions", d)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"{name}: shape {a.shape}, expected (N, 3)")
    if d.shape[0] != o.shape[0]:
        raise ValueError(f"directions: {d.shape[0]} rays, but origins has {o.shape[0]}")
    o = o.rechunk({1: 3})
    return o, d.rechunk(o.chunks)


def _intersect_block(o: np.ndarray, d: np.ndarray, target: Any, tmin: float, tmax: float,
                     options: dict[str, Any]) -> np.ndarray:
    """One block on a worker: ``float64 (n, 5)`` t, u, v, prim and instance (prim and
    instance are integers, exact in float64)."""
    hits = target.intersect(o, d, tmin, tmax, **options)
    instance = getattr(hits, "instance", np.full(len(hits.t), -1, np.int32))
    return np.stack([hits.t, hits.u, hits.v, hits.prim, instance], axis=1).astype(np.float64)


def intersect(target: BVH | Scene, origins: Any, directions: Any, tmin: float = 0.0,
              tmax: float = np.inf, **options: Any) -> DaskHits:
    """The closest hit of every ray, block by block on the workers (lazy).

    Args:
        target: an :class:`lbvh.BVH` or :class:`lbvh.Scene`.
        origins, directions: ``(N, 3)`` dask arrays (or arrays dask takes); one block
            is one query on a worker.
        tmin, tmax: scalars, as for :meth:`lbvh.BVH.intersect`.
        options: keywords of ``target.intersect``: ``options=`` a
            :class:`lbvh.QueryOptions` or its fields (``triangle_test``, ...).

    Returns:
        :class:`DaskHits`.
    """
    o, d = _rays(target, origins, directions)
    shared = dask.delayed(target, pure=True)   # one key: pickled once per worker
    packed = da.map_blocks(_intersect_block, o, d, shared, float(tmin), float(tmax), options,
                           dtype=np.float64, chunks=(o.chunks[0], (5,)))
    return DaskHits(t=packed[:, 0].astype(np.float32), prim=packed[:, 3].astype(np.int32),
                    u=packed[:, 1].astype(np.float32), v=packed[:, 2].astype(np.float32),
                    instance=packed[:, 4].astype(np.int32) if isinstance(target, Scene) else None)


def _occluded_block(o: np.ndarray, d: np.ndarray, target: Any, tmin: float, tmax: float,
                    options: dict[str, Any]) -> np.ndarray:
    return np.asarray(target.occluded(o, d, tmin, tmax, **options), dtype=bool)


def occluded(target: BVH | Scene, origins: Any, directions: Any, tmin: float = 0.0,
             tmax: float = np.inf, **options: Any) -> da.Array:
    """Whether each ray hits anything in ``[tmin, tmax]``: a lazy ``bool`` dask array
    (arguments as :func:`intersect`; ``options``: those of ``target.occluded``)."""
    o, d = _rays(target, origins, directions)
    shared = dask.delayed(target, pure=True)
    return da.map_blocks(_occluded_block, o, d, shared, float(tmin), float(tmax), options,
                         dtype=bool, chunks=(o.chunks[0],), drop_axis=1)
