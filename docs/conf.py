"""Sphinx configuration of the cifilter documentation."""

import cifilter

project = "cifilter"
author = "The cifilter developers"
copyright = "2026, The cifilter developers"
release = cifilter.__version__
version = cifilter.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "numpydoc",
]

numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
autodoc_member_order = "bysource"
autodoc_typehints = "none"

exclude_patterns = ["_build"]
html_theme = "alabaster"
html_theme_options = {"description": "Fusion under unknown correlation, on top of filterpy"}
