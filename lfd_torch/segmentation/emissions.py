"""Gaussian emissions with a Normal-Inverse-Wishart (NIW) prior (paper eq. 4).

Notation:
    K  number of features (hidden states)
    d  state dimension
    mean        (K, d)     mu_k
    covariance  (K, d, d)  Sigma_k
    NIW(m0, kappa0, nu0, Psi0):  Sigma ~ IW(nu0, Psi0),  mu | Sigma ~ N(m0, Sigma / kappa0)

All functions broadcast over leading batch dimensions and work in the dtype/device of their inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from lfd_torch.errors import ShapeMismatchError, TooFewSamplesError

__all__ = [
    "NIWPrior",
    "niw_prior_from_data",
    "niw_posterior",
    "sufficient_statistics",
    "sample_niw",
    "niw_log_density",
    "gaussian_log_density",
    "niw_log_marginal_likelihood",
]

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True, eq=False)
class NIWPrior:
    """Normal-Inverse-Wishart parameters; every field may carry leading batch dimensions ``(...)``.

    Attributes:
        mean: (..., d) prior mean m0 of mu.
        kappa: (...,) pseudo-count of the mean (> 0).
        dof: (...,) degrees of freedom nu0 of the inverse Wishart (> d - 1).
        scale: (..., d, d) scale matrix Psi0 (symmetric positive definite); E[Sigma] = Psi0 / (nu0 - d - 1).
    """

    mean: Tensor
    kappa: Tensor
    dof: Tensor
    scale: Tensor

    @property
    def dim(self) -> int:
        return self.mean.shape[-1]


def niw_prior_from_data(
    x: Tensor,
    *,
    covariance_scale: float = 0.05,
    mean_pseudo_count: float = 0.01,
    extra_dof: float = 2.0,
) -> NIWPrior:
    """A weakly informative NIW prior set from the scale of the data.

    The prior mean is the data mean; the prior expected covariance is ``covariance_scale`` times the diagonal of
    the data covariance (a state covers a region about sqrt(covariance_scale) of the data's spread per axis);
    ``dof = d + 1 + extra_dof`` so that the expected covariance exists and the prior stays weak.

    Args:
        x: (N, d) samples (all sequences stacked), finite.
        covariance_scale: ratio of the expected state covariance to the data variance, per axis.
        mean_pseudo_count: kappa0, pseudo-observations behind the prior mean (small: vague about location).
        extra_dof: nu0 - d - 1 (> 0).

    Returns:
        NIWPrior with unbatched fields.
    """
    if x.ndim != 2:
        raise ShapeMismatchError(f"x must be (N, d), got {tuple(x.shape)}")
    n, d = x.shape
    if n < 2:
        raise TooFewSamplesError(f"need at least 2 samples to set the prior scale, got {n}")
    if not (covariance_scale > 0 and mean_pseudo_count > 0 and extra_dof > 0):
        raise ValueError("covariance_scale, mean_pseudo_count and extra_dof must be positive")
    var = x.var(dim=0, unbiased=True)
    floor = var.max().clamp_min(torch.finfo(x.dtype).tiny) * 1e-6  # a flat axis still gets a proper prior
    var = torch.maximum(var, floor)
    dof = d + 1.0 + extra_dof
    scale = torch.diag(var * covariance_scale * (dof - d - 1.0))
    return NIWPrior(
        mean=x.mean(0),
        kappa=x.new_tensor(mean_pseudo_count),
        dof=x.new_tensor(dof),
        scale=scale,
    )


def sufficient_statistics(x: Tensor, weights: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Weighted counts, sums and outer-product sums of samples per state.

    Args:
        x: (..., n, d) samples.
        weights: (..., n, K) non-negative weights (one-hot labels for hard assignments; zero on padding).

    Returns:
        counts (..., K), sums (..., K, d), outer (..., K, d, d) with outer_k = sum_t w_tk x_t x_t^T.
    """
    counts = weights.sum(-2)
    sums = weights.transpose(-1, -2) @ x
    outer = torch.einsum("...nk,...ni,...nj->...kij", weights, x, x)
    return counts, sums, outer


def niw_posterior(prior: NIWPrior, counts: Tensor, sums: Tensor, outer: Tensor) -> NIWPrior:
    """Conjugate NIW update from sufficient statistics (closed form; Murphy 2007, eqs. 250-254).

    Args:
        prior: NIW prior whose fields broadcast against (..., K).
        counts: (..., K) number of samples per state.
        sums: (..., K, d).
        outer: (..., K, d, d).

    Returns:
        NIWPrior of shape (..., K): posterior parameters per state.
    """
    kappa_n = prior.kappa + counts
    dof_n = prior.dof + counts
    mean_n = (prior.kappa.unsqueeze(-1) * prior.mean + sums) / kappa_n.unsqueeze(-1)
    m0 = prior.mean
    scale_n = (
        prior.scale
        + outer
        + prior.kappa[..., None, None] * (m0.unsqueeze(-1) * m0.unsqueeze(-2))
        - kappa_n[..., None, None] * (mean_n.unsqueeze(-1) * mean_n.unsqueeze(-2))
    )
    scale_n = 0.5 * (scale_n + scale_n.transpose(-1, -2))
    return NIWPrior(mean=mean_n, kappa=kappa_n, dof=dof_n, scale=scale_n)


def _sample_wishart_cholesky(dof: Tensor, dim: int, generator: torch.Generator, like: Tensor) -> Tensor:
    """Bartlett factor A (..., d, d), lower triangular, with A A^T ~ Wishart(dof, I)."""
    shape = dof.shape
    chi_dofs = dof.unsqueeze(-1) - torch.arange(dim, dtype=like.dtype, device=like.device)  # (..., d)
    # chi^2_k = 2 * Gamma(k / 2, 1); torch._standard_gamma has no generator, so use Marsaglia-Tsang below
    diag = torch.sqrt(2.0 * _sample_gamma(chi_dofs / 2.0, generator))
    normal = torch.randn(*shape, dim, dim, generator=generator, dtype=like.dtype, device=like.device)
    lower = torch.tril(normal, diagonal=-1)
    return lower + torch.diag_embed(diag)


def _sample_gamma(shape_param: Tensor, generator: torch.Generator) -> Tensor:
    """Gamma(shape, 1) draws for every entry of ``shape_param`` (> 0), using the given generator.

    Marsaglia & Tsang (2000) squeeze method with the boost ``Gamma(a) = Gamma(a + 1) * U^(1/a)`` for a < 1.
    Vectorised rejection: all entries draw in lock-step until each has an accepted value.
    """
    a = shape_param
    boost = a < 1.0
    a1 = torch.where(boost, a + 1.0, a)
    d = a1 - 1.0 / 3.0
    c = 1.0 / torch.sqrt(9.0 * d)
    out = torch.empty_like(a)
    todo = torch.ones_like(a, dtype=torch.bool)
    for _ in range(64):
        z = torch.randn(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        u = torch.rand(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        v = (1.0 + c * z) ** 3
        ok = (v > 0) & (torch.log(u.clamp_min(1e-300)) < 0.5 * z * z + d - d * v + d * torch.log(v.clamp_min(1e-300)))
        take = ok & todo
        out = torch.where(take, d * v, out)
        todo = todo & ~ok
        if not bool(todo.any()):
            break
    else:  # pragma: no cover - acceptance probability is > 0.95 per round
        out = torch.where(todo, d, out)
    if bool(boost.any()):
        u = torch.rand(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        out = torch.where(boost, out * u.clamp_min(1e-300) ** (1.0 / a), out)
    return out.clamp_min(torch.finfo(a.dtype).tiny)


def sample_gamma(shape_param: Tensor, generator: torch.Generator) -> Tensor:
    """Gamma(shape, rate 1) draws, same shape as ``shape_param``; reproducible through ``generator``."""
    return _sample_gamma(shape_param, generator)


def sample_niw(params: NIWPrior, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Draw (mu, Sigma) from NIW distributions with batch shape (...).

    Sigma ~ IW(nu, Psi) is drawn through its precision Lambda = Sigma^-1 ~ Wishart(nu, Psi^-1), with the
    Bartlett decomposition Lambda = B B^T, B = L^-T A, Psi = L L^T; then mu ~ N(m, Sigma / kappa).

    Args:
        params: NIW parameters with batch shape (...).
        generator: source of randomness.

    Returns:
        mean (..., d), covariance (..., d, d).
    """
    d = params.dim
    batch = params.mean.shape[:-1]
    dof = params.dof.expand(batch)
    chol_scale = torch.linalg.cholesky(params.scale.expand(*batch, d, d))
    bartlett = _sample_wishart_cholesky(dof, d, generator, params.mean)
    # precision factor B = L^-T A  (so precision = B B^T); covariance = B^-T B^-1
    factor = torch.linalg.solve_triangular(chol_scale.transpose(-1, -2), bartlett, upper=True)
    eye = torch.eye(d, dtype=params.mean.dtype, device=params.mean.device).expand(*batch, d, d)
    # covariance = (B B^T)^-1 = B^-T B^-1
    factor_inv = torch.linalg.solve(factor, eye)
    covariance = factor_inv.transpose(-1, -2) @ factor_inv
    covariance = 0.5 * (covariance + covariance.transpose(-1, -2))
    kappa = params.kappa.expand(batch)
    chol_cov = torch.linalg.cholesky(covariance / kappa[..., None, None])
    z = torch.randn(*batch, d, 1, generator=generator, dtype=params.mean.dtype, device=params.mean.device)
    mean = params.mean.expand(*batch, d) + (chol_cov @ z).squeeze(-1)
    return mean, covariance


def gaussian_log_density(x: Tensor, mean: Tensor, covariance: Tensor) -> Tensor:
    """log N(x; mean_k, covariance_k) for every sample and state.

    Args:
        x: (..., n, d) samples.
        mean: (..., K, d).
        covariance: (..., K, d, d), positive definite.

    Returns:
        (..., n, K) log densities.
    """
    d = x.shape[-1]
    if mean.shape[-1] != d or covariance.shape[-2:] != (d, d):
        raise ShapeMismatchError(f"samples have dimension {d}, mean {tuple(mean.shape)}, covariance {tuple(covariance.shape)}")
    chol = torch.linalg.cholesky(covariance)  # (..., K, d, d)
    diff = x.unsqueeze(-3) - mean.unsqueeze(-2)  # (..., K, n, d)
    z = torch.linalg.solve_triangular(chol, diff.transpose(-1, -2), upper=False)  # (..., K, d, n)
    maha = (z * z).sum(-2)  # (..., K, n)
    half_logdet = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)  # (..., K)
    out = -0.5 * maha - half_logdet.unsqueeze(-1) - 0.5 * d * _LOG_2PI
    return out.transpose(-1, -2)


def _log_multigamma(a: Tensor, d: int) -> Tensor:
    j = torch.arange(d, dtype=a.dtype, device=a.device)
    return 0.25 * d * (d - 1) * math.log(math.pi) + torch.lgamma(a.unsqueeze(-1) - 0.5 * j).sum(-1)


def niw_log_density(mean: Tensor, covariance: Tensor, params: NIWPrior) -> Tensor:
    """log NIW(mean, covariance | params), batched over (...).

    Args:
        mean: (..., d).
        covariance: (..., d, d).
        params: NIW parameters broadcasting against (...).

    Returns:
        (...) log densities (with respect to Lebesgue measure on mu and the free entries of Sigma).
    """
    d = mean.shape[-1]
    nu, kappa, psi, m0 = params.dof, params.kappa, params.scale, params.mean
    chol_sigma = torch.linalg.cholesky(covariance)
    logdet_sigma = 2.0 * torch.log(torch.diagonal(chol_sigma, dim1=-2, dim2=-1)).sum(-1)
    chol_psi = torch.linalg.cholesky(psi)
    logdet_psi = 2.0 * torch.log(torch.diagonal(chol_psi, dim1=-2, dim2=-1)).sum(-1)
    sigma_inv_psi = torch.cholesky_solve(psi.expand_as(covariance), chol_sigma)
    trace = torch.diagonal(sigma_inv_psi, dim1=-2, dim2=-1).sum(-1)
    log_iw = (
        0.5 * nu * logdet_psi
        - 0.5 * nu * d * math.log(2.0)
        - _log_multigamma(0.5 * nu * torch.ones_like(logdet_sigma), d)
        - 0.5 * (nu + d + 1) * logdet_sigma
        - 0.5 * trace
    )
    diff = (mean - m0).unsqueeze(-1)
    z = torch.linalg.solve_triangular(chol_sigma, diff, upper=False).squeeze(-1)
    log_normal = -0.5 * kappa * (z * z).sum(-1) - 0.5 * logdet_sigma + 0.5 * d * torch.log(kappa) - 0.5 * d * _LOG_2PI
    return log_iw + log_normal


def niw_log_marginal_likelihood(prior: NIWPrior, counts: Tensor, sums: Tensor, outer: Tensor) -> Tensor:
    """log p(x_1..x_n) with (mu, Sigma) integrated out under the NIW prior, from sufficient statistics.

    Returns:
        (..., K) log marginal likelihoods (0 for empty states).
    """
    d = prior.dim
    post = niw_posterior(prior, counts, sums, outer)
    nu0 = prior.dof * torch.ones_like(counts)
    logdet0 = torch.logdet(prior.scale) * torch.ones_like(counts)
    logdet_n = torch.logdet(post.scale)
    return (
        -0.5 * counts * d * _LOG_2PI
        + 0.5 * d * (torch.log(prior.kappa * torch.ones_like(counts)) - torch.log(post.kappa))
        + 0.5 * nu0 * logdet0
        - 0.5 * post.dof * logdet_n
        + 0.5 * counts * d * math.log(2.0)
        + _log_multigamma(0.5 * post.dof, d)
        - _log_multigamma(0.5 * nu0, d)
    )
