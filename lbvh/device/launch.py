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


#: kernel_arg's conversions of the plain Python scalars, by exact type (the common case,
#: one dict lookup; subclasses and numpy booleans take the general path).
_PLAIN_ARGS: dict[type, Any] = {int: np.int32, float: np.float32,
                                bool: lambda value: np.int32(bool(value))}


def kernel_arg(value: Any) -> Any:
    """A kernel argument as OpenCL takes it: Python ``bool``/``int`` as ``int32``,
    ``float`` as ``float32``; numpy scalars (``float64`` too, a subclass of ``float``)
    and buffers as they are."""
    plain = _PLAIN_ARGS.get(type(value))
    if plain is not None:
        return plain(value)
    if isinstance(value, (bool, np.bool_)):
        return np.int32(bool(value))
    if isinstance(value, int):
        return np.int32(value)
    if isinstance(value, float) and not isinstance(value, np.generic):
        return np.float32(value)
    if value is None:
        raise TypeError("kernel argument None: pass a buffer (a placeholder for an unused one)")
    return value


def arg_type(value: Any) -> Any:
    """What pyopencl's ``set_scalar_arg_dtypes`` takes for one argument, as
    :func:`kernel_arg` gives it: a numpy scalar's dtype; a numpy array (a vector
    value such as ``float4``) as raw bytes of its size; ``None`` (set as it is)
    for buffers and anything else."""
    if isinstance(value, np.generic):
        return value.dtype
    if isinstance(value, np.ndarray):
        return np.dtype((np.void, value.nbytes))
    return None


#: The attribute of a kernel object that holds the argument types declared for it, and
#: the Python types of the values they were declared from (a cheaper test of "same").
_DECLARED = "_lbvh_arg_types"
_KINDS = "_lbvh_arg_kinds"


def declare_arg_types(knl: cl.Kernel, values: Sequence[Any]) -> None:
    """Declare the scalar argument types of ``knl`` from ``values`` (once, and again
    only if a call passes other types): pyopencl then packs scalars itself, where
    its generic ``set_arg`` takes 9-15 us a scalar (a launch of the traversal's 20
    arguments: 64 us of the 0.5 ms a one-ray query took; measured on PoCL 3, Zen 3).
    The caller holds the context's lock."""
    kinds = tuple(map(type, values))
    if getattr(knl, _KINDS, None) == kinds:
        return   # the same Python types: the same declared types (no vector values here)
    types = tuple(arg_type(v) for v in values)
    if getattr(knl, _DECLARED, None) != types:
        knl.set_scalar_arg_dtypes(list(types))
        setattr(knl, _DECLARED, types)
    # A numpy array's (or void scalar's) declared type is its size, not its type: never
    # matched by kind.
    setattr(knl, _KINDS, None if np.ndarray in kinds or np.void in kinds else kinds)


def run(ctx: "Context", filename: str, name: str, launch: Launch, *args: Any,
        defines: dict[str, int | str] | None = None,
        wait_for: Sequence[cl.Event] | None = None) -> cl.Event:
    """Queue kernel ``name`` of ``kernels/<filename>`` (compiled with ``defines``) over
    ``launch`` with ``args`` (see :func:`kernel_arg`); returns its event.

    The arguments are set and the kernel queued under the context's lock: kernel
    objects are shared, and their arguments are state until the launch."""
    knl = ctx.kernel(filename, name, defines)
    values = [kernel_arg(a) for a in args]
    with ctx.lock:
        declare_arg_types(knl, values)
        return knl(ctx.queue, (launch.global_size,), launch.local, *values, wait_for=wait_for)
