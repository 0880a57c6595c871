"""The documentation: the MkDocs site in docs/ builds in strict mode (a broken link,
a page left out of the navigation or a docstring mkdocstrings cannot read fails),
the README stays a front page, and every page it names exists. Every example of
the README and the pages runs from a wheel in tests/test_wheel.py."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

from conftest import REPO

DOCS = REPO / "docs"
PAGES = DOCS / "pages"


def test_the_site_builds_in_strict_mode(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs extra (mkdocs) is not installed")
    pytest.importorskip("mkdocstrings_handlers.python",
                        reason="the docs extra (mkdocstrings-python) is not installed")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q",
                           "-f", str(DOCS / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (tmp_path / "site" / "reference" / "index.html").is_file()
    reference = (tmp_path / "site" / "reference" / "index.html").read_text()
    for name in ("lbvh.build", "lbvh.BVH.intersect", "lbvh.BVH.closest_points", "lbvh.Scene"):
        assert name in reference, name


def test_every_page_is_in_the_navigation():
    config = (DOCS / "mkdocs.yml").read_text()
    listed = set(re.findall(r":\s*([\w-]+\.md)\s*$", config, re.M))
    assert listed == {p.name for p in PAGES.glob("*.md")}


def test_the_readme_is_a_front_page():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    for section in ("## Install", "## Rays", "## Point queries", "## Scenes of many meshes",
                    "## The command line", "## Speed and accuracy", "## Documentation"):
        assert section in text, section
    # the pages it names are there
    for page in re.findall(r"`(?:docs/pages/)?([\w-]+\.md)`", text):
        if page not in ("README.md",):
            assert (PAGES / page).is_file() or (REPO / page).is_file(), page
    assert "lbvh-opencl" in text   # the distribution's name, which is not the import name

