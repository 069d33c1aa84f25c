"""``python -m torch_nssm``: options before or after the subcommand, usage errors without tracebacks."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torch_nssm.cli import main

REPO = Path(__file__).resolve().parents[2]
TINY = ["--n-samples", "30", "--particles", "10", "--iterations", "1"]


def test_demo_options_before_or_after_the_subcommand():
    from torch_nssm.cli import DEMO_DEFAULTS, parse_args

    assert parse_args(["--iterations", "2", "demo"]).iterations == 2
    assert parse_args(["demo", "--iterations", "3"]).iterations == 3
    assert parse_args(["--iterations", "4"]).iterations == 4
    args = parse_args(["--gaussian", "--seed", "5", "demo", "--particles", "7"])
    assert (args.gaussian, args.seed, args.particles) == (True, 5, 7)
    defaults = parse_args(["demo"])
    assert {k: getattr(defaults, k) for k in DEMO_DEFAULTS} == DEMO_DEFAULTS
    assert parse_args([]).command is None  # the demo, with the defaults
    assert parse_args(["--seed", "3", "reproduce", "fig2"]).seed == 3
    assert parse_args(["reproduce", "fig2"]).seed == 0


def test_options_given_before_demo_are_honoured(capsys):
    threads = torch.get_num_threads()
    assert main([*TINY, "--threads", "1", "demo"]) == 0
    out = capsys.readouterr().out
    assert "N = 30" in out and "10 particles, up to 1 EM iterations" in out
    assert torch.get_num_threads() == threads  # --threads holds only while the demo runs


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--iterations", "-1"], "argument --iterations: must be >= 0, got -1"),
        (["--particles", "abc"], "argument --particles: expected an integer, got 'abc'"),
        (["demo", "--particles", "1"], "argument --particles: must be >= 2, got 1"),
        (["--n-samples", "1", "demo"], "argument --n-samples: must be >= 2, got 1"),
        (["--outliers", "2"], "argument --outliers: must lie in [0, 1), got 2"),
        (["--outliers", "nan"], "argument --outliers: must lie in [0, 1), got nan"),
        (["--seed", "-3"], "argument --seed: must be >= 0, got -3"),
        (["--threads", "0"], "argument --threads: must be >= 1, got 0"),
        (["reproduce", "fig2", "--seed", "x"], "argument --seed: expected an integer, got 'x'"),
        (["--iterations", "2", "reproduce", "fig2"], "--iterations: option(s) of the demo, not of reproduce"),
    ],
)
def test_bad_values_are_usage_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: python -m torch_nssm") and message in err
    assert "Traceback" not in err


def test_bad_value_from_the_shell_has_no_traceback():
    res = subprocess.run(
        [sys.executable, "-m", "torch_nssm", "--iterations", "-1", "demo"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        "python -m torch_nssm: error: argument --iterations: must be >= 0, got -1"
    )
