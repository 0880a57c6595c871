"""OpenCL programs: kernel sources, compiling, build logs and PoCL's compiler cache.

Kernel files live in the top-level ``kernels/`` folder (``lbvh/kernels`` in
a wheel). A file is compiled with its ``#include "..."`` lines expanded and
no ``-I`` path (:func:`kernel_source`), so that every compiler cache key is
the same wherever the package is installed. :class:`lbvh.device.Context`
keeps one compiled program per (file, defines).
"""
from __future__ import annotations

import os
import re
import shutil
import struct
import sys
import threading
import time
import warnings
from pathlib import Path

import pyopencl as cl

from .errors import DeviceError

# Set (to anything) to print every non-empty compiler log to stderr.
ENV_BUILD_LOG = "LBVH_BUILD_LOG"

# Lines a driver writes into the build log of every kernel whatever its source, so
# not findings about ours. NVIDIA's drivers since 550 note of each __kernel
# "Function k is a kernel, so overriding noinline attribute" (pyopencl #756).
DRIVER_NOTES = (re.compile(r"Function \w+ is a kernel, so overriding noinline attribute"),)


def log_findings(log: str) -> list[str]:
    """The lines of a build log that speak of a warning or an error, less
    :data:`DRIVER_NOTES`. Other compilers write progress there ("Compilation
    started"), which is not a finding either."""
    return [line for line in log.splitlines()
            if any(word in line.lower() for word in ("warning", "error"))
            and not any(note.search(line) for note in DRIVER_NOTES)]


def kernels_dir() -> Path:
    """Folder holding the OpenCL sources.

    In a wheel the sources are installed as ``lbvh/kernels``; in a source
    checkout (and an editable install) they are the top-level ``kernels/``.
    """
    package = Path(__file__).resolve().parents[1]
    for candidate in (package / "kernels", package.parent / "kernels"):
        if (candidate / "common.h").is_file():
            return candidate
    raise FileNotFoundError(
        f"lbvh: OpenCL kernel sources not found beside {package} (looked for kernels/common.h)")


def _raw_program(ctx: cl.Context, source: str):
    """An unbuilt program of exactly ``source``.

    pyopencl's ``Program.build`` appends ``-I <its install path>`` to the
    options, which makes every compiler cache key depend on where pyopencl is
    installed (a second virtual environment recompiled everything); its
    low-level program class builds with the options given and nothing more.
    """
    low = getattr(getattr(cl, "_cl", None), "_Program", None)
    return low(ctx, source) if low is not None else cl.Program(ctx, source)


def kernel_names(prog: cl.Program) -> set[str]:
    try:
        names = prog.get_info(cl.program_info.KERNEL_NAMES)
    except cl.Error:
        return set()
    return {n for n in names.split(";") if n}


_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]*"([^"]+)"[ \t]*$', re.M)


def kernel_source(filename: str) -> str:
    """The text of ``kernels/<filename>`` with its ``#include "..."`` lines expanded.

    Compiled without ``-I``, so that the source and options, hence every
    compiler cache key, are the same wherever the package is installed.
    """
    root = kernels_dir()
    seen: set[str] = set()

    def expand(name: str) -> str:
        if name in seen:   # headers are guarded; once is enough
            return ""
        seen.add(name)
        text = (root / name).read_text()
        return _INCLUDE.sub(lambda m: expand(m.group(1)), text)
    return expand(filename)


# -- the compiler's cache on disk --------------------------------------------
# PoCL keeps compiled programs in $POCL_CACHE_DIR (default ~/.cache/pocl/kcache),
# one folder per build: program.bc (LLVM bitcode) and one shared object per
# kernel and work-group shape. A file cut short (a full disk, a process killed
# while writing, a crash inside a kernel that left it half written) is loaded
# as it is: an empty program.bc gives a program without kernels
# (INVALID_KERNEL_NAME), a cut shared object aborts the process. Before the
# first compile of a process every such file is checked and the folder of a
# damaged one removed, so that PoCL compiles it again.
_cache_checked = False
_cache_lock = threading.Lock()


