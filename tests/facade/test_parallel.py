"""``n_jobs`` through joblib: restarts and chunks of data sets on loky workers and on a real
``dask.distributed`` cluster give the serial run's results; a worker dying in the middle of a
study raises ``WorkerLostError`` with the fits that finished."""

from __future__ import annotations

import os
import time
import warnings

import joblib
import numpy as np
import pytest
import torch

from torch_nssm import RobustNSSMEstimator, WorkerLostError, fit_independent
from torch_nssm.datasets import make_huang_example
from torch_nssm.models import PaperObservation, PaperTransition

N_SETS = 20
#: The data set whose worker dies in the worker-death tests.
DOOMED = 17
SENTINEL = 12345.0


def _estimator(f=None, **kw) -> RobustNSSMEstimator:
    params = dict(
        x0_mean=[0.0], n_particles=20, n_iter=4, tol=0.0, smoother="mcmc", random_state=7, n_threads=1
    )
    params.update(kw)
    f = PaperTransition(0.5, 0.5, dtype=torch.float64) if f is None else f
    return RobustNSSMEstimator(f, PaperObservation(0.5, dtype=torch.float64), **params)


def _data(n_sets: int = N_SETS):
    datas = [make_huang_example(n_samples=40 + 3 * (i % 5), random_state=i) for i in range(n_sets)]
    return [d.u for d in datas], [d.y for d in datas]


def _fit_independent(est, u, y, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit_independent(est, u, y, **kw)


def _assert_same(fits_a, fits_b, atol=1e-12):
    assert len(fits_a) == len(fits_b)
    for a, b in zip(fits_a, fits_b):
        assert a.history_.keys() == b.history_.keys()
        for key in a.history_:
            np.testing.assert_allclose(
                np.asarray(a.history_[key], float), np.asarray(b.history_[key], float), rtol=1e-12, atol=atol,
                err_msg=key,
            )
        np.testing.assert_allclose(a.log_likelihood_, b.log_likelihood_, rtol=1e-12)


@pytest.fixture(scope="module")
def serial():
    u, y = _data()
    return u, y, _fit_independent(_estimator(), u, y)


def test_a_data_sets_fit_does_not_depend_on_its_batch(serial):
    """Per-sequence streams: fitting a subset (other batch, other size) gives the same fits."""
    u, y, fits = serial
    part = _fit_independent(_estimator(), u[:3], y[:3])
    _assert_same(part, fits[:3])


def test_loky_chunks_equal_serial(serial):
    u, y, fits = serial
    with joblib.parallel_config(backend="loky"):
        par = _fit_independent(_estimator(), u, y, n_jobs=2)
    _assert_same(par, fits)


def test_restarts_in_parallel_equal_serial():
    u, y = _data(1)
    kw = dict(n_init=3, n_iter=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = _estimator(**kw).fit(u[0], y[0])
        with joblib.parallel_config(backend="loky"):
            two = _estimator(n_jobs=2, **kw).fit(u[0], y[0])
    np.testing.assert_array_equal(one.init_log_likelihoods_, two.init_log_likelihoods_)
    _assert_same([one], [two])


def test_restart_r_does_not_depend_on_n_init():
    """Run r's seed is drawn up front: adding restarts does not change the earlier runs."""
    u, y = _data(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        two = _estimator(n_init=2, n_iter=2).fit(u[0], y[0]).init_log_likelihoods_
        three = _estimator(n_init=3, n_iter=2).fit(u[0], y[0]).init_log_likelihoods_
    np.testing.assert_array_equal(two, three[:2])


class DyingTransition(PaperTransition):
    """The paper's ``f``, whose worker process exits (as on a crash or an out-of-memory kill)
    when it sees data set :data:`DOOMED`'s sentinel input, a while after starting; never in the
    process that built it."""

    def __init__(self):
        super().__init__(0.5, 0.5, dtype=torch.float64)
        self.owner = os.getpid()

    def features(self, x, u):  # what the batched E-step evaluates of a module linear in its parameters
        if os.getpid() != self.owner and bool((u == SENTINEL).any()):
            time.sleep(4.0)  # let the other chunk finish first (loky stops the others on a death)
            os._exit(3)
        return super().features(x, u)


def _doomed_data():
    u, y = _data(8)
    u[7] = np.array(u[7], dtype=float)
    u[7][-1] = SENTINEL  # the last input drives no transition that is used
    return u, y


def _check_lost(exc: WorkerLostError, u, y):
    assert 7 in exc.lost and 0 not in exc.lost
    kept = [b for b in range(8) if b not in exc.lost]
    assert all(exc.results[b] is not None for b in kept)
    assert all(exc.results[b] is None for b in exc.lost)
    reference = _fit_independent(_estimator(f=DyingTransition()), [u[b] for b in kept], [y[b] for b in kept])
    _assert_same([exc.results[b] for b in kept], reference)
    assert "data sets 4-7 are lost" in str(exc)


def test_loky_worker_death_keeps_the_finished_fits():
    u, y = _doomed_data()
    with joblib.parallel_config(backend="loky"):
        with pytest.raises(WorkerLostError, match="worker died") as info:
            _fit_independent(_estimator(f=DyingTransition()), u, y, n_jobs=2)
    _check_lost(info.value, u, y)


@pytest.fixture(scope="module")
def dask_client():
    distributed = pytest.importorskip("distributed")
    import dask

    # a task whose worker dies is not retried (it would kill the next worker too)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        cluster = distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        )
        client = distributed.Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()


def test_dask_chunks_equal_serial(serial, dask_client):
    u, y, fits = serial
    with joblib.parallel_config(backend="dask"):
        par = _fit_independent(_estimator(n_jobs=-1), u, y)
    _assert_same(par, fits)


def test_dask_restarts_equal_serial(dask_client):
    u, y = _data(1)
    kw = dict(n_init=3, n_iter=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = _estimator(**kw).fit(u[0], y[0])
        with joblib.parallel_config(backend="dask"):
            two = _estimator(n_jobs=-1, **kw).fit(u[0], y[0])
    _assert_same([one], [two])


def test_dask_worker_death_keeps_the_finished_fits(dask_client):
    u, y = _doomed_data()
    with joblib.parallel_config(backend="dask"):
        with pytest.raises(WorkerLostError, match="worker died") as info:
            _fit_independent(_estimator(f=DyingTransition()), u, y, n_jobs=2)
    _check_lost(info.value, u, y)
