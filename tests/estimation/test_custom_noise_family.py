"""A noise family defined here, outside the package, and registered from the test: the contaminated
Gaussian ``v ~ (1 - eps) N(0, Rv) + eps N(0, k Rv)`` with an estimated contamination ``eps`` (on its
own logit working scale, defined here too) and a fixed variance inflation ``k``.

It is a Gaussian scale mixture (``lam = 1`` or ``1/k``), so the latent-scale EM fits it: the
posterior probability ``pi`` of the wide component gives ``<lam> = 1 - pi + pi / k`` and
``<log lam> = -pi log k``, and the M-step's ``eps`` is the mean ``pi``.  Nothing else in the package
knows it: its fits, fitted attributes, history, standard errors, squared extrapolation and
bootstrap come from its class alone.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from torch import Tensor

from torch_nssm import RobustNSSMEstimator
from torch_nssm.core.noise import (
    NOISE_MODELS,
    JointScaleNoise,
    NoiseSpec,
    SquaredNormEvaluator,
    register_noise_model,
)
from torch_nssm.core.noise.base import gaussian_log_normaliser, random_source, step_views
from torch_nssm.core.scales import LOG_CHOLESKY, WorkingScale
from torch_nssm.datasets.paper import PaperObservation, PaperTransition

EPS, INFLATION, RV, N = 0.1, 25.0, 0.05, 600


class _Logit(WorkingScale):
    """A fraction in (0, 1) by its logit."""

    kind = "logit"

    def to_working(self, value: Tensor) -> Tensor:
        return torch.logit(value).reshape(-1)

    def from_working(self, w: Tensor, value: Tensor) -> Tensor:
        return torch.sigmoid(w).reshape(value.shape)

    def working_names(self, key: str, value: Tensor) -> list[str]:
        return [f"logit {key}"]

    def extrapolation(self, a: np.ndarray) -> np.ndarray | None:
        return np.log(a / (1.0 - a)) if np.all((a > 0) & (a < 1)) else None

    def from_extrapolation(self, c: np.ndarray, bounds) -> np.ndarray:
        return np.clip(1.0 / (1.0 + np.exp(-c)), *bounds)


LOGIT = _Logit()


@dataclass(frozen=True)
class Contaminated(NoiseSpec):
    """``eps``: initial contamination; ``inflation``: ``k``, held; ``fit_eps``: estimate ``eps``."""

    eps: float = 0.05
    inflation: float = INFLATION
    fit_eps: bool = True

    name = "contaminated-gaussian"

    def initial(self, Rv: Tensor) -> ContaminatedNoise:
        eps = torch.tensor(self.eps, dtype=Rv.dtype, device=Rv.device)
        return ContaminatedNoise(Rv=Rv, eps=eps, spec=self)

    def starting_at(self, noise: ContaminatedNoise) -> Contaminated:
        return dataclasses.replace(self, eps=float(noise.eps))


class _Evaluator(SquaredNormEvaluator):
    """``log((1 - eps) exp(-delta2 / 2) + eps k^(-p/2) exp(-delta2 / (2 k)))`` per particle."""

    def __init__(self, eps: Tensor, k: float, scale, n_particles: int):
        const = gaussian_log_normaliser(scale.n_obs, scale.logdet)
        super().__init__(const, n_particles)
        self._narrow = step_views(torch.log1p(-eps).expand_as(const)[..., None, None])
        self._wide = step_views((torch.log(eps) - 0.5 * scale.n_obs * math.log(k))[..., None, None])
        self._k = k

    def step(self, k: int, z: Tensor) -> Tensor:
        delta2 = self.squared_norm(k, z)
        narrow, wide = self._narrow[k] - 0.5 * delta2, self._wide[k] - 0.5 * delta2 / self._k
        torch.logaddexp(narrow, wide, out=self._logits_col)
        return self._logits


@dataclass(frozen=True)
class ContaminatedNoise(JointScaleNoise):
    eps: Tensor

    name = "contaminated-gaussian"
    SPEC = Contaminated
    CORE_DIMS = {"Rv": 2, "eps": 0}
    WORKING = {"Rv": LOG_CHOLESKY, "eps": LOGIT}

    @property
    def k(self) -> float:
        return self.spec.inflation

    def _wide(self, delta2: Tensor, n_obs, eps: Tensor) -> Tensor:
        """Posterior probability of the wide component."""
        k = self.k
        return torch.sigmoid(torch.logit(eps) - 0.5 * n_obs * math.log(k) + 0.5 * delta2 * (1.0 - 1.0 / k))

    def evaluator(self, scale, n_particles):
        eps = self.per_sequence("eps", scale.logdet.shape[1]).unsqueeze(0)  # (1, B)
        return _Evaluator(eps, self.k, scale, n_particles)

    def log_prob(self, residual: Tensor) -> Tensor:
        mask = torch.ones_like(residual, dtype=torch.bool)
        return self.residual_log_prob(residual, mask, True)

    def latent_expectations(self, statistics, scale, sl):
        B = statistics.shape[1]
        eps = self.per_sequence("eps", B).view(1, B, 1)
        pi = self._wide(statistics[sl], scale.n_obs[sl].unsqueeze(-1), eps)
        return 1.0 - pi + pi / self.k, -pi * math.log(self.k)

    def statistics(self, r, W, e_lam, e_log_lam, scale, sl):
        stats = super().statistics(r, W, e_lam, e_log_lam, scale, sl)
        stats["wide"] = (W * e_log_lam).sum((0, 2)) / -math.log(self.k)  # sum of pi
        return stats

    def updated(self, stats, *, fit_Rv=True, fit_shape=True):
        eps = self.eps
        if fit_shape and self.spec.fit_eps:
            eps = (stats["wide"] / stats["n_obs"].clamp_min(1)).clamp(*self.bounds("eps")).reshape(eps.shape)
        return self.replace(Rv=self._updated_scale(stats, fit_Rv), eps=eps.to(self.eps))

    def sample(self, shape, generator=None):
        draws = random_source(generator, self.Rv)
        z = draws.gaussian(shape, self.Rv)
        wide = draws.uniform(shape) < self.eps
        return z * torch.where(wide, math.sqrt(self.k), 1.0).unsqueeze(-1)

    def estimated(self, fit_Rv=True, fit_shape=True):
        return (["Rv"] if fit_Rv else []) + (["eps"] if fit_shape and self.spec.fit_eps else [])

    def bounds(self, name):
        return (1e-6, 0.5) if name == "eps" else None

    def density_of_norms(self, delta2, logdet, n_obs):
        eps, k = self.eps, self.k
        mix = torch.logaddexp(
            torch.log1p(-eps) - 0.5 * delta2, torch.log(eps) - 0.5 * n_obs * math.log(k) - 0.5 * delta2 / k
        )
        return -0.5 * (n_obs * math.log(2 * math.pi) + logdet) + mix

    def latent_weight(self, delta2, p, weight):
        """``-2 d log p / d delta2 = <lam>``; ``d log p / d logit(eps) = pi - eps``."""
        pi = self._wide(delta2, p, self.eps)
        return 1.0 - pi + pi / self.k, {"eps": weight * (pi - self.eps).unsqueeze(-1)}


@pytest.fixture
def registered():
    register_noise_model(ContaminatedNoise)
    yield ContaminatedNoise
    NOISE_MODELS.pop(ContaminatedNoise.name, None)


def _record(n: int = N, seed: int = 0):
    """The paper's system (a = 0.9, b = c = 1, Rw = 0.1) with contaminated Gaussian noise."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = 0.0
    for k in range(n - 1):
        x[k + 1] = 0.9 * x[k] + u[k] + math.sqrt(0.1) * rng.standard_normal()
    noise = Contaminated(eps=EPS).initial(torch.tensor([[RV]], dtype=torch.float64))
    v = noise.sample((n,), torch.Generator().manual_seed(seed)).numpy()[:, 0]
    return u, np.cos(x) + v


