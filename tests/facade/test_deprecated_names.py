"""The old public names still work for one release, each with a ``DeprecationWarning`` that names
its new home."""

from __future__ import annotations

import importlib

import pytest

_OLD_SMOOTHING = "torch_nssm.inference.smoothing"
_FFBSM, _FFBSI = "torch_nssm.inference.ffbsm", "torch_nssm.inference.ffbsi"

#: (module, old name, new module, new name)
ALIASES = [
    ("torch_nssm", "warm_start_estimator", "torch_nssm.starts", "distilled_start"),
    ("torch_nssm", "simulation_warm_start", "torch_nssm.starts", "simulation_start"),
    ("torch_nssm.warm_start", "warm_start_estimator", "torch_nssm.starts", "distilled_start"),
    ("torch_nssm.warm_start", "simulation_warm_start", "torch_nssm.starts", "simulation_start"),
    ("torch_nssm.warm_start", "WarmStartInfo", "torch_nssm.starts", "DistilledStartInfo"),
    ("torch_nssm.warm_start", "distill", "torch_nssm.starts", "distill"),
    ("torch_nssm.warm_start", "LinearTransition", "torch_nssm.starts", "LinearTransition"),
    ("torch_nssm.warm_start", "LinearObservation", "torch_nssm.starts", "LinearObservation"),
    ("torch_nssm.blocks", "warm_start_estimator", "torch_nssm.blocks", "distilled_start"),
    ("torch_nssm.blocks", "simulation_warm_start", "torch_nssm.blocks", "simulation_start"),
    ("torch_nssm.blocks", "WarmStartInfo", "torch_nssm.blocks", "DistilledStartInfo"),
    ("torch_nssm.blocks.warm_start", "warm_start_estimator", "torch_nssm.blocks.starts", "distilled_start"),
    ("torch_nssm.blocks.warm_start", "simulation_warm_start", "torch_nssm.blocks.starts", "simulation_start"),
    ("torch_nssm.blocks.warm_start", "WarmStartInfo", "torch_nssm.blocks.starts", "DistilledStartInfo"),
    (_OLD_SMOOTHING, "SmootherOutput", _FFBSM, "SmootherOutput"),
    (_OLD_SMOOTHING, "ffbsm", _FFBSM, "ffbsm"),
    (_OLD_SMOOTHING, "smoothed_moments", _FFBSM, "smoothed_moments"),
    (_OLD_SMOOTHING, "TINY_WEIGHT", _FFBSM, "TINY_WEIGHT"),
    (_OLD_SMOOTHING, "ffbsi", _FFBSI, "ffbsi"),
    (_OLD_SMOOTHING, "backward_trajectories", _FFBSI, "backward_trajectories"),
    (_OLD_SMOOTHING, "backward_segments", _FFBSI, "backward_segments"),
]


@pytest.mark.parametrize(("module", "old", "new_module", "new"), ALIASES, ids=lambda v: str(v))
def test_old_name_warns_and_is_the_new_object(module, old, new_module, new):
    mod = importlib.import_module(module)
    with pytest.warns(DeprecationWarning, match=rf"{module}\.{old} is deprecated.*use .*\b{new}\b"):
        value = getattr(mod, old)
    assert value is getattr(importlib.import_module(new_module), new)


def test_old_module_path_warns_and_is_the_new_module():
    import torch_nssm
    import torch_nssm.starts

    with pytest.warns(DeprecationWarning, match=r"torch_nssm\.warm_start is deprecated.*torch_nssm\.starts"):
        value = torch_nssm.__getattr__("warm_start")  # what `torch_nssm.warm_start` resolves to
    assert value is torch_nssm.starts


def test_old_start_name_still_works_end_to_end():
    """The old name runs the renamed function: the same clone with the same reference fit."""
    import numpy as np

    import torch_nssm
    from torch_nssm import RobustNSSMEstimator
    from torch_nssm.datasets import make_paper_example
    from torch_nssm.models import PaperObservation, PaperTransition

    d = make_paper_example(n_samples=60, random_state=0)
    est = RobustNSSMEstimator(
        PaperTransition(), PaperObservation(), x0_mean=[0.0], n_particles=20, first_stage=None, random_state=0
    )
    with pytest.warns(DeprecationWarning, match="distilled_start"):
        old = torch_nssm.warm_start_estimator(est, d.u, d.y, n_iter=2, n_jitter=0)
    new = torch_nssm.distilled_start(est, d.u, d.y, n_iter=2, n_jitter=0)
    np.testing.assert_array_equal(old.Rv_init, new.Rv_init)
    np.testing.assert_array_equal(old.x0_mean, new.x0_mean)


def test_unknown_names_still_raise_attribute_error():
    import torch_nssm.blocks
    import torch_nssm.warm_start

    for mod in (torch_nssm.warm_start, torch_nssm.blocks):
        with pytest.raises(AttributeError, match="no_such_name"):
            mod.no_such_name  # noqa: B018
