"""How a query runs, as data: :class:`QueryOptions`, one value every ray query takes.

The ray queries of :class:`lbvh.BVH` and :class:`lbvh.Scene` (``intersect``,
``occluded``, their ``_async`` forms, ``count_hits``, ``all_hits``) take
``options=QueryOptions(...)`` or the same fields as keywords
(``bvh.intersect(o, d, invalid_rays="miss")``); a keyword given beside ``options``
replaces that field. Each query reads the fields it has a use for and refuses the
others by name (``count_hits`` has no triangle test to choose). The defaults are the
documented ones below, in this one place.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .rays import InvalidRays, check_invalid_rays

#: The ray-triangle tests: Woop et al. 2013's watertight test, or Moller & Trumbore 1997.
TRIANGLE_TESTS = {"watertight": 0, "moller": 1}
TriangleTest = Literal["watertight", "moller"]

#: The order of a closest-hit traversal: "ordered" (depth first, the nearest child
#: first; default) or "global" (the nearest pending node of all, from a heap: Kay &
#: Kajiya 1986).
NODE_ORDERS = {"ordered": 0, "global": 1}
NodeOrder = Literal["ordered", "global"]


@dataclass(frozen=True)
class QueryOptions:
    """How a ray query runs.

    Attributes:
        invalid_rays: ``"raise"`` (default): a bad ray (NaN, infinite or beyond-float32
            components, a zero-length direction, a NaN, negative or infinite ``tmin``,
            a NaN ``tmax``, ``tmin > tmax``) raises ``ValueError`` naming the first one.
            ``"miss"``: bad rays are not traced and come back as misses, flagged in the
            answer's ``invalid``.
        triangle_test: ``"watertight"`` (Woop et al. 2013, default) or ``"moller"``
            (Moller-Trumbore); closest and any hit only.
        counters: also return the nodes visited and triangles tested per ray (default
            ``False``); closest and any hit only.
        batch_size: rays per kernel launch of host arrays (``None``, default: the
            query's own, :data:`lbvh.queries.traverse.DEFAULT_BATCH` or
            :data:`lbvh.queries.all_hits.DEFAULT_BATCH`).
        stack_size: the traversal stack's size (``None``, default: chosen from the
            tree's depth; tests set it); closest and any hit only.
        order: ``"ordered"`` (default): depth first, the nearest child first;
            ``"global"``: always the nearest pending node of all (a heap, Kay & Kajiya
            1986). The same hits; closest hit only.
    """
    invalid_rays: InvalidRays = "raise"
    triangle_test: TriangleTest = "watertight"
    counters: bool = False
    batch_size: int | None = None
    stack_size: int | None = None
    order: NodeOrder = "ordered"

    def __post_init__(self) -> None:
        check_invalid_rays(self.invalid_rays)
        if not isinstance(self.triangle_test, str) or self.triangle_test not in TRIANGLE_TESTS:
            raise ValueError(f"triangle_test: {self.triangle_test!r}; expected one of "
                             f"{', '.join(TRIANGLE_TESTS)}")
        if not isinstance(self.order, str) or self.order not in NODE_ORDERS:
            raise ValueError(f"order: {self.order!r}; expected one of {', '.join(NODE_ORDERS)}")
        if not isinstance(self.counters, bool):
            raise ValueError(f"counters: {self.counters!r}; expected True or False")
        if self.batch_size is not None:
            check_positive("batch_size", self.batch_size)
        if self.stack_size is not None:
            check_positive("stack_size", self.stack_size)

    def batch(self, default: int) -> int:
        """The rays per launch: ``batch_size``, or the query's ``default``."""
        return int(self.batch_size) if self.batch_size is not None else default


#: The fields each kind of query reads; the others are refused by name.
FIELDS_OF = {
    "intersect": ("invalid_rays", "triangle_test", "counters", "batch_size", "stack_size",
                  "order"),
    "occluded": ("invalid_rays", "triangle_test", "counters", "batch_size", "stack_size"),
    "scene_intersect": ("invalid_rays", "triangle_test", "counters", "batch_size", "order"),
    "scene_occluded": ("invalid_rays", "triangle_test", "batch_size"),
    "hits": ("invalid_rays", "batch_size"),
    # rays already checked and on the device (lbvh.queries.traverse.trace_buffers)
    "trace": ("triangle_test", "counters", "stack_size", "order"),
}


def check_positive(name: str, value: Any) -> int:
    """A positive integer option (``bool`` is not one)."""
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise ValueError(f"{name}: {value!r}; expected a positive integer")
    return int(value)


_DEFAULT = QueryOptions()
_NAMES = tuple(f.name for f in dataclasses.fields(QueryOptions))
#: The fields each query refuses: those it does not read.
_REFUSED = {query: tuple(n for n in _NAMES if n not in allowed)
            for query, allowed in FIELDS_OF.items()}


def query_options(query: str, options: QueryOptions | None, fields: dict[str, Any]
                  ) -> QueryOptions:
    """The options of one call of ``query`` (a key of :data:`FIELDS_OF`): ``options``
    (``None``: the defaults) with the keyword ``fields`` in place of its own. A field
    the query does not read, given either way, raises ``TypeError`` naming it (as an
    unknown keyword does); a bad value raises ``ValueError``. (The defaults alone, the
    common call, cost a dictionary lookup: a call of one ray takes 200 us.)"""
    if options is None and not fields:
        return _DEFAULT
    if options is not None and not isinstance(options, QueryOptions):
        raise TypeError(f"options: a {type(options).__name__}; expected lbvh.QueryOptions")
    allowed = FIELDS_OF[query]
    for name in fields:
        if name not in _NAMES:
            raise TypeError(f"{query}() got an unexpected keyword argument {name!r} "
                            f"(options: {', '.join(allowed)})")
    base = options or _DEFAULT
    merged = dataclasses.replace(base, **fields) if fields else base
    for name in _REFUSED[query]:
        if getattr(merged, name) != getattr(_DEFAULT, name):
            raise TypeError(f"{query}: the option {name!r} does not apply "
                            f"(options: {', '.join(allowed)})")
    return merged
