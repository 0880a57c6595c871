#!/usr/bin/env python
"""Build benchmark of issue 2: the device LBVH build against its floors and its peers.

For each mesh (shared scenes and generated meshes of about 100K, 1M and 4M
triangles) it measures, interleaved in the same run so that ratios share the
machine's noise:

* the LBVH build with the inputs already on the device
  (:func:`lbvh.builders.pipeline.build_tree`): every phase from OpenCL event
  profiling, the summed device time and the wall time;
* on the same Morton keys (computed once, outside the timed build): numpy's
  stable argsort, pyopencl's RadixSort on the same context, our
  :func:`lbvh.device.sort.radix_sort` alone;
* the streaming floor: one device buffer-to-buffer copy of as many bytes as
  the build must read and write at least once;
* Embree (embreex) and warp-lang on the CPU when they are importable.

Medians of ``--repeats`` runs after one warm-up run. Tree quality (depth,
duplicate codes, SAH cost) comes from the warm-up build, which ``bvh.validate()``
checks outside the timing: an invalid tree stops the benchmark.

    .venv/bin/python bench/bench_build.py [--quick] [--scenes bunny,sponza,conference]
        [--sizes 100k,1m,4m] [--kinds soup,sphere,copies] [--repeats 5] [--json out.json]

The scene files, the peers' adapters (:class:`common.Embree`,
:class:`common.Warp`) and the timing helpers are shared with the other benches
in ``bench/common.py``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# bench/common.py, beside this script; imported before numpy, for it sets
# OPENBLAS_NUM_THREADS (see there).
from common import (DEFAULT_OUT, Embree, Warp, cpu_model, library_versions, load_peers, median,
                    scene_file, timed)

import numpy as np
import pyopencl as cl

import lbvh
from lbvh import device as dev
from lbvh.builders import bounds as lbvh_bounds
from lbvh.builders.morton import KEY_DTYPE, code_bits, morton_codes
from lbvh.builders.options import LBVHOptions
from lbvh.builders.pipeline import build_tree
from lbvh.device.sort import radix_sort
from lbvh.files import load_mesh
from lbvh.report import PHASES
from lbvh.tree import Mesh
from lbvh.verification import meshes

KEY_BITS = {"auto": None, "30": 32, "63": 64}
# The pipeline is being tuned: newer versions store each triangle's box in the
# bounds stage (morton and refit read it) instead of recomputing it from the mesh.
NODE_BYTES = 32

# Targets of issue 2, as ratios from one run.
TARGET_EMBREE = 3.0        # LBVH build at least this much faster than Embree's (~1M tris)
TARGET_NUMPY = 5.0         # our sort vs numpy's stable argsort
TARGET_PYOPENCL = 10.0     # our sort vs pyopencl's RadixSort
TARGET_FLOOR = 5.0         # whole build within this factor of the streaming floor
TARGET_BYTES_PER_TRI = 128.0


# -- small helpers ----------------------------------------------------------------

def parse_size(text: str) -> int:
    """``"100k"`` -> 100000, ``"1m"`` -> 1000000, ``"2500"`` -> 2500."""
    t = text.strip().lower()
    scale = {"k": 10 ** 3, "m": 10 ** 6}.get(t[-1:], 1)
    number = t[:-1] if scale > 1 else t
    try:
        value = int(float(number) * scale)
    except ValueError:
        raise ValueError(f"size: {text!r}; expected a count such as 100k, 1m or 2500") from None
    if value < 2:
        raise ValueError(f"size: {text!r}; a mesh needs at least 2 triangles")
    return value


def size_label(n: int) -> str:
    if n >= 10 ** 6:
        return f"{n / 1e6:.3g}M"
    return f"{n / 1e3:.3g}K" if n >= 10 ** 3 else str(n)


def mtris(n: int, seconds: float) -> float:
    return n / seconds * 1e-6 if seconds > 0 else float("nan")


@dataclass
class Samples:
    """Named lists of per-repeat measurements (seconds unless the name says otherwise)."""
    values: dict[str, list[float]] = field(default_factory=dict)

    def add(self, name: str, value: float) -> None:
        self.values.setdefault(name, []).append(float(value))

    def medians(self) -> dict[str, float]:
        return {name: median(v) for name, v in self.values.items()}


# -- machine -----------------------------------------------------------------------

def versions() -> dict[str, str]:
    out = library_versions()
    for name in ("embreex", "warp", "mako"):
        try:
            module = __import__(name)
            out[name] = getattr(module, "__version__", "installed")
        except ImportError:
            out[name] = "not installed"
    return out


def machine_info(ctx: dev.Context) -> dict:
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "platform": platform.platform(),
            "device": ctx.name, "device_compute_units": ctx.compute_units,
            "versions": versions()}


# -- meshes ------------------------------------------------------------------------

@dataclass
class Case:
    name: str
    vertices: np.ndarray
    faces: np.ndarray

    @property
    def num_triangles(self) -> int:
        return len(self.faces)


def load_shared(name: str) -> Case | None:
    """A scene read from its file (:func:`common.scene_file`), or None if it is missing."""
    path = scene_file(name)
    if not path.is_file():
        print(f"[skip] scene {name}: {path} not found", file=sys.stderr)
        return None
    v, f = load_mesh(path)
    return Case(name, v, f)


def generated_cases(kinds: list[str], sizes: list[int], bunny: Case | None,
                    bunny_benched: bool) -> list[Case]:
    """Generated meshes in size order: for each size, one mesh per kind."""
    cases = []
    for n in sizes:
        for kind in kinds:
            if kind == "copies":
                if bunny is None:
                    print("[skip] copies: the bunny scene is missing", file=sys.stderr)
                    continue
                if bunny_benched and round(n / bunny.num_triangles) < 2:
                    continue   # one copy is the bunny scene itself, already measured
                v, f = meshes.copies_to((bunny.vertices, bunny.faces), n)
                cases.append(Case(f"bunny x{len(f) // len(bunny.faces)}", v, f))
            elif kind in meshes.GENERATORS:
                v, f = meshes.GENERATORS[kind](n)
                cases.append(Case(f"{kind} {size_label(n)}", v, f))
            else:
                raise ValueError(f"kind: {kind!r}; expected copies or one of "
                                 f"{', '.join(meshes.GENERATORS)}")
    return cases


# -- our build --------------------------------------------------------------------

def run_build(ctx: dev.Context, case: Case, vbuf: cl.Buffer, fbuf: cl.Buffer,
              key_bits: int | None, samples: Samples | None) -> lbvh.BVH:
    ctx.queue.finish()
    options = LBVHOptions(key_bits={None: "auto", 32: 30, 64: 63}[key_bits])
    mesh = Mesh(case.vertices, case.faces, vbuf, fbuf)
    with ctx.lock:
        bvh = lbvh.BVH(mesh, build_tree(ctx, mesh, options))
    if samples is not None:
        rep = bvh.tree.report
        for phase in PHASES:
            samples.add(f"phase_{phase}", rep.phase_seconds[phase])
        samples.add("build_device", rep.device_seconds)
        samples.add("build_wall", rep.wall_seconds)
    return bvh


def tree_figures(bvh: lbvh.BVH) -> dict:
    """Quality figures of a built tree (validated first: an invalid tree stops the bench)."""
    try:
        bvh.validate()
    except Exception as exc:
        raise SystemExit(f"INVALID TREE ({bvh.mesh.num_prims:,} triangles): {exc}") from exc
    rep = bvh.report()
    out = {"depth": rep.depth, "mean_leaf_depth": rep.mean_leaf_depth,
           "duplicate_codes": rep.duplicate_codes, "num_leaves": rep.num_leaves,
           "key_bits": rep.key_bits, "key_choice": rep.key_choice, "sort_passes": rep.sort_passes,
           "peak_device_bytes": rep.peak_device_bytes,
           "bytes_per_triangle": rep.bytes_per_triangle, "sah_cost": None}
    try:
        from lbvh.metrics.quality import sah_cost
        out["sah_cost"] = float(sah_cost(bvh))
    except ImportError:
        pass
    return out


def device_morton_keys(ctx: dev.Context, vbuf: cl.Buffer, fbuf: cl.Buffer, n: int,
                       key_bits: int) -> np.ndarray:
    """The unsorted Morton keys the build sorts, from the device stages (outside any timing)."""
    mem = dev.MemoryTracker(ctx)
    boxes, box, _ = lbvh_bounds.triangle_bounds(ctx, mem, vbuf, fbuf, n)
    keys, values, _ = morton_codes(ctx, mem, boxes, box, n, key_bits)
    scratch = [boxes, box]
    out = dev.from_device(ctx, keys, KEY_DTYPE[key_bits], (n,))
    mem.free(keys, values, *scratch)
    return out


# -- sorts on the same keys ---------------------------------------------------------

def time_numpy_argsort(keys: np.ndarray, samples: Samples | None) -> np.ndarray:
    seconds, order = timed(lambda: np.argsort(keys, kind="stable"))
    if samples is not None:
        samples.add("numpy_argsort", seconds)
    return order


def time_our_sort(ctx: dev.Context, keys: np.ndarray, key_bits: int,
                  samples: Samples | None) -> np.ndarray:
    """Sort fresh copies of the keys with lbvh.device.sort.radix_sort; returns the value order.

    The sort runs twice and the second run is timed: the first maps the pages of
    the buffers the sort allocates, which then go to the pool for the second, as
    a build's buffers serve the next build (fresh pages cost ~6 us per 4 KB on
    this machine) and as numpy's allocator reuses its heap for repeated argsorts.
    """
    n = len(keys)
    for timed_run in (False, True):
        mem = dev.MemoryTracker(ctx)
        kbuf = mem.alloc(keys.nbytes)
        vbuf = mem.alloc(4 * n)
        cl.enqueue_copy(ctx.queue, kbuf, keys)
        cl.enqueue_copy(ctx.queue, vbuf, np.arange(n, dtype=np.uint32))
        ctx.queue.finish()
        wall, result = timed(lambda: _sort_and_finish(ctx, mem, kbuf, vbuf, n, key_bits))
        if timed_run and samples is not None:
            samples.add("our_sort_wall", wall)
            samples.add("our_sort_device", dev.event_seconds(result.events))
        order = dev.from_device(ctx, result.values, np.uint32, (n,))
        mem.free(result.keys, result.values, to_pool=True)   # the sort gave back the rest
    return order


def _sort_and_finish(ctx: dev.Context, mem: dev.MemoryTracker, kbuf: cl.Buffer, vbuf: cl.Buffer,
                     n: int, key_bits: int):
    result = radix_sort(ctx, mem, kbuf, vbuf, n, key_bits)
    ctx.queue.finish()
    return result


class PyopenclSort:
    """pyopencl.algorithm.RadixSort of (key, index) pairs on our context, one per key width."""

    def __init__(self, ctx: dev.Context) -> None:
        self.ctx = ctx
        self._sorters: dict[int, Any] = {}
        self.error: str | None = None
        try:
            from pyopencl.algorithm import RadixSort  # noqa: F401  (needs mako)
            import mako  # noqa: F401
        except ImportError as exc:
            self.error = f"not available ({exc})"

    def _sorter(self, key_bits: int):
        if key_bits not in self._sorters:
            from pyopencl.algorithm import RadixSort
            ctype = "ulong" if key_bits == 64 else "uint"
            self._sorters[key_bits] = RadixSort(
                self.ctx.ctx, f"{ctype} *keys, uint *vals", key_expr="keys[i]",
                sort_arg_names=["keys", "vals"], key_dtype=KEY_DTYPE[key_bits])
        return self._sorters[key_bits]

    def run(self, keys: np.ndarray, key_bits: int, samples: Samples | None) -> np.ndarray | None:
        """Sort by the code bits (30 or 63); returns the sorted keys, None if unavailable."""
        if self.error:
            return None
        import pyopencl.array as cla
        queue = self.ctx.queue
        sorter = self._sorter(key_bits)
        kd = cla.to_device(queue, keys)
        vd = cla.arange(queue, len(keys), dtype=np.uint32)
        queue.finish()
        t0 = time.perf_counter()
        (sorted_keys, _), event = sorter(kd, vd, key_bits=code_bits(key_bits), queue=queue)
        event.wait()
        queue.finish()
        if samples is not None:
            samples.add("pyopencl_radixsort", time.perf_counter() - t0)
        return sorted_keys.get()


# -- streaming floor --------------------------------------------------------------------

def floor_bytes(num_vertices: int, n: int) -> int:
    """Bytes the build must read and write at least once: the mesh in, the tree out."""
    inputs = 12 * num_vertices + 12 * n
    outputs = (NODE_BYTES + 4) * (2 * n - 1) + 4 * n
    return inputs + outputs


class CopyFloor:
    """Two device buffers for an event-timed buffer-to-buffer copy of ``nbytes``."""

    def __init__(self, ctx: dev.Context, nbytes: int) -> None:
        self.ctx, self.nbytes = ctx, nbytes
        self.src = dev.empty(ctx, nbytes)
        self.dst = dev.empty(ctx, nbytes)
        # Touch both so that the first timed copy does not pay for page faults.
        cl.enqueue_fill_buffer(ctx.queue, self.src, np.uint8(1), 0, nbytes)
        cl.enqueue_fill_buffer(ctx.queue, self.dst, np.uint8(0), 0, nbytes)
        ctx.queue.finish()

    def run(self, samples: Samples | None) -> None:
        ev = cl.enqueue_copy(self.ctx.queue, self.dst, self.src, byte_count=self.nbytes)
        if samples is not None:
            samples.add("floor_copy", dev.event_seconds([ev]))
        ev.wait()

    def release(self) -> None:
        self.src.release()
        self.dst.release()


def phase_traffic(num_vertices: int, n: int, key_bytes: int, sort_passes: int) -> dict[str, int]:
    """Bytes each phase reads plus writes if every array it touches is streamed once.

    A model of the kernels as written (gathers of vertices counted once), so
    ``phase time / (bytes / copy bandwidth)`` says how far each phase is from
    streaming speed:
      bounds: faces + vertices in (and the triangle boxes out where they are stored);
      morton: the triangle boxes in (stored, or faces + vertices), keys + values out,
              plus the duplicate count (keys in);
      sort:   the key-bits scan (keys in) and per pass a histogram (keys in) and a
              scatter (keys + values in and out);
      emit:   sorted keys in, nodes + parents out;
      refit:  arrival counters cleared, atomics read and written, parents and
              prim_order in, triangle boxes in, leaf records in, every box out,
              one sibling box in per internal node.
    """
    mesh = 12 * n + 12 * num_vertices
    nodes = 2 * n - 1
    pair = key_bytes + 4
    # Triangle boxes: stored by bounds (32 B each) and read back, or recomputed from the mesh.
    boxes_out = boxes_in = NODE_BYTES * n  # the stored triangle boxes, one record each
    refit_sync = 4 * nodes + 8 * nodes + 4 * nodes      # clear counters, atomics, parents
    return {
        "bounds": mesh + boxes_out,
        "morton": boxes_in + pair * n + key_bytes * n,
        "sort": key_bytes * n + sort_passes * (key_bytes + 2 * pair) * n,
        "emit": key_bytes * n + (NODE_BYTES + 4) * nodes,
        "refit": refit_sync + 4 * n + boxes_in + NODE_BYTES * n
                 + NODE_BYTES * nodes + NODE_BYTES * (n - 1),
    }


# -- peers ----------------------------------------------------------------------------------

def time_embree(embree: Embree, case: Case, samples: Samples | None) -> None:
    """Embree's build of the mesh (:meth:`common.Embree.build`: setup, then the commit)."""
    setup, build, built = embree.build(case.vertices, case.faces)
    del built
    if samples is not None:
        samples.add("embree_setup", setup)
        samples.add("embree_build", build)


