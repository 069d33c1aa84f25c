"""Exact float64 references for the engine tests: a Kalman filter and an RTS smoother.

Model (the engine's time convention, docs/method.md §7)::

    x_{k+1} = A x_k + B u_k + w,   w ~ N(0, Q)
    y_k     = C x_k + D u_k + v,   v ~ N(0, R)
    x_0     ~ N(m0, P0)            (y_0 observes x_0)

NaN components of ``y_k`` are missing: the update uses the observed components only (an
all-missing sample is skipped).  Everything is plain numpy, written independently of the engine.

:func:`pairwise_smoother` is the FFBSm backward recursion of docs/method.md §3 written literally, with the
full ``L x L`` pairwise weights, for checking the engine's smoother and M-step statistics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.special import logsumexp

__all__ = ["KalmanResult", "kalman_filter", "rts_smoother", "simulate_linear", "pairwise_smoother"]


@dataclass
class KalmanResult:
    """Output of :func:`kalman_filter`.

    Attributes
    ----------
    filtered_mean, filtered_cov : (N, nx), (N, nx, nx)
        ``E[x_k | y_{0:k}]`` and its covariance.
    predicted_mean, predicted_cov : (N, nx), (N, nx, nx)
        ``E[x_k | y_{0:k-1}]`` (the prior for ``k = 0``) and its covariance.
    log_likelihood : float
        ``log p(y_{0:N-1})`` (missing components marginalised out).
    """

    filtered_mean: np.ndarray
    filtered_cov: np.ndarray
    predicted_mean: np.ndarray
    predicted_cov: np.ndarray
    log_likelihood: float


def _as2d(u: np.ndarray | None, n: int) -> np.ndarray:
    if u is None:
        return np.zeros((n, 0))
    u = np.asarray(u, dtype=np.float64)
    return u.reshape(n, -1)


def kalman_filter(A, B, C, D, Q, R, m0, P0, u, y) -> KalmanResult:
    """Kalman filter with exact log-likelihood and per-element missing outputs.

    Parameters
    ----------
    A, B, C, D, Q, R : array-like
        System matrices ``(nx, nx)``, ``(nx, nu)``, ``(p, nx)``, ``(p, nu)``, ``(nx, nx)``,
        ``(p, p)``.
    m0, P0 : array-like
        Prior of ``x_0``.
    u : array-like of shape (N, nu) or None
    y : array-like of shape (N, p); NaN marks a missing component.
    """
    A, B, C, D, Q, R = (np.asarray(M, dtype=np.float64) for M in (A, B, C, D, Q, R))
    y = np.asarray(y, dtype=np.float64)
    N, p = y.shape
    u = _as2d(u, N)
    nx = A.shape[0]
    m = np.asarray(m0, dtype=np.float64).reshape(nx).copy()
    P = np.asarray(P0, dtype=np.float64).reshape(nx, nx).copy()
    fm = np.empty((N, nx))
    fP = np.empty((N, nx, nx))
    pm = np.empty((N, nx))
    pP = np.empty((N, nx, nx))
    ll = 0.0
    for k in range(N):
        pm[k], pP[k] = m, P
        obs = ~np.isnan(y[k])
        if obs.any():
            Ck = C[obs]
            yhat = Ck @ m + D[obs] @ u[k]
            S = Ck @ P @ Ck.T + R[np.ix_(obs, obs)]
            e = y[k, obs] - yhat
            cho = np.linalg.cholesky(S)
            z = np.linalg.solve(cho, e)
            ll += -0.5 * (obs.sum() * np.log(2 * np.pi) + 2 * np.log(np.diag(cho)).sum() + z @ z)
            K = np.linalg.solve(S, Ck @ P).T  # P C^T S^-1 (S, P symmetric)
            m = m + K @ e
            I_KC = np.eye(nx) - K @ Ck
            P = I_KC @ P @ I_KC.T + K @ R[np.ix_(obs, obs)] @ K.T  # Joseph form
        fm[k], fP[k] = m, P
        m = A @ m + B @ u[k]
        P = A @ P @ A.T + Q
    return KalmanResult(fm, fP, pm, pP, float(ll))


def rts_smoother(A, kf: KalmanResult) -> tuple[np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel smoother: ``E[x_k | y_{0:N-1}]`` and its covariance."""
    A = np.asarray(A, dtype=np.float64)
    N = kf.filtered_mean.shape[0]
    sm = kf.filtered_mean.copy()
    sP = kf.filtered_cov.copy()
    for k in range(N - 2, -1, -1):
        Pf = kf.filtered_cov[k]
        Pp = kf.predicted_cov[k + 1]
        G = np.linalg.solve(Pp, A @ Pf).T  # Pf A^T Pp^-1
        sm[k] = kf.filtered_mean[k] + G @ (sm[k + 1] - kf.predicted_mean[k + 1])
        sP[k] = Pf + G @ (sP[k + 1] - Pp) @ G.T
    return sm, sP


