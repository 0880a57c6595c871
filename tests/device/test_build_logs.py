"""Every kernel variant the package compiles, and their build logs on PoCL.

``lbvh/kernel_variants.py`` lists each (kernel file, -D defines) combination
that the package's modules can ask :meth:`lbvh.device.Context.program` for.
The first tests prove that list complete: a representative set of public
calls (every builder and key width, collapse, treelets, refit, both triangle
tests with and without counters, any-hit, every render mode, wide records of
both widths and the binary walk, the MSD sort and the ray order past their
thresholds) is recorded while it compiles, on a CPU device and on the same
PoCL device run as a GPU, and every recorded combination must be in the list.

The last test compiles every variant on PoCL and reads each build log: a
warning that the ABI changes (clang: "AVX vector argument of type 'ulong8'
without 'avx512f' enabled changes the ABI", a 64-byte vector passed
differently by the kernel and by PoCL's built-in library: its lanes arrive as
garbage on such a CPU) fails, and so does any other compiler warning that
``EXPECTED_WARNINGS`` does not list with its reason. The compile runs in a
subprocess with ``LBVH_POCL_CPU=haswell`` (lbvh/pocl_target.py: PoCL then
compiles for an AVX2 CPU without AVX-512, where clang warns of those hazards,
on any x86 machine) and ``POCL_KERNEL_CACHE=0`` (a cached binary has no log).
A canary program with a known ABI hazard proves that the logs are read.

By default each code path of traverse.cl is compiled with one of the stack
sizes in turn (``covering_variants``: STACK_SIZE only sizes private arrays,
which the test verifies); ``LBVH_ALL_VARIANTS=1`` compiles every variant
(about 600, 1.5 minutes on 2 cores).
"""
from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys

import numpy as np
import pyopencl as cl
import pytest

import lbvh
from lbvh.queries.all_hits import segment_work
from lbvh.api import collapse_leaves
from lbvh.device import sort
from lbvh.queries import closest, instance_closest, packets, ray_order
from lbvh.queries.packets import PACKETS_FROM
from conftest import REPO, pocl_cpu_device, random_soup
from lbvh import device as dev
from lbvh.verification import kernel_variants as kv

# Compiler warnings that are not failures, each with the reason it is harmless:
# (kernel file regex, message regex, reason). A warning that the ABI changes is
# never listed: it means wrong values at run time on some CPU.
EXPECTED_WARNINGS: list[tuple[str, str, str]] = []

ABI_WARNING = re.compile(r"changes the ABI")
# "warning: <file>:<line>:<col>[ <Spelling=...>]: <message>", clang's diagnostics as PoCL logs them
DIAGNOSTIC = re.compile(r"^(?P<kind>warning|error): (?P<path>\S+?):(?P<line>\d+):(?P<col>\d+)"
                        r"(?: <Spelling=[^>]*>)?: (?P<msg>.*)$")
FULL = os.environ.get("LBVH_ALL_VARIANTS") == "1"


def _sources() -> dict[str, str]:
    return {p.name: p.read_text() for p in dev.kernels_dir().iterdir() if p.suffix in (".cl", ".h")}


# -- the list is complete ------------------------------------------------------------

def _record(monkeypatch) -> set[tuple]:
    """Patch Context.program (this test only) to record every (file, defines) asked for."""
    seen: set[tuple] = set()
    original = dev.Context.program

    def program(self, filename, defines=None, *args, **kwargs):
        seen.add(kv.variant_key(filename, defines))
        return original(self, filename, defines, *args, **kwargs)

    monkeypatch.setattr(dev.Context, "program", program)
    return seen


