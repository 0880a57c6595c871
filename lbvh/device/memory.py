"""Device memory: one owner per context that hands out, pools and counts every buffer.

Every device buffer of the package, build or query, comes from a context's
:class:`DeviceMemory` (``ctx.memory``) and goes back to it:

* :meth:`DeviceMemory.alloc` (uninitialised), :meth:`DeviceMemory.upload`
  (a copy of a numpy array) hand out buffers; :meth:`DeviceMemory.free`
  releases them or keeps them in the pool.
* ``in_use`` counts the bytes of the buffers handed out and not given back,
  ``peak`` its largest value since :meth:`DeviceMemory.reset_peak`; a buffer
  dropped without :meth:`~DeviceMemory.free` (a caller's query output) is
  counted out when the garbage collector takes it.
* :meth:`DeviceMemory.scope` counts what one call (a build) allocates: its
  ``peak`` is the build report's ``peak_device_bytes``.

The pool. Fresh device memory is paid for with page faults on first touch:
about a quarter of a 1M-triangle build on PoCL. A build's scratch buffers
(boxes, keys, counters) go back to the pool and serve the next build of the
same size; a scope's :meth:`~Scope.close` keeps only one build's worth. The
buffers of the last tree that was dropped (nodes, parents, primitive order,
its traversal records) are kept too and serve the next build of the same
size: a loop that rebuilds every frame then writes its trees to mapped pages.
:meth:`DeviceMemory.trim` without arguments releases both.
"""
from __future__ import annotations

import collections
import contextlib
import itertools
import math
import os
import threading
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import numpy as np
import pyopencl as cl

from .errors import DeviceError

if TYPE_CHECKING:   # annotations only: context.py imports this module
    from .context import Context

# Tests of uninitialised reads (tests/test_uninitialised.py): with this set to a
# byte value, every buffer handed out uninitialised (alloc, new or from the
# pool) is first filled with it. A kernel that reads what no command wrote then
# answers differently for different bytes.
ENV_POISON = "LBVH_POISON_BYTE"
_POISON = os.environ.get(ENV_POISON)


class DeviceBuffer(cl.Buffer):
    """A ``pyopencl.Buffer`` handed out by :class:`DeviceMemory` (usable wherever
    a ``pyopencl.Buffer`` is): ``nbytes`` is its size as counted, ``serial`` its
    number in the count, ``mem_flags`` its access flags (a pooled buffer is handed
    out again only to a request with the same ones)."""
    nbytes: int
    serial: int
    mem_flags: int
    owner: "DeviceMemory | None" = None

    def release(self) -> None:
        """Release it now; the memory that handed it out counts it out."""
        if self.owner is not None:
            self.owner.forget(self)
        super().release()


class Scope:
    """What one call allocates through :class:`DeviceMemory` while it is open.

    ``live``: bytes of its buffers not yet given back; ``peak``: the most it
    held at once. ``scratch_used`` (bytes -> count) tells :meth:`close` how
    much scratch to keep pooled for the next call of the same size.
    """

    def __init__(self, memory: "DeviceMemory") -> None:
        self.memory = memory
        self.live = 0
        self.peak = 0
        self.scratch_used: dict[int, int] = {}

    # the build stages take a scope and allocate through it
    def alloc(self, nbytes: int, scratch: bool = False) -> DeviceBuffer:
        """A buffer counted in this scope; ``scratch``: from and back to the pool."""
        return self.memory.alloc(nbytes, pooled=True, scratch=scratch, scope=self)

    def free(self, *bufs: cl.Buffer, to_pool: bool = False) -> None:
        self.memory.free(*bufs, to_pool=to_pool)

    def close(self) -> None:
        """Keep in the pool only the scratch this scope used (for the next call)."""
        self.memory.trim(self.scratch_used)