def simulate_linear(A, B, C, D, Q, R, m0, P0, u, rng: np.random.Generator):
    """Draw states ``(N, nx)`` and outputs ``(N, p)`` of the linear-Gaussian model."""
    A, B, C, D, Q, R = (np.asarray(M, dtype=np.float64) for M in (A, B, C, D, Q, R))
    u = np.asarray(u, dtype=np.float64)
    N = u.shape[0]
    nx, p = A.shape[0], C.shape[0]
    x = np.empty((N, nx))
    y = np.empty((N, p))
    x[0] = rng.multivariate_normal(
        np.asarray(m0, dtype=np.float64), np.asarray(P0, dtype=np.float64)
    )
    for k in range(N):
        if k > 0:
            x[k] = A @ x[k - 1] + B @ u[k - 1] + rng.multivariate_normal(np.zeros(nx), Q)
        y[k] = C @ x[k] + D @ u[k] + rng.multivariate_normal(np.zeros(p), R)
    return x, y


def pairwise_smoother(f, Rw, u, lengths, particles, log_weights):
    """FFBSm with explicit pairwise weights (docs/method.md §3), per sequence, in numpy float64.

    Parameters
    ----------
    f : callable
        Transition mean ``f(x, u)`` on torch tensors ``(L, nx)``, ``(L, nu)``.
    Rw : array-like (nx, nx)
        Process-noise covariance.
    u : Tensor (T, B, nu)
        Inputs, time-major.
    lengths : sequence of int
        Length of each sequence.
    particles : Tensor (T, B, L, nx)
    log_weights : Tensor (T, B, L)
        Normalised log filter weights.

    Returns
    -------
    list of (ndarray, list of ndarray)
        Per sequence: the log smoothing weights ``(T_b, L)`` and the pairwise weight matrices
        ``W_k[i, j] = W_{k,k+1|N}^{ij}`` for ``k = 0 .. T_b - 2``.
    """
    Qinv = np.linalg.inv(np.asarray(Rw, dtype=np.float64))
    out = []
    for b, n in enumerate(lengths):
        X = particles[:n, b].detach().numpy()
        logW = log_weights[:n, b].detach().numpy()
        L = X.shape[1]
        logWs = np.empty_like(logW)
        logWs[-1] = logW[-1]
        pairs = [None] * (n - 1)
        for k in range(n - 2, -1, -1):
            with torch.no_grad():
                fx = f(particles[k, b], u[k, b].expand(L, -1)).numpy()
            d = X[k + 1][None, :, :] - fx[:, None, :]  # (i, j, nx)
            logT = -0.5 * np.einsum("ijp,pq,ijq->ij", d, Qinv, d)
            logD = logsumexp(logW[k][:, None] + logT, axis=0)  # (j,)
            logWs[k] = logW[k] + logsumexp(logWs[k + 1][None, :] + logT - logD[None, :], axis=1)
            pairs[k] = np.exp(logW[k][:, None] + logWs[k + 1][None, :] + logT - logD[None, :])
        out.append((logWs, pairs))
    return out
