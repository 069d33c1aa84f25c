"""The estimation machinery does not name a noise family's own parameters: no identifier, attribute,
keyword or string in the code of ``torch_nssm`` outside ``core/noise/`` says ``dof`` or ``student``
(docstrings and comments may, as examples).  A family's parameters reach the estimator, the EM loop,
the standard errors, the acceleration, the starts, the bootstrap and the data sets through
the family's methods only (``core/noise/base.py``).

Left out, with the reason:

* ``core/noise/`` (the families and their registry) and ``noise.py`` (its public names);
* ``RobustNSSMEstimator.__init__``: scikit-learn needs the shortcut parameters (``dof_init``,
  ``fit_dof``, ``dof_bounds``) and the default ``noise="student-t"`` spelled out in its signature;
  the estimator forwards them by the registry's ``NOISE_SHORTCUTS``, never by name;
* applications that *use* the Student-t family by name: the command line (a Student-t fit and
  its ``dof_`` column), the paper's experiments (``reproduce/``) and the simulated data sets whose
  true noise has a ``dof`` argument (``datasets/paper.py``, ``datasets/manipulator.py``).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import torch_nssm

PACKAGE = Path(torch_nssm.__file__).parent
EXCLUDED = ("core/noise/", "noise.py", "cli.py", "reproduce/", "datasets/paper.py", "datasets/manipulator.py")
#: a ``dof`` token of an identifier (``dof``, ``dof_``, ``fit_dof``, ``dof_bounds``; not ``ddof``) or
#: ``student`` anywhere
FAMILY_WORD = re.compile(r"(?:^|_|\W)dof(?:_|\W|$)|student", re.IGNORECASE)


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.add(id(body[0].value))
    return out


def _words(node: ast.AST, docstrings: set[int], skip_init: bool):
    """``(line, word)`` of every name, attribute, argument, keyword and non-docstring string."""
    if skip_init and isinstance(node, ast.ClassDef) and node.name == "RobustNSSMEstimator":
        for child in node.body:
            if not (isinstance(child, ast.FunctionDef) and child.name == "__init__"):
                yield from _words(child, docstrings, skip_init)
        return
    word = None
    if isinstance(node, ast.Name):
        word = node.id
    elif isinstance(node, ast.Attribute):
        word = node.attr
    elif isinstance(node, ast.arg):
        word = node.arg
    elif isinstance(node, ast.keyword):
        word = node.arg
    elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        word = node.name
    elif isinstance(node, ast.alias):
        word = node.asname or node.name
    elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
        word = node.value
    if word:
        yield getattr(node, "lineno", 0), word
    for child in ast.iter_child_nodes(node):
        yield from _words(child, docstrings, skip_init)


def test_no_noise_family_parameter_is_named_outside_core_noise():
    found = []
    files = sorted(PACKAGE.rglob("*.py"))
    assert len(files) > 40
    for path in files:
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith(EXCLUDED):
            continue
        tree = ast.parse(path.read_text())
        for line, word in _words(tree, _docstrings(tree), rel == "estimator.py"):
            if FAMILY_WORD.search(word):
                found.append(f"{rel}:{line}: {word!r}")
    assert not found, "noise-family names outside core/noise:\n" + "\n".join(found)


def test_the_check_finds_what_it_looks_for():
    """The walk sees a ``dof`` attribute, keyword and string, and skips docstrings and ``ddof``."""
    lines = ["def f(m):", '    """dof in a docstring"""', "    m.dof", "    g(fit_dof=1, ddof=1)"]
    code = "\n".join([*lines, '    return "student-t"'])
    tree = ast.parse(code)
    hits = [w for _, w in _words(tree, _docstrings(tree), False) if FAMILY_WORD.search(w)]
    assert hits == ["dof", "fit_dof", "student-t"]
