"""The engine and the estimator on a CUDA device (skipped where torch sees no GPU).

The same exact references as on the CPU (Kalman log-likelihood, RTS smoothed moments), plus what is
particular to a GPU: every result stays on the device inside the E-step, the number of host
synchronisations of an E-step does not grow with the record's length (no round-trip per time
step), and a fitted estimator moves back to the CPU when pickled.
"""

from __future__ import annotations

import os
import pickle
import warnings
from dataclasses import fields, replace

import numpy as np
import pytest
import torch
from conftest import generator, make_model, replicate
from reference import kalman_filter, rts_smoother
from test_filter_smoother import _check_log_likelihood, _check_moments

from torch_nssm import RobustNSSMEstimator, fit_independent
from torch_nssm.core.model import SequenceBatch, StateSpaceModel
from torch_nssm.core.noise import MeasurementNoise
from torch_nssm.datasets import make_paper_example
from torch_nssm.estimation.estep import EStepOptions, e_step
from torch_nssm.inference.ffbsi import ffbsi
from torch_nssm.inference.ffbsm import ffbsm, smoothed_moments
from torch_nssm.inference.filtering import particle_filter
from torch_nssm.models import PaperObservation, PaperTransition

#: The device under test; ``TORCH_NSSM_TEST_DEVICE=cpu`` runs these tests on the CPU (a check of the
#: tests themselves on a machine without a GPU; the synchronisation test needs CUDA).
CUDA = torch.device(os.environ.get("TORCH_NSSM_TEST_DEVICE", "cuda"))
pytestmark = pytest.mark.skipif(
    CUDA.type == "cuda" and not torch.cuda.is_available(), reason="no CUDA device"
)


def _to(obj, device):
    """A model (modules and tensors) or a batch moved to ``device``."""
    if isinstance(obj, StateSpaceModel):
        kw = {}
        for fl in fields(obj):
            v = getattr(obj, fl.name)
            movable = (torch.Tensor, torch.nn.Module, MeasurementNoise)
            kw[fl.name] = v.to(device=device) if isinstance(v, movable) else v
        return replace(obj, **kw)
    return SequenceBatch(obj.u.to(device), obj.y.to(device), obj.lengths.to(device))


def _gen(seed: int) -> torch.Generator:
    return torch.Generator(device=CUDA).manual_seed(seed)


def test_log_likelihood_matches_kalman_on_cuda(record):
    sysm, u, y = record
    exact = kalman_filter(*sysm.matrices(), u, y).log_likelihood
    filt = particle_filter(_to(sysm.model(), CUDA), _to(replicate(u, y, 20), CUDA), 500, generator=_gen(11))
    assert filt.particles.device.type == filt.log_likelihood.device.type == CUDA.type
    _check_log_likelihood(filt.log_likelihood.cpu().numpy(), exact)


@pytest.mark.parametrize("smoother", ["ffbsm", "reject", "mcmc"])
def test_smoothers_match_rts_on_cuda(record, smoother):
    sysm, u, y = record
    sm, sP = rts_smoother(sysm.A, kalman_filter(*sysm.matrices(), u, y))
    model, data = _to(sysm.model(), CUDA), _to(replicate(u, y, 16), CUDA)
    filt = particle_filter(model, data, 250, generator=_gen(21))
    if smoother == "ffbsm":
        smooth = ffbsm(model, data, filt)
    else:
        smooth = ffbsi(model, data, filt, method=smoother, generator=_gen(23))
    assert smooth.log_weights.device.type == CUDA.type
    mean, cov = smoothed_moments(filt.particles, smooth.log_weights)
    _check_moments(mean.cpu(), cov.cpu(), sm, sP)


@pytest.mark.parametrize("kernel_dtype", [torch.float64, torch.float32])
def test_ffbsm_on_cuda_equals_cpu_on_the_same_particles(record, kernel_dtype):
    """Same filter particles (moved from the CPU): the exact smoother agrees to rounding.

    The two devices build the backward kernel by different formulas (the CPU: ``exp2`` of one
    product against each row's bound; a GPU: the softmax of the logits), so they agree to the
    kernel's precision: ~1e-15 relative in double precision, ~1e-7 in single (the default; on an
    H200: 2e-16 and 1.4e-7 of each statistic's largest entry).
    """
    sysm, u, y = record
    model, data = sysm.model(), replicate(u, y, 4)
    filt = particle_filter(model, data, 200, generator=generator(5))
    ref = ffbsm(model, data, filt, kernel_dtype=kernel_dtype)
    filt_gpu = replace(
        filt,
        **{
            k: getattr(filt, k).to(CUDA)
            for k in ("particles", "log_weights", "log_likelihood", "ess", "ancestors")
        },
    )
    out = ffbsm(_to(model, CUDA), _to(data, CUDA), filt_gpu, kernel_dtype=kernel_dtype)
    rel = 1e-11 if kernel_dtype == torch.float64 else 1e-5
    for name in ("log_weights", "next_mean", "transition_weights", "residual_scatter"):
        a, b = getattr(out, name).cpu(), getattr(ref, name)
        finite = torch.isfinite(b)
        # relative to each statistic's own magnitude: entries near zero carry the others' rounding
        scale = b[finite].abs().max().item()
        torch.testing.assert_close(a[finite], b[finite], rtol=rel, atol=rel * scale)