def _estimator(noise, **kw) -> RobustNSSMEstimator:
    options = dict(
        x0_mean=[0.0], Rw_init=0.1, Rv_init=0.1, noise=noise, n_particles=100, n_iter=30, tol=0,
        random_state=0,
    )
    options.update(kw)
    return RobustNSSMEstimator(PaperTransition(0.8, 0.8), PaperObservation(0.8), **options)


def test_density_sampler_and_latent_moments_agree(registered):
    """The log-density integrates the sampler's draws (KS against the mixture CDF), its derivative
    in ``delta2`` is ``-<lam> / 2``, and the filter's evaluator gives the same density."""
    from scipy import stats

    noise = Contaminated(eps=0.2).initial(torch.tensor([[0.5]], dtype=torch.float64))
    x = noise.sample((20000,), torch.Generator().manual_seed(1)).numpy()[:, 0]
    narrow, wide = stats.norm(scale=math.sqrt(0.5)), stats.norm(scale=math.sqrt(12.5))
    cdf = lambda t: 0.8 * narrow.cdf(t) + 0.2 * wide.cdf(t)  # noqa: E731
    assert stats.kstest(x, cdf).pvalue > 1e-3
    d2 = torch.linspace(0.0, 30.0, 7, dtype=torch.float64).requires_grad_(True)
    logp = noise.density_of_norms(d2, torch.tensor(math.log(0.5), dtype=torch.float64), 1.0)
    (grad,) = torch.autograd.grad(logp.sum(), d2)
    lam, _ = noise.latent_weight(d2.detach(), 1, torch.ones(7, 1, dtype=torch.float64))
    np.testing.assert_allclose(-2.0 * grad.numpy(), lam.numpy(), rtol=1e-12)
    r = torch.tensor([[0.3], [-2.0], [5.0]], dtype=torch.float64)
    ref = np.log(0.8 * narrow.pdf(r.numpy()[:, 0]) + 0.2 * wide.pdf(r.numpy()[:, 0]))
    np.testing.assert_allclose(noise.log_prob(r).numpy(), ref, rtol=1e-12)


