"""Known-answer test of a device, run the first time a process uses it (issue 14).

Every x86 CPU is a different OpenCL device to PoCL: the same kernel source
compiles to other code on Intel, Zen 3, Zen 4 and Zen 5, and one of them may
miscompile it (PoCL 3.0 on Zen 4 passed 64-byte vectors to its built-ins
through a mismatched ABI: garbage lanes, then a segfault). Before a context is
handed out, each stage of the build runs on a tiny mesh (a few hundred
triangles, every vector lane and both key widths used) and its answer is
compared exactly with its numpy twin: triangle boxes, Morton codes (30 and 63
bits), the radix sort, the Karras emission, the refit's boxes, then a whole
build's closest hits against the float64 oracle. A device that differs raises
:class:`lbvh.device.DeviceError` naming the stage and the first differing
value, instead of a silently wrong tree.

The answer is kept per device and driver version for the life of the process
(``results()``); ``LBVH_SELF_TEST=0`` skips the test.
"""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import device as dev

ENV_SELF_TEST = "LBVH_SELF_TEST"


@dataclass
class SelfTest:
    """The outcome of :func:`self_test` on one device."""
    device: str
    driver: str
    passed: bool
    seconds: float
    failure: str = ""

    def summary(self) -> str:
        if self.passed:
            return f"passed ({self.seconds * 1e3:.0f} ms)"
        return f"FAILED: {self.failure}"


_results: dict[tuple[str, str], SelfTest] = {}
_lock = threading.Lock()


def device_key(device: Any) -> tuple[str, str]:
    """(``platform / device``, driver and OpenCL version) naming a device and its driver."""
    return (f"{device.platform.name.strip()} / {device.name.strip()}",
            f"{device.driver_version.strip()} {device.version.strip()}")


def results() -> dict[tuple[str, str], SelfTest]:
    """Self-tests run in this process, by :func:`device_key`."""
    return dict(_results)


def enabled() -> bool:
    return os.environ.get(ENV_SELF_TEST, "1").strip().lower() not in ("0", "no", "false", "off")


def _mesh() -> tuple[np.ndarray, np.ndarray]:
    """A few hundred triangles: a jittered grid with duplicate centroids (equal
    30-bit codes) and a near-degenerate sliver, sized so that chunks of 8 lanes
    end short."""
    rng = np.random.default_rng(14)
    n = 203
    centres = rng.random((n, 3)).astype(np.float32) * np.float32(10.0)
    centres[100:110] = centres[100]                # duplicate keys: the emission's tie rule
    offsets = rng.normal(size=(n, 3, 3)).astype(np.float32) * np.float32(0.05)
    tris = centres[:, None, :] + offsets
    tris[7, 2] = tris[7, 0] + np.float32(1e-6)     # a sliver
    vertices = tris.reshape(-1, 3).astype(np.float32)
    faces = np.arange(3 * n, dtype=np.uint32).reshape(n, 3)
    return vertices, faces


def _first_difference(name: str, got: np.ndarray, want: np.ndarray) -> str | None:
    got, want = np.asarray(got), np.asarray(want)
    if got.shape != want.shape:
        return f"{name}: shape {got.shape}, expected {want.shape}"
    same = (got == want) | ((got != got) & (want != want)) if got.dtype.kind == "f" else got == want
    if same.all():
        return None
    flat = np.flatnonzero(~same.reshape(len(got), -1).all(axis=1))
    i = int(flat[0])
    return (f"{name}: {len(flat)} of {len(got)} entries differ; entry {i} is {got[i].tolist()}, "
            f"expected {want[i].tolist()}")


