"""Stage 5: Karras 2012 hierarchy emission on the device (kernels/emit.cl).

Writes the child links of the ``n - 1`` internal nodes, the leaf records
(unless the build's refit is to write them) and the parent links, in the
numbering of docs/pages/layout.md. Boxes are left to the refit (stage 6).
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..device import Context, MemoryTracker, run
from ..layout import NODE_DTYPE

KERNEL_FILE = "emit.cl"
#: internal nodes per vector in emit.cl (LANES) on a CPU; a GPU's work-item takes one node
LANES = 8


def lanes_for(is_cpu: bool) -> int:
    """emit.cl's LANES: eight nodes in explicit vectors on a CPU (PoCL does not
    vectorise a work-item's loop), one node per work-item on a GPU, whose
    compiler splits eight-wide vectors anyway (and got them wrong on an NVIDIA
    H200: see emit.cl)."""
    return LANES if is_cpu else 1


def kernel_defines(key_bits: int, is_cpu: bool, write_leaves: bool = True) -> dict[str, int]:
    """The -D defines kernels/emit.cl is compiled with."""
    return {"KEY_BITS": key_bits, "WRITE_LEAVES": int(write_leaves), "LANES": lanes_for(is_cpu)}


def emit_hierarchy(ctx: Context, mem: MemoryTracker, sorted_keys: cl.Buffer, n: int,
                   key_bits: int, per_item: int | None = None, write_leaves: bool = True,
                   lanes: int | None = None) -> tuple[cl.Buffer, cl.Buffer, list[cl.Event]]:
    """Device node records (boxes not yet set) and parent links for ``2n - 1`` nodes.

    ``per_item`` forces the chunk length (tests); by default the launch picks
    whole groups of ``LANES`` nodes on a CPU, one node per work-item on a GPU.
    With ``write_leaves=False`` the leaf records are left unwritten: the
    build's refit (``refit_from_boxes(karras_ranges=True)``) writes them whole.
    ``lanes`` overrides :func:`lanes_for` (tests run both forms on any device).
    """
    num_nodes = 2 * n - 1
    nodes = mem.alloc(num_nodes * NODE_DTYPE.itemsize)
    parent = mem.alloc(num_nodes * 4)
    defines = kernel_defines(key_bits, ctx.is_cpu, write_leaves)
    if lanes is not None:
        defines["LANES"] = lanes
    launch = (ctx.launch(n, min_per_item=256, gpu_per_item=defines["LANES"],
                         multiple=defines["LANES"])
              if per_item is None else ctx.launch_chunks(n, per_item))
    ev = run(ctx, KERNEL_FILE, "emit_hierarchy", launch, sorted_keys, n, launch.per_item, nodes,
             parent, defines=defines)
    return nodes, parent, [ev]


# -- pure Python twin ------------------------------------------------------------

def _common_prefix(keys: list[int], key_bits: int, i: int, j: int) -> int:
    n = len(keys)
    if j < 0 or j >= n:
        return -1
    x = keys[i] ^ keys[j]
    if x:
        return key_bits - x.bit_length()
    return key_bits + 32 - (i ^ j).bit_length()


def emit_hierarchy_python(sorted_keys, key_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Serial Karras 2012 (Figure 4), one internal node after the other, in plain Python.

    Returns ``children int32 (2n-1, 2)`` (``-1`` for leaves) and ``parent int32 (2n-1,)``.
    """
    keys = [int(k) for k in sorted_keys]
    n = len(keys)
    children = np.full((2 * n - 1, 2), -1, np.int32)
    parent = np.full(2 * n - 1, -1, np.int32)

    def delta(i: int, j: int) -> int:
        return _common_prefix(keys, key_bits, i, j)

    for i in range(n - 1):
        d = 1 if delta(i, i + 1) > delta(i, i - 1) else -1
        delta_min = delta(i, i - d)
        lmax = 2
        while delta(i, i + lmax * d) > delta_min:
            lmax *= 2
        length = 0
        t = lmax // 2
        while t >= 1:
            if delta(i, i + (length + t) * d) > delta_min:
                length += t
            t //= 2
        j = i + length * d
        delta_node = delta(i, j)
        split = 0
        t = length
        while True:
            t = (t + 1) // 2
            if delta(i, i + (split + t) * d) > delta_node:
                split += t
            if t <= 1:
                break
        gamma = i + split * d + min(d, 0)
        left = n - 1 + gamma if min(i, j) == gamma else gamma
        right = n - 1 + gamma + 1 if max(i, j) == gamma + 1 else gamma + 1
        children[i] = (left, right)
        parent[left] = parent[right] = i
    return children, parent
