"""Every (kernel file, -D defines) combination the package compiles.

:func:`lbvh.device.Context.program` compiles a kernel file once per set of
defines; this module lists, for a CPU or a GPU device, every set that the
package's modules can ask for, with the values taken from the modules' own
constants and functions (the stack buckets of :mod:`lbvh.traverse`, the
record widths of :mod:`lbvh.wide`, the digit widths of :mod:`lbvh.sort`, ...),
so that a check of every variant (build logs, other compilers, other targets)
follows the package when it changes. ``tests/device/test_build_logs.py`` and
``tests/verification/test_portability.py`` compile them; a test records what a
representative set of public calls compiles and checks that it is in this
list.

Only the package's own choices are listed: the overrides that exist for tests
and experiments (``trace_buffers(defines=...)``, ``intersect(stack_size=...)``
beyond the buckets, ``radix_sort(radix_bits=...)`` other than the package's
two digit widths) are not.

A variant is a ``(filename, defines)`` pair, ``defines`` a dict sorted by name
as :meth:`lbvh.device.Context.program` sorts it; :func:`variant_key` makes it
hashable the way the program cache does.
"""
from __future__ import annotations

import inspect
import itertools
import re
from types import SimpleNamespace
from typing import Iterable

import pyopencl as cl

from ..builders import bounds
from ..builders import collapse
from ..builders import emit
from ..builders import morton
from ..builders import ploc
from ..queries import (all_hits, closest, instance_closest, instance_hits, instances, overlap,
                       ray_order, rays, winding, winding_moments)
from ..builders import refit
from ..builders import restructure
from ..device import sort
from ..queries import packets, traverse
from ..queries import wide

Defines = dict[str, int | str]
Variant = tuple[str, Defines]


def variant_key(filename: str, defines: Defines | None) -> tuple[str, tuple]:
    """The hashable key of a variant: as lbvh.device.Context.program caches it."""
    return filename, tuple(sorted((defines or {}).items()))


def _default(function, name: str):
    return inspect.signature(function).parameters[name].default


def _fake_ctx(is_cpu: bool, exact_divide: bool, compiler_is_clang: bool) -> SimpleNamespace:
    """What the modules' define choosers read of a Context, for a device of this kind."""
    fp = cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT if exact_divide else 0
    return SimpleNamespace(is_cpu=is_cpu, compiler_is_clang=compiler_is_clang,
                           device=SimpleNamespace(single_fp_config=fp))


def _choices(value: bool | None) -> tuple[bool, ...]:
    return (False, True) if value is None else (bool(value),)


def _product(**axes: Iterable) -> list[Defines]:
    names = sorted(axes)
    return [dict(zip(names, values)) for values in itertools.product(*(axes[n] for n in names))]


