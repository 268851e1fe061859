"""Normal-inverse-Wishart (NIW) conjugate prior of a Gaussian: statistics, posterior, densities, draws.

Notation (Murphy 2007, "Conjugate Bayesian analysis of the Gaussian distribution", Sec. 9):
    d  dimension, K  Gaussians (states, clusters, tables)
    NIW(m0, kappa0, nu0, Psi0):  Sigma ~ IW(nu0, Psi0),  mu | Sigma ~ N(m0, Sigma / kappa0)
    sufficient statistics of n points x_t: counts n, sums s = sum x_t, outer Q = sum x_t x_t^T

The posterior after (n, s, Q) is NIW(m_n, kappa_n, nu_n, Psi_n) with kappa_n = kappa0 + n, nu_n = nu0 + n,
m_n = (kappa0 m0 + s) / kappa_n and Psi_n = Psi0 + Q + kappa0 m0 m0^T - kappa_n m_n m_n^T; the log marginal
likelihood with (mu, Sigma) integrated out is

    log p(x_1..n) = c(n) - nu_n / 2 log|Psi_n|,
    c(n) = -n d / 2 log pi + log Gamma_d(nu_n / 2) - log Gamma_d(nu0 / 2) + nu0 / 2 log|Psi0|
           + d / 2 (log kappa0 - log kappa_n).

These are the only implementations in the package: the GMM fitters (:mod:`~lfd_torch.gmm.pcgmm`,
:mod:`~lfd_torch.gmm.damm`) and the segmentation sampler (:mod:`lfd_torch.segmentation`) use them. Every function
broadcasts over leading batch dimensions and works in the dtype and device of its inputs; random draws come only
from the given generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.gmm.gaussian import gaussian_log_normalizer

__all__ = [
    "NIWPrior",
    "niw_prior_from_data",
    "sufficient_statistics",
    "niw_posterior",
    "niw_log_marginal_normalizer",
    "niw_log_marginal_likelihood",
    "niw_log_density",
    "inverse_wishart_log_density",
    "sample_niw",
    "sample_gamma",
    "log_multigamma",
]

_LOG_PI = math.log(math.pi)


@dataclass(frozen=True, eq=False)
class NIWPrior:
    """Normal-inverse-Wishart parameters; every field may carry leading batch dimensions ``(...)``.

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

    Raises:
        ShapeMismatchError: x is not (N, d).
        TooFewSamplesError: N < 2.
        InvalidArgumentError: a non-positive hyperparameter.
    """
    if x.ndim != 2:
        raise ShapeMismatchError(f"x must be (N, d), got {tuple(x.shape)}")
    n, d = x.shape
    if n < 2:
        raise TooFewSamplesError(f"need at least 2 samples to set the prior scale, got {n}")
    if not (covariance_scale > 0 and mean_pseudo_count > 0 and extra_dof > 0):
        raise InvalidArgumentError(f"covariance_scale, mean_pseudo_count and extra_dof must be positive, got "
                                   f"{covariance_scale}, {mean_pseudo_count}, {extra_dof}")
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
    d = x.shape[-1]
    # one matmul over the flattened outer products (a three-operand einsum is several times slower)
    outer = (weights.transpose(-1, -2) @ (x.unsqueeze(-1) * x.unsqueeze(-2)).flatten(-2)).unflatten(-1, (d, d))
    return counts, sums, outer


def niw_posterior(prior: NIWPrior, counts: Tensor, sums: Tensor, outer: Tensor) -> NIWPrior:
    """Conjugate NIW update from sufficient statistics (closed form; Murphy 2007, eqs. 250-254).

    Args:
        prior: NIW prior whose fields broadcast against (..., K).
        counts: (..., K) number of samples per state.
        sums: (..., K, d).
        outer: (..., K, d, d).

    Returns:
        NIWPrior of shape (..., K): posterior parameters per state (scale symmetrised).

    Precision: the scale is updated from raw moments, which cancel in float32 when the data lie far from the
    origin relative to their spread; the package's callers (PC-GMM, DAMM, the segmentation sampler) standardise in
    float64 first, and so should other callers.
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


def log_multigamma(a: Tensor, d: int) -> Tensor:
    """log Gamma_d(a) = d (d - 1) / 4 log pi + sum_{j<d} log Gamma(a - j / 2), elementwise (a > (d - 1) / 2)."""
    j = torch.arange(d, dtype=a.dtype, device=a.device)
    return 0.25 * d * (d - 1) * _LOG_PI + torch.lgamma(a.unsqueeze(-1) - 0.5 * j).sum(-1)