@pytest.mark.parametrize("smoother", ["ffbsm", "mcmc"])
@pytest.mark.skipif(CUDA.type != "cuda", reason="counts CUDA synchronisations")
def test_host_synchronisations_do_not_grow_with_length(smoother):
    """An E-step synchronises with the host a fixed number of times, not once per time step
    (``ffbsi``'s rejection sampler is the documented exception: its number of tries is data)."""
    data_all = make_paper_example(n_samples=120, outlier_fraction=0.1, random_state=0)
    f, g = PaperTransition(0.9, 1.0), PaperObservation(1.0)
    model = make_model(f, g, [[0.1]], [[0.1]], 3.0, [0.0], [[1.0]])
    model = _to(model, CUDA)

    def n_syncs(n: int) -> int:
        t = lambda a: torch.as_tensor(np.asarray(a)[:n], dtype=torch.float64).reshape(n, -1)  # noqa: E731
        data = _to(SequenceBatch.from_sequences([t(data_all.u)], [t(data_all.y)]), CUDA)
        torch.cuda.synchronize()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                e_step(model, data, EStepOptions(64, smoother), _gen(0))
            finally:
                torch.cuda.set_sync_debug_mode("default")
        return sum("synchroniz" in str(w.message) for w in caught)

    short, long = n_syncs(40), n_syncs(120)
    assert long <= short + 2, (short, long)


@pytest.fixture(scope="module")
def paper_data():
    return make_paper_example(n_samples=300, outlier_fraction=0.1, random_state=1)


def _estimator(device, smoother="mcmc", n_iter=25):
    return RobustNSSMEstimator(
        PaperTransition(0.5, 0.5),
        PaperObservation(0.5),
        x0_mean=[0.0],
        n_particles=100,
        n_iter=n_iter,
        tol=0,
        random_state=0,
        smoother=smoother,
        device=device,
    )


def _theta(est) -> np.ndarray:
    return np.array([est.f_.a.item(), est.f_.b.item(), est.g_.c.item()])


@pytest.mark.parametrize("smoother", ["ffbsm", "mcmc"])
def test_estimator_end_to_end_on_cuda(paper_data, smoother):
    d = paper_data
    est = _estimator(str(CUDA), smoother).fit(d.u, d.y)
    cpu = _estimator("cpu", smoother).fit(d.u, d.y)
    got, ref = _theta(est), _theta(cpu)
    # different random streams: both near the truth and near each other (Monte Carlo error)
    np.testing.assert_allclose(got, [0.9, 1.0, 1.0], atol=0.1)
    np.testing.assert_allclose(got, ref, atol=0.05)
    assert abs(float(np.asarray(est.Rw_).squeeze()) - float(np.asarray(cpu.Rw_).squeeze())) < 0.05
    w = np.asarray(est.outlier_weights_).reshape(-1)
    assert np.isfinite(w).all() and np.median(w[d.outlier_mask]) < 0.3
    # the rest of the surface runs on the device and returns host arrays
    for out in (est.predict(d.u), est.predict(d.u, d.y, horizon=3)):
        assert isinstance(out, np.ndarray) and np.isfinite(out).all()
    assert 0.0 < est.score(d.u, d.y) <= 1.0
    sm = est.smooth(d.u, d.y)
    assert np.isfinite(np.asarray(sm.mean)).all()
    states, outputs = est.simulate(d.u, n_samples=3)
    assert np.isfinite(np.asarray(outputs)).all()
    # a pickled fit loads on a machine without a GPU: its modules are saved on the CPU
    again = pickle.loads(pickle.dumps(est))
    assert all(p.device.type == "cpu" for p in again.f_.parameters())


def test_fit_independent_on_cuda():
    datas = [make_paper_example(n_samples=200, outlier_fraction=0.1, random_state=s) for s in range(4)]
    fits = fit_independent(_estimator(str(CUDA), n_iter=20), [d.u for d in datas], [d.y for d in datas])
    assert len(fits) == 4
    theta = np.array([_theta(e) for e in fits])
    assert np.isfinite(theta).all()
    assert len({tuple(np.round(t, 6)) for t in theta}) == 4  # each data set its own parameters
    np.testing.assert_allclose(theta.mean(0), [0.9, 1.0, 1.0], atol=0.1)


def test_neural_fit_end_to_end_on_cuda():
    """A network ``f``: the neural first stage (LBFGS over windows of the record) and EM run on
    the device, the fitted network stays there and simulates the record."""
    from torch_nssm.blocks.linear import LinearObservation
    from torch_nssm.datasets import make_pendulum
    from torch_nssm.neural import MLPTransition

    d = make_pendulum(n_samples=300, outlier_fraction=0.03, random_state=0, n_validation=50)
    net = MLPTransition(2, 1, hidden=(16,), random_state=0)
    g = LinearObservation(2, 1, 1, C=[[1.0, 0.0]], fit_offset=False).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = RobustNSSMEstimator(
            net, g, x0_mean=list(d.x0_guess), n_particles=50, n_iter=3, random_state=0, device=str(CUDA)
        ).fit(d.u, d.y)
    assert est.first_stage_.accepted
    assert all(p.device.type == CUDA.type for p in est.f_.parameters())
    y = np.asarray(d.y).reshape(-1)
    regular = ~np.asarray(d.outlier_mask).reshape(-1)
    free = np.asarray(est.predict(d.u)).reshape(-1)
    assert np.isfinite(free).all()
    # the trained network simulates the record far better than a constant
    assert np.sqrt(np.mean((free - y)[regular] ** 2)) < 0.5 * np.std(y[regular])

