"""Where the ray walk's time goes (issue 16): the tree or the walk's code?

Usage::

    PYTHONPATH=.venv/lib/python3.11/site-packages:/tmp/lbvh_peers \\
        .venv/bin/python bench/bench_walk.py [--scenes bunny,sponza,terrain-1m] [--out DIR]

The traversal bench's "where the gap is" table leaves the largest factor of the
gap to Embree to the walk: with our fastest tree and no host work, the kernel
is still slower than Embree. Two measurements of this script split it, each
against Embree-2t (embreex, two threads over 16 chunks, as in
``bench_traverse.py``) in the same interleaved rounds (medians of ``--repeats``),
closest hits of the bench camera's 1024x1024 rays, kernel times
(``trace_buffers``, rays already on the device):

* **Embree's tree in our walk.** Embree's own SAH builder, through its generic
  ``rtcBuildBVH`` (8-wide, leaf cost counted in blocks of 4 triangles as its
  triangle BVHs do, at most 32 triangles a leaf; the embreex wheel's library,
  called with ctypes), over the triangles' boxes; its tree converted to ours
  (:func:`nary_to_binary`: every node a balanced binary subtree of its
  children, leaves as slot ranges) and traced by our kernel, beside our best
  tree in the goal's budget and our SAH reference. If Embree's tree were what
  made Embree fast, our walk over it would close the gap.
* **Rays whose records stay in cache.** The camera's rays, the 64x64 tile at the
  image's centre repeated 256 times, and the centre ray repeated 1M times (all
  its data in L1, every branch predicted): if the gap were memory or
  mispredicted branches, it would close on the last two.

Beside each rate: nodes visited and triangles tested per ray (our kernel's
counters) and the answers' agreement with our default tree (the same hits
whatever the tree, up to ties at equal ``t``). Needs embreex (skipped
otherwise). Outputs ``bench_walk.md`` and ``bench_walk.json`` in ``--out``.
"""
from __future__ import annotations

import argparse
import ctypes
import glob
import itertools
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pyopencl as cl

import lbvh
from lbvh.builders.bounds import triangle_boxes_numpy
from lbvh.bvh import BVH
from lbvh.device import get_context
from lbvh.layout import NODE_DTYPE, parents_of
from lbvh.mesh import as_mesh
from lbvh.queries import traverse as tv
from lbvh.queries.rays import check_rays, upload_rays
from lbvh.tree import upload_tree

import common

SCENES = ("bunny", "sponza", "terrain-1m")
RAYS = (1024, 1024)
TILE = 64
EMBREE_CHUNKS = 16
#: rtcBuildBVH's arguments: 8 children a node, leaf cost in blocks of 4 triangles,
#: 1 to 32 triangles a leaf, traversal and intersection cost 1 (Embree's triangle
#: BVHs count leaves in blocks of the 4 triangles one SIMD test covers).
EMBREE_BUILD = {"branching": 8, "block": 4, "min_leaf": 1, "max_leaf": 32,
                "traversal_cost": 1.0, "intersection_cost": 1.0}
BUILD_QUALITY_MEDIUM = 1


