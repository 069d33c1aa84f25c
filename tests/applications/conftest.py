"""Shared set-up of the application tests (notebooks, case studies)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def _kernel_imports_this_checkout(monkeypatch):
    """A notebook kernel or subprocess (which inherits the environment) imports this checkout's
    ``torch_nssm`` and ``examples/``, not an installed copy."""
    paths = [str(REPO), str(REPO / "examples"), os.environ.get("PYTHONPATH", "")]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in paths if p))
