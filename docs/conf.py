"""Sphinx configuration of the elastic_jax site (build: see docs/contributing.md).

The site is built with warnings as errors (``-W``); four parts are generated here at each
build so that they cannot drift from the code: the notebooks are copied in from
``notebooks/`` (rendered with their stored outputs, not executed), the command-line
reference is printed from the argument parser, the gallery's tables are read from the
benchmark JSON in ``docs/gallery/``, and the API reference's summary tables are read from
the directives of its pages (``docs/api/``). A public name without an API entry fails the build.
"""

import pathlib
import shutil
import sys

DOCS = pathlib.Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(DOCS))

import _generate  # noqa: E402  (docs/_generate.py: the generated pages)

project = "elastic_jax"
author = "the elastic_jax developers"
copyright = "2026, the elastic_jax developers"
release = version = __import__("elastic_jax").__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "myst_nb",
]
exclude_patterns = ["_build", "**/.ipynb_checkpoints", "_*.md", "**/_*.md"]
nitpicky = True
# Types in signatures are jaxtyping shapes; the docstrings state shapes in words.
autodoc_typehints = "none"
autodoc_member_order = "bysource"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# NamedTuple fields are annotated with jaxtyping shapes; the Attributes sections say them.
napoleon_attr_annotations = False
# ShapeOptions groups its fields; render each group as a field list.
napoleon_custom_sections = [
    ("Path fields", "params_style"),
    ("Registration fields", "params_style"),
    ("Check fields", "params_style"),
]
# No intersphinx (the build runs offline): standard-library types stay plain text.
nitpick_ignore = [("py:class", "pathlib.Path")]
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3
# The notebooks are stored with their outputs (docs/execute_notebooks.py writes them).
nb_execution_mode = "off"
html_theme = "pydata_sphinx_theme"
html_title = f"elastic_jax {version}"
html_theme_options = {"navigation_with_keys": False, "show_toc_level": 2}


def _copy_notebooks() -> None:
    target = DOCS / "examples" / "notebooks"
    target.mkdir(parents=True, exist_ok=True)
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        shutil.copyfile(path, target / path.name)


def _check_public_names(app, env) -> None:
    """Every public name has an entry in the API reference, or the build fails."""
    from sphinx.util import logging

    objects = env.domains["py"].objects
    documented = {name for name, entry in objects.items() if entry.docname.startswith("api/")}
    missing = [name for name in _generate.public_names() if name not in documented]
    if missing:
        logging.getLogger(__name__).warning(
            "public names without an API entry (add an autodoc directive for each): %s",
            "; ".join(f"{name} to {_generate.api_page_for(name)}" for name in missing),
        )


def setup(app):
    _copy_notebooks()
    _generate.cli_reference(DOCS / "guides" / "_cli_reference.md")
    _generate.gallery_tables(DOCS / "gallery")
    _generate.api_summaries(DOCS / "api")
    app.connect("env-check-consistency", _check_public_names)