def _check(ctx: dev.Context) -> list[str]:
    """Run every stage on the tiny mesh; the list of differences (empty: passed)."""
    from .bounds import triangle_bounds, triangle_boxes_numpy
    from .build import build_on_device
    from .emit import emit_hierarchy, emit_hierarchy_python
    from .layout import NODE_DTYPE, children_of
    from .morton import morton_codes, morton_codes_numpy
    from .bounds import centroid_bounds_numpy, triangle_centres_numpy
    from .oracle import brute_force
    from .refit import refit_numpy
    from .sort import radix_sort, radix_sort_numpy

    v, f = _mesh()
    n = len(f)
    problems: list[str] = []

    def compare(name: str, got, want) -> None:
        diff = _first_difference(name, got, want)
        if diff:
            problems.append(diff)

    mem = dev.MemoryTracker(ctx)
    vb, fb = dev.to_device(ctx, v), dev.to_device(ctx, f)
    boxes, box, _ = triangle_bounds(ctx, mem, vb, fb, n)
    lo, hi = triangle_boxes_numpy(v, f)
    got_boxes = dev.from_device(ctx, boxes, np.float32, (n, 2, 4))[:, :, :3]
    compare("bounds.cl triangle_bounds", got_boxes.reshape(n, 6), np.hstack([lo, hi]))
    centres, bounds = triangle_centres_numpy(v, f), centroid_bounds_numpy(v, f)
    for key_bits, dtype in ((32, np.uint32), (64, np.uint64)):
        keys, values, _ = morton_codes(ctx, mem, boxes, box, n, key_bits)
        got_keys = dev.from_device(ctx, keys, dtype, (n,))
        want_keys = morton_codes_numpy(centres, bounds, key_bits)
        compare(f"morton.cl morton_codes ({key_bits}-bit keys)", got_keys, want_keys)
        res = radix_sort(ctx, mem, keys, values, n, key_bits)
        sorted_keys = dev.from_device(ctx, res.keys, dtype, (n,))
        sorted_values = dev.from_device(ctx, res.values, np.int32, (n,))
        want_sorted, want_values = radix_sort_numpy(want_keys, np.arange(n, dtype=np.int32))
        compare(f"sort.cl radix_sort ({key_bits}-bit keys)", sorted_keys, want_sorted)
        compare(f"sort.cl radix_sort values ({key_bits}-bit keys)", sorted_values, want_values)
        nodes, parent, _ = emit_hierarchy(ctx, mem, dev.to_device(ctx, want_sorted), n, key_bits)
        got_nodes = dev.from_device(ctx, nodes, NODE_DTYPE, (2 * n - 1,))
        want_children, want_parent = emit_hierarchy_python(want_sorted, key_bits)
        compare(f"emit.cl emit_hierarchy children ({key_bits}-bit keys)",
                children_of(got_nodes), want_children)
        compare(f"emit.cl emit_hierarchy parents ({key_bits}-bit keys)",
                dev.from_device(ctx, parent, np.int32, (2 * n - 1,)), want_parent)
    ctx.queue.finish()
    mem.close()
    if problems:
        return problems
    # A whole build: the refit's boxes against the numpy refit, hits against the oracle
    tree = build_on_device(ctx, v, f, vb, fb, None)
    want_lo, want_hi = refit_numpy(tree.nodes, tree.parent, tree.root, tree.prim_order, v, f)
    compare("refit.cl refit (boxes of the build)",
            np.hstack([tree.lower, tree.upper]), np.hstack([want_lo, want_hi]))
    rng = np.random.default_rng(3)
    targets = v[f[rng.integers(0, n, 64)]].mean(axis=1)
    origins = (targets + rng.normal(size=targets.shape).astype(np.float32) * 4).astype(np.float32)
    directions = (targets - origins).astype(np.float32)
    from .traverse import intersect
    hits = intersect(tree, origins, directions)
    oracle = brute_force(v, f, origins, directions)
    compare("traverse.cl traverse (closest hit, triangle)", hits.prim, oracle.prim)
    return problems


def self_test(ctx: dev.Context) -> SelfTest:
    """The known-answer test of ``ctx``'s device (run once per device and driver)."""
    key = device_key(ctx.device)
    with _lock:
        done = _results.get(key)
        if done is not None:
            return done
        start = time.perf_counter()
        with ctx.lock:
            try:
                problems = _check(ctx)
            except dev.DeviceError as exc:
                problems = [str(exc)]
        result = SelfTest(key[0], key[1], not problems, time.perf_counter() - start,
                          "; ".join(problems))
        _results[key] = result
        return result


def require(ctx: dev.Context) -> None:
    """Run the self-test (once) unless disabled; raise ``DeviceError`` if the device fails it."""
    if not enabled():
        return
    result = self_test(ctx)
    if not result.passed:
        raise dev.DeviceError(
            f"lbvh: {ctx.name} fails the self-test (its kernels give wrong answers, so no tree "
            f"built on it can be trusted): {result.failure}. Set {ENV_SELF_TEST}=0 to use it anyway.")