@dataclass
class HostOutputs:
    """What :meth:`DeviceMemory.host_outputs` makes: ``arrays`` (numpy views of
    ``block``), ``buffers`` (a sub-buffer on each), ``block`` (the ``uint8`` host
    memory) and ``block_buffer`` (its ``USE_HOST_PTR`` buffer)."""
    arrays: list[np.ndarray]
    buffers: list[cl.Buffer]
    block: np.ndarray
    block_buffer: cl.Buffer

    def release(self) -> None:
        """Release the sub-buffers and the block's buffer (not the arrays)."""
        for b in self.buffers:
            b.release()
        self.block_buffer.release()


class DeviceMemory:
    """The owner of one context's device buffers (see the module docstring)."""

    def __init__(self, ctx: cl.Context, device: cl.Device, queue: cl.CommandQueue,
                 name: str) -> None:
        self._ctx, self._queue, self._name = ctx, queue, name
        self.max_alloc = int(device.max_mem_alloc_size)
        #: Bytes a sub-buffer's origin is a multiple of (CL_DEVICE_MEM_BASE_ADDR_ALIGN, in bits).
        self.sub_align = max(1, int(device.mem_base_addr_align) // 8)
        self._in_use = 0
        self.peak = 0
        # serial -> (buffer's bytes, scopes open when it was made, finalizer), for
        # every buffer handed out and not given back; serials, not ids, since the
        # id of a collected buffer may be a new buffer's before the count settles
        self._live: dict[int, tuple[int, tuple[Scope, ...], weakref.finalize]] = {}
        self._serials = itertools.count()
        self._scratch_flag: set[int] = set()   # serials of scratch buffers
        self._scopes: list[Scope] = []
        self._scratch: dict[int, list[DeviceBuffer]] = {}
        self._recycled: dict[int, list[DeviceBuffer]] = {}
        # Filled without a lock from finalizers (the garbage collector runs them in
        # whatever thread allocates, maybe one that holds another lock); emptied
        # by the next call that takes the lock.
        self._dropped: collections.deque = collections.deque()
        self._collected: collections.deque = collections.deque()
        # Re-entrant: a finalizer may fire while this thread is inside.
        self._lock = threading.RLock()

    @property
    def in_use(self) -> int:
        """Bytes of the buffers handed out and not given back (or collected)."""
        with self._lock:
            self._settle()
            return self._in_use

    # -- handing out -----------------------------------------------------------
    def alloc(self, nbytes: int, *, pooled: bool = False, scratch: bool = False,
              scope: Scope | None = None, flags: int = cl.mem_flags.READ_WRITE) -> DeviceBuffer:
        """An uninitialised buffer of at least 4 bytes.

        ``pooled``: a pooled buffer of the same size if there is one (its pages
        are mapped). ``scratch`` (implies ``pooled``): it goes back to the pool
        when freed and counts toward what ``scope.close()`` keeps. ``scope``:
        counted in that scope as well as in the scopes open now.
        """
        nbytes = max(int(nbytes), 4)
        with self._lock:
            self._settle()
            buf = self._take_pooled(nbytes, flags) if (pooled or scratch) else None
            if buf is None:
                buf = self._new(nbytes, flags)
            self._poison(buf, nbytes)
            self._hand_out(buf, nbytes, scope)
            if scratch and scope is not None:
                scope.scratch_used[nbytes] = scope.scratch_used.get(nbytes, 0) + 1
            if scratch:
                self._scratch_flag.add(buf.serial)
            return buf

    def upload(self, array: np.ndarray, *, flags: int = cl.mem_flags.READ_ONLY,
               scope: Scope | None = None) -> DeviceBuffer:
        """A new buffer holding a copy of the contiguous numpy ``array``."""
        array = np.ascontiguousarray(array)
        with self._lock:
            self._settle()
            if array.nbytes == 0:
                buf = self._new(4, flags)
            else:
                buf = self._new(array.nbytes, flags | cl.mem_flags.COPY_HOST_PTR, array)
            self._hand_out(buf, buf.nbytes, scope)
            return buf

    def host_view(self, array: np.ndarray, *, output: bool = False,
                  readable: bool = False) -> cl.Buffer:
        """A buffer on the C-contiguous, non-empty numpy ``array``'s own memory
        (``USE_HOST_PTR``): on a device that shares the host's memory (a CPU,
        ``ctx.is_cpu``) the kernels read, or with ``output`` write, the array itself,
        with no copy either way. Written results are the array's once
        :func:`read_host_views` has returned. The caller releases the buffer; it
        holds no device memory of its own and is not counted in :attr:`in_use`.
        With ``LBVH_POISON_BYTE`` set, an ``output`` array is filled with it first,
        as :meth:`alloc` fills its buffers (tests of unwritten results); ``readable``:
        an ``output`` the kernels read back too (``READ_WRITE``)."""
        if not array.flags.c_contiguous or array.nbytes == 0:
            raise ValueError("host_view: a C-contiguous, non-empty array")
        if output and _POISON is not None:
            array.view(np.uint8).fill(int(_POISON, 0))
        flags = (cl.mem_flags.READ_WRITE if readable else cl.mem_flags.WRITE_ONLY) if output \
            else cl.mem_flags.READ_ONLY
        try:
            return cl.Buffer(self._ctx, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=array)
        except cl.Error as exc:
            raise DeviceError(f"lbvh: a buffer on {array.nbytes:,} bytes of host memory on "
                              f"{self._name} failed: {exc}") from exc

    def host_outputs(self, *specs: tuple[tuple[int, ...], Any],
                     readable: bool = False) -> HostOutputs:
        """Output arrays of the given ``(shape, dtype)`` specs, non-empty, in one block of
        host memory: one :meth:`host_view` on the block (``output``) and a sub-buffer on
        each array, which kernels write. One map of the block (:func:`read_host_views`
        of ``(out.block_buffer, out.block)``) then makes every array's contents the
        kernels' results: one wait for them all, where a host view per array waits once
        per array (35-40 us each for a one-ray query on PoCL). Each array starts at a
        multiple of :attr:`sub_align`, as sub-buffers must. ``readable``: the kernels
        read the arrays back too (a walk's scratch among the answers). The caller
        releases ``out.buffers`` and ``out.block_buffer``."""
        sizes = [math.prod(shape) * np.dtype(dtype).itemsize for shape, dtype in specs]
        if 0 in sizes:
            raise ValueError("host_outputs: an empty array")
        offsets = [0]
        for nbytes in sizes[:-1]:
            offsets.append(offsets[-1] + -(-nbytes // self.sub_align) * self.sub_align)
        block = np.empty(offsets[-1] + sizes[-1], np.uint8)
        parent = self.host_view(block, output=True, readable=readable)
        access = cl.mem_flags.READ_WRITE if readable else cl.mem_flags.WRITE_ONLY
        arrays, subs = [], []
        try:
            for (shape, dtype), at, nbytes in zip(specs, offsets, sizes):
                arrays.append(block[at:at + nbytes].view(dtype).reshape(shape))
                subs.append(parent.get_sub_region(at, nbytes, access))
        except cl.Error as exc:
            for b in subs:
                b.release()
            parent.release()
            raise DeviceError(f"lbvh: sub-buffers of {block.nbytes:,} bytes of host memory on "
                              f"{self._name} failed: {exc}") from exc
        return HostOutputs(arrays, subs, block, parent)

    def free(self, *bufs: cl.Buffer | None, to_pool: bool = False) -> None:
        """Give buffers back: scratch ones (and all with ``to_pool``: a caller about
        to allocate the same sizes again keeps their pages mapped) to the pool,
        the others released. A buffer given twice (a sort's output may be its
        input), one not handed out here, and ``None`` are skipped."""
        with self._lock:
            for buf in bufs:
                nbytes = None if buf is None else self._count_out(buf)
                if nbytes is None:
                    continue
                scratch = buf.serial in self._scratch_flag
                self._scratch_flag.discard(buf.serial)
                if scratch or to_pool:
                    self._scratch.setdefault(nbytes, []).append(buf)
                else:
                    buf.release()

    @contextlib.contextmanager
    def scope(self) -> Iterator[Scope]:
        """Count what is allocated inside the block (see :class:`Scope`)."""
        scope = Scope(self)
        with self._lock:
            self._scopes.append(scope)
        try:
            yield scope
        finally:
            with self._lock:
                self._scopes.remove(scope)

    def reset_peak(self) -> None:
        """Start a new ``peak`` from what is in use now."""
        with self._lock:
            self._settle()
            self.peak = self._in_use

    # -- trees dropped -----------------------------------------------------------
    def dropped(self, buffers: Sequence[cl.Buffer]) -> None:
        """A tree's finalizer hands its buffers here (no lock taken: see __init__);
        the next call adopts them as the last dropped tree's (see :meth:`give_back`)."""
        self._dropped.append(list(buffers))

    def give_back(self, buffers: Sequence[cl.Buffer]) -> None:
        """Keep the buffers of a tree that was dropped for the next build of the same
        size. Only the last dropped tree's buffers are kept: those kept before are
        released."""
        with self._lock:
            for bufs in self._recycled.values():
                for buf in bufs:
                    buf.release()
            self._recycled = {}
            for buf in buffers:
                nbytes = self._count_out(buf)
                self._scratch_flag.discard(getattr(buf, "serial", None))
                if nbytes is None:
                    buf.release()
                else:
                    self._recycled.setdefault(nbytes, []).append(buf)

    # -- the pool ----------------------------------------------------------------
    def trim(self, keep: dict[int, int] | None = None) -> None:
        """Release pooled scratch beyond ``keep`` (bytes -> how many buffers); without
        it, all of the pool and the buffers kept from dropped trees."""
        with self._lock:
            self._settle()
            if keep is None:
                self.give_back([])
            for nbytes, bufs in list(self._scratch.items()):
                limit = (keep or {}).get(nbytes, 0)
                while len(bufs) > limit:
                    bufs.pop().release()
                if not bufs:
                    del self._scratch[nbytes]

    def pooled_bytes(self) -> int:
        """Device bytes held in the pool between calls."""
        with self._lock:
            self._settle()
            return sum(n * len(b) for pool in (self._scratch, self._recycled)
                       for n, b in pool.items())

    def forget(self, buf: cl.Buffer) -> None:
        """Count out a buffer its holder released itself (``DeviceBuffer.release``)."""
        with self._lock:
            self._count_out(buf)
            self._scratch_flag.discard(getattr(buf, "serial", None))

    # -- inside ------------------------------------------------------------------
    def _new(self, nbytes: int, flags: int, hostbuf: np.ndarray | None = None) -> DeviceBuffer:
        if nbytes > self.max_alloc:
            raise DeviceError(f"lbvh: a buffer of {nbytes:,} bytes exceeds {self._name}'s "
                              f"largest allocation ({self.max_alloc:,} bytes); the mesh is too "
                              "large for this device")
        try:
            if hostbuf is None:
                buf = DeviceBuffer(self._ctx, flags, nbytes)
            else:
                buf = DeviceBuffer(self._ctx, flags, hostbuf=hostbuf)
        except cl.Error as exc:
            raise DeviceError(f"lbvh: allocating {nbytes:,} bytes on {self._name} failed: "
                              f"{exc}") from exc
        buf.nbytes = nbytes
        buf.mem_flags = flags & ~cl.mem_flags.COPY_HOST_PTR
        buf.owner = self
        return buf

    def _take_pooled(self, nbytes: int, flags: int) -> DeviceBuffer | None:
        # any pooled buffer of this size and these flags will do, scratch or recycled
        # (a dropped tree's buffers include read-only ones: an upload's)
        for pool in (self._scratch, self._recycled):
            free = pool.get(nbytes, [])
            for k in range(len(free) - 1, -1, -1):
                if getattr(free[k], "mem_flags", None) == flags:
                    return free.pop(k)
        return None

    def _poison(self, buf: cl.Buffer, nbytes: int) -> None:
        if _POISON is not None:
            cl.enqueue_fill_buffer(self._queue, buf, np.uint8(int(_POISON, 0)), 0, nbytes)

    def _hand_out(self, buf: DeviceBuffer, nbytes: int, scope: Scope | None) -> None:
        scopes = tuple(self._scopes) + ((scope,) if scope is not None and
                                        scope not in self._scopes else ())
        key = buf.serial = next(self._serials)
        # Counted out by the garbage collector if the holder drops it unfreed.
        fin = weakref.finalize(buf, self._collected.append, key)
        fin.atexit = False
        self._live[key] = (nbytes, scopes, fin)
        self._in_use += nbytes
        self.peak = max(self.peak, self._in_use)
        for s in scopes:
            s.live += nbytes
            s.peak = max(s.peak, s.live)

    def _count_out(self, buf: cl.Buffer) -> int | None:
        entry = self._live.pop(getattr(buf, "serial", None), None)
        if entry is None:
            return None
        nbytes, scopes, fin = entry
        fin.detach()
        self._subtract(nbytes, scopes)
        return nbytes

    def _subtract(self, nbytes: int, scopes: tuple[Scope, ...]) -> None:
        self._in_use -= nbytes
        for s in scopes:
            s.live -= nbytes

    def _settle(self) -> None:
        """Adopt dropped trees' buffers and count out collected buffers."""
        while self._collected:
            entry = self._live.pop(self._collected.popleft(), None)
            if entry is not None:
                self._subtract(entry[0], entry[1])
        while self._dropped:
            self.give_back(self._dropped.popleft())


def read_later(ctx: "Context", scope: Scope, partial: cl.Buffer, host: np.ndarray,
               after: cl.Event, reduce: Callable[[np.ndarray], int]) -> Callable[[], int]:
    """Queue the read of ``partial`` (a kernel's per-work-item results, written by
    ``after``) into ``host`` without waiting; the returned function waits for
    it, gives ``partial`` back to ``scope`` and returns ``reduce(host)``."""
    read = cl.enqueue_copy(ctx.queue, host, partial, wait_for=[after], is_blocking=False)

    def result() -> int:
        read.wait()
        scope.free(partial)
        return reduce(host)
    return result


# -- the calls the stages use (each through the context's DeviceMemory) ---------

def to_device(ctx: "Context", array: np.ndarray) -> cl.Buffer:
    """Copy a contiguous numpy array into a new read-only device buffer."""
    return ctx.memory.upload(array)


def empty(ctx: "Context", nbytes: int, flags: int = cl.mem_flags.READ_WRITE) -> cl.Buffer:
    """An uninitialised device buffer of at least 4 bytes."""
    return ctx.memory.alloc(nbytes, flags=flags)


def pooled_or_empty(ctx: "Context", nbytes: int) -> cl.Buffer:
    """A buffer of ``nbytes`` from the context's pool (pages already mapped), else a new one."""
    return ctx.memory.alloc(nbytes, pooled=True)


def from_device(ctx: "Context", buf: cl.Buffer, dtype, shape) -> np.ndarray:
    """Copy a device buffer back into a new numpy array of the given dtype and shape."""
    out = np.empty(shape, dtype=dtype)
    if out.nbytes:
        cl.enqueue_copy(ctx.queue, out, buf, is_blocking=True)
    return out


class MemoryTracker(Scope):
    """A :class:`Scope` of ``ctx.memory`` that counts only what is allocated through
    it (for callers that run single stages: tests, benches)."""

    def __init__(self, ctx: "Context") -> None:
        super().__init__(ctx.memory)


def read_host_views(queue: cl.CommandQueue, views: Sequence[tuple[cl.Buffer, np.ndarray]],
                    wait_for: Sequence[cl.Event] | None = None) -> None:
    """Make what kernels wrote to ``(buffer, array)`` pairs of
    :meth:`DeviceMemory.host_view` the arrays' contents: each buffer is mapped for
    reading (blocking) and unmapped. OpenCL guarantees a ``USE_HOST_PTR`` buffer's
    host memory holds the latest bits once its map completes; on a device that
    shares the host's memory the map copies nothing."""
    for buf, array in views:
        mapped, _ = cl.enqueue_map_buffer(queue, buf, cl.map_flags.READ, 0, array.shape,
                                          array.dtype, wait_for=wait_for, is_blocking=True)
        mapped.base.release()
