"""The same kernels on a second OpenCL 1.2 implementation: Oclgrind, when installed.

Oclgrind (Debian package ``oclgrind``) simulates a strict OpenCL 1.2 device and
checks every memory access. No GPU is lent to CI, so this is the check that
nothing relies on PoCL: every builder must produce the same tree bit for bit,
the refit the same boxes, the traversal the same hits. It runs in a subprocess
because the OpenCL loader reads ``OCL_ICD_VENDORS`` once. Install with
``apt-get install oclgrind`` to run it; without it the tests are skipped.

The run has Oclgrind's checkers on and fails on their reports: out-of-bounds
accesses (always checked), API errors (``OCLGRIND_CHECK_API=1``) and data races
(``OCLGRIND_DATA_RACES=1``), except those listed below with their reason (the
bottom-up walks' cross-work-group accesses, ordered by their atomics, which the
race detector does not see). A second test runs the same calls with the
uninitialised-value checker (``OCLGRIND_UNINITIALIZED=1``) where Oclgrind's own
bugs, reproduced first by small programs, let it be trusted.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

OCLGRIND_ICD = Path("/usr/lib/oclgrind/liboclgrind-rt-icd.so")

SCRIPT = r"""
import sys
import numpy as np
import lbvh
sys.path.insert(0, "tests")
from conftest import random_soup

v, f = random_soup(300, seed=1)
rng = np.random.default_rng(0)
targets = v[f[rng.integers(0, len(f), 200)]].mean(axis=1)
o = (rng.random((200, 3)) * 3 - 1).astype(np.float32)
d = (targets - o).astype(np.float32)
for kw in ({"key_bits": 30}, {"key_bits": 63}, {"collapse": True}, {"builder": "sah"},
           {"treelet_rounds": 2}, {"treelet_rounds": 1, "collapse": True}):
    a = lbvh.build(v, f, device="oclgrind", **kw)
    p = lbvh.build(v, f, device="pthread", **kw)
    assert "Oclgrind" in a.ctx.name and "pthread" in p.ctx.name
    a.validate()
    assert np.array_equal(a.nodes, p.nodes), kw
    ha, hp = a.intersect(o, d), p.intersect(o, d)
    assert (ha.prim >= 0).sum() > 150
    assert np.array_equal(ha.prim, hp.prim) and np.array_equal(ha.t, hp.t), kw
    assert np.array_equal(a.occluded(o, d), p.occluded(o, d)), kw
    a.refit(v * np.float32(1.5))
    p.refit(v * np.float32(1.5))
    assert np.array_equal(a.nodes, p.nodes), kw
    print("same on both:", kw)

# Both triangle tests, with and without counters, closest and any hit.
a = lbvh.build(v, f, device="oclgrind", key_bits=63)
p = lbvh.build(v, f, device="pthread", key_bits=63)
for test in ("watertight", "moller"):
    for counters in (False, True):
        ha = a.intersect(o, d, triangle_test=test, counters=counters)
        hp = p.intersect(o, d, triangle_test=test, counters=counters)
        assert np.array_equal(ha.prim, hp.prim) and np.array_equal(ha.t, hp.t), (test, counters)
        if counters:
            assert np.array_equal(ha.nodes_visited, hp.nodes_visited), test
            assert np.array_equal(ha.tris_tested, hp.tris_tested), test
        oa = a.occluded(o, d, triangle_test=test, counters=counters, return_hits=True)
        op = p.occluded(o, d, triangle_test=test, counters=counters, return_hits=True)
        assert np.array_equal(oa.hit, op.hit), (test, counters)
print("same on both: both triangle tests, counters, any hit")

# Both widths of wide records on both, and the binary walk (WIDE=0). The
# traversal asks bvh.query_data.wide_records for the device's width (8 on a CPU, as Oclgrind is):
# width_for is patched for the 4-lane records to be the ones traced.
import lbvh.queries.wide
from lbvh.queries.wide import WIDTHS
a = lbvh.build(v, f, device="oclgrind")
want = lbvh.build(v, f, device="pthread").intersect(o, d)
device_width = lbvh.queries.wide.width_for
for width in WIDTHS:
    lbvh.queries.wide.width_for = lambda ctx, width=width: width
    a.query_data.wide_records(width=width)
    got = a.intersect(o, d)
    assert a.query_data._wide.width == width and a.query_data._wide.packed, width
    assert np.array_equal(got.prim, want.prim) and np.array_equal(got.t, want.t), width
