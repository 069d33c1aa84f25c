"""``import torch_nssm`` is light: public names resolve on first use (PEP 562)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch_nssm

REPO = Path(__file__).resolve().parents[2]


def _run(code: str, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *flags, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )


def test_import_is_lazy():
    code = (
        "import json, sys, torch_nssm; "
        "print(json.dumps([m for m in ('matplotlib', 'torch_nssm.reproduce', 'torch_nssm.datasets', "
        "'torch_nssm.plotting', 'tqdm') if m in sys.modules]))"
    )
    res = _run(code)
    assert res.returncode == 0, res.stderr
    loaded = json.loads(res.stdout.strip().splitlines()[-1])
    assert not {"matplotlib", "torch_nssm.reproduce", "torch_nssm.datasets"} & set(loaded), loaded


def test_import_loads_no_plotting_scipy_or_dask():
    """``import torch_nssm`` loads neither matplotlib, scipy, dask nor scikit-learn (public names
    resolve on first use); the estimator's import loads scikit-learn's base (which loads scipy) but
    not ``sklearn.metrics``, matplotlib nor dask, and neither does a fit (torch itself loads tqdm)."""
    heavy = ("matplotlib", "scipy", "dask", "distributed", "sklearn", "sklearn.metrics")
    code = (
        "import json, sys, warnings\n"
        f"heavy = {heavy!r}\n"
        "loaded = lambda: [m for m in heavy if m in sys.modules]\n"
        "import torch_nssm\n"
        "package = loaded()\n"
        "from torch_nssm import RobustNSSMEstimator\n"
        "estimator = loaded()\n"
        "from torch_nssm.datasets import make_paper_example\n"
        "from torch_nssm.models import PaperObservation, PaperTransition\n"
        "warnings.simplefilter('ignore')\n"
        "d = make_paper_example(n_samples=40, random_state=0)\n"
        "RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0], n_particles=10,\n"
        "                    n_iter=1, first_stage=None).fit(d.u, d.y)\n"
        "print(json.dumps([package, estimator, loaded()]))\n"
    )
    res = _run(code)
    assert res.returncode == 0, res.stderr
    package, estimator, fitted = json.loads(res.stdout.strip().splitlines()[-1])
    assert package == []
    assert "sklearn" in estimator  # the check sees what is loaded
    for loaded in (estimator, fitted):
        assert not {"matplotlib", "dask", "distributed", "sklearn.metrics"} & set(loaded), loaded


def test_import_emits_no_warning():
    res = _run("import torch_nssm", "-W", "error")
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""


def test_importing_the_package_and_its_modules_emits_no_warning():
    code = (
        "import torch_nssm, torch_nssm.estimator, torch_nssm.plotting, torch_nssm.datasets, "
        "torch_nssm.models, torch_nssm.neural, torch_nssm.starts, torch_nssm.cli, "
        "torch_nssm.reproduce"
    )
    res = _run(code, "-W", "error")
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""


def test_no_tqdm_auto_unless_progress_is_shown():
    """``tqdm.auto`` warns (TqdmWarning) when imported in a notebook without ipywidgets: it is
    imported only when a progress bar is shown (``verbose > 0``, ``progress=True``)."""
    code = (
        "import json, sys, warnings\n"
        "import torch_nssm, torch_nssm.estimator, torch_nssm.reproduce\n"
        "from torch_nssm import RobustNSSMEstimator\n"
        "from torch_nssm.datasets import make_paper_example\n"
        "from torch_nssm.models import PaperObservation, PaperTransition\n"
        "warnings.simplefilter('ignore')\n"
        "d = make_paper_example(n_samples=40, random_state=0)\n"
        "RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0], n_particles=10,\n"
        "                    n_iter=1, verbose=0).fit(d.u, d.y)\n"
        "auto = lambda: [m for m in ('tqdm.auto', 'tqdm.autonotebook') if m in sys.modules]\n"
        "quiet = auto()\n"
        "RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0], n_particles=10,\n"
        "                    n_iter=1, verbose=1).fit(d.u, d.y)\n"
        "print(json.dumps([quiet, auto()]))\n"
    )
    res = _run(code)
    assert res.returncode == 0, res.stderr
    quiet, shown = json.loads(res.stdout.strip().splitlines()[-1])
    assert quiet == []
    assert shown  # the check itself sees tqdm.auto once a bar is shown


def test_public_names_resolve():
    code = (
        "import torch_nssm; "
        "[getattr(torch_nssm, n) for n in torch_nssm.__all__]; "
        "import sys; print('torch_nssm.reproduce' in sys.modules)"
    )
    res = _run(code)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().endswith("False")  # resolving every public name leaves reproduce out
    for name in torch_nssm.__all__:
        assert getattr(torch_nssm, name) is not None
        assert name in dir(torch_nssm)
    from torch_nssm import reproduce  # the optional subpackage, by name

    assert callable(reproduce.fig2)


def test_unknown_name_raises_attribute_error():
    import pytest

    with pytest.raises(AttributeError, match="no_such_name"):
        torch_nssm.no_such_name  # noqa: B018


def test_public_paths_of_moved_modules():
    """The old import paths re-export the objects of their new homes."""
    from torch_nssm import blocks, models, neural, starts
    from torch_nssm.datasets import manipulator, paper

    assert neural.MLPTransition is blocks.MLPTransition
    assert starts.distilled_start is blocks.distilled_start is torch_nssm.distilled_start
    assert starts.LinearTransition is blocks.LinearTransition
    assert models.PaperTransition is paper.PaperTransition
    assert models.ManipulatorTransition is manipulator.ManipulatorTransition
    assert set(neural.__all__) <= set(dir(neural))
