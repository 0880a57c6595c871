"""The CPU that PoCL 3.0 compiles kernels for, made consistent with its kernel library.

PoCL 3.0 (the build on PyPI, LLVM 14) picks its built-in library
(``kernel-x86_64-unknown-linux-gnu-<variant>.bc``) from the CPU's features, but
compiles user kernels for the CPU *name* its LLVM reports. On a CPU newer than
LLVM 14 (AMD Zen 5, recent Intel) that name is ``generic``, which clang refuses
as a target (``error: unknown target CPU 'generic'``): nothing compiles at all.
PoCL 5 takes the target from the library's variant instead; this module does
the same for PoCL 3.0 by writing the variant's CPU name into the device's
``llvm_cpu`` field before the first build, and only where PoCL left it at
``generic`` (or where ``$LBVH_POCL_CPU`` names a CPU explicitly, which tests use
to compile for another CPU on this one).

The field is found, not assumed: the device record is scanned for the pointer
to the target triple followed by the pointer to the CPU name, dereferencing
only addresses inside readable mappings of this process.
"""
from __future__ import annotations

import ctypes
import os
import threading

ENV_CPU = "LBVH_POCL_CPU"

# PoCL's "distro" kernel-library variants, in increasing order, with the CPU
# each was built for and the /proc/cpuinfo flags it needs (PoCL's own table,
# lib/CL/pocl_llvm_utils.cc, in cpuinfo's spelling: lzcnt is "abm", bmi "bmi1").
_VARIANTS = (
    ("sse2", "athlon64", ("sse2",)),
    ("ssse3", "core2", ("sse2", "ssse3", "cx16")),
    ("sse41", "penryn", ("sse2", "sse4_1", "cx16")),
    ("avx", "sandybridge", ("sse2", "avx", "cx16", "popcnt")),
    ("avx_f16c", "ivybridge", ("sse2", "avx", "cx16", "popcnt", "f16c")),
    ("avx_fma4", "bdver1", ("sse2", "avx", "cx16", "popcnt", "xop", "fma4")),
    ("avx2", "haswell", ("sse2", "avx", "avx2", "cx16", "popcnt", "abm", "f16c", "fma",
                         "bmi1", "bmi2")),
    ("avx512", "skylake-avx512", ("sse2", "avx512f")),
)

_TRIPLE = b"x86_64-unknown-linux-gnu"
_lock = threading.Lock()
_done: dict[int, tuple[str, str]] = {}   # device pointer -> (PoCL's name, the one in force)
_keep: list = []                          # the C strings written into devices stay alive


def cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def kernel_library_variant(flags: set[str] | None = None) -> tuple[str, str]:
    """(variant, CPU name) of the kernel library PoCL 3.0 loads on this CPU."""
    flags = cpu_flags() if flags is None else flags
    best = _VARIANTS[0]
    for variant in _VARIANTS:
        if all(f in flags for f in variant[2]):
            best = variant
    return best[0], best[1]


def _readable() -> list[tuple[int, int]]:
    ranges = []
    with open("/proc/self/maps") as f:
        for line in f:
            addr, perm = line.split()[:2]
            if perm.startswith("r"):
                lo, hi = (int(x, 16) for x in addr.split("-"))
                ranges.append((lo, hi))
    return ranges


def _c_string(ranges, ptr: int, n: int = 48) -> bytes | None:
    for lo, hi in ranges:
        if lo <= ptr and ptr + n <= hi:
            return ctypes.string_at(ptr, n).split(b"\0", 1)[0]
    return None


def _cpu_slot(device_ptr: int, words: int = 1024):
    """The device record's ``llvm_cpu`` word (ctypes array, index, current name)."""
    ranges = _readable()
    if not any(lo <= device_ptr and device_ptr + words * 8 <= hi for lo, hi in ranges):
        return None
    record = (ctypes.c_uint64 * words).from_address(device_ptr)
    for i in range(words - 1):
        if _c_string(ranges, record[i]) == _TRIPLE:
            name = _c_string(ranges, record[i + 1])
            if name:
                return record, i + 1, name.decode()
    return None


def target_cpu(device) -> tuple[str, str] | None:
    """(PoCL's CPU name, the one in force) for a PoCL CPU device once fixed, else None."""
    return _done.get(int(device.int_ptr))


def fix_target_cpu(device) -> tuple[str, str] | None:
    """Make PoCL 3.0 compile for a CPU clang knows, consistent with its kernel library.

    Call before the first program build on ``device`` (a ``pyopencl.Device``).
    Returns (PoCL's CPU name, the name in force), or None where the device is not
    a PoCL CPU device or its record could not be read. Idempotent.
    """
    import pyopencl as cl
    key = int(device.int_ptr)
    with _lock:
        if key in _done:
            return _done[key]
        if (device.platform.name.strip().lower() != "portable computing language"
                or not device.type & cl.device_type.CPU):
            return None
        slot = _cpu_slot(key)
        if slot is None:
            return None
        record, index, name = slot
        wanted = os.environ.get(ENV_CPU) or None
        if wanted is None and name == "generic":
            wanted = kernel_library_variant()[1]
        if wanted is not None and wanted != name:
            buf = ctypes.create_string_buffer(wanted.encode())
            _keep.append(buf)
            record[index] = ctypes.addressof(buf)
        _done[key] = (name, wanted or name)
        return _done[key]
