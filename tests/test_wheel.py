"""The wheel works outside the repository: it carries the kernels, the teapot, the
saved views and ``py.typed``, and every example of the README's sections of
:data:`SECTIONS` and of the documentation's pages (docs/pages) runs from it:
the ```python and ```sh blocks (```console blocks are commands for a checkout,
```py blocks sketches that need more than lbvh).

The wheel is built from the checkout and installed (without its dependencies:
the machine may have no network) into a fresh virtual environment; that
environment reads the dependencies from the test's own environment through a
``.pth`` file, which adds their folder to ``sys.path`` after its own
site-packages and does not run that folder's ``.pth`` files, so the editable
install of the checkout is not seen (a test checks ``lbvh.__file__``). The
examples run in a temporary folder outside the repository, with the
environment's ``bin`` first on ``PATH``; they are read from README.md and the
pages, so the test follows the documentation.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from conftest import REPO
from lbvh.version import __version__

#: The README sections whose examples must run from a wheel (and every page's).
SECTIONS = ("Rays", "Point queries", "Scenes of many meshes", "trimesh's interfaces",
            "The command line")
#: The documentation's pages.
PAGES = sorted((REPO / "docs" / "pages").glob("*.md"))
DATA_FILES = ("lbvh/py.typed", "lbvh/data/teapot.obj", "lbvh/data/cameras.json",
              "lbvh/data/README.md", "lbvh/data/licenses/common-3d-test-models_README.md")


def readme_section(title: str) -> str:
    text = (REPO / "README.md").read_text()
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", text, re.S | re.M)
    assert match, f"README.md has no section {title!r}"
    return match.group(1)


def code_blocks(text: str) -> list[tuple[str, str]]:
    """``(language, code)`` of the ```python and ```sh blocks of a Markdown text."""
    return re.findall(r"^```(python|sh)\n(.*?)^```", text, re.S | re.M)


def readme_examples() -> list[tuple[str, str, str]]:
    """``(where, language, code)`` of every ```python and ```sh block of the README's
    :data:`SECTIONS` and of the documentation's pages."""
    return ([(title, lang, code) for title in SECTIONS
             for lang, code in code_blocks(readme_section(title))]
            + [(f"docs/pages/{page.name}", lang, code) for page in PAGES
               for lang, code in code_blocks(page.read_text())])


class Installed:
    """The wheel, and a fresh virtual environment with it installed."""

    def __init__(self, root: Path) -> None:
        self.work = root / "work"      # where the examples run: outside the repository
        self.work.mkdir()
        wheels = root / "wheels"
        self._run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                   "-w", str(wheels), str(REPO)])
        self.wheel = next(wheels.glob("lbvh_opencl-*.whl"))
        self.env = root / "env"
        self._run([sys.executable, "-m", "venv", "--without-pip", str(self.env)])
        self.python = self.env / "bin" / "python"
        self._run([sys.executable, "-m", "pip", "--python", str(self.python), "install", "-q",
                   "--no-deps", "--no-index", str(self.wheel)])
        site = self.run_python("import sysconfig; print(sysconfig.get_paths()['purelib'])").strip()
        ours = {sysconfig.get_paths()[key] for key in ("purelib", "platlib")}
        (Path(site) / "_dependencies_of_the_test.pth").write_text("\n".join(sorted(ours)) + "\n")

    @staticmethod
    def _run(argv: list[str]) -> None:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{' '.join(argv)}\n{done.stdout}\n{done.stderr}"

    def environ(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items()
               if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
        env["PATH"] = f"{self.env / 'bin'}:/usr/bin:/bin"
        return env

    def run(self, argv: list[str]) -> subprocess.CompletedProcess:
        return subprocess.run(argv, cwd=self.work, env=self.environ(), capture_output=True,
                              text=True, timeout=120)

    def run_python(self, code: str) -> str:
        done = self.run([str(self.python), "-c", code])
        assert done.returncode == 0, f"{code}\n{done.stdout}\n{done.stderr}"
        return done.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    return Installed(tmp_path_factory.mktemp("wheel"))


def test_wheel_carries_kernels_data_and_py_typed(installed):
    names = zipfile.ZipFile(installed.wheel).namelist()
    for kernel in ("bounds", "morton", "sort", "emit", "refit"):
        assert f"lbvh/kernels/{kernel}.cl" in names
    assert "lbvh/kernels/common.h" in names
    for name in DATA_FILES:
        assert name in names
    with zipfile.ZipFile(installed.wheel) as wheel:
        assert wheel.read("lbvh/data/teapot.obj") == (REPO / "scenes" / "teapot.obj").read_bytes()


def test_the_fresh_environment_uses_the_wheel_not_the_checkout(installed):
    code = ("import lbvh, lbvh.data, numpy as np; from lbvh.device import kernels_dir;"
            "b = lbvh.build(np.eye(3, dtype=np.float32), [[0, 1, 2]]); b.validate();"
            "v, f = lbvh.data.teapot(); print(lbvh.__file__); print(kernels_dir());"
            "print(lbvh.data.path('teapot')); print(len(f))")
    package, kernels, teapot, triangles = installed.run_python(code).split()
    site = str(installed.env)
    assert package.startswith(site) and kernels.startswith(site) and teapot.startswith(site)
    assert not package.startswith(str(REPO)) and int(triangles) == 6320
    assert (Path(package).parent / "py.typed").is_file()


def test_the_installed_command_prints_its_version(installed):
    done = installed.run([str(installed.env / "bin" / "lbvh"), "--version"])
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"lbvh {__version__}"


def test_the_readme_examples_are_there():
    examples = readme_examples()
    languages = [lang for _, lang, _ in examples]
    assert languages.count("python") >= 10 and languages.count("sh") >= 2, examples
    # every page that shows how to call lbvh has a running example
    for page in ("start.md", "rays.md", "points.md", "scenes.md"):
        assert any(where == f"docs/pages/{page}" for where, _, _ in examples), page
    for title, _, code in examples:
        # nothing of the source tree: a wheel user has none of it
        assert "scenes/" not in code and "../shared" not in code, (title, code)


def test_the_readme_sections_have_no_relative_links():
    # The README is the wheel's long description: links into the tree would break there.
    for title in SECTIONS:
        relative = re.findall(r"\]\((?!https?://)[^)]*\)", readme_section(title))
        assert not relative, (title, relative)


@pytest.mark.parametrize("index", range(len(readme_examples())),
                         ids=[f"{title}-{lang}-{i}" for i, (title, lang, _) in
                              enumerate(readme_examples())])
def test_a_readme_example_runs_from_the_wheel(installed, index):
    title, lang, code = readme_examples()[index]
    if lang == "python":
        argv = [str(installed.python), "-c", code]
    else:
        argv = ["bash", "-e", "-u", "-o", "pipefail", "-c", code]
    done = installed.run(argv)
    assert done.returncode == 0, f"{title} ({lang}):\n{code}\n{done.stdout}\n{done.stderr}"
    # every file the example writes lands in the work folder
    for written in re.findall(r"-o (\S+)|\.save\(\"([^\"]+)\"\)", code):
        name = next(part for part in written if part)
        assert (installed.work / name).is_file(), name