class WarpBuilds:
    """warp's ``wp.Mesh`` with every constructor, one figure each; a constructor that
    fails once (its error in ``failed``) is not run again."""

    def __init__(self, warp: Warp) -> None:
        self.warp = warp
        self.failed: dict[str, str] = {}

    def run(self, points: Any, indices: Any, samples: Samples | None) -> None:
        for cons in self.warp.CONSTRUCTORS:
            if cons in self.failed:
                continue
            try:
                seconds, mesh = timed(lambda: self.warp.mesh(points, indices, cons))
            except Exception as exc:  # noqa: BLE001  (report any peer failure, keep benchmarking)
                self.failed[cons] = f"{type(exc).__name__}: {exc}"
                continue
            del mesh
            if samples is not None:
                samples.add(f"warp_{cons}", seconds)


# -- one mesh -------------------------------------------------------------------------------

def bench_case(ctx: dev.Context, case: Case, key_bits: int | None, repeats: int,
               peer_repeats: int, pyocl: PyopenclSort, embree: Embree | None,
               warp: WarpBuilds | None, peer_warmup: bool = True) -> dict:
    """All measurements of one mesh, interleaved round by round after one warm-up round.

    The peers (slow on big meshes) need a warm-up only once per process
    (thread pools); ``peer_warmup=False`` skips their round 0.
    """
    n, nv = case.num_triangles, len(case.vertices)
    vbuf, fbuf = dev.to_device(ctx, case.vertices), dev.to_device(ctx, case.faces)
    bvh = run_build(ctx, case, vbuf, fbuf, key_bits, None)          # warm-up
    quality = tree_figures(bvh)
    width = {30: 32, 63: 64}[quality["key_bits"]]   # the key's width in bits
    del bvh
    keys = device_morton_keys(ctx, vbuf, fbuf, n, width)
    floor = CopyFloor(ctx, floor_bytes(nv, n))
    warp_arrays = warp.warp.arrays(case.vertices, case.faces) if warp else None

    samples = Samples()
    checks = {}
    for round_ in range(repeats + 1):
        s = samples if round_ > 0 else None
        bvh = run_build(ctx, case, vbuf, fbuf, key_bits, s)
        del bvh
        order = time_numpy_argsort(keys, s)
        ours = time_our_sort(ctx, keys, width, s)
        theirs = pyocl.run(keys, width, s)
        floor.run(s)
        if round_ == 0:
            checks["our_sort_matches_numpy_stable"] = bool(np.array_equal(ours, order))
            if theirs is not None:
                checks["pyopencl_keys_match"] = bool(np.array_equal(theirs, keys[order]))
        if (round_ == 0 and peer_warmup) or 0 < round_ <= peer_repeats:
            if embree:
                time_embree(embree, case, s)
            if warp:
                warp.run(*warp_arrays, s)
    floor.release()
    del vbuf, fbuf
    if not checks["our_sort_matches_numpy_stable"]:
        raise SystemExit(f"{case.name}: lbvh.device.sort.radix_sort differs from numpy's stable argsort")
    return summarise(case, samples, quality, checks, width)