def nary_to_binary(root: int, children: dict[int, list[int]], leaves: dict[int, list[int]],
                   lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An n-ary tree as ours: ``(nodes NODE_DTYPE, prim_order int32)``, root 0.

    ``children`` maps an inner node to its children, ``leaves`` a leaf to its
    primitives; ``lo``, ``hi`` are the primitives' boxes. Each inner node of k
    children becomes a balanced binary subtree over them (k - 1 nodes); a leaf
    holds its primitives as a range of slots in ``prim_order``; every box is the
    union of its primitives' boxes."""
    nodes: list[Any] = []
    order: list[int] = []

    def emit(ref: int) -> int:
        if ref in leaves:
            prims = leaves[ref]
            i = len(nodes)
            nodes.append((lo[prims].min(axis=0), len(order), hi[prims].max(axis=0), -len(prims)))
            order.extend(prims)
            return i
        return group(children[ref])

    def group(refs: list[int]) -> int:
        if len(refs) == 1:
            return emit(refs[0])
        i = len(nodes)
        nodes.append(None)
        half = (len(refs) + 1) // 2
        a, b = group(refs[:half]), group(refs[half:])
        nodes[i] = (np.minimum(nodes[a][0], nodes[b][0]), a,
                    np.maximum(nodes[a][2], nodes[b][2]), b)
        return i

    emit(root)
    out = np.zeros(len(nodes), NODE_DTYPE)
    for k, (lower, a, upper, b) in enumerate(nodes):
        out[k]["lower"], out[k]["a"], out[k]["upper"], out[k]["b"] = lower, a, upper, b
    return out, np.asarray(order, np.int32)


class _Prim(ctypes.Structure):
    _fields_ = [("lx", ctypes.c_float), ("ly", ctypes.c_float), ("lz", ctypes.c_float),
                ("geom", ctypes.c_uint), ("ux", ctypes.c_float), ("uy", ctypes.c_float),
                ("uz", ctypes.c_float), ("prim", ctypes.c_uint)]


_CREATE_NODE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p)
_SET_CHILDREN = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.POINTER(ctypes.c_void_p),
                                 ctypes.c_uint, ctypes.c_void_p)
_SET_BOUNDS = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint,
                               ctypes.c_void_p)
_CREATE_LEAF = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.POINTER(_Prim),
                                ctypes.c_size_t, ctypes.c_void_p)


class _BuildArguments(ctypes.Structure):
    """Embree's RTCBuildArguments (rtcore_builder.h), field by field."""
    _fields_ = [("byte_size", ctypes.c_size_t), ("quality", ctypes.c_int), ("flags", ctypes.c_int),
                ("branching", ctypes.c_uint), ("max_depth", ctypes.c_uint),
                ("block", ctypes.c_uint), ("min_leaf", ctypes.c_uint),
                ("max_leaf", ctypes.c_uint), ("traversal_cost", ctypes.c_float),
                ("intersection_cost", ctypes.c_float), ("bvh", ctypes.c_void_p),
                ("primitives", ctypes.POINTER(_Prim)), ("count", ctypes.c_size_t),
                ("capacity", ctypes.c_size_t), ("create_node", _CREATE_NODE),
                ("set_children", _SET_CHILDREN), ("set_bounds", _SET_BOUNDS),
                ("create_leaf", _CREATE_LEAF), ("split", ctypes.c_void_p),
                ("progress", ctypes.c_void_p), ("user", ctypes.c_void_p)]


def embree_library() -> ctypes.CDLL:
    """The Embree 4 library of the embreex wheel (``ImportError`` without embreex)."""
    import embreex
    where = os.path.dirname(os.path.dirname(embreex.__file__))
    found = sorted(glob.glob(os.path.join(where, "embreex.libs", "libembree4*.so*")))
    if not found:
        raise ImportError(f"no libembree4 beside embreex in {where}")
    lib = ctypes.CDLL(found[0])
    lib.rtcNewDevice.restype, lib.rtcNewDevice.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
    lib.rtcNewBVH.restype, lib.rtcNewBVH.argtypes = ctypes.c_void_p, [ctypes.c_void_p]
    lib.rtcBuildBVH.restype = ctypes.c_void_p
    lib.rtcBuildBVH.argtypes = [ctypes.POINTER(_BuildArguments)]
    for name in ("rtcReleaseBVH", "rtcReleaseDevice"):
        getattr(lib, name).argtypes = [ctypes.c_void_p]
    return lib


