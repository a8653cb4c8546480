"""Sphinx configuration of the sb3-hieros documentation (``make docs``: HTML and the doctests, warnings as errors)."""

from __future__ import annotations

import os
import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # sb3_hieros and benchmarks from this checkout
sys.path.insert(0, str(ROOT / "docs" / "_ext"))
os.environ.setdefault("MUJOCO_GL", "egl")

import sb3_hieros  # noqa: E402

project = "sb3-hieros"
author = "sb3-hieros contributors"
copyright = "sb3-hieros contributors"
release = sb3_hieros.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.intersphinx",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
    "hieros_docs",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
# the benchmark scripts' tables are included into the results pages or kept as data, not pages of their own
exclude_patterns = [
    "_build",
    "README.md",
    "**/README.md",
    "cpu_suite/*.md",
    "cpu_suite/*/*.md",
    "sample_efficiency/*.md",
    "atari100k/*.md",
]
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

html_theme = "sphinx_rtd_theme"
html_title = f"sb3-hieros {release}"
html_static_path: list[str] = []

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"show-inheritance": True}
autodoc_inherit_docstrings = True
# the docstrings' :param: lines name SB3 and torch types that are not documented here
nitpicky = False

intersphinx_mapping: dict[str, tuple[str, str | None]] = {}  # no network: nothing to fetch


def _drop_missing_design(app: object, docname: str, source: list[str]) -> None:
    """The Reference toctree lists docs/design.md (the package's design); a checkout without that page builds too."""
    if docname == "index" and not (ROOT / "docs" / "design.md").exists():
        source[0] = source[0].replace("\ndesign\n", "\n")


#: A star that unpacks a shape in a docstring, as in ``(n, *obs_shape)``, not the start of an emphasis.
_SHAPE_STAR = re.compile(r"(?:(?<=\()|(?<=, ))\*(?=\w)")


def _escape_shape_stars(app: object, what: str, name: str, obj: object, options: object, lines: list[str]) -> None:
    """Docstrings write shapes as ``(B, T, *shape)``; escape the star so that reST does not read an emphasis."""
    lines[:] = [_SHAPE_STAR.sub(r"\\*", line) for line in lines]


def setup(app: object) -> None:
    app.connect("source-read", _drop_missing_design)  # type: ignore[attr-defined]
    app.connect("autodoc-process-docstring", _escape_shape_stars)  # type: ignore[attr-defined]
