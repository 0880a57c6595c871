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

import contextlib
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np
import pyopencl as cl

from .pocl_target import fix_target_cpu

ENV_DEVICE = "LBVH_DEVICE"

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
            for pool in (self._scratch, self._recycled):
                free = pool.get(nbytes)
                if free:
                    return free.pop()
            return None

    def give_scratch(self, buf: cl.Buffer, nbytes: int) -> None:
        with self._lock:
            self._scratch.setdefault(nbytes, []).append(buf)

    def give_back(self, buffers: Sequence[tuple[cl.Buffer, int]]) -> None:
        """Keep the buffers ``(buffer, bytes)`` of a tree that was dropped for the
        next build of the same size (called by the tree's finalizer). Only the
        last dropped tree's buffers are kept: the ones kept before are released."""
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
            return sum(n * len(b) for pool in (self._scratch, self._recycled)
                       for n, b in pool.items())

    # -- programs ------------------------------------------------------------
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
        """A kernel object of a cached program (kernel objects are cached too)."""
        key = (filename, name, tuple(sorted((defines or {}).items())))
        knl = self._kernels.get(key)
        if knl is None:
            knl = getattr(self.program(filename, defines), name)
            self._kernels[key] = knl
        return knl

    def compiled_programs(self) -> int:
        """Number of programs compiled in this context so far (for tests of the cache)."""
        return len(self._programs)

    def _compile(self, filename: str, defines: dict[str, int | str]) -> cl.Program:
        root = kernels_dir()
        source = (root / filename).read_text()
        options = [f"-I{root}", "-cl-std=CL1.2"]
        options += [f"-D{k}={v}" for k, v in defines.items()]
        if self.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
            # The Morton quantisation divides; correctly rounded division keeps it
            # bit-identical to the numpy twin on devices that offer it.
            options.append("-cl-fp32-correctly-rounded-divide-sqrt")
        prog = cl.Program(self.ctx, source)
        try:
            return prog.build(options=options)
        except cl.RuntimeError as exc:
            log = _build_log(prog, self.device)
            raise DeviceError(
                f"lbvh: compiling kernels/{filename} for {self.name} failed "
                f"(options: {' '.join(options)})\n{log or exc}") from exc


def _build_log(prog: cl.Program, dev: cl.Device) -> str:
    try:
        return prog.get_build_info(dev, cl.program_build_info.LOG)
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
            _contexts[key] = ctx
        return ctx


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


def empty(ctx: Context, nbytes: int, flags=cl.mem_flags.READ_WRITE) -> cl.Buffer:
    """An uninitialised device buffer of at least 4 bytes."""
    return cl.Buffer(ctx.ctx, flags, max(int(nbytes), 4))


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
