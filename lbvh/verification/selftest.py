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

The check runs in a child process (a kernel that crashes fails the test, not
the caller) the first time a device, driver version, compile target and
kernel source are seen; the answer is kept in ``~/.cache/lbvh/selftest`` and
for the life of the process (``results()``). ``LBVH_SELF_TEST=0`` skips it.
"""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import device as dev
from ..builders.bounds import (centroid_bounds_numpy, triangle_bounds, triangle_boxes_numpy,
                               triangle_centres_numpy)
from ..builders.emit import emit_hierarchy, emit_hierarchy_python
from ..builders.morton import morton_codes, morton_codes_numpy
from ..builders.pipeline import build_tree
from ..builders.refit import refit_numpy
from ..bvh import BVH
from ..device.pocl_target import fix_target_cpu, target_cpu
from ..device.sort import radix_sort, radix_sort_numpy
from ..layout import NODE_DTYPE, children_of
from ..queries.traverse import intersect
from ..tree import Mesh
from ..version import __version__
from .oracle import brute_force

ENV_SELF_TEST = "LBVH_SELF_TEST"


@dataclass
class SelfTest:
    """The outcome of :func:`self_test` on one device."""
    device: str
    driver: str
    passed: bool
    seconds: float
    failure: str = ""
    kept: bool = False   # read from the cache of an earlier process

    def summary(self) -> str:
        when = "in an earlier run" if self.kept else f"in {self.seconds * 1e3:.0f} ms"
        return f"passed ({when})" if self.passed else f"FAILED ({when}): {self.failure}"


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


def _check(ctx: dev.Context, stage=lambda name: None) -> list[str]:
    """Run every stage on the tiny mesh; the list of differences (empty: passed).

    ``stage(name)`` is called before each kernel runs (the child process of
    :func:`self_test` prints it, so a crash names the kernel it crashed in).
    """
    v, f = _mesh()
    n = len(f)
    problems: list[str] = []

    def compare(name: str, got, want) -> None:
        diff = _first_difference(name, got, want)
        if diff:
            problems.append(diff)

    mem = dev.MemoryTracker(ctx)
    vb, fb = dev.to_device(ctx, v), dev.to_device(ctx, f)
    stage("bounds.cl triangle_bounds")
    boxes, box, _ = triangle_bounds(ctx, mem, vb, fb, n)
    lo, hi = triangle_boxes_numpy(v, f)
    got_boxes = dev.from_device(ctx, boxes, np.float32, (n, 2, 4))[:, :, :3]
    compare("bounds.cl triangle_bounds", got_boxes.reshape(n, 6), np.hstack([lo, hi]))
    centres, bounds = triangle_centres_numpy(v, f), centroid_bounds_numpy(v, f)
    for key_bits, dtype in ((32, np.uint32), (64, np.uint64)):
        stage(f"morton.cl morton_codes ({key_bits}-bit keys)")
        keys, values, _ = morton_codes(ctx, mem, boxes, box, n, key_bits)
        got_keys = dev.from_device(ctx, keys, dtype, (n,))
        want_keys = morton_codes_numpy(centres, bounds, key_bits)
        compare(f"morton.cl morton_codes ({key_bits}-bit keys)", got_keys, want_keys)
        stage(f"sort.cl radix_sort ({key_bits}-bit keys)")
        res = radix_sort(ctx, mem, keys, values, n, key_bits)
        sorted_keys = dev.from_device(ctx, res.keys, dtype, (n,))
        sorted_values = dev.from_device(ctx, res.values, np.int32, (n,))
        want_sorted, want_values = radix_sort_numpy(want_keys, np.arange(n, dtype=np.int32))
        compare(f"sort.cl radix_sort ({key_bits}-bit keys)", sorted_keys, want_sorted)
        compare(f"sort.cl radix_sort values ({key_bits}-bit keys)", sorted_values, want_values)
        stage(f"emit.cl emit_hierarchy ({key_bits}-bit keys)")
        nodes, parent, _ = emit_hierarchy(ctx, mem, dev.to_device(ctx, want_sorted), n, key_bits)
        ctx.queue.finish()
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
    stage("a whole build (bounds, morton, sort, emit, refit)")
    tree = BVH(Mesh(v, f, vb, fb), build_tree(ctx, Mesh(v, f, vb, fb)))
    want_lo, want_hi = refit_numpy(tree.nodes, tree.tree.read("parent"), tree.root,
                                   tree.prim_order, v, f)
    compare("refit.cl refit (boxes of the build)",
            np.hstack([tree.nodes["lower"], tree.nodes["upper"]]), np.hstack([want_lo, want_hi]))
    rng = np.random.default_rng(3)
    targets = v[f[rng.integers(0, n, 64)]].mean(axis=1)
    origins = (targets + rng.normal(size=targets.shape).astype(np.float32) * 4).astype(np.float32)
    directions = (targets - origins).astype(np.float32)
    stage("wide.cl and traverse.cl (closest hits)")
    hits = intersect(tree, origins, directions)
    oracle = brute_force(v, f, origins, directions)
    compare("traverse.cl traverse (closest hit, triangle)", hits.prim, oracle.prim)
    return problems


def _cache_file(device: Any) -> Path:
    """Where the answer for this device (a ``pyopencl.Device``), driver, compile target
    and kernel source is kept."""
    h = hashlib.sha1()
    for name in sorted(p.name for p in dev.kernels_dir().iterdir() if p.suffix in (".cl", ".h")):
        h.update(name.encode() + (dev.kernels_dir() / name).read_bytes())
    h.update(repr((device_key(device), target_cpu(device), __version__)).encode())
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lbvh" / "selftest" / f"{h.hexdigest()}.json"


def _device_label(device: Any) -> str:
    """A name :func:`lbvh.device.find_device` resolves to exactly this device."""
    matches = [d for label, d in dev.all_devices() if label == device_key(device)[0]]
    index = next((k for k, d in enumerate(matches) if d.int_ptr == device.int_ptr), 0)
    return f"{device_key(device)[0]}#{index}"


def _run_child(ctx: dev.Context) -> SelfTest:
    """The check in a child process: a kernel that crashes fails the test, not the caller."""
    key = device_key(ctx.device)
    env = dict(os.environ, **{ENV_SELF_TEST: "child"})
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-m", "lbvh.verification.selftest", _device_label(ctx.device)],
                              capture_output=True, text=True, timeout=300, env=env)
    except subprocess.TimeoutExpired:
        return SelfTest(key[0], key[1], False, time.perf_counter() - start,
                        "the self-test did not finish in 300 s")
    seconds = time.perf_counter() - start
    lines = proc.stdout.splitlines()
    stages = [line[len("stage: "):] for line in lines if line.startswith("stage: ")]
    verdict = next((json.loads(line[len("result: "):]) for line in lines
                    if line.startswith("result: ")), None)
    if verdict is not None:
        return SelfTest(key[0], key[1], verdict["passed"], seconds, verdict["failure"])
    if proc.returncode < 0:
        how = f"signal {signal.Signals(-proc.returncode).name}"
    else:
        how = f"exit status {proc.returncode}"
    where = f" in {stages[-1]}" if stages else ""
    tail = proc.stderr.strip().splitlines()[-3:]
    return SelfTest(key[0], key[1], False, seconds,
                    f"the self-test process died ({how}){where}" + (f": {' | '.join(tail)}" if tail else ""))


def self_test(ctx: dev.Context) -> SelfTest:
    """The known-answer test of ``ctx``'s device, run once per device, driver and kernel source.

    It runs in a child process, so that a miscompiled kernel that crashes
    fails the test instead of the caller; the answer is kept in
    ``~/.cache/lbvh/selftest`` for the next processes.
    """
    key = device_key(ctx.device)
    with _lock:
        done = _results.get(key)
        if done is not None:
            return done
        path = _cache_file(ctx.device)
        result = None
        try:
            kept = json.loads(path.read_text())
            result = SelfTest(key[0], key[1], bool(kept["passed"]), float(kept["seconds"]),
                              str(kept["failure"]), kept=True)
        except (OSError, ValueError, KeyError, TypeError):
            pass
        if result is None:
            result = _run_child(ctx)
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_text(json.dumps({"passed": result.passed, "failure": result.failure,
                                           "device": key[0], "driver": key[1],
                                           "seconds": result.seconds}))
                os.replace(tmp, path)
            except OSError:
                pass   # a read-only home: the test runs again next time
        _results[key] = result
        return result


def pending(device: Any) -> bool:
    """Whether this process's first context on ``device`` (a ``pyopencl.Device``) will
    run the self-test, compiling the build's kernels in a child process (a few
    seconds): it is enabled and no earlier run on this device, driver, compile target
    and kernel source kept its answer. The command line says so before it waits."""
    if not enabled() or os.environ.get(ENV_SELF_TEST) == "child":
        return False
    with _lock:
        if device_key(device) in _results:
            return False
    fix_target_cpu(device)   # what the context would set first: part of the answer's key
    return not _cache_file(device).is_file()


def run_here(ctx: dev.Context) -> SelfTest:
    """The check in this process (what the child runs), printing each stage first."""
    key = device_key(ctx.device)
    start = time.perf_counter()

    def stage(name: str) -> None:
        print(f"stage: {name}", flush=True)
    with ctx.lock:
        try:
            problems = _check(ctx, stage)
        except dev.DeviceError as exc:
            problems = [str(exc)]
    return SelfTest(key[0], key[1], not problems, time.perf_counter() - start, "; ".join(problems))


def require(ctx: dev.Context) -> None:
    """Run the self-test (once) unless disabled; raise ``DeviceError`` if the device fails it."""
    if not enabled() or os.environ.get(ENV_SELF_TEST) == "child":
        return
    result = self_test(ctx)
    if not result.passed:
        raise dev.DeviceError(
            f"lbvh: {ctx.name} fails the self-test, so no tree built on it can be trusted: "
            f"{result.failure}. Set {ENV_SELF_TEST}=0 to use it anyway.")


def main(argv: list[str] | None = None) -> int:
    """``python -m lbvh.verification.selftest DEVICE``: the child process of :func:`self_test`."""
    args = sys.argv[1:] if argv is None else argv
    ctx = dev.get_context(args[0] if args else None)
    result = run_here(ctx)
    print("result: " + json.dumps({"passed": result.passed, "failure": result.failure}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
