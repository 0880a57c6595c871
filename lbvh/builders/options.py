"""Options of the builders and optimisers, as data with documented defaults.

Each builder and optimiser takes one frozen options object; its fields are
checked when it is made, so a bad value is refused before anything is
uploaded. :func:`options_from` turns ``lbvh.build``'s keyword arguments into
them: the one place where an unknown name is refused.

=============================  =====================================================
options                        for
=============================  =====================================================
:class:`LBVHOptions`           ``builder="lbvh"``: the device pipeline (Karras 2012)
                               and its treelet restructuring (Karras & Aila 2013)
:class:`SAHOptions`            ``builder="sah"``: the serial full-sweep SAH reference
:class:`SplitOptions`          ``builder="median"`` and ``"midpoint"``: the course's
                               top-down object splits (:mod:`lbvh.builders.topdown`)
:class:`SBVHOptions`           ``builder="sbvh"``: spatial splits (Stich et al. 2009,
                               :mod:`lbvh.builders.sbvh`)
:class:`PLOCOptions`           ``builder="ploc"``: bottom-up clustering on the device
                               (Meister & Bittner 2018, :mod:`lbvh.builders.ploc`)
:class:`CollapseOptions`       ``collapse=True``: the leaf collapse after an LBVH build
=============================  =====================================================
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..metrics.cost import C_NODE, C_TRI, MAX_LEAF_SIZE, check_sah_constants
from .morton import AUTO_DUPLICATE_FRACTION
from .ray_sampled import as_ray_sample
from .restructure import (TREELET_LEAVES, TREELET_MIN_LEAVES, check_min_leaves, check_rounds,
                          check_treelet_leaves)

#: ``key_bits`` as the caller gives it -> bits of a key (``None``: chosen per mesh).
KEY_CHOICES = {"auto": None, 30: 32, 63: 64, "30": 32, "63": 64}

BUILDERS = ("lbvh", "sah", "median", "midpoint", "sbvh", "ploc")
#: The host builders that split top down without a cost model.
SPLIT_BUILDERS = ("median", "midpoint")


@dataclass(frozen=True)
class LBVHOptions:
    """The device LBVH build.

    Attributes:
        key_bits: ``30`` (``uint32`` keys), ``63`` (``uint64`` keys) or ``"auto"``
            (default): 30 bits unless more than ``auto_duplicate_fraction`` of the
            30-bit codes are duplicates.
        auto_duplicate_fraction: the threshold of ``"auto"`` (default 0.5).
        treelet_rounds: rounds of treelet restructuring after the refit (default 0:
            the Karras 2012 tree); each lowers the SAH cost for a longer build.
        treelet_leaves: leaves per treelet, 3 to 7 (default 7, as Karras & Aila):
            a round with 5 costs about a third of one with 7 and on the bench
            scenes gives most of its gain.
        treelet_min_leaves: after the first round, rebuild only the treelets of
            subtrees with at least this many leaves, doubled in each further round
            (default 14; 0: every treelet in every round). The first round has
            rebuilt the lower levels; see :func:`lbvh.builders.restructure.round_min_leaves`.
    """
    key_bits: int | str = "auto"
    auto_duplicate_fraction: float = AUTO_DUPLICATE_FRACTION
    treelet_rounds: int = 0
    treelet_leaves: int = TREELET_LEAVES
    treelet_min_leaves: int = TREELET_MIN_LEAVES

    def __post_init__(self) -> None:
        try:
            KEY_CHOICES[self.key_bits]
        except (KeyError, TypeError):
            raise ValueError(f"key_bits: {self.key_bits!r}; expected 30, 63 or 'auto'") from None
        check_rounds(self.treelet_rounds)
        check_treelet_leaves(self.treelet_leaves)
        check_min_leaves(self.treelet_min_leaves)

    @property
    def wanted_bits(self) -> int | None:
        """Bits of a key asked for (32 or 64), or ``None`` for ``"auto"``."""
        return KEY_CHOICES[self.key_bits]


@dataclass(frozen=True)
class SAHOptions:
    """The serial SAH reference: cost of a node visit ``c_node`` (default
    :data:`~lbvh.metrics.cost.C_NODE`), of a triangle test ``c_tri``
    (:data:`~lbvh.metrics.cost.C_TRI`), largest leaf ``max_leaf_size``
    (:data:`~lbvh.metrics.cost.MAX_LEAF_SIZE`; bigger nodes are always split).

    ``rays`` (default ``None``: the SAH's areas): a sample of the rays the tree
    will trace, a :class:`~lbvh.builders.ray_sampled.RaySample` or an ``(origins,
    directions)`` pair; splits are then costed by the fraction of those rays
    that enter each side (Nabata et al. 2013, :mod:`lbvh.builders.ray_sampled`),
    smoothed towards the area ratio by ``ray_prior`` pseudo-rays (default 16),
    over ``ray_candidates`` candidates per axis (default 32: 16 evenly spaced and
    the 16 cheapest by area) in nodes that sample rays enter. ``lbvh.build`` ends each ray at its closest
    hit in the mesh's default LBVH first (its time is in the build's)."""
    c_node: float = C_NODE
    c_tri: float = C_TRI
    max_leaf_size: int = MAX_LEAF_SIZE
    rays: Any = None
    ray_prior: float = 16.0
    ray_candidates: int = 32

    def __post_init__(self) -> None:
        check_sah_constants(self.c_node, self.c_tri, self.max_leaf_size)
        object.__setattr__(self, "rays", as_ray_sample(self.rays))
        if isinstance(self.ray_prior, bool) or not isinstance(self.ray_prior, (int, float)) \
                or not 0 < self.ray_prior < np.inf:
            raise ValueError(f"ray_prior: {self.ray_prior!r}; expected a finite number > 0")
        if isinstance(self.ray_candidates, bool) \
                or not isinstance(self.ray_candidates, (int, np.integer)) \
                or not 2 <= self.ray_candidates <= 1 << 16:
            raise ValueError(f"ray_candidates: {self.ray_candidates!r}; expected an integer "
                             "in [2, 65536]")


@dataclass(frozen=True)
class SplitOptions:
    """The median and midpoint builders: nodes of at most ``max_leaf_size``
    primitives are leaves (default 1, as the LBVH's)."""
    max_leaf_size: int = 1

    def __post_init__(self) -> None:
        check_sah_constants(C_NODE, C_TRI, self.max_leaf_size)


@dataclass(frozen=True)
class SBVHOptions:
    """The SBVH (spatial splits): the SAH constants and largest leaf of
    :class:`SAHOptions`; ``alpha`` (default ``1e-5``, Stich et al.'s): spatial splits
    are tried where the best object split's sides overlap by more than ``alpha``
    times the root's area; ``bins`` (32): slabs per axis of a spatial split;
    ``max_growth`` (2.0): spatial splits stop once the references reach this many
    times the triangles; ``object_below`` (16): a node of at most this many
    references gets object splits only (the SAH reference's sweep): on the bunny
    3.3x faster to build than spatial splits down to the leaves, for an SAH cost
    0.01% higher."""
    c_node: float = C_NODE
    c_tri: float = C_TRI
    max_leaf_size: int = MAX_LEAF_SIZE
    alpha: float = 1e-5
    bins: int = 32
    max_growth: float = 2.0
    object_below: int = 16

    def __post_init__(self) -> None:
        check_sah_constants(self.c_node, self.c_tri, self.max_leaf_size)
        if not (isinstance(self.alpha, (int, float)) and 0 <= self.alpha <= 1):
            raise ValueError(f"alpha: {self.alpha!r}; expected a number in [0, 1]")
        if isinstance(self.bins, bool) or not isinstance(self.bins, (int, np.integer)) \
                or not 2 <= self.bins <= 1024:
            raise ValueError(f"bins: {self.bins!r}; expected an integer in [2, 1024]")
        if not (isinstance(self.max_growth, (int, float)) and self.max_growth >= 1):
            raise ValueError(f"max_growth: {self.max_growth!r}; expected a number >= 1")
        if isinstance(self.object_below, bool) or not isinstance(self.object_below, (int, np.integer)) \
                or self.object_below < 1:
            raise ValueError(f"object_below: {self.object_below!r}; expected an integer >= 1")


#: PLOC's search radius by default (bench/bench_ploc.py compares radii).
PLOC_RADIUS = 16
#: The largest search radius: each cluster tries 2 * radius candidates in every step
#: (one compile per radius: kernels/ploc.cl's RADIUS).
PLOC_MAX_RADIUS = 256


@dataclass(frozen=True)
class PLOCOptions:
    """The device PLOC build (Meister & Bittner 2018, :mod:`lbvh.builders.ploc`).

    Attributes:
        radius: each cluster looks for its nearest neighbour among this many
            clusters on either side in Morton order (default 16; an integer from
            1 to 256). A larger radius finds better pairs (most often a lower SAH
            cost) for a longer build.

    The leaves are single triangles sorted by 63-bit Morton codes (``key_bits``
    is not an option of this builder: 30 is refused, ``"auto"`` and 63 are the
    same here).
    """
    radius: int = PLOC_RADIUS

    def __post_init__(self) -> None:
        if isinstance(self.radius, bool) or not isinstance(self.radius, (int, np.integer)) \
                or not 1 <= self.radius <= PLOC_MAX_RADIUS:
            raise ValueError(f"radius: {self.radius!r}; expected an integer from 1 to "
                             f"{PLOC_MAX_RADIUS}")


@dataclass(frozen=True)
class CollapseOptions:
    """The leaf collapse: the same SAH constants as :class:`SAHOptions`;
    ``max_leaf_size`` is the largest leaf it makes (existing leaves stay)."""
    c_node: float = C_NODE
    c_tri: float = C_TRI
    max_leaf_size: int = MAX_LEAF_SIZE

    def __post_init__(self) -> None:
        check_sah_constants(self.c_node, self.c_tri, self.max_leaf_size)


def field_names(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def make(cls: type, given: dict[str, Any], what: str) -> Any:
    """``cls(**given)``, refusing unknown names with ``what`` in the message."""
    unknown = set(given) - field_names(cls)
    if unknown:
        raise ValueError(f"unknown option(s) for {what}: {', '.join(sorted(unknown))}")
    return cls(**given)


def options_from(builder: str, collapse: "bool | CollapseOptions", given: dict[str, Any],
                 options: "LBVHOptions | SAHOptions | SplitOptions | PLOCOptions | None" = None
                 ) -> tuple[LBVHOptions | SAHOptions | SplitOptions | PLOCOptions,
                            CollapseOptions | None]:
    """The options objects of ``lbvh.build(builder=..., collapse=..., options=..., **given)``.

    ``options`` (an options object of the builder) and ``collapse`` (``True``
    or a :class:`CollapseOptions`) may be given as data; otherwise, with
    ``builder="lbvh"`` the names of :class:`LBVHOptions` in ``given`` go to
    the build and, with ``collapse``, the others to :class:`CollapseOptions`;
    with ``builder="sah"`` all go to :class:`SAHOptions`, with ``"median"`` or
    ``"midpoint"`` to :class:`SplitOptions`, with ``"ploc"`` to :class:`PLOCOptions`
    (the LBVH's options checked and dropped, as for the host builders). Raises
    ``ValueError`` on an unknown builder or name, a bad value, an option of the other
    builder, or the same option given both ways.
    """
    if builder not in BUILDERS:
        raise ValueError(f"builder: {builder!r}; expected one of {', '.join(BUILDERS)}")
    expected = {"lbvh": LBVHOptions, "sah": SAHOptions, "sbvh": SBVHOptions,
                "ploc": PLOCOptions}.get(builder, SplitOptions)
    if options is not None:
        if not isinstance(options, expected):
            raise ValueError(f"options: {type(options).__name__} given; builder={builder!r} "
                             f"takes {expected.__name__}")
        clash = set(given) & field_names(expected)
        if clash:
            raise ValueError(f"{', '.join(sorted(clash))}: given both in options and as a "
                             "keyword")
        given = {**{f.name: getattr(options, f.name) for f in dataclasses.fields(options)},
                 **given}
    if isinstance(collapse, CollapseOptions):
        if builder != "lbvh":
            raise ValueError("collapse: only for builder='lbvh' (the SAH builder already makes "
                             "multi-triangle leaves)")
        own = LBVHOptions(**{k: v for k, v in given.items() if k in field_names(LBVHOptions)})
        rest = set(given) - field_names(LBVHOptions)
        if rest:
            raise ValueError(f"unknown option(s) for the lbvh builder: {', '.join(sorted(rest))} "
                             "(the collapse's options are in collapse=CollapseOptions(...))")
        return own, collapse
    if not isinstance(collapse, (bool, np.bool_)):
        raise ValueError(f"collapse: {collapse!r}; expected True, False or a CollapseOptions")
    if builder == "sbvh" or builder in SPLIT_BUILDERS:
        if collapse:
            raise ValueError(f"collapse: only for builder='lbvh' (the {builder} builder makes "
                             "leaves of max_leaf_size)")
        _host_builder_ignores_lbvh_options(builder, given)
        cls = SBVHOptions if builder == "sbvh" else SplitOptions
        return make(cls, given, f"the {builder} builder"), None
    if builder == "ploc":
        if collapse:
            raise ValueError("collapse: only for builder='lbvh' (collapse a PLOC tree's leaves "
                             "with lbvh.api.collapse_leaves(bvh))")
        key_bits = given.get("key_bits", "auto")
        _host_builder_ignores_lbvh_options("ploc", given)   # checks key_bits
        if KEY_CHOICES[key_bits] == 32:
            raise ValueError(f"key_bits: {key_bits!r}; the ploc builder sorts 63-bit Morton "
                             "codes (63 or 'auto')")
        return make(PLOCOptions, given, "the ploc builder"), None
    if builder == "sah":
        if collapse:
            raise ValueError("collapse: only for builder='lbvh' (the SAH builder already makes "
                             "multi-triangle leaves)")
        _host_builder_ignores_lbvh_options("sah", given)
        return make(SAHOptions, given, "the sah builder"), None
    own = {k: v for k, v in given.items() if k in field_names(LBVHOptions)}
    rest = {k: v for k, v in given.items() if k not in own}
    options = LBVHOptions(**own)
    if not collapse:
        if rest:
            raise ValueError(f"unknown option(s) for the lbvh builder: {', '.join(sorted(rest))}")
        return options, None
    return options, make(CollapseOptions, rest, "the leaf collapse")


def _host_builder_ignores_lbvh_options(builder: str, given: dict[str, Any]) -> None:
    """The LBVH's own options, given to another builder (the command line passes its
    defaults to every builder): checked, then dropped from ``given``; treelet rounds,
    which would change the tree, are refused."""
    lbvh_only = LBVHOptions(**{k: given.pop(k) for k in field_names(LBVHOptions) & set(given)})
    if lbvh_only.treelet_rounds:
        raise ValueError(f"treelet_rounds: only for builder='lbvh' (the {builder} builder's "
                         "tree is its own)")