def _logdet(matrix: Tensor) -> Tensor:
    """log|P| of (..., d, d) positive-definite matrices (NaN where the determinant is negative); closed forms for
    d <= 2, where a batched LU costs more than the rest of the marginal likelihood."""
    d = matrix.shape[-1]
    if d == 1:
        return torch.log(matrix[..., 0, 0])
    if d == 2:
        return torch.log(matrix[..., 0, 0] * matrix[..., 1, 1] - matrix[..., 0, 1] * matrix[..., 1, 0])
    return torch.logdet(matrix)


def niw_log_marginal_normalizer(prior: NIWPrior, counts: Tensor) -> Tensor:
    """The part c(n) of the NIW log marginal likelihood that depends on the data only through the count.

    ``log p(x_1..n) = c(n) - (nu0 + n) / 2 log|Psi_n|`` (module docstring). A sampler that evaluates many
    candidate clusters can tabulate c(n) once and only compute log|Psi_n| per candidate.

    Args:
        prior: NIW prior whose fields broadcast against ``counts``.
        counts: (...) sample counts (float).

    Returns:
        (...) tensor c(n).
    """
    d = prior.dim
    nu0 = prior.dof
    return (
        -0.5 * d * _LOG_PI * counts
        + log_multigamma(0.5 * (nu0 + counts), d)
        - log_multigamma(0.5 * nu0, d)
        + 0.5 * nu0 * _logdet(prior.scale)
        + 0.5 * d * (torch.log(prior.kappa) - torch.log(prior.kappa + counts))
    )


def niw_log_marginal_likelihood(prior: NIWPrior, counts: Tensor, sums: Tensor, outer: Tensor) -> Tensor:
    """log p(x_1..x_n) with (mu, Sigma) integrated out under the NIW prior, from sufficient statistics.

    Args:
        prior: NIW prior whose fields broadcast against (..., K).
        counts: (..., K) sample counts (float).
        sums: (..., K, d).
        outer: (..., K, d, d).

    Returns:
        (..., K) log marginal likelihoods; exactly 0 for empty states.
    """
    post = niw_posterior(prior, counts, sums, outer)
    out = niw_log_marginal_normalizer(prior, counts) - 0.5 * post.dof * _logdet(post.scale)
    return torch.where(counts > 0, out, torch.zeros_like(out))


def inverse_wishart_log_density(
    covariance: Tensor, dof: Tensor, scale: Tensor, *, cholesky: Tensor | None = None
) -> Tensor:
    """log IW(Sigma | nu, Psi) = nu / 2 log|Psi| - nu d / 2 log 2 - log Gamma_d(nu / 2) - (nu + d + 1) / 2 log|Sigma|
    - tr(Psi Sigma^-1) / 2, batched over (...).

    Args:
        covariance: (..., d, d) Sigma, positive definite.
        dof: (...) nu (> d - 1), broadcasting against (...).
        scale: (..., d, d) Psi, positive definite, broadcasting against (...).
        cholesky: the lower Cholesky factor of ``covariance`` when the caller has it.

    Returns:
        (...) log densities (with respect to Lebesgue measure on the free entries of Sigma).
    """
    d = covariance.shape[-1]
    chol_sigma = torch.linalg.cholesky(covariance) if cholesky is None else cholesky
    logdet_sigma = 2.0 * torch.log(torch.diagonal(chol_sigma, dim1=-2, dim2=-1)).sum(-1)
    logdet_psi = 2.0 * torch.log(torch.diagonal(torch.linalg.cholesky(scale), dim1=-2, dim2=-1)).sum(-1)
    trace = torch.diagonal(torch.cholesky_solve(scale.expand_as(covariance), chol_sigma), dim1=-2, dim2=-1).sum(-1)
    return (
        0.5 * dof * logdet_psi
        - 0.5 * dof * d * math.log(2.0)
        - log_multigamma(0.5 * dof * torch.ones_like(logdet_sigma), d)
        - 0.5 * (dof + d + 1) * logdet_sigma
        - 0.5 * trace
    )


