"""The information's sampler and windowed covariance run in inference mode; no inference tensor may
leave them: not into :class:`ParameterUncertainty`, the estimator's ``standard_errors_``, the
accelerated EM's :class:`InformationAt`, nor the model (whose autograd must still work after)."""

from __future__ import annotations

import warnings

import numpy as np
import torch
from conftest import generator, inference_tensors, paper_model, simulate

from torch_nssm import RobustNSSMEstimator
from torch_nssm.blocks.linear import LinearObservation, LinearTransition
from torch_nssm.core.model import SequenceBatch
from torch_nssm.estimation.acceleration import information_at
from torch_nssm.estimation.estep import EStepOptions, e_step
from torch_nssm.estimation.uncertainty import observed_information
from torch_nssm.inference.ffbsi import backward_segments


def _paper_estep():
    model = paper_model(dof=4.0)
    data = SequenceBatch.from_sequences(*simulate(model, [120, 90], np.random.default_rng(1), 0.1))
    return model, data, e_step(model, data, EStepOptions(60), generator(2))


def _no_tensors(obj) -> list[str]:
    """Paths of any tensors in a result made of arrays (inference or not: there should be none)."""
    if isinstance(obj, torch.Tensor):
        return ["tensor"]
    if isinstance(obj, dict):
        return [p for v in obj.values() for p in _no_tensors(v)]
    if isinstance(obj, (list, tuple)):
        return [p for v in obj for p in _no_tensors(v)]
    return []


def test_information_outputs_hold_noinference_tensors():
    model, data, est = _paper_estep()
    Js = backward_segments(
        model, data, est.filter, 30, [0, 40], 50, log_weights=est.smoother.log_weights,
        generator=generator(3),
    )
    assert not Js.is_inference()
    Js[0, 0, 0, 0] = 0  # an ordinary tensor: modifiable outside inference mode

    unc = observed_information(model, data, est, n_trajectories=40, generator=generator(4))
    assert inference_tensors(unc, "unc") == []
    assert _no_tensors(vars(unc)) == []
    assert np.isfinite(unc.information).all()

    info = information_at(model, data, est, generator(5))
    assert info is not None and inference_tensors(info, "info") == []

    # the model's parameters still train: a loss through f and g, and its gradients
    params = [p for m in (model.f, model.g) for p in m.parameters()]
    assert not any(p.is_inference() for p in params) and not model.Rw.is_inference()
    x = torch.nan_to_num(data.y[:, :, :1])
    loss = model.f(x, data.u).square().sum() + model.g(x, data.u).square().sum()
    loss.backward()
    assert all(p.grad is not None for p in params if p.requires_grad)


def test_estimator_standard_errors_hold_noinference_tensors():
    rng = np.random.default_rng(0)
    A, B = np.array([[0.8, 0.2], [-0.3, 0.6]]), np.array([[1.0], [0.5]])
    x, u = np.zeros((120, 2)), rng.standard_normal((120, 1))
    for k in range(119):
        x[k + 1] = A @ x[k] + B @ u[k] + 0.3 * rng.standard_normal(2)
    y = x + 0.25 * rng.standard_normal((120, 2))
    g = LinearObservation(2, 1, 2, fit_offset=False)
    g.C.requires_grad_(False)
    est = RobustNSSMEstimator(
        LinearTransition(2, 1, A=A, B=B), g, x0_mean=np.zeros(2), noise="gaussian",
        n_particles=50, n_iter=2, tol=0, random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(u, y)
        se = est.standard_errors_
        ci = est.confidence_intervals()
    assert inference_tensors(se, "se") == [] and _no_tensors(se) == []
    assert inference_tensors(ci, "ci") == [] and _no_tensors(ci) == []
    assert inference_tensors(est._uncertainty, "unc") == []
    assert not any(p.is_inference() for p in est.f_.parameters())
    est.f_.A.sum().backward()  # the fitted module still takes autograd