def embree_tree(lib: ctypes.CDLL, lo: np.ndarray, hi: np.ndarray, branching: int, block: int,
                min_leaf: int, max_leaf: int, traversal_cost: float, intersection_cost: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Embree's SAH tree over the boxes ``lo``, ``hi`` (rtcBuildBVH, one thread), as
    ours (:func:`nary_to_binary`)."""
    n = len(lo)
    prims = (_Prim * n)()
    words = np.ctypeslib.as_array(prims).view(np.float32).reshape(n, 8)
    words[:, 0:3], words[:, 4:7] = lo, hi
    ints = words.view(np.uint32)
    ints[:, 3], ints[:, 7] = 0, np.arange(n, dtype=np.uint32)
    children: dict[int, list[int]] = {}
    leaves: dict[int, list[int]] = {}

    ids = itertools.count(1)   # the handles Embree keeps: never 0 (NULL)

    def create_node(_alloc, _count, _user):
        key = next(ids)
        children[key] = []
        return key

    def set_children(node, kids, count, _user):
        children[node] = [kids[k] for k in range(count)]

    def create_leaf(_alloc, p, count, _user):
        key = next(ids)
        leaves[key] = [p[k].prim for k in range(count)]
        return key

    callbacks = (_CREATE_NODE(create_node), _SET_CHILDREN(set_children),
                 _SET_BOUNDS(lambda *_: None), _CREATE_LEAF(create_leaf))
    device = lib.rtcNewDevice(b"threads=1")
    bvh = lib.rtcNewBVH(device)
    try:
        args = _BuildArguments(ctypes.sizeof(_BuildArguments), BUILD_QUALITY_MEDIUM, 0, branching,
                               64, block, min_leaf, max_leaf, traversal_cost, intersection_cost,
                               bvh, prims, n, n, *callbacks, None, None, None)
        root = lib.rtcBuildBVH(ctypes.byref(args))
    finally:
        lib.rtcReleaseBVH(bvh)
        lib.rtcReleaseDevice(device)
    return nary_to_binary(root, children, leaves, lo, hi)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default="bench/results")
    args = p.parse_args(argv)
    try:
        lib, embree = embree_library(), common.Embree()
    except ImportError as exc:
        print(f"bench_walk: embreex is needed ({exc})")
        return 0
    pool = ThreadPoolExecutor(2)
    cams = common.load_cameras()
    rows: list[dict[str, Any]] = []
    started = time.perf_counter()
    report = common.report_start(common.command_line("bench_walk.py", argv),
                                 get_context(), {"embree": f"embree {embree.version}"})

    def embree_2t(built: Any, o: np.ndarray, d: np.ndarray) -> float:
        edges = np.linspace(0, len(o), EMBREE_CHUNKS + 1).astype(int)
        parts = [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]
        t = time.perf_counter()
        list(pool.map(lambda s: embree.trace(built, o[s], d[s]), parts))
        return time.perf_counter() - t

    # Embree's trees first, all of them: its task scheduler is the process's, and
    # once embreex has made a scene (on every core) rtcBuildBVH takes its parallel
    # path whatever its device's thread count, and builds another tree (measured:
    # 18.3 nodes a ray on terrain-1m's camera rays against 12.0). One thread, before
    # any scene, gives the same tree every run.
    scenes, embree_trees = {}, {}
    for name in args.scenes.split(","):
        scene = common.load_bench_scene(name, RAYS, cams)
        if isinstance(scene, str):
            print(f"{name}: skipped ({scene})")
            continue
        lo, hi = triangle_boxes_numpy(*as_mesh(scene.vertices, scene.faces))
        t0 = time.perf_counter()
        embree_trees[name] = embree_tree(lib, lo, hi, **EMBREE_BUILD)
        scenes[name] = (scene, time.perf_counter() - t0)
    for name, (scene, build_s) in scenes.items():
        o, d = (np.ascontiguousarray(a, np.float32) for a in scene.camera.rays())
        default = lbvh.build(scene.vertices, scene.faces)
        trees = {"ours, best in budget (treelets3-5+collapse)":
                 lbvh.build(scene.vertices, scene.faces, treelet_rounds=3, treelet_leaves=5,
                            collapse=True),
                 "ours, SAH reference": lbvh.build(scene.vertices, scene.faces, builder="sah")}
        nodes, order = embree_trees.pop(name)
        trees["Embree's builder (rtcBuildBVH), our walk"] = BVH(default.mesh, upload_tree(
            default.ctx, nodes, parents_of(nodes, 0), order, 0, "embree"))
        built = embree.build(scene.vertices, scene.faces)[2]
        w, h = RAYS
        pixel = np.arange(w * h).reshape(h, w)
        tile = pixel[h // 2 - TILE // 2:h // 2 + TILE // 2, w // 2 - TILE // 2:w // 2 + TILE // 2]
        sets = {"camera": None, "centre tile repeated": np.tile(tile.ravel(), w * h // TILE ** 2),
                "centre ray repeated": np.full(w * h, pixel[h // 2, w // 2])}
        want = default.intersect(o, d).prim
        for set_name, index in sets.items():
            so, sd = (o, d) if index is None else (o[index], d[index])
            rays = upload_rays(default.ctx, check_rays(so, sd))
            labels = list(trees) if index is None else list(trees)[:1]

            def ours(bvh: BVH) -> float:
                t = time.perf_counter()
                tv.trace_buffers(bvh.query_data, rays)
                bvh.ctx.queue.finish()
                return time.perf_counter() - t

            for label in labels:
                ours(trees[label])
            embree_2t(built, so, sd)
            times = {label: [] for label in labels}
            peer = []
            for _ in range(args.repeats):
                for label in labels:
                    times[label].append(ours(trees[label]))
                peer.append(embree_2t(built, so, sd))
            for label in labels:
                bvh = trees[label]
                counted = tv.trace_buffers(bvh.query_data, rays, counters=True)
                counts = np.empty((len(so), 2), np.int32)
                cl.enqueue_copy(bvh.ctx.queue, counts, counted.counters, is_blocking=True)
                agree = (float((bvh.intersect(o, d).prim == want).mean()) if index is None
                         else None)
                rows.append({"scene": name, "rays": set_name, "tree": label,
                             "mrays": len(so) / np.median(times[label]) / 1e6,
                             "embree_mrays": len(so) / np.median(peer) / 1e6,
                             "ratio": float(np.median(np.array(peer) / np.array(times[label]))),
                             "nodes": float(counts[:, 0].mean()),
                             "tris": float(counts[:, 1].mean()), "agree": agree,
                             "embree_build_s": build_s if "Embree" in label else None})
                r = rows[-1]
                print(f"{name:10s} {set_name:22s} {label:44s} {r['mrays']:6.2f} Mrays/s "
                      f"(embree-2t {r['embree_mrays']:6.2f}) ours/embree {r['ratio']:.2f} "
                      f"nodes {r['nodes']:5.1f} tris {r['tris']:4.1f}", flush=True)
            rays.release()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report["duration_seconds"] = time.perf_counter() - started
    report.update(rows=rows, embree_build=EMBREE_BUILD)
    lines = ["# Where the walk's time goes: Embree's tree in our walk, rays in cache", "",
             *common.header_lines(report), "",
             "Closest hits, kernel times (`trace_buffers`), against Embree-2t in the same "
             f"rounds (medians of {args.repeats}); see the docstring of `bench/bench_walk.py`.",
             "", "| scene | rays | tree | ours Mrays/s | Embree-2t Mrays/s | ours / Embree-2t "
             "| nodes/ray | tris/ray | same hits as the default tree |", "|---|---|---|---:|---:|"
             "---:|---:|---:|---:|"]
    for r in rows:
        agree = "-" if r["agree"] is None else f"{r['agree']:.5f}"
        lines.append(f"| {r['scene']} | {r['rays']} | {r['tree']} | {r['mrays']:.2f} | "
                     f"{r['embree_mrays']:.2f} | {r['ratio']:.2f} | {r['nodes']:.1f} | "
                     f"{r['tris']:.1f} | {agree} |")
    common.write_report(report, "\n".join(lines) + "\n",
                        {"markdown": out / "bench_walk.md", "json": out / "bench_walk.json"}, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
