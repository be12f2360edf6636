"""Sphinx configuration: the API reference from the docstrings, the Markdown pages through MyST.

Build (tests/test_docs.py does the same, warnings as errors)::

    sphinx-build -W --keep-going -b html docs docs/_build/html
"""
from __future__ import annotations

import sys
from pathlib import Path

# Document the checkout this file belongs to, whether or not torchconn is installed.
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent / "_ext"))

import torchconn  # noqa: E402

project = "torchconn"
author = "torchconn developers"
release = version = torchconn.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",  # Google-style Args:/Returns:/Raises: sections of the docstrings
    "myst_parser",  # the pages are Markdown (README-style), autodoc runs inside {eval-rst} blocks
    "public_api",  # _ext/public_api.py: each object documented once, under the name users import
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "README.md"]

# No network: no intersphinx, no remote images.
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
# A method without a docstring of its own is left out rather than shown with its base class's
# text (torch's "Define the computation performed at every call" on every nn.Module.forward).
autodoc_inherit_docstrings = False
napoleon_google_docstring = True
napoleon_numpy_docstring = False
myst_heading_anchors = 3  # "conventions.md#2-errata-in-the-report"-style links between pages

html_theme = "alabaster"
html_static_path: list[str] = []
