"""Sphinx configuration of ivdrem's documentation site (``./run docs``).

Pages are Markdown (MyST); the API reference is generated from the numpydoc docstrings of
every public module (``_ext/apipages.py`` writes one page per module from its ``__all__``);
the gallery runs the scripts ``examples/plot_*.py`` (sphinx-gallery) and shows their figures.
Warnings are errors (``./run docs`` passes ``-W``), so a broken page, link or docstring
fails the build, and the suite builds the site (tests/test_site.py).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(REPO))
# examples run without a display and without progress bars (both only change output)
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("CI", "true")

import ivdrem  # noqa: E402

project = "ivdrem"
author = "the ivdrem developers"
copyright = "the ivdrem developers, MIT licence"
release = ivdrem.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "sphinx_gallery.gen_gallery",
    "apipages",
]

# docs/models.md, docs/mixing.md and docs/controller.md keep the heading levels their authors
# gave them (a level may be skipped); every other warning fails the build
suppress_warnings = ["myst.header"]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "gallery/*.ipynb",
                    "gallery/*.py", "gallery/*.md5", "gallery/*.codeobj.json",
                    "gallery/*.zip"]
templates_path = []
nitpicky = False

# --- Markdown (MyST) ----------------------------------------------------------------
myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 4          # [text](page.md#a-heading) resolves, or the build fails
# a link to a file of the repository that is not a page (a script, a TOML file) is a
# download link of that file
myst_links_external_new_tab = False

# --- API reference ------------------------------------------------------------------
autodoc_default_options = {"member-order": "bysource"}
autodoc_typehints = "none"          # the numpydoc sections say the types
autodoc_preserve_defaults = True
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_validation_checks = set()  # prose docstrings are welcome; sections are optional

# --- gallery ------------------------------------------------------------------------
sphinx_gallery_conf = {
    "examples_dirs": str(REPO / "examples"),
    "gallery_dirs": "gallery",
    "filename_pattern": r"/plot_",     # run every plot_*.py and show its figures
    "ignore_pattern": r"^(?!.*plot_)",  # the other scripts of examples/ are not gallery items
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "plot_gallery": "True",
    "within_subsection_order": "FileNameSortKey",
    "min_reported_time": 1,
    "run_stale_examples": True,        # every build runs every example (they take seconds)
}

# --- HTML ---------------------------------------------------------------------------
html_theme = "furo"
html_title = f"ivdrem {release}"
html_static_path = ["_static"]
html_show_sourcelink = False
