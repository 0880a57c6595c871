"""Progress of long jobs (issue 19, item 9): a tqdm bar on a terminal, nothing elsewhere."""
from __future__ import annotations

import io
import sys

import numpy as np

import lbvh
from conftest import random_soup
from lbvh.progress import bar


class Terminal(io.StringIO):
    """stderr as a terminal would be, recording what is drawn."""

    def isatty(self) -> bool:
        return True


def test_a_bar_is_drawn_on_a_terminal_only(monkeypatch):
    for stream, drawn in ((Terminal(), True), (io.StringIO(), False)):
        monkeypatch.setattr(sys, "stderr", stream)
        with bar(10, "job", "step") as b:
            b.update(10)
        assert ("job" in stream.getvalue()) == drawn


def test_forced_on_or_off(monkeypatch):
    quiet, loud = Terminal(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", quiet)
    with bar(3, "off", enabled=False) as b:
        b.update(3)
    monkeypatch.setattr(sys, "stderr", loud)
    with bar(3, "on", enabled=True) as b:
        b.update(3)
    assert quiet.getvalue() == "" and "on" in loud.getvalue()


def test_the_sah_build_shows_its_progress_and_the_same_tree(monkeypatch):
    v, f = random_soup(3000, seed=2)
    plain = lbvh.build(v, f, builder="sah", progress=False)
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    shown = lbvh.build(v, f, builder="sah", progress=True)
    assert "SAH build" in term.getvalue() and "/3000" in term.getvalue()
    assert np.array_equal(shown.nodes, plain.nodes)


def test_lbvh_check_draws_a_bar_on_a_terminal_and_prints_the_same_rows(monkeypatch, capsys):
    from lbvh.cli import main
    args = ["check", "--builders", "lbvh30", "--cases", "1_triangle,flat_plane"]
    assert main(args) == 0
    plain = capsys.readouterr()
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert main(args) == 0
    rows = capsys.readouterr().out
    assert "lbvh check" in term.getvalue() and "/2 [" in term.getvalue()
    assert "lbvh check" not in plain.err
    strip = [line.split()[:2] for line in rows.splitlines() if line.startswith(("1_triangle", "flat"))]
    assert strip == [line.split()[:2] for line in plain.out.splitlines()
                     if line.startswith(("1_triangle", "flat"))] and len(strip) == 2