lbvh.queries.wide.width_for = device_width
b = lbvh.BVH.from_arrays(a.nodes, a.prim_order, a.root, v, f, builder="x", device="oclgrind")
assert not b.query_data.wide_records(max_bytes=0).packed
got = b.intersect(o, d)
assert np.array_equal(got.prim, want.prim) and np.array_equal(got.t, want.t)
print("same on both: wide records of 4 and 8 lanes, binary nodes")

# The CPU paths that need large inputs on PoCL, at a small size: the MSD sort
# and the ray order.
import pyopencl as cl
import lbvh.device.sort
from lbvh import device as dev
from lbvh.queries.ray_order import ray_order
lbvh.device.sort.MSD_MIN_KEYS = 1000
# All 30 bits varying: the speculated passes run; 29 bits: they must stay idle.
keys = rng.integers(0, 1 << 30, 5000).astype(np.uint32)
keys[:2] = (0, (1 << 30) - 1)
narrow = keys >> np.uint32(1)
values = np.arange(5000, dtype=np.uint32)
lo, hi = v.min(axis=0), v.max(axis=0)
answers = []
for name in ("oclgrind", "pthread"):
    ctx = dev.get_context(name)
    mem = dev.MemoryTracker(ctx)
    rw = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR  # the sort works in place
    orders = []
    # 8-bit MSD digits leave three bucket passes: the path through the arrays
    for k, radix_bits, passes in ((keys, 11, 3), (narrow, 11, 3), (keys, 8, 4)):
        res = lbvh.device.sort.radix_sort(ctx, mem, cl.Buffer(ctx.ctx, rw, hostbuf=k),
                                   cl.Buffer(ctx.ctx, rw, hostbuf=values), 5000, 32,
                                   radix_bits=radix_bits)
        assert res.passes == passes
        orders.append(dev.from_device(ctx, res.values, np.uint32, (5000,)))
    order, _ = ray_order(ctx, dev.to_device(ctx, o), dev.to_device(ctx, d), len(o), lo, hi)
    answers.append(orders + [dev.from_device(ctx, order, np.int32, (len(o),))])
assert np.array_equal(answers[0][0], np.argsort(keys, kind="stable"))
assert np.array_equal(answers[0][1], np.argsort(narrow, kind="stable"))
assert np.array_equal(answers[0][2], answers[0][0])
assert all(np.array_equal(a, b) for a, b in zip(*answers))
print("same on both: MSD sort and ray order")

# A call that fails by design: with OCLGRIND_CHECK_API=1 Oclgrind must report it.
try:
    cl.Kernel(dev.get_context("oclgrind").program("bounds.cl"), "lbvh_api_canary")
except cl.Error:
    pass
