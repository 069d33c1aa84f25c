"""Clear errors before any work starts: each bad argument gives a ValueError or TypeError that
names the argument and the problem, and neither the particle filter nor the smoother has run.

(Numerical failures *during* a fit, which must keep the last good parameters, are tested in
``test_estimator.py``.)
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import torch
from torch import nn

import torch_nssm._model_state as model_state_module
from torch_nssm import RobustNSSMEstimator
from torch_nssm.models import PaperObservation, PaperTransition

N = 40
RNG = np.random.default_rng(0)
U = RNG.standard_normal(N)
Y = np.cos(RNG.standard_normal(N))


class WrongShape(nn.Module):
    """Returns ``(..., 2)`` whatever is asked."""

    def forward(self, x, u):
        return torch.zeros(*x.shape[:-1], 2, dtype=x.dtype)


class Broken(nn.Module):
    def forward(self, x, u):
        raise RuntimeError("boom")


def make(**kw) -> RobustNSSMEstimator:
    params = dict(x0_mean=[0.0], n_particles=10, n_iter=1, tol=0.0, random_state=0)
    params.update(kw)
    f = params.pop("f", PaperTransition(0.5, 0.5))
    g = params.pop("g", PaperObservation(0.5))
    return RobustNSSMEstimator(f, g, **params)


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if the E-step or the particle filter is reached."""

    def forbidden(*args, **kwargs):
        raise AssertionError("work started before the arguments were checked")

    monkeypatch.setattr(model_state_module, "e_step", forbidden)  # the estimator's E-step and filter
    monkeypatch.setattr(model_state_module, "particle_filter", forbidden)


BAD_DATA = [
    # (u, y, exception, message naming the argument)
    (U[:-1], Y, ValueError, r"u and y must have the same length, got 39 and 40"),
    (U.reshape(N, 1, 1), Y, ValueError, r"u must be 1-D .* or 2-D .* got shape \(40, 1, 1\)"),
    (U, Y.reshape(N, 1, 1), ValueError, r"y must be 1-D .* or 2-D"),
    (np.where(np.arange(N) == 7, np.nan, U), Y, ValueError, r"u contains NaN .* sample 7"),
    (np.where(np.arange(N) == 3, np.inf, U), Y, ValueError, r"u contains NaN or infinite"),
    (U, np.full(N, np.nan), ValueError, r"y is all missing"),
    (U, np.where(np.arange(N) == 2, np.inf, Y), ValueError, r"y contains infinite values"),
    (U, None, ValueError, r"y is required"),
    (U[:1], Y[:1], ValueError, r"y must have at least 2 samples, got 1 sample"),
    (U, Y + 1j, ValueError, r"y: Complex data not supported"),
    (np.array(["a"] * N), Y, TypeError, r"u must be array-like of real numbers"),
    (scipy.sparse.csr_matrix(U.reshape(N, 1)), Y, TypeError, r"u: sparse input is not supported"),
    ([U[:20], U[20:]], [Y[:20], Y[20:], Y], ValueError, r"u and y must hold the same number"),
    (U, [Y[:20], Y[20:]], ValueError, r"y is a list of records, so u must be a list"),
    ([U[:20], U[20:]], Y, ValueError, r"u is a list of records, so y must be a list"),
    ([U[:20], U[20:-1]], [Y[:20], Y[20:]], ValueError, r"u\[1\] and y\[1\] must have the same"),
    ([U[:20], U[20:]], [Y[:20], np.full(20, np.nan)], ValueError, r"y\[1\] is all missing"),
]


@pytest.mark.parametrize("u, y, exc, match", BAD_DATA)
def test_bad_data(no_work, u, y, exc, match):
    with pytest.raises(exc, match=match):
        make().fit(u, y)


