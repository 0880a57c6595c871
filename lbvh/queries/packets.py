"""Closest hits and any hits by packets of 8 rays (kernels/packet_traverse.cl).

Coherent rays (a camera's, a scanner's, rays towards one light), traced in the
Morton order of their origins and directions (:mod:`lbvh.queries.ray_order`),
go through the tree 8 at a time on a CPU: each wide record is fetched, ordered
and pushed once for the packet, its children's boxes tested against the 8 rays
in one vector slab test each (Wald et al. 2001; Wald, Boulos & Shirley 2007).
Each ray keeps its own mask bit, its own entry distances and its own closest
hit, so a packet gives every ray exactly the answer of the single-ray walk of
:mod:`lbvh.queries.traverse` (same t, u, v and triangle, ties included: of
triangles hit at exactly the same t, the lowest index; any hit: the same rays
hit). The twin is that walk, which the tests hold it to bit for bit.

:func:`trace_packets` is the device-level call; :func:`packets_apply` says
whether a query takes it.
"""
from __future__ import annotations

import pyopencl as cl

from .. import device as dev
from .rays import DeviceRays
from .target import QueryTarget, query_target

KERNEL_FILE = "packet_traverse.cl"

#: Rays per packet: the CPU's float8 (the kernel's vectors).
PACKET = 8

#: Rays per work-item: 8 packets, as the single-ray walk's 64 rays
#: (lbvh.queries.traverse).
RAYS_PER_ITEM = 64

#: Calls of fewer rays go ray by ray: a second launch costs more than packets save.
PACKETS_FROM = 4096


def packets_apply(ctx: dev.Context, wide_packed: bool, width: int, counters: bool,
                  node_order: str) -> bool:
    """Whether a query can run by packets: on a CPU, through 8-wide records, without
    counters (the single-ray walk counts) and in the default node order."""
    return (ctx.is_cpu and wide_packed and width == PACKET and not counters
            and node_order == "ordered")


#: The single-ray kernel's defines that the packets' kernel takes as they are.
_SHARED_DEFINES = ("TRIANGLE_TEST", "STACK_SIZE", "SLAB_PAD", "EXACT_LEAVES", "CLANG_MOVMSK",
                   "CLANG_CTZ")


def packet_defines(defines: dict, any_hit: bool, ordered: bool) -> dict[str, int | str]:
    """The -D defines of kernels/packet_traverse.cl from the single-ray kernel's
    (:func:`lbvh.queries.traverse.kernel_defines` and the tree's): its triangle test,
    stack, slab pad, leaves and lane builtins; any hit or closest; rays in an
    ``order`` buffer or not."""
    own = {k: v for k, v in defines.items() if k in _SHARED_DEFINES}
    own.update(ANY_HIT=int(bool(any_hit)), RAY_ORDER=int(bool(ordered)), WIDTH=PACKET)
    return own


def trace_packets(target: QueryTarget, rays: DeviceRays, *, any_hit: bool, defines: dict,
                  hits: cl.Buffer, flags: cl.Buffer, deferred: cl.Buffer) -> cl.Event:
    """Trace checked rays on the device (in their ``order``, once ``ready``) by packets
    into ``hits`` (four planes of ``count`` float32: t, u, v, primitive bits) and
    ``flags`` (int32), as
    :func:`lbvh.queries.traverse.trace_buffers` does; ``defines`` are the single-ray
    kernel's (its triangle test, stack and slab pad). The packets whose rays are not
    coherent (kernels/packet_traverse.cl ``packet_coherent``) are not traced: their
    rays' indices are written to ``deferred`` (``int32 (count,)``, -1 for the rays
    traced here) for the single-ray walk to trace in that order. Returns the kernel's
    event."""
    target = query_target(target)   # a BVH gives its query data
    ctx, tree = target.ctx, target.tree
    order = rays.order
    wide = target.wide_records()
    count = int(rays.count)
    per = max(PACKET, min(RAYS_PER_ITEM, -(-count // max(1, ctx.work_items()))))
    per = -(-per // PACKET) * PACKET
    launch = ctx.launch_chunks(count, per)
    own = packet_defines(defines, any_hit, order is not None)
    return dev.run(ctx, KERNEL_FILE, "traverse_packets", launch, tree.nodes, wide.buffer,
                   tree.prim_order, target.mesh.vertices_buf, target.slot_faces(), tree.root,
                   wide.root_x, wide.root_y, tree.num_nodes, rays.origins, rays.directions,
                   rays.tmin, rays.tmax, rays.interval_stride,
                   order if order is not None else flags, hits, flags, deferred, count,
                   launch.per_item,
                   defines=own, wait_for=list(rays.ready))


__all__ = ["PACKET", "PACKETS_FROM", "RAYS_PER_ITEM", "packet_defines", "packets_apply", "trace_packets"]