def niw_log_density(mean: Tensor, covariance: Tensor, params: NIWPrior) -> Tensor:
    """log NIW(mean, covariance | params) = log IW(Sigma | nu, Psi) + log N(mu; m, Sigma / kappa), batched over (...).

    Args:
        mean: (..., d).
        covariance: (..., d, d).
        params: NIW parameters broadcasting against (...).

    Returns:
        (...) log densities (with respect to Lebesgue measure on mu and the free entries of Sigma).
    """
    d = mean.shape[-1]
    kappa = params.kappa
    chol_sigma = torch.linalg.cholesky(covariance)
    log_iw = inverse_wishart_log_density(covariance, params.dof, params.scale, cholesky=chol_sigma)
    z = torch.linalg.solve_triangular(chol_sigma, (mean - params.mean).unsqueeze(-1), upper=False).squeeze(-1)
    # N(mu; m, Sigma / kappa) through the factor of Sigma: |Sigma / kappa|^-1/2 = kappa^(d/2) |Sigma|^-1/2
    log_normal = gaussian_log_normalizer(chol_sigma) + 0.5 * d * torch.log(kappa) - 0.5 * kappa * (z * z).sum(-1)
    return log_iw + log_normal


def sample_gamma(shape: Tensor, generator: torch.Generator, *, max_rounds: int = 64) -> Tensor:
    """Gamma(shape, rate 1) draws for every entry of ``shape`` (>= 0), reproducible through ``generator``.

    Marsaglia & Tsang (2000) squeeze method with the boost ``Gamma(a) = Gamma(a + 1) * U^(1/a)`` for a < 1.
    All entries draw in lock-step until each has an accepted value (torch._standard_gamma takes no generator).

    Args:
        shape: (...) shape parameters.
        generator: torch generator on shape's device.
        max_rounds: rejection rounds (acceptance is > 95 % per round; the rare leftovers take the mode).

    Returns:
        (...) draws, floored at the smallest positive normal number of the dtype.
    """
    a = shape
    boost = a < 1.0
    a1 = torch.where(boost, a + 1.0, a)
    d = a1 - 1.0 / 3.0
    c = 1.0 / torch.sqrt(9.0 * d)
    out = d.clone()
    todo = torch.ones_like(a, dtype=torch.bool)
    for _ in range(max_rounds):
        z = torch.randn(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        u = torch.rand(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        v = (1.0 + c * z) ** 3
        ok = (v > 0) & (torch.log(u.clamp_min(1e-300)) < 0.5 * z * z + d - d * v + d * torch.log(v.clamp_min(1e-300)))
        out = torch.where(ok & todo, d * v, out)
        todo = todo & ~ok
        if not bool(todo.any()):
            break
    if bool(boost.any()):
        u = torch.rand(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        out = torch.where(boost, out * u.clamp_min(1e-300) ** (1.0 / a), out)
    return out.clamp_min(torch.finfo(a.dtype).tiny)


def _sample_bartlett(dof: Tensor, dim: int, generator: torch.Generator) -> Tensor:
    """Bartlett factor A (..., d, d), lower triangular, with A A^T ~ Wishart(dof, I); dof (...)."""
    chi_dofs = dof.unsqueeze(-1) - torch.arange(dim, dtype=dof.dtype, device=dof.device)  # (..., d)
    diag = torch.sqrt(2.0 * sample_gamma(chi_dofs / 2.0, generator))  # chi^2_k = 2 Gamma(k / 2, 1)
    normal = torch.randn(*dof.shape, dim, dim, generator=generator, dtype=dof.dtype, device=dof.device)
    return torch.tril(normal, diagonal=-1) + torch.diag_embed(diag)


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
    dtype, device = params.mean.dtype, params.mean.device
    chol_scale = torch.linalg.cholesky(params.scale.expand(*batch, d, d))
    bartlett = _sample_bartlett(params.dof.to(dtype=dtype, device=device).expand(batch), d, generator)
    factor = torch.linalg.solve_triangular(chol_scale.transpose(-1, -2), bartlett, upper=True)  # B = L^-T A
    eye = torch.eye(d, dtype=dtype, device=device).expand(*batch, d, d)
    factor_inv = torch.linalg.solve(factor, eye)
    covariance = factor_inv.transpose(-1, -2) @ factor_inv  # (B B^T)^-1 = B^-T B^-1
    covariance = 0.5 * (covariance + covariance.transpose(-1, -2))
    kappa = params.kappa.expand(batch)
    chol_cov = torch.linalg.cholesky(covariance / kappa[..., None, None])
    z = torch.randn(*batch, d, 1, generator=generator, dtype=dtype, device=device)
    mean = params.mean.expand(*batch, d) + (chol_cov @ z).squeeze(-1)
    return mean, covariance
