"""Sphinx configuration of the jaxsync documentation.

Build (what CI runs; warnings are errors):

    pip install -e ".[docs]"
    sphinx-build -W --keep-going -b html docs docs/_build/html

Pages are Markdown (MyST); the API reference is generated from the docstrings
(``docs/_ext/apiref.py``) and the benchmark tables from the result files in
``benchmarks/results`` (``docs/_ext/benchtables.py``), both at build time. No code of the
pages runs here: tests/test_docs.py runs it.
"""

from __future__ import annotations

import os
import sys

DOCS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(DOCS)
sys.path.insert(0, ROOT)                                # a checkout that is not installed still builds
sys.path.insert(0, os.path.join(DOCS, "_ext"))
os.environ.setdefault("JAX_PLATFORMS", "cpu")           # importing jaxsync for autodoc needs no accelerator

project = "jaxsync"
author = "the jaxsync developers"
copyright = "the jaxsync developers"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "myst_parser",
    "apiref",
    "benchtables",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
suppress_warnings = ["myst.header"]      # pages may start at a level-2 heading under a level-1 title

myst_enable_extensions = ["colon_fence", "deflist", "dollarmath"]
myst_heading_anchors = 3

# API reference: one entry per public name, Google-style sections, Sphinx roles resolved.
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_class_signature = "mixed"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# A docstring that is not valid reST is a warning (an error under -W, as in CI); set
# JAXSYNC_DOCS_STRICT=0 to show such docstrings as written instead while drafting.
apiref_strict_docstrings = os.environ.get("JAXSYNC_DOCS_STRICT", "1") not in ("", "0")

html_theme = "furo"
html_title = "jaxsync"
html_static_path: list[str] = []
html_show_sourcelink = False
