"""Device selection, command queues and the per-context program cache.

Every stage of the pipeline asks this module for its compiled program with
:func:`program`; a program is compiled once per (context, file, defines) and
reused, so a second build of another mesh compiles nothing.

The device is PoCL's CPU device unless the caller names another one, either
with the ``device=`` argument of the public functions or with the
``LBVH_DEVICE`` environment variable.  A device is named by a case-insensitive
substring of ``"<platform name> / <device name>"`` (``"pocl"``, ``"nvidia"``,
``"cuda"``), optionally followed by ``#k`` to pick the k-th match.
"""
from __future__ import annotations

import collections
import contextlib
import functools
import os
import re
import shutil
import struct
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np
import pyopencl as cl

from .pocl_target import fix_target_cpu

ENV_DEVICE = "LBVH_DEVICE"
# Set (to anything) to print every non-empty compiler log to stderr.
ENV_BUILD_LOG = "LBVH_BUILD_LOG"

# PoCL's platform name; the default device is the first device of this platform.
_POCL_PLATFORM = "portable computing language"


def kernels_dir() -> Path:
    """Folder holding the OpenCL sources.

    In a wheel the sources are installed as ``lbvh/kernels``; in a source
    checkout (and an editable install) they are the top-level ``kernels/``.
    """
    here = Path(__file__).resolve().parent
    for candidate in (here / "kernels", here.parent / "kernels"):
        if (candidate / "common.h").is_file():
            return candidate
    raise FileNotFoundError(
        f"lbvh: OpenCL kernel sources not found beside {here} (looked for kernels/common.h)")


class DeviceError(RuntimeError):
    """An OpenCL device could not be found, or a program failed to compile."""


def _all_devices() -> list[tuple[str, cl.Device]]:
    found = []
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:  # no ICD loader or no platform at all
        raise DeviceError(f"lbvh: no OpenCL platform available ({exc})") from exc
    for platform in platforms:
        try:
            devices = platform.get_devices()
        except cl.Error:
            continue
        for dev in devices:
            found.append((f"{platform.name.strip()} / {dev.name.strip()}", dev))
    return found


def find_device(name: str | None = None) -> cl.Device:
    """Return the OpenCL device named by ``name``, ``$LBVH_DEVICE`` or PoCL's CPU device."""
    if name is None:
        name = os.environ.get(ENV_DEVICE) or None
    devices = _all_devices()
    if not devices:
        raise DeviceError("lbvh: no OpenCL device found")
    if name is None:
        for label, dev in devices:
            if label.lower().startswith(_POCL_PLATFORM) and dev.type & cl.device_type.CPU:
                return dev
        listing = "\n  ".join(label for label, _ in devices)
        raise DeviceError(
            "lbvh: PoCL's CPU device was not found (pip install pocl-binary-distribution); "
            f"pick one of these with device= or ${ENV_DEVICE}:\n  {listing}")
    pattern, _, index = name.partition("#")
    matches = [dev for label, dev in devices if pattern.lower() in label.lower()]
    k = int(index) if index else 0
    if k >= len(matches):
        listing = "\n  ".join(label for label, _ in devices)
        raise DeviceError(f"lbvh: no OpenCL device matches {name!r}; available:\n  {listing}")
    return matches[k]


def describe(dev: cl.Device) -> str:
    """One line naming a device, its platform and its OpenCL version, for reports."""
    return f"{dev.platform.name.strip()} / {dev.name.strip()} ({dev.version.strip()})"


@dataclass
class Launch:
    """How a data-parallel loop over ``count`` items is cut into work-items.

    On a CPU device (PoCL) a work-item is a loop iteration on a core, so each
    work-item takes a contiguous chunk of ``per_item`` items and work-groups
    have one work-item; on a GPU each work-item takes one item.
    """
    count: int
    per_item: int
    global_size: int
    local_size: int | None

    @property
    def local(self) -> tuple[int] | None:
        return None if self.local_size is None else (self.local_size,)