def summarise(case: Case, samples: Samples, quality: dict, checks: dict, width: int) -> dict:
    n, nv = case.num_triangles, len(case.vertices)
    med = samples.medians()
    fb = floor_bytes(nv, n)
    copy = med["floor_copy"]
    copy_bw = 2 * fb / copy if copy > 0 else float("nan")     # read + write
    traffic = phase_traffic(nv, n, width // 8, quality["sort_passes"] or 0)
    vs_floor = {p: med[f"phase_{p}"] / (traffic[p] / copy_bw) for p in PHASES}
    vs_floor["build"] = med["build_device"] / (sum(traffic.values()) / copy_bw)
    out = {
        "mesh": case.name, "triangles": n, "vertices": nv,
        "input_bytes": int(case.vertices.nbytes + case.faces.nbytes),
        "repeats": len(samples.values["build_wall"]),
        "median_seconds": med,
        "samples_seconds": samples.values,
        "mtris_per_second": {k: mtris(n, v) for k, v in med.items()
                             if k.startswith(("phase_", "build_", "our_sort_w", "our_sort_d",
                                              "numpy", "pyopencl", "embree_build", "warp"))},
        "quality": quality,
        "checks": checks,
        "floor": {"bytes": fb, "copy_seconds": copy, "copy_bandwidth_bytes_per_s": copy_bw,
                  "phase_bytes": traffic, "phase_over_streaming": vs_floor},
        "ratios": ratios(samples.values),
    }
    return out


def ratios(values: dict[str, list[float]]) -> dict[str, float | None]:
    """Median over rounds of a / b measured in the same round.

    A round measures everything about one mesh within a second or two, so a
    slow stretch of the shared machine tends to slow both sides of a ratio;
    the peers run in the first rounds only, and the pairs stop with them.
    """
    def ratio(a: str, b: str) -> float | None:
        pairs = [x / y for x, y in zip(values.get(a, []), values.get(b, [])) if y > 0]
        return median(pairs) if pairs else None
    return {
        "embree_build_over_lbvh_wall": ratio("embree_build", "build_wall"),
        "numpy_argsort_over_our_sort_wall": ratio("numpy_argsort", "our_sort_wall"),
        "pyopencl_over_our_sort_wall": ratio("pyopencl_radixsort", "our_sort_wall"),
        "numpy_argsort_over_our_sort_device": ratio("numpy_argsort", "our_sort_device"),
        "pyopencl_over_our_sort_device": ratio("pyopencl_radixsort", "our_sort_device"),
        "build_device_over_floor": ratio("build_device", "floor_copy"),
        "build_wall_over_floor": ratio("build_wall", "floor_copy"),
        "warp_sah_over_lbvh_wall": ratio("warp_sah", "build_wall"),
    }


# -- Markdown ----------------------------------------------------------------------------------

def ms(seconds: float | None) -> str:
    if seconds is None or not np.isfinite(seconds):
        return "-"
    return f"{seconds * 1e3:.1f}" if seconds < 10 else f"{seconds * 1e3:.0f}"


def fmt(x: float | None, digits: int = 1) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |",
             "|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def build_table(results: list[dict]) -> str:
    rows = []
    for r in results:
        med, q, n = r["median_seconds"], r["quality"], r["triangles"]
        phases = [f"{ms(med[f'phase_{p}'])} ({fmt(mtris(n, med[f'phase_{p}']), 0)})" for p in PHASES]
        rows.append([r["mesh"], f"{n:,}", str(q["key_bits"]),
                     *phases, ms(med["build_device"]), ms(med["build_wall"]),
                     fmt(mtris(n, med["build_device"])), fmt(mtris(n, med["build_wall"])),
                     fmt(q["bytes_per_triangle"]), str(q["depth"]), fmt(q["mean_leaf_depth"]),
                     f"{q['duplicate_codes']:,}", fmt(q["sah_cost"])])
    return table(["mesh", "tris", "key bits", *[f"{p} ms (Mt/s)" for p in PHASES], "device ms",
                  "wall ms", "Mt/s dev", "Mt/s wall", "B/tri", "depth", "mean leaf depth",
                  "dup codes", "SAH"], rows)


def sort_table(results: list[dict]) -> str:
    rows = []
    for r in results:
        med, rat, fl = r["median_seconds"], r["ratios"], r["floor"]
        rows.append([r["mesh"], f"{r['triangles']:,}", str(r["quality"]["sort_passes"]),
                     f"{ms(med['our_sort_device'])} / {ms(med['our_sort_wall'])}",
                     ms(med["numpy_argsort"]), ms(med.get("pyopencl_radixsort")),
                     fmt(rat["numpy_argsort_over_our_sort_wall"]),
                     fmt(rat["pyopencl_over_our_sort_wall"]),
                     f"{fl['bytes'] / 2**20:.0f}", ms(fl["copy_seconds"]),
                     fmt(fl["copy_bandwidth_bytes_per_s"] / 1e9),
                     fmt(rat["build_device_over_floor"])])
    return table(["mesh", "tris", "passes", "our sort ms (dev / wall)", "numpy argsort ms",
                  "pyopencl RadixSort ms", "numpy / ours", "pyopencl / ours", "floor MiB",
                  "floor copy ms", "copy GB/s", "build dev / floor"], rows)


def peer_table(results: list[dict], warp_cons: tuple[str, ...]) -> str:
    rows = []
    for r in results:
        med, rat = r["median_seconds"], r["ratios"]
        rows.append([r["mesh"], f"{r['triangles']:,}", ms(med["build_wall"]),
                     ms(med.get("embree_build")), ms(med.get("embree_setup")),
                     fmt(rat["embree_build_over_lbvh_wall"]),
                     *[ms(med.get(f"warp_{c}")) for c in warp_cons]])
    return table(["mesh", "tris", "LBVH wall ms", "Embree build ms", "embreex setup ms",
                  "Embree / LBVH", *[f"warp {c} ms" for c in warp_cons]], rows)


def floor_table(results: list[dict]) -> str:
    rows = []
    for r in results:
        fl = r["floor"]
        over = fl["phase_over_streaming"]
        mib = sum(fl["phase_bytes"].values()) / 2**20
        rows.append([r["mesh"], f"{r['triangles']:,}", fmt(fl["copy_bandwidth_bytes_per_s"] / 1e9),
                     *[f"{fl['phase_bytes'][p] / 2**20:.0f} MiB: {fmt(over[p])}x" for p in PHASES],
                     f"{mib:.0f} MiB: {fmt(over['build'])}x"])
    return table(["mesh", "tris", "copy GB/s", *PHASES, "build"], rows)


def targets(results: list[dict], near: int = 10 ** 6) -> tuple[str, list[dict]]:
    """Target lines for the meshes closest to ``near`` triangles (the issue's 1M)."""
    if not results:
        return "", []
    best = min(abs(np.log(r["triangles"] / near)) for r in results)
    chosen = [r for r in results if abs(np.log(r["triangles"] / near)) <= best + 0.2]
    lines, out = [], []

    def line(what: str, value: float | None, goal: str, ok: bool | None) -> str:
        mark = "n/a" if ok is None else ("MET" if ok else "NOT MET")
        return f"  - {what}: {fmt(value, 2)} (target {goal}) {mark}"

    for r in chosen:
        rat, q = r["ratios"], r["quality"]
        checks = [  # (key, label, value, goal text, met?)
            ("embree", "Embree build / LBVH build (wall)", rat["embree_build_over_lbvh_wall"],
             f">= {TARGET_EMBREE:g}x", lambda v: v >= TARGET_EMBREE),
            ("numpy", "numpy stable argsort / our sort (wall)", rat["numpy_argsort_over_our_sort_wall"],
             f">= {TARGET_NUMPY:g}x", lambda v: v >= TARGET_NUMPY),
            ("pyopencl", "pyopencl RadixSort / our sort (wall)", rat["pyopencl_over_our_sort_wall"],
             f">= {TARGET_PYOPENCL:g}x", lambda v: v >= TARGET_PYOPENCL),
            ("floor", "LBVH build (device) / streaming-floor copy", rat["build_device_over_floor"],
             f"<= {TARGET_FLOOR:g}x", lambda v: v <= TARGET_FLOOR),
            ("bytes", "peak device bytes per triangle beyond the input", q["bytes_per_triangle"],
             f"< {TARGET_BYTES_PER_TRI:g} B", lambda v: v < TARGET_BYTES_PER_TRI),
        ]
        lines.append(f"- {r['mesh']} ({r['triangles']:,} triangles):")
        entry = {"mesh": r["mesh"], "triangles": r["triangles"]}
        for key, label, value, goal, met in checks:
            ok = None if value is None else bool(met(value))
            lines.append(line(label, value, goal, ok))
            entry[key] = {"value": value, "target": goal, "met": ok}
        out.append(entry)
    return "\n".join(lines), out


# -- main -----------------------------------------------------------------------------------------

def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="small run (< 60 s): bunny and 50K meshes, 3 repeats")
    p.add_argument("--scenes", default=None,
                   help="shared scenes, comma-separated (bunny, sponza, conference, sibenik, "
                        "teapot, suzanne) or 'none'; default bunny,sponza,conference")
    p.add_argument("--sizes", default=None, help="generated mesh sizes; default 100k,1m,4m")
    p.add_argument("--kinds", default=None,
                   help="generated kinds: soup, sphere, terrain, copies (of the bunny); "
                        "default soup,sphere,copies")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats (median); default 5")
    p.add_argument("--peer-repeats", type=int, default=None,
                   help="repeats of the slow peers (Embree, warp); default min(repeats, 3)")
    p.add_argument("--no-peers", action="store_true", help="skip Embree and warp")
    p.add_argument("--key-bits", choices=sorted(KEY_BITS), default="auto")
    p.add_argument("--device", default=None, help="OpenCL device name (default: PoCL's CPU)")
    p.add_argument("--json", default=str(DEFAULT_OUT / "bench_build.json"),
                   help="where to write every figure (default bench/out/bench_build.json)")
    args = p.parse_args(argv)
    quick = args.quick
    args.scenes = args.scenes or ("bunny" if quick else "bunny,sponza,conference")
    args.sizes = args.sizes or ("50k" if quick else "100k,1m,4m")
    args.kinds = args.kinds or ("soup,sphere" if quick else "soup,sphere,copies")
    args.repeats = args.repeats or (3 if quick else 5)
    if args.repeats < 1:
        p.error("--repeats must be at least 1")
    args.peer_repeats = min(args.repeats, args.peer_repeats or 3)
    return args


