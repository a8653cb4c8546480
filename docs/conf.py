"""Sphinx configuration of the sb3-hieros documentation (``make docs``: HTML and the doctests, warnings as errors)."""

from __future__ import annotations

import os
import pathlib
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
exclude_patterns = ["_build", "README.md", "**/README.md"]
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

html_theme = "sphinx_rtd_theme"
html_title = f"sb3-hieros {release}"
html_static_path: list[str] = []

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_inherit_docstrings = True
# the docstrings' :param: lines name SB3 and torch types that are not documented here
nitpicky = False

intersphinx_mapping: dict[str, tuple[str, str | None]] = {}  # no network: nothing to fetch
