"""The README and the docstrings say what the code is: paths, modules, commands, options, citations."""

from __future__ import annotations

import importlib
import re
import shlex
from pathlib import Path

from torch_nssm import RobustNSSMEstimator
from torch_nssm.cli import parse_args
from torch_nssm.models import PaperObservation, PaperTransition

REPO = Path(__file__).resolve().parents[2]
README = (REPO / "README.md").read_text()
TOP_DIRS = ("torch_nssm", "examples", "notebooks", "docs", "benchmarks", "tests")

#: Files that still cite the old "docs/method.md §n" and are owned by another change right now; they are
#: to cite "docs/method.md §n" like the rest (remove each from this list once it does).
PENDING_NOTES: set[str] = set()  # files still citing the old NOTES file (none)


def _code_spans(text: str) -> list[str]:
    return re.findall(r"`([^`\n]+)`", text)


def test_readme_paths_exist():
    paths = [s for s in _code_spans(README) if re.fullmatch(rf"(?:{'|'.join(TOP_DIRS)})/[\w./-]*", s)]
    assert "torch_nssm/datasets/" in paths
    missing = [p for p in paths if not (REPO / p).exists()]
    assert not missing, f"README names paths that do not exist: {missing}"


def test_readme_layout_files_exist():
    """In the layout list, a bare ``file.py`` or ``folder/`` lies under its bullet's folder."""
    section = README.split("## How it works", 1)[1]
    bullets = re.split(r"\n- ", section.split("\nConventions:", 1)[0])[1:]
    assert len(bullets) >= 8
    missing = []
    for bullet in bullets:
        spans = _code_spans(bullet)
        base = REPO / spans[0] if spans[0].endswith("/") else (REPO / spans[0]).parent
        for name in spans[1:]:
            if re.fullmatch(r"\w+\.py|\w+/", name) and not (base / name).exists():
                missing.append(f"{spans[0]}: {name}")
    assert not missing, f"README's layout names files that do not exist: {missing}"


def _resolve(dotted: str):
    try:
        return importlib.import_module(dotted)
    except ModuleNotFoundError:
        parent, _, attr = dotted.rpartition(".")
        return getattr(importlib.import_module(parent), attr)


def test_readme_modules_and_names_resolve():
    names = sorted({m for s in _code_spans(README) for m in re.findall(r"\btorch_nssm(?:\.\w+)+", s)})
    assert "torch_nssm.blocks.linear.LinearTransition" in names
    broken = []
    for name in names:
        try:
            _resolve(name)
        except (ImportError, AttributeError) as exc:
            broken.append(f"{name}: {exc}")
    assert not broken, f"README names modules or objects that do not exist: {broken}"


def test_readme_commands_parse():
    lines = [
        ln.split("#", 1)[0].strip()
        for block in re.findall(r"^```bash\n(.*?)^```", README, flags=re.S | re.M)
        for ln in block.splitlines()
    ]
    cli = [ln for ln in lines if ln.startswith("python -m torch_nssm")]
    assert "python -m torch_nssm" in cli and any("reproduce" in ln for ln in cli)
    for line in cli:
        parse_args(shlex.split(line)[3:])  # a usage error would raise SystemExit
    pyproject = (REPO / "pyproject.toml").read_text()
    for marker in re.findall(r"python -m pytest -m (\w+)", README):
        assert f'"{marker}:' in pyproject, f"README uses the unregistered pytest marker {marker!r}"


def test_readme_options_are_estimator_parameters():
    params = RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0]).get_params()
    table = [ln for ln in README.splitlines() if ln.startswith("| `")]
    assert len(table) >= 8
    spans = [s for ln in table for s in _code_spans(ln.split("|")[1])]
    options = {re.match(r"\w+", s).group() for s in spans if not s.startswith('"')}
    assert {"noise", "n_particles", "fit_dof"} <= options
    assert not options - set(params), f"README's options table names unknown options {options - set(params)}"


def _text_files():
    yield REPO / "README.md"
    for top in TOP_DIRS:
        for path in (REPO / top).rglob("*"):
            if path.suffix in (".py", ".md", ".ipynb") and ".ipynb_checkpoints" not in path.parts:
                yield path


def test_method_notes_are_cited_as_docs_method_md():
    """Docstrings cite docs/method.md (in the repository), not a NOTES file (not in it), and
    every cited section exists."""
    sections = {int(n) for n in re.findall(r"^## (\d+)\.", (REPO / "docs/method.md").read_text(), re.M)}
    assert sections == set(range(1, 8))
    stale, bad = [], []
    for path in _text_files():
        rel = path.relative_to(REPO).as_posix()
        text = path.read_text(errors="replace")
        if re.search(r"\bNOTES\b", text) and rel not in PENDING_NOTES and rel != "tests/facade/test_docs.py":
            stale.append(rel)
        for cite in re.findall(r"docs/method\.md (§[\d\s,§–-]+)", text):
            cited = {int(n) for n in re.findall(r"\d+", cite)}
            if not cited <= sections:
                bad.append(f"{rel}: {cite.strip()}")
    assert not stale, f"files still cite NOTES: {stale}"
    assert not bad, f"citations of sections that docs/method.md does not have: {bad}"

