"""The FAST settings of every reproduction experiment run and write their figures and tables."""

from __future__ import annotations

from pathlib import Path

import pytest

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
