"""The FAST settings of every reproduction experiment run and write their figures and tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from torch_nssm import reproduce
from torch_nssm.cli import build_parser, main


@pytest.mark.parametrize("name", list(reproduce.EXPERIMENTS))
def test_fast_experiment_writes_files(name, tmp_path):
    res = reproduce.EXPERIMENTS[name](fast=True, out_dir=tmp_path, seed=0, progress=False)
    assert res["files"]
    for f in res["files"]:
        assert Path(f).exists() and Path(f).parent == tmp_path
    assert list(tmp_path.glob("*.png"))
    assert list(tmp_path.glob("*.md")) and list(tmp_path.glob("*.csv"))
    assert (tmp_path / f"{name}_settings.json").exists()
    assert res["settings"]["fast"] is True
    assert "|" in res["table"]
    for table in tmp_path.glob("*.md"):  # what is missing is said in words
        words = table.read_text().replace("|", " ").split()
        assert not {"nan", "None"} & set(words), table.name


def test_reproduce_restores_the_callers_thread_count(tmp_path, monkeypatch):
    """The experiments run single-threaded, then leave torch's thread setting as they found it."""
    from torch_nssm import RobustNSSMEstimator

    seen = []
    fit = RobustNSSMEstimator.fit

    def spy(self, *args, **kwargs):
        seen.append(torch.get_num_threads())
        return fit(self, *args, **kwargs)

    monkeypatch.setattr(RobustNSSMEstimator, "fit", spy)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        reproduce.fig2(fast=True, out_dir=tmp_path, progress=False)
        assert seen == [1]  # one thread while fitting
        assert torch.get_num_threads() == 2  # the caller's setting afterwards
    finally:
        torch.set_num_threads(before)


def test_table1_fast_numbers(tmp_path):
    res = reproduce.table1(fast=True, out_dir=tmp_path, progress=False)
    assert res["estimates"].shape == (4, 3)
    assert res["bias_norm"] >= 0 and len(res["std"]) == 3
    text = (tmp_path / "table1.md").read_text()
    assert "0.0216" in text and "0.0662" in text


def test_cli_parses_reproduce(tmp_path):
    args = build_parser().parse_args(["reproduce", "fig2", "--fast", "--out", str(tmp_path)])
    assert args.command == "reproduce" and args.experiment == "fig2"
    assert args.fast and args.out == str(tmp_path)
    default = build_parser().parse_args([])
    assert default.command is None  # the default command is still the demo


def test_cli_reproduce_runs(tmp_path, capsys):
    assert main(["reproduce", "fig2", "--fast", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "fig2.png").exists() and (tmp_path / "fig2.csv").exists()
    assert "fig2" in capsys.readouterr().out


def test_table1_fast_reports_the_50_iteration_budget(tmp_path):
    res = reproduce.table1(fast=True, out_dir=tmp_path, progress=False, n_sets=3, n_iter=12)
    assert res["settings"]["n_iter"] == 12 and res["estimates"].shape == (3, 3)
    path = res["bias_norm_path"]
    assert path.shape == (13,) and np.all(np.isfinite(path))
    # index 0 is the initial value (0.5, 0.5, 0.5): ||(0.9, 1, 1) - 0.5|| = 0.98
    assert path[0] == pytest.approx(np.linalg.norm([0.4, 0.5, 0.5]))
    assert path[-1] < path[0]  # EM moved towards the truth
    # with fewer than 50 iterations the "50-iteration" numbers are those of the last iteration
    assert res["bias_norm_50"] == pytest.approx(path[-1])
    assert len(res["std_50"]) == 3 and np.all(np.asarray(res["std_50"]) > 0)
    assert res["iterations_to_target"] is None  # 12 iterations on 300 samples do not reach 0.010
    assert "After 12 iterations" in (tmp_path / "table1.md").read_text()


def test_manipulator_kalman_mle_is_the_maximum_likelihood():
    """The exact (Kalman) MLE: a local maximum of the exact likelihood, near the truth within its s.e."""
    from torch_nssm.datasets import make_manipulator

    data = make_manipulator(n_samples=200, outlier_fraction=0.1, random_state=1)
    res = reproduce.manipulator_kalman_mle(data)
    theta, se = np.array(res["theta"]), np.array(res["se"])
    keep = ~data.outlier_mask
    nll = reproduce._manipulator_nll(theta, data, keep)
    for step in ([0.01, 0], [0, 0.01], [-0.01, 0], [0, -0.01]):
        assert nll < reproduce._manipulator_nll(theta + np.array(step), data, keep)
    assert np.all(se > 0) and np.all(se < 0.2)
    assert np.all(np.abs(theta - 1.0) < 4 * se)
    # keeping the outliers (values up to 1 rad on 0.01 rad noise) ruins the Gaussian likelihood
    polluted = reproduce.manipulator_kalman_mle(data, drop_outliers=False)
    assert np.abs(np.array(polluted["theta"]) - 1).max() > np.abs(theta - 1).max()
