"""Sphinx configuration of evseg_torch's documentation (``make docs``, output in ``docs/_build/html``).

The API reference is generated from the package's docstrings: ``sphinx.ext.autosummary`` walks
``evseg_torch`` recursively (``api.rst``), so the page tree follows the package whatever modules move;
each module's page documents the members defined in it (re-exports are documented where they are
defined, once). Docstrings are Google style (napoleon). The Markdown pages (README, changelog,
benchmarks, design pages, notes) are read by myst-parser.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # document this checkout, not another installed copy

import evseg_torch  # noqa: E402

project = "evseg_torch"
author = "evseg_torch developers"
copyright = "evseg_torch developers, GPL-3.0-or-later"
release = evseg_torch.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "myst_parser",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
templates_path = ["_templates"]
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

# API reference: one page per module, generated into docs/api/ (not committed).
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {
    "members": True,
    "show-inheritance": True,
    "member-order": "bysource",
    # A package's __init__ re-exports names defined in its modules; each is documented once, on the
    # page of the module that defines it (autodoc skips members imported from elsewhere).
    "ignore-module-all": True,
}
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented_params"
autodoc_member_order = "bysource"
autoclass_content = "class"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_attr_annotations = True
# "Attributes:" sections as fields of their class, so that fields autodoc also documents (NamedTuple and
# dataclass fields) are not described twice.
napoleon_use_ivar = True

# Markdown: heading anchors so the README's "#section" links resolve; $...$ maths in the design pages.
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

nitpicky = False

html_theme = "alabaster"
html_title = f"evseg_torch {release}"
html_static_path: list[str] = []


def _link_changelog_page(app, relative_path, parent_docname, content):
    """The README links ``CHANGELOG.md`` at the repository's root; in these pages that is the changelog
    page (``changelog.md`` includes it)."""
    if relative_path.name == "README.md":
        content[0] = content[0].replace("](CHANGELOG.md)", "](docs/changelog.md)")


def setup(app):
    app.connect("include-read", _link_changelog_page)
