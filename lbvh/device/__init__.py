"""The device layer: devices and contexts, programs, memory, launches and the radix sort.

Nothing here knows of trees or rays; every other layer runs its kernels
through a :class:`Context` (``lbvh.device.get_context``).

========================  ==========================================================
module                    what it holds
========================  ==========================================================
``context``               devices, :class:`Context` (queue, program cache, lock)
``programs``              kernel sources, compiling, build logs, PoCL's cache check
``memory``                :class:`DeviceMemory`, the one owner of device buffers
``launch``                :class:`Launch` geometry and :func:`run`, the launch helper
``pocl_target``           PoCL 3.0's CPU target on CPUs newer than its LLVM
``sort``                  the radix sort of (key, value) pairs (kernels/sort.cl)
========================  ==========================================================
"""
from .context import (CONTEXT_CHECKS, ENV_DEVICE, Context, all_devices, describe,
                      event_seconds, find_device, get_context, queued_together, serialised)
from .errors import DeviceError
from .launch import Launch, kernel_arg, run
from .memory import (ENV_POISON, DeviceBuffer, DeviceMemory, MemoryTracker, Scope, empty,
                     from_device, pooled_or_empty, read_host_views, read_later, to_device)
from .programs import (ENV_BUILD_LOG, check_compiler_cache, kernel_source,
                       kernels_dir, pocl_cache_dir)

__all__ = ["CONTEXT_CHECKS", "ENV_DEVICE", "Context", "all_devices", "describe", "event_seconds", "find_device",
           "get_context", "queued_together", "serialised", "DeviceError", "Launch", "kernel_arg",
           "run", "ENV_POISON", "DeviceBuffer", "DeviceMemory", "MemoryTracker", "Scope", "empty",
           "from_device", "pooled_or_empty", "read_host_views", "read_later", "to_device", "ENV_BUILD_LOG",
           "check_compiler_cache", "kernel_source", "kernels_dir", "pocl_cache_dir"]