@dataclass
class Context:
    """An OpenCL context on one device with a profiling queue and a program cache."""
    device: cl.Device
    ctx: cl.Context = field(init=False)
    queue: cl.CommandQueue = field(init=False)
    _programs: dict = field(init=False, default_factory=dict)
    _kernels: dict = field(init=False, default_factory=dict)
    _scratch: dict = field(init=False, default_factory=dict)
    _recycled: dict = field(init=False, default_factory=dict)
    _logs: dict = field(init=False, default_factory=dict)
    _dropped: collections.deque = field(init=False, default_factory=collections.deque)
    # Re-entrant: a tree's finalizer (give_back, run by the garbage collector at any
    # allocation) may fire while this thread is inside the pool.
    _lock: threading.RLock = field(init=False, default_factory=threading.RLock)

    def __post_init__(self) -> None:
        # Before anything compiles: PoCL 3.0's CPU target (see pocl_target.py)
        self.target_cpu = fix_target_cpu(self.device)
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(
            self.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
        self.is_cpu = bool(self.device.type & cl.device_type.CPU)
        # PoCL compiles kernels with clang: kernels may use clang builtins behind a define
        self.compiler_is_clang = self.device.platform.name.strip().lower() == _POCL_PLATFORM
        self.compute_units = max(1, int(self.device.max_compute_units))
        self.name = describe(self.device)
        if self.target_cpu and self.target_cpu[0] != self.target_cpu[1]:
            self.name += f", kernels compiled for {self.target_cpu[1]}"

    # -- launch geometry ---------------------------------------------------
    def work_items(self) -> int:
        """How many heavy work-items to run at once: a few per core on a CPU."""
        return self.compute_units * 8 if self.is_cpu else self.compute_units * 2048

    def launch(self, count: int, min_per_item: int = 1024, gpu_per_item: int = 1,
               multiple: int = 1) -> Launch:
        """Cut ``count`` items into contiguous chunks, one chunk per work-item.

        On a CPU a chunk holds at least ``min_per_item`` items, a multiple of
        ``multiple`` (a kernel's vector width), and there are a few chunks per
        core; on a GPU a chunk holds ``gpu_per_item`` items.
        """
        count = max(int(count), 0)
        if self.is_cpu:
            per_item = max(min_per_item, -(-count // self.work_items()))
            return self.launch_chunks(count, -(-per_item // multiple) * multiple)
        return self.launch_chunks(count, gpu_per_item)

    def launch_chunks(self, count: int, per_item: int) -> Launch:
        """Chunks of exactly ``per_item`` items (the last one shorter), on any device."""
        count, per_item = max(int(count), 0), max(1, int(per_item))
        items = max(1, -(-count // per_item))
        if self.is_cpu:
            return Launch(count, per_item, items, 1)
        local = 64
        return Launch(count, per_item, -(-items // local) * local, local)

    # -- scratch buffers kept between builds --------------------------------
    # Fresh device memory is paid for with page faults on first touch: about a
    # quarter of a 1M-triangle build on PoCL. A build's scratch buffers (boxes,
    # keys, counters) go back to this pool and serve the next build of the same
    # size; trim_scratch() keeps only one build's worth. The output buffers
    # (nodes, parents, primitive order) of the last tree that was dropped are
    # kept too (give_back) and serve the next build of the same size: a loop
    # that rebuilds every frame then writes its trees to mapped pages.
    # trim_scratch() without arguments releases both.
    def take_scratch(self, nbytes: int) -> cl.Buffer | None:
        with self._lock:
            self._adopt_dropped()
            for pool in (self._scratch, self._recycled):
                free = pool.get(nbytes)
                if free:
                    return free.pop()
            return None

    def give_scratch(self, buf: cl.Buffer, nbytes: int) -> None:
        with self._lock:
            self._scratch.setdefault(nbytes, []).append(buf)

    def dropped(self, buffers: Sequence[tuple[cl.Buffer, int]]) -> None:
        """A tree's finalizer hands its buffers here. The garbage collector runs
        it in whatever thread allocates, maybe one that holds another lock, so
        it takes no lock: the next call that uses the pool adopts them."""
        self._dropped.append(list(buffers))

    def _adopt_dropped(self) -> None:
        while self._dropped:
            self.give_back(self._dropped.popleft())

    def give_back(self, buffers: Sequence[tuple[cl.Buffer, int]]) -> None:
        """Keep the buffers ``(buffer, bytes)`` of a tree that was dropped for the
        next build of the same size. Only the last dropped tree's buffers are
        kept: the ones kept before are released."""
        with self._lock:
            for bufs in self._recycled.values():
                for buf in bufs:
                    buf.release()
            self._recycled = {}
            for buf, nbytes in buffers:
                self._recycled.setdefault(nbytes, []).append(buf)

    def trim_scratch(self, keep: dict[int, int] | None = None) -> None:
        """Release pooled scratch beyond ``keep`` (bytes -> how many buffers); without
        it, all of the pool and the buffers kept from dropped trees."""
        with self._lock:
            self._adopt_dropped()
            if keep is None:
                self.give_back([])
            for nbytes, bufs in list(self._scratch.items()):
                limit = (keep or {}).get(nbytes, 0)
                while len(bufs) > limit:
                    bufs.pop().release()
                if not bufs:
                    del self._scratch[nbytes]

    def scratch_bytes(self) -> int:
        """Device bytes held in the scratch pool between builds."""
        with self._lock:
            self._adopt_dropped()
            return sum(n * len(b) for pool in (self._scratch, self._recycled)
                       for n, b in pool.items())

    # -- programs ------------------------------------------------------------
    @property
    def lock(self) -> threading.RLock:
        """Held by every public call while it uses this context's queue.

        All of a context's work goes through one in-order queue; a call holds
        this lock from its first command to its last read, so commands of two
        threads never interleave (a queued_together gate of one thread would
        otherwise hold back a blocking read of another: the deadlock of issue
        14). Re-entrant: public calls call each other.
        """
        return self._lock

    def program(self, filename: str, defines: dict[str, int | str] | None = None) -> cl.Program:
        """Compile ``kernels/<filename>`` with ``-D`` defines, once per context."""
        defines = dict(sorted((defines or {}).items()))
        key = (filename, tuple(defines.items()))
        with self._lock:
            prog = self._programs.get(key)
            if prog is None:
                prog = self._compile(filename, defines)
                self._programs[key] = prog
            return prog

    def kernel(self, filename: str, name: str, defines: dict[str, int | str] | None = None) -> cl.Kernel:
        """A kernel object of a cached program (kernel objects are cached too).

        A program whose binary came from a damaged compiler cache can lack
        kernels (PoCL answers ``INVALID_KERNEL_NAME``); it is then compiled
        afresh once, bypassing the cache, before the error is raised.
        """
        key = (filename, name, tuple(sorted((defines or {}).items())))
        with self._lock:
            knl = self._kernels.get(key)
            if knl is None:
                prog = self.program(filename, defines)
                if name not in _kernel_names(prog):
                    prog = self._recompile(filename, defines, f"kernel {name} missing")
                    if name not in _kernel_names(prog):
                        raise DeviceError(f"lbvh: kernels/{filename} compiled for {self.name} has "
                                          f"no kernel {name} (it has: "
                                          f"{', '.join(sorted(_kernel_names(prog))) or 'none'})")
                knl = cl.Kernel(prog, name)
                self._kernels[key] = knl
            return knl

    def compiled_programs(self) -> int:
        """Number of programs compiled in this context so far (for tests of the cache)."""
        return len(self._programs)

    def build_log(self, filename: str, defines: dict[str, int | str] | None = None) -> str:
        """The compiler's log of a program compiled in this context ('' when it said nothing)."""
        return self._logs.get((filename, tuple(sorted((defines or {}).items()))), "")

    def build_options(self, defines: dict[str, int | str]) -> list[str]:
        """The options a kernel file is compiled with: no path (see :func:`kernel_source`)."""
        options = ["-cl-std=CL1.2"] + [f"-D{k}={v}" for k, v in sorted(defines.items())]
        if self.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
            # The Morton quantisation divides; correctly rounded division keeps it
            # bit-identical to the numpy twin on devices that offer it.
            options.append("-cl-fp32-correctly-rounded-divide-sqrt")
        return options

    def _recompile(self, filename: str, defines: dict[str, int | str] | None,
                   why: str) -> cl.Program:
        defines = dict(sorted((defines or {}).items()))
        key = (filename, tuple(sorted(defines.items())))
        with self._lock:
            self._kernels = {k: v for k, v in self._kernels.items() if k[0] != filename
                             or k[2] != key[1]}
            prog = self._compile(filename, defines, salt=why)
            self._programs[key] = prog
            return prog

    def _compile(self, filename: str, defines: dict[str, int | str], salt: str = "") -> cl.Program:
        check_compiler_cache()
        source = kernel_source(filename)
        if salt:
            # A different source is a different entry in every cache, so the
            # damaged one is bypassed. PoCL keys its cache by the preprocessed
            # source, so the difference must survive preprocessing: a typedef.
            nonce = f"{os.getpid()}_{time.time_ns()}"
            source += f"\n/* lbvh: compiled afresh: {salt} */ typedef int lbvh_afresh_{nonce};\n"
        options = self.build_options(defines)
        key = (filename, tuple(sorted(defines.items())))
        raw = _raw_program(self.ctx, source)
        try:
            with warnings.catch_warnings():
                # The log is kept (build_log) and checked by the tests; pyopencl's
                # "Non-empty compiler output" warning would only repeat it.
                warnings.simplefilter("ignore", cl.CompilerWarning)
                raw.build(" ".join(options).encode(), [self.device])
        except cl.Error as exc:
            log = _build_log(raw, self.device)
            raise DeviceError(
                f"lbvh: compiling kernels/{filename} for {self.name} failed "
                f"(options: {' '.join(options)})\n{log or exc}") from exc
        log = _build_log(raw, self.device).strip()
        self._logs[key] = log
        if log and os.environ.get(ENV_BUILD_LOG):
            sys.stderr.write(f"lbvh: build log of kernels/{filename} {' '.join(options)}:\n{log}\n")
        prog = cl.Program(raw)
        if not salt and not _kernel_names(prog):
            return self._compile(filename, defines, salt="no kernels in the binary")
        return prog


def _raw_program(ctx: cl.Context, source: str):
    """An unbuilt program of exactly ``source``.

    pyopencl's ``Program.build`` appends ``-I <its install path>`` to the
    options, which makes every compiler cache key depend on where pyopencl is
    installed (a second virtual environment recompiled everything); its
    low-level program class builds with the options given and nothing more.
    """
    low = getattr(getattr(cl, "_cl", None), "_Program", None)
    return low(ctx, source) if low is not None else cl.Program(ctx, source)


def _kernel_names(prog: cl.Program) -> set[str]:
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


_contexts: dict[int, Context] = {}
_contexts_lock = threading.Lock()


def get_context(device: str | cl.Device | Context | None = None) -> Context:
    """The shared :class:`Context` for a device (created on first use)."""
    if isinstance(device, Context):
        return device
    dev = device if isinstance(device, cl.Device) else find_device(device)
    key = int(dev.int_ptr)
    with _contexts_lock:
        ctx = _contexts.get(key)
        if ctx is None:
            ctx = Context(dev)
            # Before the context is handed out: its kernels give the right
            # answers on this device (lbvh/selftest.py), or DeviceError.
            from .selftest import require
            require(ctx)
            _contexts[key] = ctx
        return ctx


def serialised(func: Callable) -> Callable:
    """Run ``func(tree, ...)`` holding ``tree.ctx.lock`` (see :attr:`Context.lock`)."""
    @functools.wraps(func)
    def locked(tree, *args, **kwargs):
        with tree.ctx.lock:
            return func(tree, *args, **kwargs)
    return locked


def event_seconds(events: Sequence[cl.Event]) -> float:
    """Sum of the device execution times of finished events, in seconds."""
    total = 0
    for ev in events:
        ev.wait()
        total += ev.profile.end - ev.profile.start
    return total * 1e-9


@contextlib.contextmanager
def queued_together(ctx: Context) -> Iterator[None]:
    """Commands queued inside the block start only once the block ends.

    On a CPU device the host thread shares the cores with the kernels: once a
    kernel runs, queueing the next one can wait milliseconds for a core, and
    the device idles in between. A barrier on a user event (OpenCL 1.2) holds
    the queue until every command of the block is in it. Nothing inside the
    block may wait for a command queued inside it (it would never run);
    waiting for one queued before the block is fine.
    """
    gate = cl.UserEvent(ctx.ctx)
    cl.enqueue_barrier(ctx.queue, wait_for=[gate])
    try:
        yield
    finally:
        gate.set_status(cl.command_execution_status.COMPLETE)


def read_later(ctx: Context, mem: "MemoryTracker", partial: cl.Buffer, host: np.ndarray,
               after: cl.Event, reduce: Callable[[np.ndarray], int]) -> Callable[[], int]:
    """Queue the read of ``partial`` (a kernel's per-work-item results, written by
    ``after``) into ``host`` without waiting; the returned function waits for
    it, gives ``partial`` back to ``mem`` and returns ``reduce(host)``."""
    read = cl.enqueue_copy(ctx.queue, host, partial, wait_for=[after], is_blocking=False)

    def result() -> int:
        read.wait()
        mem.free(partial)
        return reduce(host)
    return result


def to_device(ctx: Context, array: np.ndarray) -> cl.Buffer:
    """Copy a contiguous numpy array into a new read-only device buffer."""
    array = np.ascontiguousarray(array)
    flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
    if array.nbytes == 0:
        return cl.Buffer(ctx.ctx, cl.mem_flags.READ_ONLY, 4)
    return cl.Buffer(ctx.ctx, flags, hostbuf=array)


# Tests of uninitialised reads (tests/test_uninitialised.py): with this set to a
# byte value, every buffer handed out uninitialised (empty, MemoryTracker.alloc,
# new or from the pool) is first filled with it. A kernel that reads what no
# command wrote then answers differently for different bytes.
ENV_POISON = "LBVH_POISON_BYTE"
_POISON = os.environ.get(ENV_POISON)


def poison(ctx: Context, buf: cl.Buffer, nbytes: int) -> None:
    """Fill ``buf`` with ``$LBVH_POISON_BYTE`` where it is set (tests only)."""
    if _POISON is not None:
        cl.enqueue_fill_buffer(ctx.queue, buf, np.uint8(int(_POISON, 0)), 0, nbytes)


def empty(ctx: Context, nbytes: int, flags=cl.mem_flags.READ_WRITE) -> cl.Buffer:
    """An uninitialised device buffer of at least 4 bytes."""
    nbytes = max(int(nbytes), 4)
    buf = cl.Buffer(ctx.ctx, flags, nbytes)
    poison(ctx, buf, nbytes)
    return buf


def pooled_or_empty(ctx: Context, nbytes: int) -> cl.Buffer:
    """A buffer of ``nbytes`` from the context's pool (pages already mapped), else a new one."""
    buf = ctx.take_scratch(max(int(nbytes), 4))
    if buf is None:
        return empty(ctx, nbytes)
    poison(ctx, buf, max(int(nbytes), 4))
    return buf


def from_device(ctx: Context, buf: cl.Buffer, dtype, shape) -> np.ndarray:
    """Copy a device buffer back into a new numpy array of the given dtype and shape."""
    out = np.empty(shape, dtype=dtype)
    if out.nbytes:
        cl.enqueue_copy(ctx.queue, out, buf, is_blocking=True)
    return out


class MemoryTracker:
    """Counts the device bytes a build holds, to report its peak.

    Buffers are allocated through :meth:`alloc` and given back with
    :meth:`free` as soon as a stage no longer needs them. Scratch buffers
    (``scratch=True``: nothing of them outlives the build) come from and go
    back to the context's pool; :meth:`close` trims the pool to what this
    build used.
    """

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx
        self.live = 0
        self.peak = 0
        self._sizes: dict[int, tuple[int, bool]] = {}
        self._scratch_used: dict[int, int] = {}

    def alloc(self, nbytes: int, scratch: bool = False) -> cl.Buffer:
        nbytes = max(int(nbytes), 4)
        # Any pooled buffer of this size will do, scratch or not: its pages are
        # already mapped.
        buf = self.ctx.take_scratch(nbytes)
        if buf is None:
            max_alloc = int(self.ctx.device.max_mem_alloc_size)
            if nbytes > max_alloc:
                raise DeviceError(f"lbvh: a buffer of {nbytes:,} bytes exceeds {self.ctx.name}'s "
                                  f"largest allocation ({max_alloc:,} bytes); the mesh is too large "
                                  "for this device")
            try:
                buf = cl.Buffer(self.ctx.ctx, cl.mem_flags.READ_WRITE, nbytes)
            except cl.Error as exc:
                raise DeviceError(f"lbvh: allocating {nbytes:,} bytes on {self.ctx.name} failed: "
                                  f"{exc}") from exc
        poison(self.ctx, buf, nbytes)
        if scratch:
            self._scratch_used[nbytes] = self._scratch_used.get(nbytes, 0) + 1
        self._sizes[id(buf)] = (nbytes, scratch)
        self.live += nbytes
        self.peak = max(self.peak, self.live)
        return buf

    def free(self, *bufs: cl.Buffer, to_pool: bool = False) -> None:
        """Give buffers back: scratch to the pool, others released unless ``to_pool``
        (a caller about to allocate the same sizes again keeps their pages mapped)."""
        for buf in bufs:
            entry = self._sizes.pop(id(buf), None)
            if entry is None:
                continue
            nbytes, scratch = entry
            self.live -= nbytes
            if scratch or to_pool:
                self.ctx.give_scratch(buf, nbytes)
            else:
                buf.release()

    def close(self) -> None:
        """Keep in the pool only the scratch this build used (for the next one)."""
        self.ctx.trim_scratch(self._scratch_used)