def kernel_variants(is_cpu: bool, *, exact_divide: bool | None = None,
                    compiler_is_clang: bool | None = None) -> list[Variant]:
    """Every (kernel file, defines) the package compiles on a CPU (``is_cpu``) or
    GPU device.

    ``exact_divide``: whether the device has correctly rounded float32
    division (it sets traverse.cl's ``SLAB_PAD``); ``compiler_is_clang``:
    whether the platform compiles with clang (PoCL: refit.cl's
    ``CLANG_PREFETCH``, winding.cl's ``INLINE_SQRT``, traverse.cl's
    ``CLANG_MOVMSK`` and ``CLANG_CTZ``). ``None`` (the default) lists both values: every device of
    that kind. :func:`variants_for` gives one context's list.
    """
    ctxs = [_fake_ctx(is_cpu, d, c) for d in _choices(exact_divide)
            for c in _choices(compiler_is_clang)]
    out: dict[tuple, Variant] = {}

    def add(filename: str, defines: Defines) -> None:
        defines = dict(sorted(defines.items()))
        out.setdefault(variant_key(filename, defines), (filename, defines))

    key_bits = sorted(morton.KEY_DTYPE)                         # 32- and 64-bit keys
    add(bounds.KERNEL_FILE, {})
    for bits in key_bits:                                       # morton_codes, count_duplicates
        add(morton.KERNEL_FILE, {"KEY_BITS": bits})
    # emit_hierarchy: the build leaves the leaves to the refit; the default writes them
    write_leaves = sorted({int(_default(emit.emit_hierarchy, "write_leaves")), 0})
    for bits, leaves in itertools.product(key_bits, write_leaves):
        add(emit.KERNEL_FILE, emit.kernel_defines(bits, is_cpu, bool(leaves)))
    # sort.cl: key_bits (its default digit width) and the passes (the device's width)
    default_radix = _default(sort.kernel_defines, "radix_bits")
    for ctx in ctxs:
        for bits in key_bits:
            for radix in sorted({default_radix, sort.radix_bits_for(ctx)}):
                add(sort.KERNEL_FILE, sort.kernel_defines(bits, ctx.is_cpu, radix))
    # refit.cl: clear_arrivals (no defines) and refit
    add(refit.KERNEL_FILE, {})
    for ctx in ctxs:
        for karras in (0, 1):
            add(refit.KERNEL_FILE, {"KARRAS_RANGES": karras,
                                    "CLANG_PREFETCH": int(ctx.compiler_is_clang)})
    for leaves in (5, restructure.TREELET_LEAVES):   # the default and the bench's smaller size
        add(restructure.KERNEL_FILE, {"TREELET_LEAVES": leaves})
    add(collapse.KERNEL_FILE, {})
    # ploc.cl: the default search radius, the device's lanes, clang's prefetch or not
    for ctx in ctxs:
        add(ploc.KERNEL_FILE, ploc.kernel_defines(ploc.PLOC_RADIUS, ctx.is_cpu,
                                                  ctx.compiler_is_clang))
    add(ray_order.KERNEL_FILE, {})
    for width in wide.WIDTHS:                                   # wide_level, wide_records
        add(wide.KERNEL_FILE, {"WIDTH": width})
    # traverse.cl: order_faces (no defines) and traverse
    add(traverse.KERNEL_FILE, {})
    for ctx in ctxs:
        for any_hit, counters, test, stack in itertools.product(
                (False, True), (False, True), traverse.TRIANGLE_TESTS, traverse.STACK_BUCKETS):
            base = traverse.kernel_defines(ctx, any_hit, test, counters, stack)
            # wide records of either width (width_for: 8 on a CPU, 4 elsewhere; both
            # listed for both kinds, as wide.cl, which bvh.wide_records(width=) compiles for
            # either), or the binary nodes (WIDE=0, where records would not fit) with
            # the record width still set
            # trees with spatial splits (builder="sbvh") add EXACT_LEAVES=0
            for extra in _product(WIDE=(1, 0), WIDTH=wide.WIDTHS, RAY_ORDER=(0, 1)):
                for clipped in ({}, {"EXACT_LEAVES": 0}):
                    add(traverse.KERNEL_FILE, {**base, **extra, **clipped})
                    if not any_hit:   # intersect(order="global"): closest hits only
                        add(traverse.KERNEL_FILE, {**base, **extra, **clipped, "ORDER_GLOBAL": 1})
    # packet_traverse.cl: packets of 8 rays on a CPU (closest and any hit, no counters, the
    # default node order) through 8-wide records, in the rays' order or not
    if is_cpu:
        for ctx in ctxs:
            for any_hit, test, stack in itertools.product(
                    (False, True), traverse.TRIANGLE_TESTS, traverse.STACK_BUCKETS):
                base = traverse.kernel_defines(ctx, any_hit, test, False, stack)
                for ordered, clipped in itertools.product((False, True), ({}, {"EXACT_LEAVES": 0})):
                    add(packets.KERNEL_FILE, packets.packet_defines({**base, **clipped}, any_hit,
                                                                    ordered))
    # device_rays.cl: the checks and marks (no defines), the result's arrays, and
    # the conversion of each element type lbvh reads from pyopencl arrays
    add(rays.DEVICE_KERNEL_FILE, {})
    for counters in (0, 1):
        add(rays.DEVICE_KERNEL_FILE, {"COUNTERS": counters})
    for ctype in rays.DEVICE_SOURCE_TYPES.values():
        add(rays.DEVICE_KERNEL_FILE, {"SRC_T": ctype, **({"SRC_IS_DOUBLE": 1}
                                                          if ctype == "double" else {})})
    # overlap.cl: both passes, one stack size per bucket
    for ctx, stack, count in itertools.product(ctxs, traverse.STACK_BUCKETS, (0, 1)):
        add(overlap.KERNEL_FILE, {"STACK_SIZE": stack, "COUNT": count})
        for width in wide.WIDTHS:   # through wide records of either width
            add(overlap.KERNEL_FILE, {"STACK_SIZE": stack, "COUNT": count, "WIDE": 1,
                                      "WIDTH": width, **wide.lane_defines(ctx)})
    # all_hits.cl: both passes (the count with and without counters, and signed; the
    # collecting pass with and without SLOTS_ONLY), one stack size per bucket, the slab
    # padding of the device, through binary nodes and the device's wide records
    hit_passes = ({"COUNT": 1}, {"COUNT": 1, "SIGNED": 1}, {"COUNT": 0},
                  {"COUNT": 0, "SLOTS_ONLY": 1})
    add(all_hits.KERNEL_FILE, {})   # move_runs (no defines)
    for ctx in ctxs:
        for stack, hit_pass in itertools.product(traverse.STACK_BUCKETS, hit_passes):
            add(all_hits.KERNEL_FILE, {"STACK_SIZE": stack, **hit_pass,
                                       "SLAB_PAD": traverse.slab_pad(ctx)})
            for width in wide.WIDTHS:   # the records' width, as traverse.cl's
                add(all_hits.KERNEL_FILE, {"STACK_SIZE": stack, **hit_pass,
                                           "SLAB_PAD": traverse.slab_pad(ctx),
                                           **all_hits.wide_defines(ctx, width)})
        for width, hit_pass in itertools.product(wide.WIDTHS, hit_passes):
            # the streams with their leaf lanes' triangles one by one (tests)
            add(all_hits.KERNEL_FILE, {"STACK_SIZE": traverse.STACK_BUCKETS[0], **hit_pass,
                                       "SLAB_PAD": traverse.slab_pad(ctx),
                                       **all_hits.wide_defines(ctx, width), "LANE_TRIANGLES": 0})
        for stack in traverse.STACK_BUCKETS:   # segment_work: the counting pass's counters
            add(all_hits.KERNEL_FILE, {"STACK_SIZE": stack, "COUNT": 1, "COUNTERS": 1,
                                       "SLAB_PAD": traverse.slab_pad(ctx)})
    # instance_hits.cl: all_hits.cl's two passes through a scene (no counters), one stack
    # size per bucket, the slab padding of the device
    for ctx in ctxs:
        for stack, hit_pass in itertools.product(traverse.STACK_BUCKETS, hit_passes):
            if hit_pass.get("SIGNED"):   # a scene's counts are never signed
                continue
            add(instance_hits.KERNEL_FILE, {"STACK_SIZE": stack, **hit_pass,
                                            "SLAB_PAD": traverse.slab_pad(ctx)})
    # instances.cl: closest and any hit, counters, both triangle tests, one stack per bucket
    for ctx in ctxs:
        for any_hit, counters, test, stack in itertools.product(
                (False, True), (False, True), traverse.TRIANGLE_TESTS, traverse.STACK_BUCKETS):
            for clipped in ({}, {"EXACT_LEAVES": 0}):
                add(instances.KERNEL_FILE, {**traverse.kernel_defines(ctx, any_hit, test, counters,
                                                                      stack), **clipped})
    # winding.cl: one stack size per bucket, the points in their order or sorted, through
    # binary nodes and wide records of either width
    for ctx, stack, ordered in itertools.product(ctxs, traverse.STACK_BUCKETS, (0, 1)):
        add(winding.KERNEL_FILE, {"STACK_SIZE": stack, "POINT_ORDER": ordered,
                                  **winding.kernel_defines(ctx)})
        for width in wide.WIDTHS:
            add(winding.KERNEL_FILE, {"STACK_SIZE": stack, "POINT_ORDER": ordered, "WIDE": 1,
                                      "WIDTH": width, **wide.lane_defines(ctx),
                                      **winding.kernel_defines(ctx)})
    # winding_moments.cl: the order the trees keep, into one row per node or the rows of
    # wide records of either width
    for width in (None, *wide.WIDTHS):
        add(winding_moments.KERNEL_FILE,
            winding_moments.kernel_defines(winding_moments.DEFAULT_ORDER, width))
    # closest.cl: one stack size per bucket (NO_FP64 is for tests only), through binary
    # nodes and wide records of either width
    for ctx, stack, ordered in itertools.product(ctxs, traverse.STACK_BUCKETS, (0, 1)):
        add(closest.KERNEL_FILE, {"STACK_SIZE": stack, "POINT_ORDER": ordered})
        for width in wide.WIDTHS:
            add(closest.KERNEL_FILE, {"STACK_SIZE": stack, "POINT_ORDER": ordered, "WIDE": 1,
                                      "WIDTH": width, **wide.lane_defines(ctx)})
    # instance_closest.cl: closest points through a scene, as closest.cl's
    for stack, ordered in itertools.product(traverse.STACK_BUCKETS, (0, 1)):
        add(instance_closest.KERNEL_FILE, {"STACK_SIZE": stack, "POINT_ORDER": ordered})
    return list(out.values())


