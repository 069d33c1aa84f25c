"""The README's figures agree with where they are measured (``benchmarks/README.md`` and the rounds
in ``benchmarks/HISTORY.md``), and its words agree with what the code does (outlier weights above 1;
what a GPU user can expect)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
BENCHMARKS = "\n".join((ROOT / "benchmarks" / name).read_text() for name in ("README.md", "HISTORY.md"))


def _section(text: str, start: str, end: str) -> str:
    i = text.index(start)
    return text[i : text.index(end, i)]


def _flat(text: str) -> str:
    return " ".join(text.split())


def test_silverbox_table_shows_todays_defaults_as_benchmarks_records_them():
    section = _section(README, "**Silverbox**", "## Continuous-time models")
    rows = {}
    for line in section.splitlines():
        if line.startswith("|") and "---" not in line:
            cells = [c.strip(" *") for c in line.strip("|").split("|")]
            rows[tuple(cells[:2])] = cells[2:]
    # 3,000 samples with 5 % outliers: benchmarks/README.md's run of the notebook's comparison
    bench = _flat(BENCHMARKS)
    assert "first stage alone (the baseline) 1.18 / 0.89 mV (arrow full / without the extrapolated " \
        "tail) in 4 s" in bench
    assert "the defaults 1.18 / 0.88 mV in 19 s, gen2 + D then EM 0.45 / 0.30 mV in 32 s" in bench
    assert rows[("3,000 samples, 5 % outliers", "first stage alone (the baseline)")] == ["1.18", "0.89", "4"]
    assert rows[("3,000 samples, 5 % outliers", "defaults")] == ["1.18", "0.88", "19"]
    gen2 = ("3,000 samples, 5 % outliers", "`gen2 + D` grey box (model study), then EM")
    assert rows[gen2] == ["0.45", "0.30", "32"]
    # the whole multisine part: benchmarks/README.md's last full-record run
    assert "**182 s (5 % outliers) / 174 s (clean)**, all 90,372 samples, the same RMSE 1.19 / 0.87 and " \
        "1.20 / 0.88 mV" in bench
    assert rows[("all 90,372 samples, 5 % outliers", "defaults")] == ["1.19", "0.87", "182"]
    assert rows[("all 90,372 samples, clean", "defaults")] == ["1.20", "0.88", "174"]
    # the old noise-model study (EM from the equation-error start) is not presented as the defaults
    assert "1.99" not in section and "6.18" not in section


def test_long_record_figures_are_those_of_benchmarks():
    notes = _flat(_section(README, "- **Long records.**", "- **Memory.**"))
    bench = _flat(BENCHMARKS)
    assert "windows of 1,000: 0.73 s** (E-step 0.55 s), exact 5.50 s" in bench
    assert "exact 5.5 s" not in notes  # the README says it in words
    assert "an exact EM iteration takes 5.5 s" in notes and "it takes 0.73 s" in notes
    assert "**windows of 1,000: 23.2 s, 15.9 GB; exact 58.3 s, 13.5 GB**" in bench
    assert "23 s per EM iteration with a 15.9 GB peak (exact pass: 58 s, 13.5 GB)" in notes
    assert "182 s with 5 % outliers, 174 s clean" in notes


def test_gpu_note_speaks_to_the_user():
    note = _flat(_section(README, "- **GPU.**", "- **Long records.**"))
    assert not re.search(r"lent|this project's sessions|has not run on one", note)
    assert "What to expect" in note and "--device cuda" in note


def test_outlier_weights_are_described_as_they_are():
    """``E[lambda | y] = (dof + p) / (dof + delta^2)`` exceeds 1 for a small residual (the fitted
    weights of tests/facade/test_plotting.py reach above 1 and stay below the bound)."""
    intro = _flat(README[: README.index("## Quick start")])
    assert "near 1 for a regular sample" not in intro
    assert "`E[λ_k | y] = (dof + p) / (dof + δ_k²)`" in intro
    assert "above 1 for a small residual (up to `(dof + p) / dof`" in intro