"""


def _env(tmp_path, **oclgrind) -> dict:
    """The environment of a subprocess whose OpenCL loader sees Oclgrind (and PoCL,
    which pyopencl's wheel finds by itself), with Oclgrind's options ``oclgrind``."""
    vendors = tmp_path / "vendors"
    vendors.mkdir(exist_ok=True)
    (vendors / "oclgrind.icd").write_text(f"{OCLGRIND_ICD}\n")
    env = dict(os.environ, OCL_ICD_VENDORS=str(vendors), PYOPENCL_NO_CACHE="1", **oclgrind)
    env.pop("LBVH_DEVICE", None)
    return env


# -- Oclgrind's reports on stderr ---------------------------------------------------------
# A report is a line that does not start with white space followed by its
# tab-indented lines ("\tKernel: refit", "\tFirst entity: ... Group(0,0,0)",
# "\tAt line 150 (column 20) of input.cl:", "\t  <the source line>").

REPORT_HEADS = ("Invalid ", "Uninitialized ", "Controlflow depends", "Read-write data race",
                "Write-write data race", "Oclgrind", "Work-group divergence", "Unaligned ",
                "Atomic ", "Stack ", "Unsupported")


def oclgrind_reports(stderr: str) -> list[dict]:
    """Oclgrind's reports in a subprocess's stderr: head, kernel, work-groups of the
    entities involved, source lines, full text."""
    reports, current = [], None
    for line in stderr.splitlines():
        if line.startswith(("\t", " ")) and current is not None:
            current["lines"].append(line.strip())
            continue
        current = None
        if line.startswith(REPORT_HEADS):
            current = {"head": line.strip(), "lines": []}
            reports.append(current)
    for r in reports:
        body = r["lines"]
        r["kernel"] = next((x.split(":", 1)[1].strip() for x in body if x.startswith("Kernel:")), "")
        r["groups"] = [re.search(r"Group\(([^)]*)\)", x).group(1) for x in body
                       if x.startswith(("First entity", "Second entity", "Entity"))
                       and re.search(r"Group\(([^)]*)\)", x)]
        r["source"] = [body[i + 1] for i, x in enumerate(body[:-1]) if x.startswith("At line")]
        r["text"] = "\n    ".join([r["head"], *[x for x in body if x]])
    return reports


# Oclgrind's API checker (OCLGRIND_CHECK_API=1) on calls that fail by design:
# (regex over the report's lines, reason).
EXPECTED_API_ERRORS = [
    (r"CL_INVALID_KERNEL_NAME\n.*Kernel 'lbvh_api_canary' not found",
     "the script's own failing call, which proves that the API checker is on"),
    (r"Function: clCreateKernel\n.*CL_INVALID_KERNEL_NAME\n.*Kernel '_source' not found",
     "pyopencl's Kernel constructor looks for a `_source` attribute of the program, which "
     "Program.__getattr__ turns into a kernel lookup by that name: it fails, as meant "
     "(reproduced with pyopencl alone: cl.Kernel(prg, name) on Oclgrind)"),
    (r"Function: clGetDeviceInfo\n.*CL_INVALID_VALUE\n.*For argument 'param_name'",
     "pyopencl's Kernel constructor queries a device property of OpenCL 2.0 or later, which "
     "Oclgrind (an OpenCL 1.2 device) does not know; pyopencl handles the error (the same "
     "cl.Kernel call without lbvh)"),
]

# Kernels whose bottom-up walks cross work-groups (Karras 2012, section 4): each
# walk bumps its parent's arrival counter (an atomic, between fences: common.h,
# second_arrival) and only the second arrival reads what the first one wrote (the
# sibling's box, the node's words) and writes over the node. Every such pair of
# accesses is ordered by that atomic; Oclgrind's race detector orders accesses of
# different work-groups by nothing (OpenCL 1.2 defines no order between them
# except through atomics of the same address) and reports each pair as a race.
# Reports inside one work-group, or in any other kernel, fail.
BOTTOM_UP_WALKS = {
    "refit": "the refit's walk (refit.cl): the second arrival reads the sibling's box and "
             "writes the parent's over its range word and arrival counter (KARRAS_RANGES)",
    "restructure_treelets": "the treelet walk (restructure.cl): the second arrival reads the "
             "root's box, the treelet's nodes, costs and parent links that the walks below "
             "wrote, and rewrites them",
    "collapse_costs": "the collapse walk (collapse.cl): the second arrival reads the children's "
             "statistics that other walks wrote",
}


def classify(reports: list[dict]) -> tuple[list[str], dict[str, int]]:
    """(the reports that fail, as text; how many of each expected kind were seen)."""
    failures, expected = [], {}
    for r in reports:
        if r["head"].startswith("Oclgrind - OpenCL runtime error"):
            body = "\n".join(r["lines"])
            reason = next((why for pattern, why in EXPECTED_API_ERRORS
                           if re.search(pattern, body)), None)
        elif "data race" in r["head"]:
            reason = (BOTTOM_UP_WALKS.get(r["kernel"])
                      if len(set(r["groups"])) == 2 else None)
        else:   # out-of-bounds accesses, uninitialised values, divergence, anything else
            reason = None
        if reason is None:
            failures.append(r["text"])
        else:
            expected[reason] = expected.get(reason, 0) + 1
    return failures, expected


def _summary(failures: list[str], limit: int = 40) -> str:
    counts: dict[str, int] = {}
    for text in failures:
        counts[text] = counts.get(text, 0) + 1
    lines = [f"{n} x {text}" for text, n in list(counts.items())[:limit]]
    more = len(counts) - limit
    return "\n".join(lines) + (f"\n... and {more} more distinct reports" if more > 0 else "")


@pytest.mark.skipif(not OCLGRIND_ICD.exists(), reason="Oclgrind not installed (apt-get install oclgrind)")
def test_builders_refit_and_traversal_agree_on_oclgrind(tmp_path):
    """Bit for bit the same as PoCL, with Oclgrind's checks on: every access is checked
    against its buffer (always on: "Invalid read/write" is an out-of-bounds access), every
    API call (OCLGRIND_CHECK_API), and every pair of accesses of different work-items
    (OCLGRIND_DATA_RACES). Any report fails but those listed above with their reason."""
    env = _env(tmp_path, OCLGRIND_CHECK_API="1", OCLGRIND_DATA_RACES="1",
               OCLGRIND_MAX_ERRORS="100000")
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr[-3000:]
    assert out.stdout.count("same on both") == 9
    reports = oclgrind_reports(out.stderr)
    assert any("lbvh_api_canary" in r["text"] for r in reports), (
        "Oclgrind did not report the script's failing clCreateKernel: is OCLGRIND_CHECK_API on?")
    out_of_bounds = [r["text"] for r in reports if r["head"].startswith("Invalid")]
    assert not out_of_bounds, "out-of-bounds accesses on Oclgrind:\n" + _summary(out_of_bounds)
    failures, _ = classify(reports)
    assert not failures, "Oclgrind reports:\n" + _summary(failures)


# -- uninitialised values ----------------------------------------------------------------
# Oclgrind's uninitialised-value checker (OCLGRIND_UNINITIALIZED=1) runs only where
# it works: Oclgrind 21.10 (Debian bookworm) has bugs that these small programs
# reproduce, each a reason to skip (the check turns itself on with a fixed Oclgrind).

PLUGIN_BUGS = {
    "crash": (
        "kernel void k(global int *a) { int4 m = vload4(0, a); int8 e = (int8)(m, m); a[20] = e.s5; }",
        "one", "it crashes (SIGSEGV in Uninitialized::instructionExecuted) on a shufflevector "
        "that makes a vector of another length, e.g. (int8)(int4, int4), which emit.cl uses "
        "(and, at -O2, float3 parts of float4 everywhere)"),
    "partial": (
        "kernel void k(global int *a) { a[1] = 3; a[2] = a[1]; }",
        "first_word", "after a command that initialises part of a buffer (here the host writes "
        "its first 4 bytes; lbvh.wide writes the root's record index so), the kernel's own "
        "stores to the rest are not recorded and reading them back is reported uninitialised"),
}

PROBE = r"""
import sys
import numpy as np
import pyopencl as cl
platform = [p for p in cl.get_platforms() if "Oclgrind" in p.name][0]
ctx = cl.Context(platform.get_devices())
queue = cl.CommandQueue(ctx)
buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 256)
if sys.argv[2] == "first_word":
    cl.enqueue_copy(queue, buf, np.int32([7]), is_blocking=True)
