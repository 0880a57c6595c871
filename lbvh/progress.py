"""Progress of long jobs on the terminal (tqdm), off when stderr is not one.

The SAH reference build over many triangles, ``lbvh check`` and the benches
take from seconds to minutes; they show a bar on stderr while they run. Where
stderr is not a terminal (a pipe, a log, CI) nothing is drawn, so logs stay
clean; ``enabled=True``/``False`` forces either.
"""
from __future__ import annotations

import sys

from tqdm import tqdm


def bar(total: int, desc: str, unit: str = "it", enabled: bool | None = None) -> tqdm:
    """A progress bar to ``update()`` and ``close()`` (or use as a context manager);
    ``enabled=None``: shown only when stderr is a terminal. ``bar.write(text)``
    prints a line above the bar (or plainly, when there is none)."""
    show = sys.stderr.isatty() if enabled is None else bool(enabled)
    return tqdm(total=total, desc=desc, unit=unit, disable=not show, file=sys.stderr,
                leave=False, dynamic_ncols=True)