def split(text: str) -> list[str]:
    return [] if text.strip().lower() == "none" else [t.strip() for t in text.split(",") if t.strip()]


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    ctx = dev.get_context(args.device)
    key_bits = KEY_BITS[args.key_bits]
    pyocl = PyopenclSort(ctx)
    peers, peer_status = load_peers(not args.no_peers)
    for family, status in peer_status.items():
        if family not in peers and not args.no_peers:
            print(f"[peer] {family}: {status}", file=sys.stderr)
    embree = peers.get("embree")
    warp = WarpBuilds(peers["warp"]) if "warp" in peers else None
    if pyocl.error:
        print(f"[peer] pyopencl RadixSort: {pyocl.error}", file=sys.stderr)

    scene_cases = [c for c in (load_shared(s) for s in split(args.scenes)) if c is not None]
    bunny = next((c for c in scene_cases if c.name == "bunny"), None)
    bunny_benched = bunny is not None
    kinds = split(args.kinds)
    if "copies" in kinds and bunny is None:
        bunny = load_shared("bunny")
    sizes = [parse_size(s) for s in split(args.sizes)]
    cases = scene_cases + generated_cases(kinds, sizes, bunny, bunny_benched)

    results = []
    for i, case in enumerate(cases):
        t0 = time.perf_counter()
        print(f"[bench] {case.name}: {case.num_triangles:,} triangles ...", file=sys.stderr, flush=True)
        results.append(bench_case(ctx, case, key_bits, args.repeats, args.peer_repeats, pyocl,
                                  embree, warp, peer_warmup=i == 0))
        print(f"[bench]   done in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)

    machine = machine_info(ctx)
    warp_cons = Warp.CONSTRUCTORS if warp else ()
    target_text, target_data = targets(results)
    print(f"# LBVH build benchmark\n\n{machine['cpu']}, {machine['cores']} cores; device: "
          f"{machine['device']}\nmedian of {args.repeats} repeats (peers: {args.peer_repeats}); "
          f"key bits: {args.key_bits}\n")
    print("## LBVH device build (inputs on the device)\n")
    print(build_table(results) + "\n")
    print("## Same keys, same run: sorts and the streaming floor\n")
    print(sort_table(results) + "\n")
    print("## Peers (same mesh, same run)\n")
    if embree is None and warp is None:
        print("embreex: not installed; warp-lang: not installed\n" if not args.no_peers
              else "skipped (--no-peers)\n")
    else:
        if embree is None:
            print("embreex: not installed\n")
        if warp is None:
            print("warp-lang: not installed\n")
        print(peer_table(results, warp_cons) + "\n")
        for cons, why in (warp.failed.items() if warp else ()):
            print(f"warp {cons}: failed ({why})\n")
    print("## Each phase against the streaming floor (modelled bytes / copy bandwidth)\n")
    print(floor_table(results) + "\n")
    print("## Targets (ratios from this run, meshes nearest 1M triangles)\n")
    print(target_text + "\n")
    elapsed = time.perf_counter() - t_start
    print(f"total benchmark time {elapsed:.0f} s")

    out = {"machine": machine, "settings": {k: v for k, v in vars(args).items()},
           "elapsed_seconds": elapsed, "results": results, "targets": target_data,
           "warp_failed": warp.failed if warp else {}}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1, default=float))
    print(f"[bench] figures written to {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