def variants_for(ctx) -> list[Variant]:
    """The variants one :class:`lbvh.device.Context` can compile."""
    exact = bool(ctx.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT)
    return kernel_variants(ctx.is_cpu, exact_divide=exact,
                           compiler_is_clang=ctx.compiler_is_clang)


def conditional_defines(source: str) -> set[str]:
    """Names tested by the preprocessor (``#if``, ``#elif``, ``#ifdef``,
    ``defined(...)``) in a kernel source: the defines that select code, as
    opposed to those that only give a value (an array size, a literal).
    ``#ifndef NAME`` is left out: the kernels use it for include guards and for
    a define's default value (``#ifndef X`` / ``#define X ...``), which every
    variant that passes ``X`` overrides."""
    names = set()
    for line in source.splitlines():
        m = re.match(r"\s*#\s*(if|elif|ifdef)\b(.*)", line)
        if m:
            names |= set(re.findall(r"[A-Za-z_]\w*", m.group(2))) - {"defined"}
    return names


def covering_variants(variants: list[Variant], sources: dict[str, str],
                      value_only: Iterable[str] = ("STACK_SIZE",),
                      strength: int | None = None) -> list[Variant]:
    """A subset of ``variants``: every combination of the defines other than
    ``value_only``, each with one value of the ``value_only`` defines, chosen so
    that every value of each is compiled at least once.

    ``strength`` t (``None``: every combination) keeps, of the combinations of a
    file's code-selecting defines, a greedy covering array of strength t: every
    set of t (define, value) pairs that some variant of the file holds is held by
    a kept one (Cohen et al. 1997, AETG's greedy choice). Interactions of more than
    t switches are then not all compiled: the full product is the default.

    ``value_only`` names defines that only give a value (traverse.cl's
    STACK_SIZE sizes its private stack arrays; SLAB_PAD is a float literal):
    they multiply the variants without selecting other code. A name that the
    preprocessor tests in a file's source or in a header of ``sources``
    (:func:`conditional_defines`) raises ``ValueError``: it selects code, and
    every one of its values must be compiled with every other combination.
    """
    value_only = tuple(value_only)
    header = "".join(text for name, text in sources.items() if name.endswith(".h"))
    picked: dict[tuple, Variant] = {}
    groups: dict[tuple, list[Variant]] = {}
    for filename, defines in variants:
        code = (filename, tuple((k, v) for k, v in defines.items() if k not in value_only))
        groups.setdefault(code, []).append((filename, defines))
    files = {filename for filename, _ in variants}
    for filename in sorted(files):
        tested = conditional_defines(sources[filename] + header) & set(value_only)
        if tested:
            raise ValueError(f"{filename}: {', '.join(sorted(tested))} selects code "
                             "(tested by the preprocessor): not a value-only define")

    def values(v: Variant) -> set[tuple]:
        return {(v[0], k, val) for k, val in v[1].items() if k in value_only}

    if strength is not None:
        groups = {code: groups[code] for code in _strength_cover(list(groups), strength)}
    used: dict[tuple, int] = {}   # how often each value-only value was picked: round robin
    for members in groups.values():
        best = min(members, key=lambda v: sum(used.get(x, 0) for x in values(v)))
        picked[variant_key(*best)] = best
        for x in values(best):
            used[x] = used.get(x, 0) + 1
    for members in groups.values():   # values no pick brought (more values than groups)
        for v in members:
            if values(v) - set(used):
                picked[variant_key(*v)] = v
                used.update((x, 1) for x in values(v))
    return list(picked.values())


def _strength_cover(codes: list[tuple], strength: int) -> list[tuple]:
    """Of ``codes`` ``(filename, ((define, value), ...))``, a subset in which every
    ``strength`` pairs held together by some code of a file are held together by a
    kept one: the greedy choice, the code that holds most uncovered sets first
    (ties to the earlier code, so the choice is the same on every run)."""
    if strength < 1:
        raise ValueError(f"strength must be at least 1, not {strength}")
    kept: list[tuple] = []
    for filename in sorted({code[0] for code in codes}):
        mine = [code for code in codes if code[0] == filename]
        sets = {code: set(itertools.combinations(code[1], min(strength, len(code[1]))))
                for code in mine}
        needed = set().union(*sets.values())
        while needed:
            best = max(mine, key=lambda code: len(sets[code] & needed))
            kept.append(best)
            needed -= sets[best]
    return kept
