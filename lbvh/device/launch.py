"""Launch geometry and the one helper every kernel launch goes through.

On a CPU device (PoCL) a work-item is a loop iteration on a core: each
work-item takes a contiguous chunk of items, a few chunks per core, and a
work-group has one work-item. On a GPU each work-item takes one item (or a
few) in work-groups of 64. :meth:`lbvh.device.Context.launch` chooses the
:class:`Launch`; :func:`run` queues a kernel over it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import pyopencl as cl

if TYPE_CHECKING:   # for annotations only: context.py imports this module
    from .context import Context


@dataclass
class Launch:
    """How a data-parallel loop over ``count`` items is cut into work-items:
    ``per_item`` items each, ``global_size`` work-items in groups of
    ``local_size`` (``None``: the runtime's choice)."""
    count: int
    per_item: int
    global_size: int
    local_size: int | None

    @property
    def local(self) -> tuple[int] | None:
        return None if self.local_size is None else (self.local_size,)


def kernel_arg(value: Any) -> Any:
    """A kernel argument as OpenCL takes it: Python ``bool``/``int`` as ``int32``,
    ``float`` as ``float32``; numpy scalars (``float64`` too, a subclass of ``float``)
    and buffers as they are."""
    if isinstance(value, (bool, np.bool_)):
        return np.int32(bool(value))
    if isinstance(value, int):
        return np.int32(value)
    if isinstance(value, float) and not isinstance(value, np.generic):
        return np.float32(value)
    if value is None:
        raise TypeError("kernel argument None: pass a buffer (a placeholder for an unused one)")
    return value


def run(ctx: "Context", filename: str, name: str, launch: Launch, *args: Any,
        defines: dict[str, int | str] | None = None,
        wait_for: Sequence[cl.Event] | None = None) -> cl.Event:
    """Queue kernel ``name`` of ``kernels/<filename>`` (compiled with ``defines``) over
    ``launch`` with ``args`` (see :func:`kernel_arg`); returns its event."""
    knl = ctx.kernel(filename, name, defines)
    return knl(ctx.queue, (launch.global_size,), launch.local, *map(kernel_arg, args),
               wait_for=wait_for)
