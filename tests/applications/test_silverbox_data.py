"""Tests of the Silverbox reader (``examples/silverbox/data.py``).

The data are not shipped: the tests look in ``$TORCH_NSSM_SILVERBOX`` or
``../shared/data/silverbox`` beside the repository and skip when ``SNLS80mV.csv`` is absent.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "examples"))

from silverbox.data import SILVERBOX_ARROW_END, SILVERBOX_FS, load_silverbox  # noqa: E402

SILVERBOX_DIR = Path(os.environ.get("TORCH_NSSM_SILVERBOX", REPO / ".." / "shared" / "data" / "silverbox"))
SILVERBOX_N = 131_072

# ------------------------------------------------------------------------------------------
# Silverbox
# ------------------------------------------------------------------------------------------

needs_silverbox = pytest.mark.skipif(
    not (SILVERBOX_DIR / "SNLS80mV.csv").is_file(),
    reason=f"Silverbox data not found at {SILVERBOX_DIR.resolve()} (shared reference data)",
)


@needs_silverbox
@pytest.mark.parametrize(
    "part, n",
    [
        ("all", SILVERBOX_N),
        ("arrow", SILVERBOX_ARROW_END),
        ("multisine", SILVERBOX_N - SILVERBOX_ARROW_END),
    ],
)
def test_silverbox_parts(part, n):
    u, y = load_silverbox(SILVERBOX_DIR, part=part)
    assert u.shape == (n, 1) and y.shape == (n, 1)
    assert u.dtype == np.float64 and y.dtype == np.float64
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(y))


@needs_silverbox
def test_silverbox_values_and_split():
    u, y = load_silverbox(SILVERBOX_DIR, part="all")
    # first data row of SNLS80mV.csv: 0.0057756,0.0093978,
    assert u[0, 0] == pytest.approx(0.0057756) and y[0, 0] == pytest.approx(0.0093978)
    ua, ya = load_silverbox(SILVERBOX_DIR, part="arrow")
    um, ym = load_silverbox(SILVERBOX_DIR, part="multisine")
    np.testing.assert_array_equal(np.vstack([ua, um]), u)
    np.testing.assert_array_equal(np.vstack([ya, ym]), y)
    # returned arrays are independent copies
    u[0, 0] = 123.0
    assert load_silverbox(SILVERBOX_DIR, part="all")[0][0, 0] != 123.0
    assert SILVERBOX_FS == pytest.approx(610.3515625)


@needs_silverbox
def test_silverbox_default_path(monkeypatch):
    # the default search finds ../shared/data/silverbox relative to the repository root ...
    monkeypatch.delenv("TORCH_NSSM_SILVERBOX", raising=False)
    monkeypatch.chdir("/")
    u, _ = load_silverbox(part="arrow")
    assert u.shape == (SILVERBOX_ARROW_END, 1)


@needs_silverbox
def test_silverbox_environment_variable(monkeypatch, tmp_path):
    # ... and $TORCH_NSSM_SILVERBOX, when set, is the only place looked at
    monkeypatch.chdir("/")
    monkeypatch.setenv("TORCH_NSSM_SILVERBOX", str(SILVERBOX_DIR.resolve()))
    u, _ = load_silverbox(part="arrow")
    assert u.shape == (SILVERBOX_ARROW_END, 1)
    monkeypatch.setenv("TORCH_NSSM_SILVERBOX", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="TORCH_NSSM_SILVERBOX"):
        load_silverbox(part="arrow")


@needs_silverbox
def test_silverbox_other_file():
    if not (SILVERBOX_DIR / "Schroeder80mV.csv").is_file():
        pytest.skip("Schroeder80mV.csv not present")
    u, y = load_silverbox(SILVERBOX_DIR, part="all", file="Schroeder80mV.csv")
    assert u.shape == y.shape == (SILVERBOX_N, 1)
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(y))
    with pytest.raises(ValueError, match="part"):
        load_silverbox(SILVERBOX_DIR, part="arrow", file="Schroeder80mV.csv")


def test_silverbox_missing(tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(FileNotFoundError) as exc:
        load_silverbox(missing)
    msg = str(exc.value)
    assert str(missing.resolve()) in msg and "nonlinear-benchmarks" in msg


def test_silverbox_bad_part(tmp_path):
    with pytest.raises(ValueError, match="part"):
        load_silverbox(tmp_path, part="train")
