"""``lbvh check``: the command line and its table (the hard-case suite run by every builder).

The rules a case must meet are in :mod:`lbvh.verification.rules` (``python -m
pydoc lbvh.verification.rules``), the float32 error analysis behind them in
:mod:`lbvh.verification.error_analysis`, the running of cases and builders in
:mod:`lbvh.verification.runner`, the cases in :mod:`lbvh.verification.hard_cases`.

In the table, ``wrong`` counts rays with a wrong answer (closest hit, any hit,
and leaks), ``ambig`` rays whose answer differs from the oracle's but is right
within float32 rounding (ties on shared edges and vertices, grazing hits, thin
triangles: :class:`~lbvh.verification.rules.Judge`); ``worst rel dt`` is the
largest ``|t - t_ref| / t_ref`` over rays that hit the reference's triangle at
least 1/1000 of the scene's extent from their origin; ``dt/bound`` the largest
ratio of the error to the bound.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict

from . import hard_cases
from ..progress import bar as progress_bar
from .rules import Outcome
from .runner import BUILDERS, run, warm_up

#: Cases ``--quick`` leaves out (the slowest oracle comparisons); slow cases need ``--large``.
QUICK_SKIPS = ("identical_triangles", "closed_cube_vertices_edges", "closed_sphere_stack2")


COLUMNS = ("case", "builder", "result", "build ms", "depth", "stack", "overflow", "wrong",
           "ambig", "worst rel dt", "dt/bound")
WIDTHS = [28, 18, 7, 9, 5, 5, 8, 6, 6, 12, 8]


def _row(o: Outcome) -> tuple[str, ...]:
    if o.skipped:
        return (o.case, o.builder, "skipped") + ("",) * (len(COLUMNS) - 3)
    result = "passed" if o.passed else "FAILED"
    stack = f"{o.stack}{'*' if o.forced_stack else ''}" if o.stack >= 0 else ""
    return (o.case, o.builder, result, f"{o.build_seconds * 1e3:.1f}",
            str(o.depth) if o.depth >= 0 else "", stack,
            str(o.overflow + o.any_hit_overflow),
            str(o.mismatches + o.any_hit_mismatches + o.leaks), str(o.ambiguous),
            f"{o.worst_rel_t:.2e}", f"{o.worst_t_over_bound:.3f}")


def format_row(o: Outcome, widths: list[int] = WIDTHS) -> str:
    return "  ".join(cell.ljust(w) for cell, w in zip(_row(o), widths)).rstrip()


def totals(outcomes: list[Outcome]) -> dict[str, dict[str, int]]:
    """``{builder: {"passed": n, "failed": n, "skipped": n}}``."""
    out: dict[str, dict[str, int]] = {}
    for o in outcomes:
        t = out.setdefault(o.builder, {"passed": 0, "failed": 0, "skipped": 0})
        t["skipped" if o.skipped else "passed" if o.passed else "failed"] += 1
    return out


def format_totals(outcomes: list[Outcome]) -> str:
    lines = []
    for builder, t in totals(outcomes).items():
        skipped = f", {t['skipped']} skipped" if t["skipped"] else ""
        lines.append(f"{builder:18s} {t['passed']} passed, {t['failed']} failed{skipped}")
    return "\n".join(lines)


def select_cases(names: list[str] | None, quick: bool, large: bool) -> list[str]:
    """The case names to run: those asked for (all by default), less slow ones
    without ``large`` and the slowest oracle comparisons with ``quick``."""
    if names:
        for name in names:
            if name not in hard_cases.CASES:
                raise ValueError(f"--cases: unknown case {name!r}; known: "
                                 f"{', '.join(hard_cases.CASES)}")
        return list(names)
    chosen = []
    for name in hard_cases.CASES:
        if name == "over_2_24_triangles" and not large:
            continue
        if quick and name in QUICK_SKIPS:
            continue
        chosen.append(name)
    return chosen


def select_builders(names: list[str] | None) -> list[str]:
    if not names:
        return list(BUILDERS)
    for name in names:
        if name not in BUILDERS:
            raise ValueError(f"--builders: unknown builder {name!r}; known: {', '.join(BUILDERS)}")
    return list(names)


def _split(values: list[str] | None) -> list[str] | None:
    """``--x a,b --x c`` -> ``[a, b, c]``."""
    if not values:
        return None
    return [item for value in values for item in value.split(",") if item]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--builders", action="append", metavar="B[,B...]",
                   help=f"builders to run (default all: {', '.join(BUILDERS)})")
    p.add_argument("--cases", action="append", metavar="C[,C...]",
                   help="cases to run (default all but the large one)")
    p.add_argument("--quick", action="store_true",
                   help=f"leave out the slowest cases ({', '.join(QUICK_SKIPS)})")
    p.add_argument("--large", action="store_true",
                   help="also run the case over 2^24 triangles (a minute per LBVH builder, "
                        "7 GB of memory)")
    p.add_argument("--json", action="store_true", help="print the outcomes as JSON lines")
    p.add_argument("--device", default=None, help="OpenCL device name substring")


def cmd_check(args: argparse.Namespace) -> int:
    """Run the suite and print one line per case and builder, then the totals;
    exit status 1 if anything failed."""
    builders = select_builders(_split(args.builders))
    cases = select_cases(_split(args.cases), args.quick, args.large)

    def show(o: Outcome) -> None:
        lines = [json.dumps(asdict(o))] if args.json else \
            [format_row(o, WIDTHS)] + [f"    {failure}" for failure in o.failures()]
        for line in lines:
            runs.write(line, file=sys.stdout)   # above the bar, or plainly without one
        sys.stdout.flush()
        runs.update(1)

    if not args.json:
        print(f"{len(cases)} cases x {len(builders)} builders "
              f"(rules: python -m pydoc lbvh.verification.rules)", flush=True)
        print("  ".join(c.ljust(w) for c, w in zip(COLUMNS, WIDTHS)).rstrip(), flush=True)
    warm_up(builders, args.device)
    start = time.perf_counter()
    with progress_bar(len(cases) * len(builders), "lbvh check", "run") as runs:
        outcomes = run(cases, builders, args.device, progress=show)
    if not args.json:
        print(f"\ntotals ({time.perf_counter() - start:.0f} s):")
        print(format_totals(outcomes))
        for o in outcomes:
            if o.skipped:
                print(f"skipped {o.case} / {o.builder}: {o.skipped}")
    return exit_status(outcomes)


def exit_status(outcomes: list[Outcome]) -> int:
    """1 if an outcome that ran failed, else 0 (skipped outcomes do not count)."""
    return 0 if all(o.passed or o.skipped for o in outcomes) else 1