BAD_PARAMS = [
    # (estimator arguments, exception, message naming the argument)
    (dict(x0_mean=None), ValueError, r"x0_mean is required"),
    (dict(x0_mean=[np.nan]), ValueError, r"x0_mean must be finite"),
    (dict(x0_mean=[0.0, 0.0]), ValueError, r"x0_mean has 2 entries but f \(PaperTransition\) declares nx=1"),
    (dict(f=WrongShape()), ValueError, r"f\(x, u\) must return shape \(\.\.\., 1\) \(the state"),
    (dict(g=WrongShape()), ValueError, r"g\(x, u\) must return shape \(\.\.\., 1\) \(the number"),
    (dict(g=Broken()), ValueError, r"g\(x, u\) failed .*RuntimeError: boom"),
    (dict(f="a x + b u"), TypeError, r"f must be a torch.nn.Module"),
    (dict(g=lambda x, u: x), TypeError, r"g must be a torch.nn.Module"),
    (dict(Rw_init=-0.1), ValueError, r"Rw_init must be positive definite"),
    (dict(Rw_init=[[0.1, 0.0], [0.0, 0.1]]), ValueError, r"Rw_init must be a \(1, 1\) matrix"),
    (dict(Rv_init=0.0), ValueError, r"Rv_init must be positive definite"),
    (dict(Rv_init=[[np.inf]]), ValueError, r"Rv_init must be finite"),
    (dict(x0_cov=-1.0), ValueError, r"x0_cov must be positive definite"),
    (
        dict(x0_mean=[0.0, 0.0], x0_cov=[[1.0, 2.0], [0.0, 1.0]]),
        ValueError,
        r"x0_cov must be symmetric",
    ),
    (dict(dof_init=0.0), ValueError, r"dof_init must be > 0"),
    (dict(dof_init=-3.0), ValueError, r"dof_init must be > 0"),
    (dict(dof_init="5"), TypeError, r"dof_init must be a number"),
    (dict(dof_bounds=(10.0, 1.0)), ValueError, r"dof_bounds must satisfy 0 < low < high"),
    (dict(dof_bounds=5.0), ValueError, r"dof_bounds must be a pair"),
    (dict(n_particles=1), ValueError, r"n_particles must be >= 2, got 1"),
    (dict(n_particles=10.5), TypeError, r"n_particles must be an integer"),
    (dict(n_iter=-1), ValueError, r"n_iter must be >= 0"),
    (dict(n_init=0), ValueError, r"n_init must be >= 1"),
    (dict(init_jitter=-0.1), ValueError, r"init_jitter must be >= 0"),
    (dict(tol=-1.0), ValueError, r"tol must be >= 0"),
    (dict(max_iter_mstep=0), ValueError, r"max_iter_mstep must be >= 1"),
    (dict(learning_rate=0.0), ValueError, r"learning_rate must be > 0"),
    (dict(ess_threshold=1.5), ValueError, r"ess_threshold must lie in \[0, 1\]"),
    (dict(chunk_size=0), ValueError, r"chunk_size must be >= 1"),
    (dict(warm_start="yes"), TypeError, r"warm_start must be True or False"),
    (dict(resampling="bootstrap"), ValueError, r"resampling must be one of .*'bootstrap'"),
    (dict(noise="cauchy"), ValueError, r"noise must be one of .*'cauchy'"),
    (dict(optimizer="sgd"), ValueError, r"optimizer must be one of .*'sgd'"),
    (dict(smoother="kalman"), ValueError, r"smoother must be one of .*'kalman'"),
    (dict(dtype=torch.float16), ValueError, r"dtype must be torch.float32 or torch.float64"),
    (dict(device="cuda:99"), ValueError, r"device 'cuda:99' is not available"),
    (dict(device="no-such-device"), ValueError, r"device 'no-such-device' is not a valid"),
]


@pytest.mark.parametrize("kw, exc, match", BAD_PARAMS)
def test_bad_parameters(no_work, kw, exc, match):
    with pytest.raises(exc, match=match):
        make(**kw).fit(U, Y)


