"""Running the hard cases: each case (:mod:`lbvh.verification.hard_cases`) built
by each builder of :data:`BUILDERS`, its tree checked, its rays traced and the
answers judged by the rules (:mod:`lbvh.verification.rules`): one
:class:`~lbvh.verification.rules.Outcome` per case and builder.
"""
from __future__ import annotations

import time
from typing import Any, Iterable

import numpy as np

from ..api import build
from ..layout import node_depths
from ..queries.traverse import stack_need, stack_size_for
from . import hard_cases
from .hard_cases import Case
from .rules import Judge, Outcome, compare_any, compare_closest, reference

#: Builders by the names ``--builders`` takes: the options given to :func:`lbvh.build`.
BUILDERS: dict[str, dict[str, Any]] = {
    "lbvh30": {"builder": "lbvh", "key_bits": 30},
    "lbvh63": {"builder": "lbvh", "key_bits": 63},
    "lbvh-auto": {"builder": "lbvh", "key_bits": "auto"},
    "lbvh30-collapse": {"builder": "lbvh", "key_bits": 30, "collapse": True},
    "lbvh63-collapse": {"builder": "lbvh", "key_bits": 63, "collapse": True},
    "lbvh-auto-collapse": {"builder": "lbvh", "key_bits": "auto", "collapse": True},
    "lbvh-auto-treelets": {"builder": "lbvh", "key_bits": "auto", "treelet_rounds": 2},
    "sah": {"builder": "sah"},
    # the SAH reference costed by a sample of rays (lbvh/builders/ray_sampled.py): the
    # case's own rays, or rays through the mesh's vertices (build_with)
    "sah-rays": {"builder": "sah", "rays": "the case's rays"},
    "median": {"builder": "median"},
    "midpoint": {"builder": "midpoint"},
    "sbvh": {"builder": "sbvh"},
    "ploc": {"builder": "ploc"},
}

#: Builders that cannot run a case in reasonable time, with the reason (reported, not run).
SKIPS: dict[tuple[str, str], str] = {
    ("over_2_24_triangles", "sah"): "the serial SAH would need an estimated 20+ minutes and "
                                    "10+ GB for 2^24 triangles (it takes 149 s and 1.4 GB "
                                    "for 2^21)",
    ("over_2_24_triangles", "sah-rays"): "the serial SAH would need an estimated 20+ minutes "
                                         "and 10+ GB for 2^24 triangles",
    ("over_2_24_triangles", "median"): "the host reference's sorts of 2^24 centres per level "
                                       "would need 10+ GB (its device counterpart is the LBVH)",
    ("over_2_24_triangles", "midpoint"): "the host reference's sorts of 2^24 centres per level "
                                         "would need 10+ GB (its device counterpart is the LBVH)",
    ("over_2_24_triangles", "sbvh"): "the host SBVH builds about 5,000 triangles a second: "
                                     "an hour for 2^24",
}


#: At most this many of a case's rays sample the ray-sampled SAH (``"sah-rays"``).
SAMPLE_RAYS = 4096


def build_with(builder: str, vertices: np.ndarray, faces: np.ndarray, origins: Any = None,
               directions: Any = None, device: Any = None) -> Any:
    """:func:`lbvh.build` with the options of ``BUILDERS[builder]``; ``"sah-rays"`` takes
    its sample from the rays given (at most :data:`SAMPLE_RAYS` of those with a finite,
    non-zero direction and a finite origin), else rays from the centre of the mesh's box
    through its vertices."""
    options = dict(BUILDERS[builder])
    if "rays" in options:
        sample = None
        if origins is not None:
            o, d = np.asarray(origins, np.float32), np.asarray(directions, np.float32)
            good = np.isfinite(o).all(axis=1) & np.isfinite(d).all(axis=1) & (d != 0).any(axis=1)
            if good.any():
                sample = o[good][:SAMPLE_RAYS], d[good][:SAMPLE_RAYS]
        if sample is None:   # rays from the box's centre through vertices
            v = np.asarray(vertices, np.float64)
            centre = (v.min(axis=0) + v.max(axis=0)) / 2
            with np.errstate(over="ignore", invalid="ignore"):
                d = (v[:SAMPLE_RAYS] - centre).astype(np.float32)
            d = d[np.isfinite(d).all(axis=1) & (d != 0).any(axis=1)]
            if not len(d):
                d = np.float32([[1, 0, 0]])
            sample = np.tile(centre.astype(np.float32), (len(d), 1)), d
        options["rays"] = sample
    return build(vertices, faces, device=device, **options)