def _public_calls(ctx: dev.Context, monkeypatch) -> None:
    """A representative set of public calls on ``ctx`` (a fresh Context: nothing cached)."""
    from lbvh.queries.wide import WIDTHS

    v, f = random_soup(400, seed=3)
    rng = np.random.default_rng(1)
    targets = v[f[rng.integers(0, len(f), 256)]].mean(axis=1)
    o = (rng.random((256, 3)) * 3 - 1).astype(np.float32)
    d = (targets - o).astype(np.float32)
    # Mostly duplicated triangles: "auto" moves to 63-bit keys.
    dup_v = np.concatenate([v[:30]] * 20)
    dup_f = np.arange(len(dup_v), dtype=np.uint32).reshape(-1, 3)
    trees = [lbvh.build(v, f, device=ctx, key_bits=30), lbvh.build(v, f, device=ctx, key_bits=63),
             lbvh.build(v, f, device=ctx), lbvh.build(dup_v, dup_f, device=ctx),
             lbvh.build(v, f, device=ctx, collapse=True),
             lbvh.build(v, f, device=ctx, treelet_rounds=2),
             lbvh.build(v, f, device=ctx, treelet_rounds=1, collapse=True, max_leaf_size=4),
             lbvh.build(v, f, device=ctx, builder="sah"),
             lbvh.build(v, f, device=ctx, builder="sbvh"),
             lbvh.build(v, f, device=ctx, builder="ploc")]
    assert trees[3].tree.report.key_bits == 63 and trees[2].tree.report.key_bits == 30
    many = -(-PACKETS_FROM // len(o))
    for bvh in trees:
        clipped = bvh.tree.clipped_leaves   # no box queries, winding or refit on an SBVH
        for test in ("watertight", "moller"):
            for counters in (False, True):
                bvh.intersect(o, d, triangle_test=test, counters=counters)
                bvh.occluded(o, d, triangle_test=test, counters=counters)
            # calls large enough for packets of rays (on a CPU)
            many_o, many_d = np.repeat(o, many, axis=0), np.repeat(d, many, axis=0)
            bvh.intersect(many_o, many_d, triangle_test=test)
            bvh.occluded(many_o, many_d, triangle_test=test)
        bvh.closest_points(o)
        if not clipped:
            bvh.overlapping(o, o + np.float32(0.1))
        bvh.intersect(o, d, order="global", counters=True)
        bvh.intersect(o, d, order="global", triangle_test="moller")
        bvh.count_hits(o, d)
        bvh.all_hits(o, d, max_hits=2)
        segment_work(bvh, o, d)
        if clipped:
            continue
        bvh.signed_distance(o)
        bvh.refit(v * np.float32(1.25) if len(bvh.vertices) == len(v) else bvh.vertices * 2)
        bvh.intersect(o, d)
    collapse_leaves(trees[7])
    # scenes of instances: closest and any hit, counters, both triangle tests, every hit and
    # the counts; with a mesh of spatial splits too
    for parts in (trees[:2], [trees[0], trees[8]]):
        scene = lbvh.Scene(parts, [0, 1, 0], np.tile(np.eye(3, 4), (3, 1, 1)) * 1.5)
        for test in ("watertight", "moller"):
            scene.intersect(o, d, triangle_test=test, counters=True)
            scene.intersect(o, d, triangle_test=test)
            scene.occluded(o, d, triangle_test=test)
        scene.count_hits(o, d)
        scene.all_hits(o, d, max_hits=2)
        scene.closest_points(o)
    # Wide records of both widths, and the binary walk where records would not fit.
    bvh = trees[0]
    for width in WIDTHS:
        bvh.query_data.wide_records(width=width)
        bvh.intersect(o, d, counters=True)
        bvh.occluded(o, d)
        bvh.closest_points(o)
        bvh.winding_numbers(o)
    binary = lbvh.BVH.from_arrays(bvh.nodes, bvh.prim_order, bvh.root, bvh.vertices, bvh.faces,
                                  builder="x", device=ctx)
    assert not binary.query_data.wide_records(max_bytes=0).packed
    binary.intersect(o, d)
    binary.closest_points(o)
    binary.winding_numbers(o)
    binary.intersect(o, d, order="global")
    binary.occluded(o, d, counters=True)
    # Rays in pyopencl arrays: float32 in place, every other element type converted,
    # counters split, a bad ray turned into a miss.
    import pyopencl.array as cl_array
    for dtype in (np.float32, np.float64, np.int32, np.uint32, np.int64, np.uint64):
        do = cl_array.to_device(ctx.queue, np.abs(o).astype(dtype))
        dd = cl_array.to_device(ctx.queue, np.ones_like(d).astype(dtype))
        bvh.intersect(do, dd, counters=True).get()
    bad = d.copy()
    bad[0] = np.nan
    bvh.intersect(cl_array.to_device(ctx.queue, o), cl_array.to_device(ctx.queue, bad),
                  invalid_rays="miss").get()
    # Every render mode.
    from lbvh.rendering.render import MODES
    cam = lbvh.Camera([0.5, 0.5, 3.0], [0.5, 0.5, 0.5], [0, 1, 0], 40.0, 8, 6)
    for mode in MODES:
        lbvh.render(trees[1], cam, mode, ao_samples=2)
    # The ray order and the MSD sort run past thresholds (batches of 64K rays over
    # trees of 1M nodes; 64K keys): lowered here, they only decide whether.
    monkeypatch.setattr(ray_order, "MIN_RAYS", 256)
    monkeypatch.setattr(closest, "MIN_POINTS", 256)
    monkeypatch.setattr(instance_closest, "MIN_POINTS", 256)
    monkeypatch.setattr(ray_order, "MIN_NODES", 256)
    monkeypatch.setattr(sort, "MSD_MIN_KEYS", 256)
    assert lbvh.queries.ray_order.worth_ordering(len(o), trees[0].tree.num_nodes)
    trees[0].intersect(o, d)
    trees[4].occluded(o, d)
    trees[0].closest_points(o)
    scene.closest_points(o)
    lbvh.build(v, f, device=ctx, key_bits=63).intersect(o, d)


@pytest.mark.parametrize("kind", ["cpu", "gpu"])
def test_variant_list_is_complete(monkeypatch, kind):
    """Everything the public calls compile is in kernel_variants (CPU and GPU flavours:
    the GPU run is PoCL's CPU device with the package's GPU choices, ctx.is_cpu = False)."""
    seen = _record(monkeypatch)
    device = dev.find_device(None)
    if kind == "cpu" and not (device.type & cl.device_type.CPU):
        # the CPU's choices on a GPU (LBVH_DEVICE) would run emit.cl's vector form,
        # which NVIDIA's compiler gets wrong (kernels/emit.cl): they run on PoCL's CPU
        device = pocl_cpu_device("the CPU's choices run on a CPU")
    ctx = dev.Context(device)   # a fresh program cache
    ctx.is_cpu = kind == "cpu"
    _public_calls(ctx, monkeypatch)
    listed = {kv.variant_key(f, d) for f, d in kv.kernel_variants(ctx.is_cpu)}
    missing = sorted(seen - listed)
    assert not missing, ("compiled but not in lbvh.verification.kernel_variants.kernel_variants("
                         f"is_cpu={ctx.is_cpu}):\n" + "\n".join(map(str, missing)))
    # The calls reach every kernel file (else the recording proves little)
    files = {p.name for p in dev.kernels_dir().glob("*.cl")}
    cpu_only = set() if ctx.is_cpu else {packets.KERNEL_FILE}   # packets of rays: CPUs only
    assert {f for f, _ in seen} == files - cpu_only
    # and the list names no file that does not exist, for either kind
    assert {f for f, _ in kv.kernel_variants(True) + kv.kernel_variants(False)} == files
    # The context's own list is a subset of the kind's
    assert {kv.variant_key(f, d) for f, d in kv.variants_for(ctx)} <= listed


def test_covering_variants_cover_every_code_path_and_value():
    sources = _sources()
    for is_cpu in (True, False):
        full = kv.kernel_variants(is_cpu)
        cover = kv.covering_variants(full, sources)
        assert {kv.variant_key(*v) for v in cover} <= {kv.variant_key(*v) for v in full}
        for filename in {f for f, _ in full}:
            keys = {k for f, d in full if f == filename for k in d}
            for name in keys:
                values = {d.get(name) for f, d in full if f == filename}
                assert values == {d.get(name) for f, d in cover if f == filename}, (filename, name)
            # every combination of the defines other than STACK_SIZE
            strip = lambda d: tuple((k, x) for k, x in d.items() if k != "STACK_SIZE")  # noqa: E731
            assert ({strip(d) for f, d in full if f == filename}
                    == {strip(d) for f, d in cover if f == filename}), filename
        # strength t: every t (define, value) pairs some variant of a file holds, a kept one holds
        for t in (1, 2, 3):
            cover = kv.covering_variants(full, sources, strength=t)
            assert {kv.variant_key(*v) for v in cover} <= {kv.variant_key(*v) for v in full}
            for filename in {f for f, _ in full}:
                def sets(vs):
                    out = set()
                    for f, d in vs:
                        if f == filename:
                            items = tuple((k, x) for k, x in d.items() if k != "STACK_SIZE")
                            out |= set(itertools.combinations(items, min(t, len(items))))
                    return out
                assert sets(full) == sets(cover), (filename, t)
            stacks = {d.get("STACK_SIZE") for f, d in cover if f == "traverse.cl"}
            assert stacks == {d.get("STACK_SIZE") for f, d in full if f == "traverse.cl"}
    # strength 3 cuts traverse.cl's product (test_portability compiles it)
    three = kv.covering_variants(kv.kernel_variants(False), sources, strength=3)
    assert len(three) < len(kv.covering_variants(kv.kernel_variants(False), sources))
    with pytest.raises(ValueError, match="strength must be at least 1"):
        kv.covering_variants(kv.kernel_variants(False), sources, strength=0)
    with pytest.raises(ValueError, match="WIDE selects code"):
        kv.covering_variants(kv.kernel_variants(True), sources, value_only=("WIDE",))


# -- the build logs ---------------------------------------------------------------------

COMPILE_SCRIPT = r"""
import json, sys, warnings
import pyopencl as cl
warnings.simplefilter("ignore", cl.CompilerWarning)
from lbvh import device as dev
from lbvh.verification import kernel_variants as kv
from lbvh.device import pocl_target

ctx = dev.Context(dev.find_device(None))
print(json.dumps({"device": ctx.name, "target": pocl_target.target_cpu(ctx.device)}), flush=True)
CANARY = ("__attribute__((noinline)) ulong8 twice(ulong8 x) { return x + x; }\n"
          "__kernel void canary(__global ulong8 *p) { p[0] = twice(p[0]); }\n")
canary = cl.Program(ctx.ctx, CANARY).build(options=["-cl-std=CL1.2"])
print(json.dumps({"canary": canary.get_build_info(ctx.device, cl.program_build_info.LOG)}), flush=True)
variants = kv.variants_for(ctx)
if sys.argv[1] != "all":
    sources = {p.name: p.read_text() for p in dev.kernels_dir().iterdir()}
    variants = kv.covering_variants(variants, sources)
for filename, defines in variants:
    try:
        prog = ctx.program(filename, defines)
        if hasattr(ctx, "build_log"):
            log = ctx.build_log(filename, defines)
        else:
            log = prog.get_build_info(ctx.device, cl.program_build_info.LOG)
        out = {"log": log, "error": None}
    except dev.DeviceError as exc:
        out = {"log": "", "error": str(exc)}
    print(json.dumps({"file": filename, "defines": defines, **out}), flush=True)
"""

INCLUDE = re.compile(r'[ \t]*#[ \t]*include[ \t]*"([^"]+)"[ \t]*')


def expand_includes(filename: str, seen: set | None = None) -> tuple[str, list[tuple[str, int]]]:
    """``kernels/<filename>`` with its includes expanded as lbvh.device.kernel_source
    expands them (each header once), and the (file, line) each line comes from."""
    seen = set() if seen is None else seen
    if filename in seen:
        return "", []
    seen.add(filename)
    pieces, origins = [], []
    for number, line in enumerate((dev.kernels_dir() / filename).read_text().split("\n"), 1):
        m = INCLUDE.fullmatch(line)
        if m:
            text, where = expand_includes(m.group(1), seen)
            pieces.append(text)
            origins += where or [(filename, number)]
        else:
            pieces.append(line)
            origins.append((filename, number))
    return "\n".join(pieces), origins


def line_map(filename: str):
    """A function from a line of the source the package compiles to "file:line" in kernels/."""
    if not hasattr(dev, "kernel_source"):         # the file itself is compiled, with -I
        return lambda line: f"{filename}:{line}"
    text, origins = expand_includes(filename)
    if text != dev.kernel_source(filename):       # expanded otherwise: keep its numbers
        return lambda line: f"{filename} (expanded):{line}"
    return lambda line: ("%s:%d" % origins[line - 1] if 0 < line <= len(origins)
                         else f"{filename}:{line}")


def diagnostics(log: str, filename: str) -> list[tuple[str, str]]:
    """(kind, "file:line:col: message") of each warning or error in a PoCL build log;
    PoCL's temporary copy of the source is mapped back to the kernel files."""
    where = line_map(filename)
    found = []
    for line in log.splitlines():
        m = DIAGNOSTIC.match(line.strip())
        if m:
            path, number = m["path"], int(m["line"])
            place = (where(number) if "/pocl/" in path or "tempfile" in path
                     else f"{os.path.basename(path)}:{number}")
            found.append((m["kind"], f"{place}:{m['col']}: {m['msg']}"))
        elif line.strip().startswith(("warning:", "error:")):
            found.append((line.strip().split(":", 1)[0], f"{filename}: {line.strip()}"))
    return found


def expected(filename: str, message: str) -> str | None:
    for file_re, msg_re, reason in EXPECTED_WARNINGS:
        if re.search(file_re, filename) and re.search(msg_re, message):
            return reason
    return None


def test_include_expansion_matches_the_package():
    """The logs' line map expands includes as lbvh.device.kernel_source does."""
    if not hasattr(dev, "kernel_source"):
        pytest.skip("lbvh.device compiles the kernel files themselves (-I), nothing to map")
    for path in dev.kernels_dir().glob("*.cl"):
        assert expand_includes(path.name)[0] == dev.kernel_source(path.name), path.name


def test_stack_size_only_sizes_arrays():
    """covering_variants compiles each STACK_SIZE once: it must select no code."""
    sources = _sources()
    assert "STACK_SIZE" not in kv.conditional_defines(sources["traverse.cl"] + sources["common.h"])
    assert re.search(r"\[STACK_SIZE\]", sources["traverse.cl"])


def test_build_logs_have_no_abi_or_unexpected_warnings():
    env = dict(os.environ, LBVH_POCL_CPU="haswell", POCL_KERNEL_CACHE="0", PYOPENCL_NO_CACHE="1")
    env.pop("LBVH_DEVICE", None)
    out = subprocess.run([sys.executable, "-c", COMPILE_SCRIPT, "all" if FULL else "cover"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    rows = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    head, canary, results = rows[0], rows[1], rows[2:]
    if head["target"] is None or head["target"][1] != "haswell":
        pytest.skip(f"PoCL's compile target could not be forced to haswell on {head['device']} "
                    f"(lbvh.device.pocl_target.target_cpu: {head['target']}): clang would not warn of "
                    "64-byte vector ABI hazards here")
    assert ABI_WARNING.search(canary["canary"]), (
        "the canary (a ulong8 argument of a function kept out of line) gave no ABI warning: "
        f"the build logs are not being read. Its log: {canary['canary']!r}")
    assert results, "no variant was compiled"
    failures = []
    for r in results:
        name = f"kernels/{r['file']} {r['defines']}"
        if r["error"]:
            failures.append(f"{name}: does not compile:\n    {r['error'][-1500:]}")
            continue
        bad = [text for kind, text in diagnostics(r["log"], r["file"])
               if kind == "error" or ABI_WARNING.search(text) or expected(r["file"], text) is None]
        if bad:
            failures.append(f"{name}: {len(bad)} warning(s):\n    " + "\n    ".join(bad))
    if failures:
        pytest.fail(f"{len(failures)} of {len(results)} variants compiled on {head['device']} "
                    f"(target {head['target'][1]}) warn that the ABI changes or of something "
                    "EXPECTED_WARNINGS does not list:\n" + "\n".join(failures), pytrace=False)
