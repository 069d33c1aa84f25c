"""Noise models: multivariate Student-t (and Gaussian) measurement noise, Gaussian process noise.

The measurement noise ``v ~ St(0, R, nu)`` is the Gaussian scale mixture
``v | lam ~ N(0, R / lam)``, ``lam ~ Gamma(nu / 2, rate = nu / 2)``.  Given a residual with squared
Mahalanobis norm ``delta2`` over ``p`` observed components, the latent scale has the posterior
``Gamma((nu + p) / 2, rate = (nu + delta2) / 2)``, whose moments are the weights of the M-step
(NOTES §1).  Gaussian noise is the limit ``nu -> inf`` with ``lam == 1``; it runs on the same code
path (``dof = inf``).

Missing output components are handled by *masking*: the scale matrix restricted to the observed
components is embedded in an identity (``M R M + (I - M)``), residuals are zeroed where missing,
and ``p`` becomes the number of observed components.  A marginal of a t is a t with the same DOF,
so this gives the exact density of the observed part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "MaskedScale",
    "masked_scale",
    "student_t_log_prob",
    "latent_scale_expectations",
    "solve_dof",
    "dof_equation",
    "sample_student_t",
]


@dataclass
class MaskedScale:
    """Scale matrix restricted to the observed components of each sample.

    Attributes
    ----------
    chol_inv : Tensor, shape (..., p, p)
        Inverse of the lower Cholesky factor of ``M R M + (I - M)``; ``chol_inv @ r`` whitens a
        residual ``r`` that is zero where missing.
    logdet : Tensor, shape (...)
        ``log det`` of the observed block of ``R``.
    n_obs : Tensor, shape (...)
        Number of observed components ``p_eff``.
    mask : Tensor, shape (..., p), bool
        True where the component is observed.
    """

    chol_inv: Tensor
    logdet: Tensor
    n_obs: Tensor
    mask: Tensor

    def select(self, index) -> MaskedScale:
        """The scales of the sequences ``index`` (second dimension of time-major ``(T, B, ...)``)."""
        return MaskedScale(
            self.chol_inv[:, index], self.logdet[:, index], self.n_obs[:, index], self.mask[:, index]
        )

    def whitener(self) -> Tensor:
        """``chol_inv`` with zero columns at the missing components, ``(..., p, p)``: applied to a
        residual whose missing entries are finite (see :meth:`fill_missing`), it needs no mask."""
        return self.chol_inv * self.mask.unsqueeze(-2).to(self.chol_inv.dtype)

    def fill_missing(self, y: Tensor) -> Tensor:
        """Outputs ``y`` (shape of the mask) with the missing entries set to 0."""
        return torch.where(self.mask, y, torch.zeros_like(y))

    def whiten(self, resid: Tensor, k: int | None = None) -> Tensor:
        """Whiten residuals of shape ``(..., L, p)`` (leading dims as the mask's, plus particles);
        with ``k``, residuals ``(B, L, p)`` of time step ``k`` of a time-major scale."""
        chol_inv, mask = (self.chol_inv, self.mask) if k is None else (self.chol_inv[k], self.mask[k])
        resid = torch.where(mask.unsqueeze(-2), resid, torch.zeros_like(resid))
        if resid.shape[-1] == 1:  # no batch of 1x1 products
            return resid * chol_inv[..., 0].unsqueeze(-2)
        return torch.einsum("...ij,...lj->...li", chol_inv, resid)


def masked_scale(R: Tensor, mask: Tensor) -> MaskedScale:
    """Build the per-sample scale of the observed components.

    Parameters
    ----------
    R : Tensor, shape (..., p, p)
        Symmetric positive-definite scale matrix (broadcast against ``mask``).
    mask : Tensor, shape (..., p), bool
        True where the output component is observed.

    Returns
    -------
    MaskedScale
    """
    m = mask.to(R.dtype)
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    Rm = R * m.unsqueeze(-1) * m.unsqueeze(-2) + eye * (1.0 - m).unsqueeze(-1)
    chol = torch.linalg.cholesky(Rm)
    chol_inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return MaskedScale(chol_inv=chol_inv, logdet=logdet, n_obs=m.sum(-1), mask=mask)


def student_t_log_prob(delta2: Tensor, logdet: Tensor, n_obs: Tensor, dof: Tensor) -> Tensor:
    """Log-density of a multivariate Student-t (or Gaussian when ``dof`` is infinite).

    ``log St = lgamma((nu+p)/2) - lgamma(nu/2) - p/2 log(nu pi) - 1/2 log det R
    - (nu+p)/2 log(1 + delta2/nu)``.

    Parameters
    ----------
    delta2 : Tensor
        Squared Mahalanobis norms of the residuals.
    logdet : Tensor
        ``log det R`` of the observed block (broadcast against ``delta2``).
    n_obs : Tensor
        Number of observed components ``p`` (broadcast); ``0`` gives log-density 0.
    dof : Tensor
        Degrees of freedom (broadcast); ``inf`` selects the Gaussian density.

    Returns
    -------
    Tensor
        Log-densities, shape of the broadcast inputs.
    """
    dof = torch.as_tensor(dof, dtype=delta2.dtype, device=delta2.device)
    gauss = -0.5 * (n_obs * math.log(2.0 * math.pi) + logdet + delta2)
    if torch.isinf(dof).all():
        return gauss
    nu = torch.where(torch.isinf(dof), torch.ones_like(dof), dof)
    half = 0.5 * (nu + n_obs)
    t = (
        torch.lgamma(half)
        - torch.lgamma(0.5 * nu)
        - 0.5 * n_obs * torch.log(nu * math.pi)
        - 0.5 * logdet
        - half * torch.log1p(delta2 / nu)
    )
    return torch.where(torch.isinf(dof), gauss, t)


def latent_scale_expectations(delta2: Tensor, n_obs: Tensor, dof: Tensor) -> tuple[Tensor, Tensor]:
    """Posterior moments of the latent scale ``lam`` given a residual (NOTES §1, paper eqs. 27-28).

    ``<lam> = (nu + p) / (nu + delta2)`` and ``<log lam> = psi((nu+p)/2) - log((nu + delta2)/2)``.
    For Gaussian noise (``dof = inf``) ``<lam> = 1`` and ``<log lam> = 0``.

    Returns
    -------
    (Tensor, Tensor)
        ``<lam>`` and ``<log lam>``, shape of the broadcast inputs.
    """
    dof = torch.as_tensor(dof, dtype=delta2.dtype, device=delta2.device)
    inf = torch.isinf(dof)
    nu = torch.where(inf, torch.ones_like(dof), dof)
    denominator = nu + delta2
    e_lam = (nu + n_obs) / denominator
    # digamma on the (usually much smaller) broadcast of nu and p only, not per residual
    e_log = torch.digamma(0.5 * (nu + n_obs)) - torch.log(0.5 * denominator)
    if not bool(inf.any()):
        return e_lam, e_log
    return (
        torch.where(inf, torch.ones_like(e_lam), e_lam),
        torch.where(inf, torch.zeros_like(e_log), e_log),
    )


def dof_equation(nu: Tensor, c: Tensor) -> Tensor:
    """``h(nu) = 1 + log(nu/2) - psi(nu/2) + c`` (paper eq. 38, NOTES §5); decreasing in ``nu``."""
    return 1.0 + torch.log(0.5 * nu) - torch.digamma(0.5 * nu) + c


def solve_dof(c: Tensor, dof_min: float = 0.1, dof_max: float = 1000.0, n_bisect: int = 100) -> Tensor:
    """Root of the DOF equation ``h(nu) = 0`` bracketed in ``[dof_min, dof_max]``, in float64.

    ``c = mean(<log lam> - <lam>) <= -1`` guarantees a root on ``(0, inf)``; the result is clipped
    to the bracket when the root lies outside it.  Works element-wise on a batch of ``c``
    (bisection on ``log nu``, which is monotone and needs no derivative).

    Parameters
    ----------
    c : Tensor
        The sufficient statistic, any shape.
    dof_min, dof_max : float
        The bracket.
    n_bisect : int
        Number of bisection steps (100 gives full float64 precision on the log scale).

    Returns
    -------
    Tensor
        The DOF estimates, float64, shape of ``c``.
    """
    if not 0 < dof_min < dof_max:
        raise ValueError(f"dof bounds must satisfy 0 < dof_min < dof_max, got ({dof_min}, {dof_max})")
    c = torch.as_tensor(c, dtype=torch.float64)
    lo = torch.full_like(c, math.log(dof_min))
    hi = torch.full_like(c, math.log(dof_max))
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        positive = dof_equation(torch.exp(mid), c) > 0
        lo = torch.where(positive, mid, lo)
        hi = torch.where(positive, hi, mid)
    return torch.exp(0.5 * (lo + hi))


def sample_student_t(
    shape: tuple[int, ...], chol: Tensor, dof: Tensor, generator: torch.Generator | None = None
) -> Tensor:
    """Draw Student-t (or Gaussian for infinite ``dof``) noise with scale ``chol @ chol.T``.

    Parameters
    ----------
    shape : tuple of int
        Leading shape of the draws; the result has shape ``shape + (p,)``.
    chol : Tensor, shape (p, p)
        Lower Cholesky factor of the scale matrix.
    dof : Tensor or float
        Degrees of freedom (scalar).
    generator : torch.Generator, optional

    Returns
    -------
    Tensor
    """
    p = chol.shape[-1]
    z = torch.randn(*shape, p, dtype=chol.dtype, device=chol.device, generator=generator)
    z = z @ chol.transpose(-1, -2)
    dof = float(dof)
    if math.isinf(dof):
        return z
    # lam ~ Gamma(nu/2, rate nu/2) via the chi-square of nu degrees of freedom: sum of normals is
    # not available for non-integer nu, so use torch's Gamma sampler with a seeded generator-free
    # fallback (torch.distributions has no generator argument): draw through torch._standard_gamma.
    conc = torch.full(shape, 0.5 * dof, dtype=chol.dtype, device=chol.device)
    if generator is not None:
        # Reproducible gamma draws: transform uniforms through the inverse CDF is costly; instead
        # seed the global stream from the generator, draw, and restore it.
        seed = int(torch.randint(0, 2**62, (1,), generator=generator, device=generator.device))
        with torch.random.fork_rng(devices=[] if chol.device.type == "cpu" else [chol.device]):
            torch.manual_seed(seed)
            g = torch._standard_gamma(conc)
    else:
        g = torch._standard_gamma(conc)
    lam = g / (0.5 * dof)
    return z / torch.sqrt(lam).unsqueeze(-1)