def pocl_cache_dir() -> Path:
    if os.environ.get("POCL_CACHE_DIR"):
        return Path(os.environ["POCL_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pocl" / "kcache"


def _file_whole(path: Path) -> bool:
    """Whether a cached bitcode or ELF shared object is complete, from its headers."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError:
        return False
    if path.suffix == ".bc":
        try:
            return _bitcode_whole(path.read_bytes())
        except OSError:
            return False
    if head[:4] != b"\x7fELF" or len(head) < 64 or head[4] != 2:   # 64-bit ELF
        return False
    order = "<" if head[5] == 1 else ">"
    shoff, = struct.unpack_from(order + "Q", head, 0x28)
    shentsize, shnum = struct.unpack_from(order + "HH", head, 0x3A)
    return shoff + shentsize * shnum <= size


def _bitcode_whole(data: bytes) -> bool:
    """Whether LLVM bitcode holds its module and string table blocks, none cut short.

    The top level of a bitstream (LLVM's "Bitstream Format") is a sequence of
    blocks, each opened by ENTER_SUBBLOCK (abbreviation id 1 in 2 bits), its
    block id (VBR8), abbreviation width (VBR4), alignment to 32 bits and its
    length in 32-bit words; a file cut anywhere leaves its last block short.
    """
    if data[:4] == b"\xde\xc0\x17\x0b" and len(data) >= 20:   # wrapper: offset, size
        offset, size = struct.unpack_from("<II", data, 8)
        if offset + size > len(data):
            return False
        data = data[offset:offset + size]
    if data[:4] != b"BC\xc0\xde":
        return False
    bits = int.from_bytes(data[4:], "little")
    total, pos, blocks = 8 * (len(data) - 4), 0, set()

    def read(width: int) -> int:
        nonlocal pos
        value = (bits >> pos) & ((1 << width) - 1)
        pos += width
        return value

    def vbr(width: int) -> int:
        value, shift = 0, 0
        while True:
            piece = read(width)
            value |= (piece & ((1 << (width - 1)) - 1)) << shift
            shift += width - 1
            if not piece >> (width - 1) or pos > total:
                return value

    while total - pos >= 32:
        if read(2) != 1:                       # only blocks at the top level
            return (bits >> (pos - 2)) == 0 and bool(blocks)   # zero padding at the end
        blocks.add(vbr(8))
        vbr(4)
        pos = -(-pos // 32) * 32
        if total - pos < 32:
            return False
        words = read(32)
        pos += 32 * words
        if pos > total:
            return False
    return {8, 23} <= blocks                   # MODULE_BLOCK and STRTAB_BLOCK


def check_compiler_cache(root: Path | None = None) -> list[str]:
    """Remove damaged entries of PoCL's kernel cache (once per process); returns them."""
    global _cache_checked
    with _cache_lock:
        if root is None:
            if _cache_checked:
                return []
            _cache_checked = True
            root = pocl_cache_dir()
        removed = []
        if not root.is_dir():
            return removed
        for entry in root.glob("*/*"):
            if not entry.is_dir():
                continue
            files = list(entry.glob("program.bc")) + list(entry.glob("*/*/*.so"))
            if any(not _file_whole(f) for f in files):
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(str(entry))
        return removed


def _build_log(prog, dev: cl.Device) -> str:
    try:
        return prog.get_build_info(dev, cl.program_build_info.LOG) or ""
    except cl.Error:
        return ""


# common.h's device_fence(), which the bottom-up walks (refit, winding moments,
# treelets, collapse) put around the atomic that tells the second walk at a node
# that its sibling's results are written. OpenCL 1.2's mem_fence orders memory
# within a work-group only; that suffices on a CPU (one coherent memory) but not on
# NVIDIA's GPUs, where it is a work-group fence (Futhark issue 734): on the H200,
# builds of 4M triangles made node boxes that missed part of a child. There the
# fence is PTX's membar.gl; on other GPUs, OpenCL C 2.0/3.0's device-scope fence
# where the device has it. A GPU with neither keeps mem_fence, which OpenCL 1.2
# does not promise to reach other work-groups, and runs the walks as one
# work-group (Context.walk_launch).
FENCE_MEM_FENCE, FENCE_NVIDIA, FENCE_DEVICE_SCOPE = 0, 1, 2
# OpenCL C 3.0's optional features that memory_scope_device with acq_rel needs
_SCOPE_FEATURES = {"__opencl_c_atomic_scope_device", "__opencl_c_atomic_order_acq_rel"}
_CL_DEVICE_OPENCL_C_FEATURES = 0x106F


def device_scope_std(device: cl.Device) -> str | None:
    """The ``-cl-std`` that gives ``device`` OpenCL C's device-scope fences
    (``"CL3.0"`` or ``"CL2.0"``), or ``None``."""
    try:
        features = {f.name for f in device.get_info(_CL_DEVICE_OPENCL_C_FEATURES)}
    except (cl.Error, AttributeError, TypeError, ValueError):
        # before OpenCL 3.0 the query does not exist, and OpenCL C 2.0 has the fences
        match = re.match(r"OpenCL C (\d+)\.(\d+)", device.opencl_c_version or "")
        return "CL2.0" if match and (int(match[1]), int(match[2])) >= (2, 0) else None
    # OpenCL 3.0: the fences are optional features of OpenCL C 3.0
    return "CL3.0" if _SCOPE_FEATURES <= features else None


def device_fence(device: cl.Device) -> int:
    """The ``DEVICE_FENCE`` define for ``device`` (``FENCE_*`` above)."""
    if device.type & cl.device_type.CPU:
        return FENCE_MEM_FENCE
    if "nvidia" in device.vendor.lower():
        return FENCE_NVIDIA
    return FENCE_DEVICE_SCOPE if device_scope_std(device) else FENCE_MEM_FENCE


def build_options(device: cl.Device, defines: dict[str, int | str],
                  fence: int | None = None) -> list[str]:
    """The options a kernel file is compiled with: no path (see :func:`kernel_source`).
    Besides ``defines``, every file gets ``DEVICE_FENCE`` (``fence``, by default the
    device's: :func:`device_fence`); OpenCL C 1.2 but where that fence needs OpenCL
    C 2.0 or 3.0."""
    fence = device_fence(device) if fence is None else fence
    defines = {"DEVICE_FENCE": fence, **defines}
    std = device_scope_std(device) if fence == FENCE_DEVICE_SCOPE else "CL1.2"
    if std is None:
        raise DeviceError(f"lbvh: DEVICE_FENCE={fence} needs OpenCL C 2.0, or 3.0's "
                          f"{' and '.join(sorted(_SCOPE_FEATURES))}; the device has neither")
    options = [f"-cl-std={std}"] + [f"-D{k}={v}" for k, v in sorted(defines.items())]
    if device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
        # The Morton quantisation divides; correctly rounded division keeps it
        # bit-identical to the numpy twin on devices that offer it.
        options.append("-cl-fp32-correctly-rounded-divide-sqrt")
    return options


def compile_program(ctx: cl.Context, device: cl.Device, device_name: str, filename: str,
                    defines: dict[str, int | str], salt: str = "",
                    fence: int | None = None) -> tuple[cl.Program, str]:
    """Compile ``kernels/<filename>`` for ``device``: ``(program, build log)``.

    ``salt`` (a reason) makes the source differ from every cached one, so a
    damaged entry of a compiler cache is bypassed; ``fence``: see
    :func:`build_options`. A compile error raises :class:`DeviceError` with the log.
    """
    check_compiler_cache()
    source = kernel_source(filename)
    if salt:
        # A different source is a different entry in every cache, so the
        # damaged one is bypassed. PoCL keys its cache by the preprocessed
        # source, so the difference must survive preprocessing: a typedef.
        nonce = f"{os.getpid()}_{time.time_ns()}"
        source += f"\n/* lbvh: compiled afresh: {salt} */ typedef int lbvh_afresh_{nonce};\n"
    options = build_options(device, defines, fence)
    raw = _raw_program(ctx, source)
    try:
        with warnings.catch_warnings():
            # The log is kept (Context.build_log) and checked by the tests; pyopencl's
            # "Non-empty compiler output" warning would only repeat it.
            warnings.simplefilter("ignore", cl.CompilerWarning)
            raw.build(" ".join(options).encode(), [device])
    except cl.Error as exc:
        log = _build_log(raw, device)
        raise DeviceError(
            f"lbvh: compiling kernels/{filename} for {device_name} failed "
            f"(options: {' '.join(options)})\n{log or exc}") from exc
    log = _build_log(raw, device).strip()
    if log and os.environ.get(ENV_BUILD_LOG):
        sys.stderr.write(f"lbvh: build log of kernels/{filename} {' '.join(options)}:\n{log}\n")
    prog = cl.Program(raw)
    if not salt and not kernel_names(prog):
        return compile_program(ctx, device, device_name, filename, defines,
                               salt="no kernels in the binary", fence=fence)
    return prog, log