else:
    cl.enqueue_copy(queue, buf, np.arange(64, dtype=np.int32), is_blocking=True)
prg = cl.Program(ctx, sys.argv[1]).build(options=["-cl-opt-disable"])
cl.Kernel(prg, "k")(queue, (1,), None, buf)
queue.finish()
print("ran")
"""

# Reports of the uninitialised-value checker that are not failures: (regex, reason).
EXPECTED_UNINITIALISED: list[tuple[str, str]] = []


def _plugin_bugs(env: dict) -> list[str]:
    found = []
    for name, (kernel, init, what) in PLUGIN_BUGS.items():
        out = subprocess.run([sys.executable, "-c", PROBE, kernel, init], cwd=REPO, env=env,
                             capture_output=True, text=True, timeout=120)
        if out.returncode != 0 or "ran" not in out.stdout or "Uninitialized" in out.stderr:
            found.append(what)
    return found


@pytest.mark.skipif(not OCLGRIND_ICD.exists(), reason="Oclgrind not installed (apt-get install oclgrind)")
def test_no_uninitialised_values_on_oclgrind(tmp_path):
    """The same calls with Oclgrind's uninitialised-value checker: no kernel reads memory
    that nothing wrote. Compiled at -cl-opt-disable: at -O2 LLVM stores a float3 made
    into a float4 as a vector with an undefined lane followed by a store of that lane,
    which the checker reports although memory ends fully written."""
    env = _env(tmp_path, OCLGRIND_UNINITIALIZED="1", OCLGRIND_BUILD_OPTIONS="-cl-opt-disable",
               OCLGRIND_MAX_ERRORS="100000")
    bugs = _plugin_bugs(env)
    if bugs:
        version = subprocess.run(["oclgrind", "--version"], capture_output=True, text=True)
        name = (version.stdout.strip().splitlines() or ["Oclgrind"])[0]
        pytest.skip(f"{name}'s uninitialised-value checker cannot be trusted here: "
                    + "; and ".join(bugs))
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, ("Oclgrind crashed or a check failed:\n" + out.stdout[-2000:]
                                 + out.stderr[-3000:])
    failures = [r["text"] for r in oclgrind_reports(out.stderr)
                if r["head"].startswith(("Uninitialized", "Controlflow depends", "Invalid"))
                and not any(re.search(p, r["text"]) for p, _ in EXPECTED_UNINITIALISED)]
    assert not failures, "uninitialised values on Oclgrind:\n" + _summary(failures)
