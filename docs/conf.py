"""Sphinx configuration of the torch_nssm documentation site.

Build it with ``python -m sphinx -W --keep-going -b html docs docs/_build/html`` (the ``docs``
extra has the tools).  Nothing is downloaded and no notebook is executed at build time: the
notebooks are rendered with their stored outputs.
"""

from __future__ import annotations

import importlib
import inspect
import os
import re
import sys
import types

sys.path.insert(0, os.path.abspath(".."))

import torch_nssm  # noqa: E402

project = "torch_nssm"
author = "torch_nssm developers"
copyright = "torch_nssm developers"
release = torch_nssm.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "myst_nb",
]

# Markdown (MyST) and notebooks beside reStructuredText; the notebooks are shown as stored.
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
nb_execution_mode = "off"
myst_enable_extensions = ["dollarmath"]
myst_heading_anchors = 3

templates_path = ["_templates"]
exclude_patterns = ["_build", "results", "notebooks/reproduction_out", "**/.ipynb_checkpoints"]

# API reference: one page per public name, generated from the numpydoc docstrings.
autosummary_generate = True
autosummary_ignore_module_all = False
autodoc_default_options = {"member-order": "bysource"}
autodoc_typehints = "none"
autodoc_class_signature = "separated"
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False

# No network at build time.
intersphinx_mapping: dict = {}

html_theme = "furo"
html_title = f"torch_nssm {release}"
html_static_path: list = []


# --------------------------------------------------------------------------- API pages
#: The public submodules; each gets a page listing its ``__all__``, and each class and function of
#: it a page of its own (autosummary).  Constants are documented on the module's page.
PUBLIC_MODULES = [
    "noise", "neural", "starts", "blocks", "models", "datasets",
    "metrics", "evaluation", "diagnostics", "plotting",
]
HERE = os.path.dirname(os.path.abspath(__file__))


def _kind(obj) -> str:
    if inspect.isclass(obj):
        return "Exceptions" if issubclass(obj, BaseException) else "Classes"
    if isinstance(obj, types.ModuleType):
        return "Modules"
    return "Functions" if callable(obj) else "Constants"


def _module_page(name: str) -> str:
    full = f"torch_nssm.{name}"
    module = importlib.import_module(full)
    groups: dict[str, list[str]] = {}
    elsewhere: list[tuple[str, str]] = []
    for member in module.__all__:
        obj = getattr(module, member)
        kind = _kind(obj)
        if kind in ("Classes", "Exceptions") and id(obj) in _DOCUMENTED:
            elsewhere.append((member, _DOCUMENTED[id(obj)]))  # one page per class: its first public path
            continue
        if kind in ("Classes", "Exceptions"):
            _DOCUMENTED[id(obj)] = f"{full}.{member}"
        groups.setdefault(kind, []).append(member)
    title = f"``{full}``"
    lines = [title, "=" * len(title), "", f".. automodule:: {full}", "   :no-members:", "",
             f".. currentmodule:: {full}", ""]
    for kind in ("Classes", "Exceptions", "Functions"):
        if kind in groups:
            lines += [kind, "-" * len(kind), "", ".. autosummary::", "   :toctree: .", "   :nosignatures:"]
            if kind != "Functions":
                lines.append("   :template: autosummary/class.rst")
            lines += [""] + [f"   {m}" for m in groups[kind]] + [""]
    if elsewhere:
        lines += ["Documented at another public path", "---------------------------------", ""]
        lines += [f"* ``{m}``: :class:`{target}`" for m, target in elsewhere] + [""]
    if "Constants" in groups:
        lines += ["Constants", "---------", ""]
        for m in groups["Constants"]:
            obj = getattr(module, m)
            lines += [f".. py:data:: {m}", f"   :type: {type(obj).__name__}", ""]
            lines += [f"   {line}" for line in _constant_doc(m, obj)] + [""]
    return "\n".join(lines)


def _constant_doc(name: str, obj) -> list[str]:
    """The ``#:`` comment above the constant's definition, found in the module that defines it."""
    from sphinx.pycode import ModuleAnalyzer

    for modname, mod in sorted(sys.modules.items()):
        if not modname.startswith("torch_nssm") or getattr(mod, name, None) is not obj:
            continue
        try:
            docs = ModuleAnalyzer.for_module(modname).find_attr_docs()
        except Exception:  # a module without source
            continue
        if ("", name) in docs:
            return [line for line in docs[("", name)] if line.strip() or True]
    return ["(no description)"]


#: id of each class documented so far -> the public path of its page
_DOCUMENTED: dict[int, str] = {}


def _write_api_pages() -> None:
    for name in ("RobustNSSMEstimator", "LinearInParameters", "ContinuousTimeTransition", "StateEstimate",
                 "NumericalError", "WorkerLostError"):  # api_toplevel.rst
        _DOCUMENTED[id(getattr(torch_nssm, name))] = f"torch_nssm.{name}"
    out = os.path.join(HERE, "generated")
    os.makedirs(out, exist_ok=True)
    for name in PUBLIC_MODULES:
        path = os.path.join(out, f"torch_nssm.{name}.rst")
        text = _module_page(name)
        if not os.path.exists(path) or open(path, encoding="utf-8").read() != text:
            with open(path, "w", encoding="utf-8") as fh:
                fh.write(text)


_write_api_pages()


# --------------------------------------------------------------------------- links
#: The Markdown files link to the notebooks as ``../notebooks/x.ipynb`` (right on GitHub); on the
#: site the notebooks are the documents ``notebooks/x`` (``docs/notebooks`` links to the repository's
#: folder, and MyST would resolve a file link through it to outside the source directory), so such
#: links become ``{doc}`` references.  Links to folders (``results/``) become plain text.
_NOTEBOOK_LINK = re.compile(r"\[([^\]]*)\]\(\.\./notebooks/([\w-]+)\.ipynb\)")
_FOLDER_LINK = re.compile(r"\[([^\]]*)\]\([^)\s]*/\)")


def _site_links(app, docname, source) -> None:
    text = _NOTEBOOK_LINK.sub(lambda m: f"{{doc}}`{m[1].replace('`', '')} <notebooks/{m[2]}>`", source[0])
    source[0] = _FOLDER_LINK.sub(r"\1", text)


def _skip_member(app, what, name, obj, skip, options):
    """scikit-learn's generated metadata-routing methods (``set_fit_request`` ...) are not ours."""
    if re.fullmatch(r"set_\w+_request", name):
        return True
    return None


def setup(app):
    app.connect("source-read", _site_links)
    app.connect("autodoc-skip-member", _skip_member)