def _nonfinite_boxes(bvh: Any) -> int:
    finite = np.isfinite(bvh.nodes["lower"]).all(axis=1) & np.isfinite(bvh.nodes["upper"]).all(axis=1)
    return int((~finite).sum())


def run_case(case: Case, builder: str, judge: Judge | None = None, device: Any = None,
             bvh_out: list | None = None) -> Outcome:
    """Build ``case`` with ``builder`` (a key of :data:`BUILDERS`) and check every rule.

    ``judge`` is ``Judge(case, reference(case))`` (made if not given). With
    ``bvh_out`` (a list) the tree is appended to it, for callers that test more.
    """

    if builder not in BUILDERS:
        raise ValueError(f"unknown builder {builder!r}; known: {', '.join(BUILDERS)}")
    out = Outcome(case.name, builder, hard_cases.ISSUE_CASE.get(case.name, 0),
                  len(case.faces), case.num_rays)
    if (case.name, builder) in SKIPS:
        out.skipped = SKIPS[(case.name, builder)]
        return out
    try:
        start = time.perf_counter()
        bvh = build_with(builder, case.vertices, case.faces, case.origins, case.directions,
                         device)
        out.build_seconds = time.perf_counter() - start
    except Exception as exc:  # a failed build is a result to report, not a crash
        out.error = f"build raised {type(exc).__name__}: {exc}"
        return out
    if bvh_out is not None:
        bvh_out.append(bvh)
    try:
        bvh.validate()
    except ValueError as exc:
        out.validate_error = str(exc)
    out.nonfinite_boxes = _nonfinite_boxes(bvh)
    out.forced_stack = case.stack_size is not None
    out.tree_stack = stack_size_for(bvh.query_data)
    out.stack = case.stack_size if out.forced_stack else out.tree_stack
    out.stack_need = stack_need(bvh.query_data)
    out.depth = int(node_depths(bvh.tree.read("parent"), bvh.root).max()) if bvh.tree.num_nodes > 1 else 0
    if out.validate_error:  # tracing a broken tree proves nothing more
        return out
    judge = Judge(case, reference(case)) if judge is None else judge
    try:
        _trace_and_compare(case, bvh, judge, out)
    except Exception as exc:
        out.error = f"query raised {type(exc).__name__}: {exc}"
    return out


def _trace_and_compare(case: Case, bvh: Any, judge: Judge, out: Outcome) -> None:
    options = {"stack_size": case.stack_size} if case.stack_size is not None else {}
    rays = (case.origins, case.directions, case.tmin, case.tmax)
    closest = bvh.intersect(*rays, **options)
    any_hit = bvh.occluded(*rays, return_hits=True, **options)
    out.overflow = int(closest.overflow_count)
    out.any_hit_overflow = int(any_hit.overflow_count)
    agreement = compare_closest(judge, closest.prim, closest.t, closest.overflow)
    out.mismatches = int(agreement.wrong.sum())
    out.ambiguous = agreement.ambiguous
    out.worst_rel_t = agreement.worst_rel_t
    out.worst_t_over_bound = agreement.worst_t_over_bound
    out.first_mismatch = agreement.first
    out.any_hit_mismatches = int(compare_any(judge, any_hit.prim, any_hit.t,
                                             any_hit.overflow).sum())
    if case.must_hit is not None:
        out.leaks = int((case.must_hit & ~closest.hit & ~closest.overflow).sum())


def run(case_names: Iterable[str], builders: Iterable[str], device: Any = None,
        progress=None) -> list[Outcome]:
    """Every case by every builder; ``progress(outcome)`` is called after each."""
    outcomes = []
    builders = list(builders)
    for name in case_names:
        case = hard_cases.make(name)
        judge = None
        for builder in builders:
            if judge is None and (case.name, builder) not in SKIPS:
                judge = Judge(case, reference(case))
            outcome = run_case(case, builder, judge, device)
            outcomes.append(outcome)
            if progress is not None:
                progress(outcome)
    return outcomes


def warm_up(builders: list[str], device: Any = None) -> None:
    """Build and trace two triangles with each builder, so that the kernels are
    compiled before anything is timed (through :func:`build_with`, as the cases are:
    ``"sah-rays"`` needs its sample made)."""

    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.uint32([[0, 1, 2], [0, 1, 3]])
    for builder in builders:
        bvh = build_with(builder, v, f, device=device)
        bvh.intersect(v[:1] - 1, np.float32([[1, 1, 1]]))
        bvh.occluded(v[:1] - 1, np.float32([[1, 1, 1]]))
