"""The kernels compile for GPUs, without a GPU: Debian's clang for AMD and NVIDIA targets.

No GPU is lent to CI. clang compiles OpenCL C for ``amdgcn-amd-amdhsa`` (the
target of AMD's ROCm OpenCL, itself clang) and ``nvptx64-nvidia-cuda`` (PTX,
what NVIDIA's OpenCL runs), so every kernel variant the package compiles for
a GPU (``lbvh.verification.kernel_variants.kernel_variants(is_cpu=False)``: 4-wide
records, 8-bit sort digits, the GPU scratch size, ...) is compiled here as
OpenCL C 1.2 down to the target's assembly (``-S``: front end and code
generator both run; a construct a GPU back end cannot select fails here).
Any error fails, and any warning that ``EXPECTED_WARNINGS`` does not list
with its reason.

A third run compiles the kernels that test for ``cl_khr_fp64`` as for a GPU
without double precision (an optional extension in OpenCL 1.2). The device
libraries are not needed (``-nogpulib`` for amdgcn: the built-ins stay calls,
declared by clang's OpenCL header). Install clang with
``apt-get install clang`` (Debian bookworm: clang 14, with both targets built
in); without it, or without a target, the test is skipped and says why.
By default the code paths of a file are a covering array of strength 3 (every
three of its code-selecting defines' values are compiled together at least
once: 120 compiles a target instead of 537), each with one STACK_SIZE and one
SLAB_PAD in turn (value-only defines, see ``covering_variants``);
``LBVH_ALL_VARIANTS=1`` compiles every variant.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor

import pytest

from lbvh import device as dev
from lbvh.verification import kernel_variants as kv

TARGETS = {
    "amdgcn": ["-target", "amdgcn-amd-amdhsa", "-mcpu=gfx90a", "-nogpulib"],
    "nvptx64": ["-target", "nvptx64-nvidia-cuda"],
    # A GPU without double precision (cl_khr_fp64 is optional in OpenCL 1.2): the
    # kernels that test for it (traverse.cl's watertight test) take their float path.
    "nvptx64-no-fp64": ["-target", "nvptx64-nvidia-cuda", "-Xclang", "-cl-ext=-cl_khr_fp64"],
}
# Warnings that are not failures: (target regex, kernel file regex, message regex, reason).
EXPECTED_WARNINGS: list[tuple[str, str, str, str]] = []

DIAGNOSTIC = re.compile(r"^(?P<path>[^\s:][^:]*):(?P<line>\d+):(?P<col>\d+): "
                        r"(?P<kind>warning|error|fatal error): (?P<msg>.*)$")
FULL = os.environ.get("LBVH_ALL_VARIANTS") == "1"
STRENGTH = 3   # every three code-selecting values together (covering_variants)


def _clang() -> str | None:
    for name in ("clang", "clang-16", "clang-15", "clang-14"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _targets(clang: str) -> str:
    out = subprocess.run([clang, "-print-targets"], capture_output=True, text=True, timeout=60)
    return out.stdout


def _variants(target: str) -> list[kv.Variant]:
    variants = kv.kernel_variants(is_cpu=False)
    sources = {p.name: p.read_text() for p in dev.kernels_dir().iterdir()}
    if "no-fp64" in target:   # only the files that read cl_khr_fp64 compile otherwise
        header = "".join(t for n, t in sources.items() if n.endswith(".h"))
        variants = [v for v in variants if "cl_khr_fp64" in sources[v[0]] + header]
    if FULL:
        return variants
    return kv.covering_variants(variants, sources, value_only=("STACK_SIZE", "SLAB_PAD"),
                                strength=STRENGTH)


def _compile(clang: str, target: str, filename: str, defines: dict) -> tuple[int, str]:
    root = dev.kernels_dir()
    cmd = [clang, *TARGETS[target], "-x", "cl", "-cl-std=CL1.2", "-Xclang",
           "-finclude-default-header", f"-I{root}", *[f"-D{k}={v}" for k, v in defines.items()],
           "-S", "-o", os.devnull, str(root / filename)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    return out.returncode, out.stderr


def _expected(target: str, filename: str, message: str) -> str | None:
    for target_re, file_re, msg_re, reason in EXPECTED_WARNINGS:
        if re.search(target_re, target) and re.search(file_re, filename) and re.search(msg_re, message):
            return reason
    return None


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_gpu_variants_compile_with_clang(target):
    clang = _clang()
    if clang is None:
        pytest.skip("clang not installed (apt-get install clang): GPU targets not compiled")
    arch = TARGETS[target][1].split("-")[0]
    if not re.search(rf"^\s*{arch}\b", _targets(clang), re.M):
        pytest.skip(f"{clang} has no {arch} target built in ({clang} -print-targets)")
    variants = _variants(target)
    with ThreadPoolExecutor(max(1, os.cpu_count() or 1)) as pool:
        results = list(pool.map(lambda v: (v, *_compile(clang, target, *v)), variants))
    failures = []
    for (filename, defines), rc, stderr in results:
        bad = []
        for line in stderr.splitlines():
            m = DIAGNOSTIC.match(line)
            if m:
                text = f"{os.path.basename(m['path'])}:{m['line']}:{m['col']}: {m['kind']}: {m['msg']}"
                if m["kind"] != "warning" or _expected(target, filename, m["msg"]) is None:
                    bad.append(text)
            elif line.startswith(("clang: error", "error:", "fatal error:")) or "LLVM ERROR" in line:
                bad.append(line)
        if rc != 0 and not bad:
            bad.append(f"exit status {rc}: {stderr.strip()[-1500:]}")
        if bad:
            failures.append(f"kernels/{filename} {defines}:\n    " + "\n    ".join(bad))
    if failures:
        pytest.fail(f"{len(failures)} of {len(variants)} GPU variants fail or warn with {clang} "
                    f"for {' '.join(TARGETS[target])}:\n" + "\n".join(failures), pytrace=False)
