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

import numpy as np
import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError
from lfd_torch.gmm.gaussian import NotPositiveDefiniteError, gaussian_log_normalizer
from lfd_torch.utils import check_float, check_generator, check_int, check_tensor, solver_errors

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

    Construction checks the types, dtypes (one for all fields) and shapes of the fields (d >= 1, batch shapes that
    broadcast), that ``mean`` and ``scale`` are finite, ``kappa > 0``, ``dof > d - 1`` (finite) and that ``scale``
    is symmetric positive definite (a Cholesky factorisation in float64).

    Raises:
        ShapeMismatchError: a field that is not a floating-point tensor, ``scale`` not (..., d, d), d = 0, mixed
            dtypes or devices, or batch shapes that do not broadcast.
        NonFiniteError: NaN or Inf in ``mean`` or ``scale``.
        InvalidArgumentError: ``kappa <= 0``, ``dof <= d - 1`` (or NaN / Inf), or a ``scale`` that is not
            symmetric positive definite, naming the field.
    """

    mean: Tensor
    kappa: Tensor
    dof: Tensor
    scale: Tensor

    def __post_init__(self) -> None:
        for name in ("mean", "kappa", "dof", "scale"):
            t = getattr(self, name)
            if not isinstance(t, Tensor) or not t.is_floating_point():
                what = t.dtype if isinstance(t, Tensor) else type(t).__name__
                raise ShapeMismatchError(f"NIWPrior.{name} must be a floating-point torch.Tensor, got {what}")
        if self.mean.ndim < 1 or self.scale.ndim < 2 or self.scale.shape[-2:] != (self.dim, self.dim):
            raise ShapeMismatchError(f"NIWPrior.mean must be (..., d) and NIWPrior.scale (..., d, d), got "
                                     f"{tuple(self.mean.shape)} and {tuple(self.scale.shape)}")  # fmt: skip
        if self.dim == 0:
            raise ShapeMismatchError(f"NIWPrior.mean must be (..., d) with d >= 1, got {tuple(self.mean.shape)}")
        dtypes = {name: getattr(self, name).dtype for name in ("mean", "kappa", "dof", "scale")}
        if len(set(dtypes.values())) > 1 or len({getattr(self, n).device for n in dtypes}) > 1:
            raise ShapeMismatchError(f"NIWPrior fields must share one dtype and device, got "
                                     f"{ {n: str(t) for n, t in dtypes.items()} }")  # fmt: skip
        try:  # numpy's rule (torch.broadcast_shapes imports sympy on its first call)
            np.broadcast_shapes(self.mean.shape[:-1], self.kappa.shape, self.dof.shape, self.scale.shape[:-2])
        except ValueError as exc:
            raise ShapeMismatchError(f"NIWPrior batch shapes do not broadcast: mean {tuple(self.mean.shape)}, kappa "
                                     f"{tuple(self.kappa.shape)}, dof {tuple(self.dof.shape)}, scale "
                                     f"{tuple(self.scale.shape)}") from exc  # fmt: skip
        for name in ("mean", "scale"):
            if not bool(torch.isfinite(_distinct(getattr(self, name))).all()):
                raise NonFiniteError(f"NIWPrior.{name} contains NaN or Inf")
        if not bool((self.kappa > 0).all() & torch.isfinite(self.kappa).all()):
            raise InvalidArgumentError(f"NIWPrior.kappa must be finite and > 0, got {_few(self.kappa)}")
        if not bool((self.dof > self.dim - 1).all() & torch.isfinite(self.dof).all()):
            raise InvalidArgumentError(f"NIWPrior.dof must be finite and > d - 1 = {self.dim - 1}, got "
                                       f"{_few(self.dof)}")  # fmt: skip
        scale = _distinct(self.scale).to(torch.float64)
        asym = (scale - scale.transpose(-1, -2)).abs().amax((-2, -1), keepdim=False) if scale.numel() else scale
        tol = 1e-6 * scale.abs().amax((-2, -1)).clamp_min(torch.finfo(self.scale.dtype).tiny) if scale.numel() else 0
        _, info = torch.linalg.cholesky_ex(scale)
        if scale.numel() and (bool((info != 0).any()) or bool((asym > tol).any())):
            raise InvalidArgumentError("NIWPrior.scale must be symmetric positive definite (its Cholesky "
                                       "factorisation in float64 fails, or it is not symmetric)")

    @property
    def dim(self) -> int:
        return self.mean.shape[-1]


def _distinct(t: Tensor) -> Tensor:
    """``t`` without the batch dimensions it was expanded along (stride 0): the same distinct values, checked once."""
    index = tuple(slice(0, 1) if stride == 0 and size > 1 else slice(None) for stride, size in zip(t.stride(), t.shape))
    return t[index]


def _few(t: Tensor) -> str:
    values = t.detach().reshape(-1)[:4].tolist()
    return f"{values}{' ...' if t.numel() > 4 else ''}"


def _niw_unchecked(mean: Tensor, kappa: Tensor, dof: Tensor, scale: Tensor) -> NIWPrior:
    """NIWPrior without the checks of its constructor (fields valid by construction, e.g. a posterior)."""
    out = object.__new__(NIWPrior)
    for name, value in (("mean", mean), ("kappa", kappa), ("dof", dof), ("scale", scale)):
        object.__setattr__(out, name, value)
    return out


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
    ``dof = d + 1 + extra_dof`` so that the expected covariance exists and the prior stays weak. Every axis'
    variance is floored at 1e-6 of the largest one and at (eps max(|x|, 1))^2, the spread rounding leaves: constant
    data (zero variance) still give a proper prior with a positive definite scale.

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
        NonFiniteError: NaN, Inf or an overflowing magnitude in x.
        InvalidArgumentError: a hyperparameter that is not a positive finite number (naming it).
    """
    check_tensor(x, "x", ndim=2, min_rows=2, shape_hint="(N, d)")
    n, d = x.shape
    if d == 0:
        raise ShapeMismatchError(f"x must be (N, d) with d >= 1, got {tuple(x.shape)}")
    for name, value in (("covariance_scale", covariance_scale), ("mean_pseudo_count", mean_pseudo_count),
                        ("extra_dof", extra_dof)):
        check_float(value, name, low=0.0, low_open=True)
    var = x.var(dim=0, unbiased=True)
    # a flat axis still gets a proper prior: 1e-6 of the largest variance, and at least the variance that rounding
    # the data's magnitude leaves, (eps max(|x|, 1))^2 (a normal number), so that constant data give a positive
    # definite scale rather than a subnormal or zero one
    info = torch.finfo(x.dtype)
    resolution = (info.eps * x.abs().max().clamp_min(1.0)) ** 2
    floor = torch.maximum(var.max() * 1e-6, resolution)
    var = torch.maximum(var, floor)
    dof = d + 1.0 + extra_dof
    scale = torch.diag(var * covariance_scale * (dof - d - 1.0))
    return _niw_unchecked(
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

    Raises:
        InvalidArgumentError: ``prior`` is not an NIWPrior, or ``counts`` holds a negative or NaN count.
    """
    if not isinstance(prior, NIWPrior):
        raise InvalidArgumentError(f"prior must be an NIWPrior, got {type(prior).__name__}")
    if not isinstance(counts, Tensor) or not bool((counts >= 0).all()):
        what = _few(counts) if isinstance(counts, Tensor) else type(counts).__name__
        raise InvalidArgumentError(f"counts must be a tensor of non-negative sample counts, got {what}")
    return _niw_posterior_unchecked(prior, counts, sums, outer)


def _niw_posterior_unchecked(prior: NIWPrior, counts: Tensor, sums: Tensor, outer: Tensor) -> NIWPrior:
    """:func:`niw_posterior` without its argument checks (the samplers' inner loops; counts >= 0 by construction)."""
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
    return _niw_unchecked(mean=mean_n, kappa=kappa_n, dof=dof_n, scale=scale_n)


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

    Raises:
        InvalidArgumentError: ``prior`` is not an NIWPrior, or ``counts`` holds a negative or NaN count.
        ShapeMismatchError: ``sums`` not (..., K, d) or ``outer`` not (..., K, d, d) for counts (..., K).
    """
    if not isinstance(prior, NIWPrior):
        raise InvalidArgumentError(f"prior must be an NIWPrior, got {type(prior).__name__}")
    if not isinstance(counts, Tensor) or not isinstance(sums, Tensor) or not isinstance(outer, Tensor):
        raise ShapeMismatchError("counts, sums and outer must be tensors")
    d = prior.dim
    if sums.shape != (*counts.shape, d) or outer.shape != (*counts.shape, d, d):
        raise ShapeMismatchError(f"sums must be (..., K, d) and outer (..., K, d, d) for counts (..., K) = "
                                 f"{tuple(counts.shape)} and d = {d}, got sums {tuple(sums.shape)} and outer "
                                 f"{tuple(outer.shape)}")  # fmt: skip
    if not bool((counts >= 0).all()):
        raise InvalidArgumentError(f"counts must be non-negative sample counts, got {_few(counts[~(counts >= 0)])}")
    return _niw_log_marginal_likelihood_unchecked(prior, counts, sums, outer)


def _niw_log_marginal_likelihood_unchecked(prior: NIWPrior, counts: Tensor, sums: Tensor, outer: Tensor) -> Tensor:
    """:func:`niw_log_marginal_likelihood` without its argument checks."""
    post = _niw_posterior_unchecked(prior, counts, sums, outer)
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
    """Gamma(shape, rate 1) draws for every entry of ``shape`` (finite, >= 0), reproducible through ``generator``.

    Marsaglia & Tsang (2000) squeeze method with the boost ``Gamma(a) = Gamma(a + 1) * U^(1/a)`` for a < 1.
    All entries draw in lock-step until each has an accepted value (torch._standard_gamma takes no generator).

    Args:
        shape: (...) shape parameters.
        generator: torch generator on shape's device.
        max_rounds: rejection rounds (acceptance is > 95 % per round; the rare leftovers take the mode).

    Returns:
        (...) draws, floored at the smallest positive normal number of the dtype (a shape of 0, the degenerate
        limit, draws that floor).

    Raises:
        InvalidArgumentError: a negative, NaN or Inf shape, ``max_rounds`` not in [1, 10000], or no generator.
        ShapeMismatchError: ``shape`` is not a floating-point tensor.
    """
    if not isinstance(shape, Tensor) or not shape.is_floating_point():
        what = shape.dtype if isinstance(shape, Tensor) else type(shape).__name__
        raise ShapeMismatchError(f"shape must be a floating-point tensor of Gamma shape parameters, got {what}")
    check_generator(generator, where="sample_gamma")
    check_int(max_rounds, "max_rounds", low=1, high=10_000)
    if shape.numel() and not bool(((shape >= 0) & (shape < math.inf)).all()):
        bad = shape[~((shape >= 0) & (shape < math.inf))]
        raise InvalidArgumentError(f"shape (Gamma shape parameters) must be finite and >= 0, got {_few(bad)}")
    return _sample_gamma_unchecked(shape, generator, max_rounds=max_rounds)


def _sample_gamma_unchecked(shape: Tensor, generator: torch.Generator, *, max_rounds: int = 64) -> Tensor:
    """:func:`sample_gamma` without its argument checks (the samplers' inner loops)."""
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
    diag = torch.sqrt(2.0 * _sample_gamma_unchecked(chi_dofs / 2.0, generator))  # chi^2_k = 2 Gamma(k / 2, 1)
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

    Raises:
        InvalidArgumentError: ``params`` is not an NIWPrior, no generator, or ``params.scale`` is not positive
            definite (that error is also a ``torch.linalg.LinAlgError``, as before).
        SolverError: the draw cannot be factorised (a degenerate draw in finite precision).
    """
    if not isinstance(params, NIWPrior):
        raise InvalidArgumentError(f"params must be an NIWPrior, got {type(params).__name__}")
    check_generator(generator, where="sample_niw")
    d = params.dim
    batch = params.mean.shape[:-1]
    dtype, device = params.mean.dtype, params.mean.device
    try:
        chol_scale = torch.linalg.cholesky(params.scale.expand(*batch, d, d))
    except torch.linalg.LinAlgError as exc:
        raise NotPositiveDefiniteError(f"params.scale is not symmetric positive definite: {exc}") from exc
    except RuntimeError as exc:  # a scale that does not broadcast against the mean's batch
        raise ShapeMismatchError(f"params.scale {tuple(params.scale.shape)} does not broadcast against params.mean "
                                 f"{tuple(params.mean.shape)}: {exc}") from exc  # fmt: skip
    bartlett = _sample_bartlett(params.dof.to(dtype=dtype, device=device).expand(batch), d, generator)
    with solver_errors("sample_niw (the inverse-Wishart draw)"):
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
