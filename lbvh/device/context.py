"""Devices, contexts, their queues, their program caches and the lock each public call holds.

The device is PoCL's CPU device unless the caller names another one, either
with the ``device=`` argument of the public functions or with the
``LBVH_DEVICE`` environment variable.  A device is named by a case-insensitive
substring of ``"<platform name> / <device name>"`` (``"pocl"``, ``"nvidia"``,
``"cuda"``), optionally followed by ``#k`` to pick the k-th match.

Every stage asks its context for its kernel with :meth:`Context.kernel`; a
program is compiled once per (context, file, defines) (:mod:`.programs`) and
reused, so a second build of another mesh compiles nothing. Device memory is
the context's :class:`~lbvh.device.memory.DeviceMemory` (``ctx.memory``).
"""
from __future__ import annotations

import contextlib
import functools
import os
import threading
from dataclasses import dataclass, field
from typing import Callable, Iterator, Sequence

import pyopencl as cl

from .errors import DeviceError
from .launch import Launch
from .memory import DeviceMemory
from .pocl_target import fix_target_cpu
from .programs import compile_program, kernel_names
from . import programs

ENV_DEVICE = "LBVH_DEVICE"

# PoCL's platform name; the default device is the first device of this platform.
_POCL_PLATFORM = "portable computing language"

#: Checks a new context must pass before :func:`get_context` hands it out
#: (the self-test, registered by :mod:`lbvh.verification.selftest`).
CONTEXT_CHECKS: list[Callable[["Context"], None]] = []


def all_devices() -> list[tuple[str, cl.Device]]:
    """Every OpenCL device: ``("<platform> / <device>", device)`` pairs."""
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


def _searchable(label: str) -> str:
    """What a device name is looked for in: its label, and "pocl" for PoCL's devices
    (whose platform calls itself "Portable Computing Language")."""
    label = label.lower()
    return label + " (pocl)" if label.startswith(_POCL_PLATFORM) else label


def find_device(name: str | None = None) -> cl.Device:
    """Return the OpenCL device named by ``name``, ``$LBVH_DEVICE`` or PoCL's CPU device."""
    if name is None:
        name = os.environ.get(ENV_DEVICE) or None
    devices = all_devices()
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
    matches = [dev for label, dev in devices if pattern.lower() in _searchable(label)]
    k = int(index) if index else 0
    if k >= len(matches):
        listing = "\n  ".join(label for label, _ in devices)
        raise DeviceError(f"lbvh: no OpenCL device matches {name!r}; available:\n  {listing}")
    return matches[k]


def describe(dev: cl.Device) -> str:
    """One line naming a device, its platform and its OpenCL version, for reports."""
    return f"{dev.platform.name.strip()} / {dev.name.strip()} ({dev.version.strip()})"


@dataclass
class Context:
    """An OpenCL context on one device with a profiling queue and a program cache."""
    device: cl.Device
    ctx: cl.Context = field(init=False)
    queue: cl.CommandQueue = field(init=False)
    _programs: dict = field(init=False, default_factory=dict)
    _kernels: dict = field(init=False, default_factory=dict)
    _logs: dict = field(init=False, default_factory=dict)
    # Re-entrant: public calls call each other (see :attr:`lock`).
    _lock: threading.RLock = field(init=False, default_factory=threading.RLock)

    def __post_init__(self) -> None:
        # Before anything compiles: PoCL 3.0's CPU target (see pocl_target.py)
        self.target_cpu = fix_target_cpu(self.device)
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(
            self.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
        self.name = describe(self.device)
        if self.target_cpu and self.target_cpu[0] != self.target_cpu[1]:
            self.name += f", kernels compiled for {self.target_cpu[1]}"
        #: The one owner of this context's device buffers.
        self.memory = DeviceMemory(self.ctx, self.device, self.queue, self.name)
        self.is_cpu = bool(self.device.type & cl.device_type.CPU)
        # PoCL compiles kernels with clang: kernels may use clang builtins behind a define
        self.compiler_is_clang = self.device.platform.name.strip().lower() == _POCL_PLATFORM
        self.compute_units = max(1, int(self.device.max_compute_units))
        #: common.h's DEVICE_FENCE for every kernel (:func:`.programs.device_fence`).
        self.fence = programs.device_fence(self.device)
        #: Whether that fence reaches every work-group (a CPU's coherent memory,
        #: NVIDIA's membar.gl, OpenCL C 2.0/3.0's device scope); where not, the
        #: bottom-up walks run as one work-group (:meth:`walk_launch`).
        self.fence_reaches_device = bool(self.device.type & cl.device_type.CPU) or \
            self.fence != programs.FENCE_MEM_FENCE

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

    def walk_launch(self, count: int, min_per_item: int = 256) -> Launch:
        """The launch of a bottom-up walk over ``count`` leaves (the refit, the
        treelets, the collapse's costs, the winding moments: common.h's
        second_arrival). As :meth:`launch` where the device's fence reaches every
        work-group; on a GPU without such a fence (OpenCL C 1.2 alone, not NVIDIA's),
        one work-group of up to 256 work-items walks every leaf: slower, but the
        handshake of two walks then needs only the work-group's own mem_fence."""
        if self.fence_reaches_device:
            return self.launch(count, min_per_item)
        count = max(int(count), 0)
        local = max(1, min(256, int(self.device.max_work_group_size)))
        return Launch(count, max(1, -(-count // local)), local, local)

    def launch_chunks(self, count: int, per_item: int) -> Launch:
        """Chunks of exactly ``per_item`` items (the last one shorter), on any device."""
        count, per_item = max(int(count), 0), max(1, int(per_item))
        items = max(1, -(-count // per_item))
        if self.is_cpu:
            return Launch(count, per_item, items, 1)
        local = 64
        return Launch(count, per_item, -(-items // local) * local, local)

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
                if name not in kernel_names(prog):
                    prog = self._recompile(filename, defines, f"kernel {name} missing")
                    if name not in kernel_names(prog):
                        raise DeviceError(f"lbvh: kernels/{filename} compiled for {self.name} has "
                                          f"no kernel {name} (it has: "
                                          f"{', '.join(sorted(kernel_names(prog))) or 'none'})")
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
        """The options a kernel file is compiled with (:func:`.programs.build_options`)."""
        return programs.build_options(self.device, defines, self.fence)

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
        prog, log = compile_program(self.ctx, self.device, self.name, filename, defines, salt,
                                    self.fence)
        self._logs[(filename, tuple(sorted(defines.items())))] = log
        return prog


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
            # answers on this device (lbvh/verification/selftest.py), or DeviceError.
            for check in CONTEXT_CHECKS:
                check(ctx)
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
