"""The reproduction's tables say in words what they lack: a target the bias norm did not reach,
a standard error the observed information does not give (no "None", no "nan")."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from torch_nssm.reproduce import manipulator_study, paper
from torch_nssm.reproduce.manipulator_study import _standard_error_note, _table2_row

SETTINGS = dict(n_sets=3, n_samples=300, n_iter=12, n_particles=50, n_avg=5)


def test_table1_note_says_the_target_was_not_reached():
    note = paper._table1_note(SETTINGS, 0, 9.0, 10, None, 12, 0.1234, np.ones(3), 0.1234)
    assert "None" not in note
    assert "Bias norm <= 0.010 (last 10 iterates averaged) not reached in 12 iterations" in note
    assert "it ends at 0.1234" in note
    reached = paper._table1_note(SETTINGS, 0, 9.0, 10, 7, 12, 0.008, np.ones(3), 0.008)
    assert "from iteration 7 on" in reached


def _fit(theta1: float, theta2: float, n_iter: int = 8):
    history = {
        "f.theta1": np.linspace(0.8, theta1, n_iter + 1), "f.theta2": np.linspace(0.8, theta2, n_iter + 1)
    }
    f = SimpleNamespace(theta1=torch.tensor(theta1), theta2=torch.tensor(theta2))
    return SimpleNamespace(f_=f, history_=history)


def test_table2_row_and_note_say_why_a_standard_error_is_missing():
    oracle = {"theta": (1.02, 1.06), "se": (0.07, 0.05)}
    row = _table2_row(0.05, _fit(0.88, 0.83), 1.5, (12.4, 16.6), (np.nan, 0.0182), oracle)
    assert row[-1] == "none / 0.0182"
    row = _table2_row(0.1, _fit(0.82, 0.83), 1.3, (18.0, 17.0), (np.nan, np.nan), oracle)
    assert row[-1] == "none / none"
    note = _standard_error_note({0.05: (np.nan, 0.0182), 0.1: (np.nan, np.nan), 0.2: (0.026, 0.013)}, 8)
    assert "'none' (at 5%, 10% outliers): no standard error, because the observed information" in note
    assert "after 8 EM iterations" in note and "nan" not in note
    assert _standard_error_note({0.2: (0.026, 0.013)}, 8) == ""
    assert manipulator_study.TABLE2_HEADER[-1] == "s.e. theta1 / theta2 (ours)"