class ScalarTransition(nn.Module):
    """``a x + b u`` for one state, written without declaring ``nx``: elementwise on a longer ``x``."""

    def forward(self, x, u):
        return 0.9 * x + u


class CosObservation(nn.Module):
    """``cos(x)``, elementwise: one column per state entry."""

    def forward(self, x, u):
        return torch.cos(x)


class FirstState(nn.Module):
    """A one-state transition that reads ``x[..., :1]``: it returns one state whatever ``x`` is."""

    def forward(self, x, u):
        return 0.9 * x[..., :1] + u


WRONG_X0_MEAN = [
    # (f, g, message): the error names x0_mean, not g, when x0_mean has the wrong length
    (PaperTransition(0.5, 0.5), PaperObservation(0.5), r"x0_mean has 2 entries but f \(PaperTransition\) "
     r"declares nx=1"),
    (ScalarTransition(), CosObservation(), r"g returns one column per state entry: is x0_mean the right "
     r"length \(2 entries\)"),
    (FirstState(), CosObservation(), r"f returns 1 state\(s\) for 2: .* x0_mean has the wrong length "
     r"\(2 entries, needs 1\)"),
]


@pytest.mark.parametrize("f, g, match", WRONG_X0_MEAN)
def test_x0_mean_of_the_wrong_length_is_named(no_work, f, g, match):
    with pytest.raises(ValueError, match=match):
        make(f=f, g=g, x0_mean=[0.0, 0.0]).fit(U, Y)


TRANSPOSED = [
    # (u, y, message): a (1, N) record says it looks transposed
    (U.reshape(1, N), Y.reshape(1, N), r"y must have at least 2 samples, got 1 sample\(s\); y has shape "
     r"\(1, 40\).*transposed\? Pass y.T \(shape \(40, 1\)\) or a 1-D array of 40 samples"),
    (U, Y.reshape(1, N), r"y has shape \(1, 40\).*transposed"),
    (U.reshape(1, N), Y, r"u and y must have the same length, got 1 and 40; u has shape \(1, 40\).*Pass u.T"),
]


@pytest.mark.parametrize("u, y, match", TRANSPOSED)
def test_a_transposed_record_is_named(no_work, u, y, match):
    with pytest.raises(ValueError, match=match):
        make().fit(u, y)


def test_output_count_mismatch_names_g(no_work):
    with pytest.raises(ValueError, match=r"g\(x, u\) must return shape \(\.\.\., 2\)"):
        make().fit(U, np.stack([Y, Y], 1))


@pytest.fixture(scope="module")
def fitted():
    return make(n_iter=0).fit(U, Y)


BAD_AFTER_FIT = [
    ("predict", (np.zeros((N, 2)),), {}, ValueError, r"u has 2 input columns, expected 1"),
    ("predict", (None,), {}, ValueError, r"u is required"),
    ("predict", (U.reshape(1, N),), {}, ValueError, r"u has 40 input columns, expected 1.*Pass u.T"),
    ("score", (U, np.stack([Y, Y], 1)), {}, ValueError, r"y has 2 output columns, expected 1"),
    ("score", (U, Y), dict(sample_weight=np.ones(3)), ValueError, r"sample_weight must have 40"),
    ("smooth", (U[:-2], Y), {}, ValueError, r"u and y must have the same length"),
    ("filter", (U, np.full(N, np.nan)), {}, ValueError, r"y is all missing"),
    ("log_likelihood", (np.where(U > 0, np.nan, U), Y), {}, ValueError, r"u contains NaN"),
    ("simulate", (U,), dict(n_samples=0), ValueError, r"n_samples must be >= 1"),
    ("predict", (U, Y), dict(horizon=-2), ValueError, r"horizon must be >= 0"),
]


@pytest.mark.parametrize("method, args, kw, exc, match", BAD_AFTER_FIT)
def test_bad_arguments_after_fit(fitted, no_work, method, args, kw, exc, match):
    with pytest.raises(exc, match=match):
        getattr(fitted, method)(*args, **kw)