def test_a_registered_family_fits_recovers_its_parameters_and_gets_standard_errors(registered):
    u, y = _record()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fit's own advice (convergence) is not under test
        est = _estimator("contaminated-gaussian").fit(u, y)  # by its registry name
    # the fitted attributes and the history are the family's parameters, nothing else
    assert not hasattr(est, "dof_") and "dof" not in est.history_
    assert est.history_["eps"].shape == (31,) and est.history_["eps"][-1] == est.eps_
    se = est.standard_errors_
    assert set(se) == {"f.a", "f.b", "g.c", "Rw", "Rv", "eps"}
    assert all(np.all(np.isfinite(v)) and np.all(v > 0) for v in se.values())
    # recovery, within the standard errors (measured on seeds 0-2: |error| / se below 1.1)
    assert abs(est.eps_ - EPS) < 2.5 * se["eps"] and 0.01 < se["eps"] < 0.05
    assert abs(est.Rv_[0, 0] - RV) < 2.5 * se["Rv"][0, 0]
    assert abs(est.f_.a.item() - 0.9) < 3 * se["f.a"] and abs(est.g_.c.item() - 1.0) < 3 * se["g.c"]
    lo, hi = est.confidence_intervals(0.99)["eps"]
    assert lo < EPS < hi
    assert "logit eps" in est._parameter_uncertainty().working_names
    # outlier weights: about the wide component's share of the samples is down-weighted
    assert 0.02 < np.mean(est.outlier_weights_ < 0.5) < 0.2


def test_the_family_as_an_object_accelerated_and_bootstrapped(registered):
    """The specification object instead of the name (the same fit), the squared extrapolation of
    ``eps`` on its logit scale, and a bootstrap that restarts the family at its fitted values."""
    u, y = _record(300, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        by_name = _estimator("contaminated-gaussian", n_iter=5).fit(u, y)
        by_object = _estimator(Contaminated(), n_iter=5).fit(u, y)
        accelerated = _estimator(Contaminated(), n_iter=8, acceleration="newton").fit(u, y)
        boot = by_object.bootstrap(u, n_boot=2, n_iter=2, n_particles=30, random_state=0)
    np.testing.assert_array_equal(by_name.history_["eps"], by_object.history_["eps"])
    assert 0.0 < accelerated.eps_ < 0.5 and np.all(np.isfinite(accelerated.history_["eps"]))
    assert boot.samples["eps"].shape == (2,) and np.all((boot.samples["eps"] > 0) & (boot.samples["eps"] < 1))


def test_closed_form_scores_of_the_family_match_autograd(registered):
    """The family's scores (``latent_weight``) equal reverse-mode autograd of its ``residual_log_prob``
    on the rows of backward-simulated trajectories."""
    from torch_nssm.core.model import SequenceBatch, StateSpaceModel
    from torch_nssm.estimation import uncertainty as U
    from torch_nssm.estimation.estep import EStepOptions, e_step
    from torch_nssm.inference.ffbsi import backward_segments

    u, y = _record(80, seed=2)
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    data = SequenceBatch.from_sequences([torch.as_tensor(u)[:, None]], [torch.as_tensor(y)[:, None]])
    noise = Contaminated(eps=0.15).initial(t([[0.02]]))
    f, g = PaperTransition(0.9, 1.0), PaperObservation(1.0)
    model = StateSpaceModel(f, g, t([[0.1]]), noise, t([0.0]), t([[1.0]]))
    est = e_step(model, data, EStepOptions(n_particles=50), torch.Generator().manual_seed(0))
    blocks, _ = U._blocks(model, True, True, True)
    ll = U._LogLikelihood(model, blocks)
    w0 = torch.cat([b.to_working() for b in blocks])
    starts, length, _ = U._pieces(data.y.shape[0], 6, 24)
    Js = backward_segments(
        model, data, est.filter, 7, starts, length, log_weights=est.smoother.log_weights,
        generator=torch.Generator().manual_seed(0),
    )
    rows = U._piece_rows(est.filter.particles, data, Js, starts)
    fast = U._closed_form_scores(ll, w0, rows)
    reference = U._row_scores_autograd(ll, w0, rows, True)
    np.testing.assert_allclose(fast.numpy(), reference.numpy(), rtol=1e-9, atol=1e-9)
