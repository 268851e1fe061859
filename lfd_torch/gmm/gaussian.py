"""Multivariate Gaussian log-density, evaluated through Cholesky factors.

    log N(x; mu, Sigma) = -0.5 ||L^-1 (x - mu)||^2 - sum_i log L_ii - 0.5 d log(2 pi),   Sigma = L L^T.

:func:`gaussian_log_normalizer` is the part that does not depend on x; :func:`gaussian_log_density` is the full
density of n points under K Gaussians; :class:`GaussianBank` caches the factors of K fixed Gaussians and evaluates
many points feature-major (the hot path of controllers that query the same Gaussians at every tick). The
:class:`~lfd_torch.gmm.model.GMM` caches the normaliser of each component and whitens points with its cached L^-1.

Quadratic-feature form (:func:`gaussian_quadratic_weights`, :func:`quadratic_features`): log N(x) is a quadratic
function of x, w_k . phi(x - c) with phi = [e_a e_b (a <= b), e, 1]; K Gaussians (or any quadratic functions, e.g.
their sums) at n points are then a single (K, F) x (F, n) matrix product, F = d (d + 1) / 2 + d + 1.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, InvalidGMMError, ShapeMismatchError
from lfd_torch.utils import check_tensor

__all__ = [
    "GaussianBank",
    "LOG_2PI",
    "gaussian_log_density",
    "gaussian_log_normalizer",
    "gaussian_quadratic_weights",
    "quadratic_feature_pairs",
    "quadratic_features",
    "quadratic_weights",
]

LOG_2PI = math.log(2.0 * math.pi)


class NotPositiveDefiniteError(InvalidArgumentError, torch.linalg.LinAlgError):
    """A covariance that cannot be factorised: an InvalidArgumentError naming the argument, and still the
    ``torch.linalg.LinAlgError`` that callers of the sampling loops map to a SolverError."""


def gaussian_log_normalizer(cholesky: Tensor) -> Tensor:
    """log of the Gaussian normalising constant, -0.5 log|2 pi Sigma|, from the Cholesky factor of Sigma.

    Args:
        cholesky: (..., d, d) lower Cholesky factors L with L L^T = Sigma.

    Returns:
        (...) tensor -sum_i log L_ii - 0.5 d log(2 pi).
    """
    d = cholesky.shape[-1]
    return -torch.log(torch.diagonal(cholesky, dim1=-2, dim2=-1)).sum(-1) - 0.5 * d * LOG_2PI


def gaussian_log_density(x: Tensor, mean: Tensor, covariance: Tensor) -> Tensor:
    """log N(x_t; mean_k, covariance_k) for every sample t and Gaussian k.

    Leading batch dimensions broadcast between ``x`` and the parameters.

    Args:
        x: (..., n, d) samples.
        mean: (..., K, d).
        covariance: (..., K, d, d), positive definite.

    Returns:
        (..., n, K) log densities, in the dtype and device of the inputs.

    Raises:
        ShapeMismatchError: the trailing dimensions, dtypes or devices of the three arguments disagree.
        InvalidArgumentError: a covariance that is not positive definite (naming ``covariance``).

    This is the inner kernel of the samplers (called at every sweep), so it does not scan its inputs for NaN or Inf:
    a non-finite ``x`` gives non-finite rows. The public entry points that take data (:class:`GMM` methods,
    :meth:`GaussianBank.log_density`, the fitters) check their points first.
    """
    for name, t in (("x", x), ("mean", mean), ("covariance", covariance)):
        if not isinstance(t, Tensor):
            raise ShapeMismatchError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if x.ndim < 2 or mean.ndim < 1 or covariance.ndim < 2:
        raise ShapeMismatchError(f"x, mean and covariance must have shapes (..., n, d), (..., K, d), (..., K, d, d), "
                                 f"got {tuple(x.shape)}, {tuple(mean.shape)}, {tuple(covariance.shape)}")  # fmt: skip
    d = x.shape[-1]
    if mean.shape[-1] != d or covariance.shape[-2:] != (d, d):
        raise ShapeMismatchError(
            f"samples have dimension {d}, mean {tuple(mean.shape)}, covariance {tuple(covariance.shape)}"
        )
    if not (x.dtype == mean.dtype == covariance.dtype) or not (x.device == mean.device == covariance.device):
        raise ShapeMismatchError(f"x ({x.dtype} on {x.device}), mean ({mean.dtype} on {mean.device}) and covariance "
                                 f"({covariance.dtype} on {covariance.device}) must share dtype and device")  # fmt: skip
    try:
        chol = torch.linalg.cholesky(covariance)  # (..., K, d, d)
    except torch.linalg.LinAlgError as exc:  # free on valid input: no scan of the factors
        raise NotPositiveDefiniteError(f"covariance is not symmetric positive definite: {exc}") from exc
    diff = x.unsqueeze(-3) - mean.unsqueeze(-2)  # (..., K, n, d)
    z = torch.linalg.solve_triangular(chol, diff.transpose(-1, -2), upper=False)  # (..., K, d, n)
    maha = (z * z).sum(-2)  # (..., K, n)
    return (gaussian_log_normalizer(chol).unsqueeze(-1) - 0.5 * maha).transpose(-1, -2)


class GaussianBank:
    """K fixed Gaussians with cached whitening, evaluated at many points at once.

    The whitening matrices are stacked into one (K d, d) matrix, so that log N(x; mu_k, Sigma_k) for n points is one
    matrix product and a reduction over the middle axis of a (K, d, n) tensor: reductions over a trailing axis of
    size d are several times slower on CPUs.

    Args:
        means: (K, d).
        covariances: (K, d, d), symmetric positive definite.

    Raises:
        ShapeMismatchError: shapes, dtypes or devices that disagree. NonFiniteError: NaN or Inf in a parameter.
        InvalidGMMError: a covariance that is not positive definite (naming its index).
    """

    def __init__(self, means: Tensor, covariances: Tensor):
        check_tensor(means, "means", ndim=2, bounded=False, shape_hint="(K, d)")
        K, d = means.shape
        check_tensor(covariances, "covariances", ndim=3, dtype=means.dtype, device=means.device, bounded=False,
                     shape_hint=f"({K}, {d}, {d})")  # fmt: skip
        if covariances.shape != (K, d, d):
            raise ShapeMismatchError(f"covariances must have shape {(K, d, d)}, got {tuple(covariances.shape)}")
        chol, info = torch.linalg.cholesky_ex(covariances)
        if K and bool((info != 0).any()):
            k = int(torch.nonzero(info != 0)[0])
            raise InvalidGMMError(f"covariances[{k}] is not symmetric positive definite")
        eye = torch.eye(d, dtype=chol.dtype, device=chol.device).expand(K, d, d)
        chol_inv = torch.linalg.solve_triangular(chol, eye, upper=False)
        self.n_components, self.dim = K, d
        shift = (chol_inv @ means.unsqueeze(-1)).reshape(K * d, 1)
        # z = [L^-1, -L^-1 mu] [x; 1] / sqrt(2), so that log N = log_norm - ||z||^2: one product, no subtraction
        self._affine = torch.cat([chol_inv.reshape(K * d, d), -shift], dim=1) * math.sqrt(0.5)  # (K d, d + 1)
        self._log_norm = gaussian_log_normalizer(chol).reshape(K, 1)

    def log_density(self, x: Tensor) -> Tensor:
        """(n, K) log N(x_t; mu_k, Sigma_k) of (n, d) points, in the bank's dtype and device.

        Raises:
            ShapeMismatchError: not an (n, d) tensor of the bank's dtype and device. NonFiniteError: NaN or Inf in x
                (:meth:`log_density_fm`, the feature-major hot path, does not scan its input).
        """
        check_tensor(x, "x", ndim=2, last_dim=self.dim, dtype=self._affine.dtype, device=self._affine.device,
                     bounded=False, shape_hint=f"(n, {self.dim})")  # fmt: skip
        return self.log_density_fm(x.T).T

    def log_density_fm(self, xt: Tensor) -> Tensor:
        """Feature-major form: (d, n) points to a (K, n) tensor of log densities."""
        n = xt.shape[1]
        xa = torch.cat([xt, torch.ones((1, n), dtype=xt.dtype, device=xt.device)])  # (d + 1, n)
        z = torch.mm(self._affine, xa).view(self.n_components, self.dim, n)
        out = torch.addcmul(self._log_norm, z[:, 0], z[:, 0], value=-1.0)
        for a in range(1, self.dim):  # d fused multiply-adds: a reduction over a middle axis of size d is slower
            out.addcmul_(z[:, a], z[:, a], value=-1.0)
        return out


# ---------------------------------------------------------------------------------------------- quadratic forms
def quadratic_feature_pairs(d: int, device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
    """Index pairs (a, b), a <= b, of the quadratic features of :func:`quadratic_features` (row-major upper
    triangle): two (d (d + 1) / 2,) long tensors."""
    return torch.triu_indices(d, d, device=device).unbind(0)


def quadratic_features(e: Tensor) -> Tensor:
    """phi(e) = [e_a e_b for a <= b, e_1 .. e_d, 1] of feature-major points.

    Any quadratic function q(e) = e^T Q e + l^T e + c is then one dot product w . phi(e) with w from
    :func:`quadratic_weights`, so that K of them at n points are one (K, F) x (F, n) matrix product.

    Args:
        e: (d, n) points, one column per point.

    Returns:
        (F, n) features, F = d (d + 1) / 2 + d + 1, dtype and device of ``e``.
    """
    if e.ndim != 2:
        raise ShapeMismatchError(f"points must have shape (d, n), got {tuple(e.shape)}")
    d, n = e.shape
    a, b = quadratic_feature_pairs(d, e.device)
    out = torch.empty((a.numel() + d + 1, n), dtype=e.dtype, device=e.device)
    torch.mul(e.index_select(0, a), e.index_select(0, b), out=out[: a.numel()])
    out[a.numel() : a.numel() + d] = e
    out[-1] = 1.0
    return out


def quadratic_weights(matrix: Tensor, linear: Tensor, constant: Tensor) -> Tensor:
    """Weights w with w . phi(e) = e^T Q e + l^T e + c (:func:`quadratic_features`).

    Args:
        matrix: (..., d, d) Q (symmetrised here: only Q + Q^T matters).
        linear: (..., d) l.
        constant: (...) c.

    Returns:
        (..., F) weights: Q_aa for e_a^2, Q_ab + Q_ba for e_a e_b (a < b), then l, then c.
    """
    d = matrix.shape[-1]
    a, b = quadratic_feature_pairs(d, matrix.device)
    sym = matrix + matrix.transpose(-2, -1)
    quad = torch.where(a == b, 0.5, 1.0).to(dtype=matrix.dtype) * sym[..., a, b]
    return torch.cat([quad, linear, constant.unsqueeze(-1)], dim=-1)


def gaussian_quadratic_weights(means: Tensor, covariances: Tensor, center: Tensor) -> Tensor:
    """Weights of log N(x; mu_k, Sigma_k) as quadratic forms of e = x - center.

    log N = -0.5 (e - m_k)^T Sigma_k^-1 (e - m_k) + log normaliser, m_k = mu_k - center: w_k . phi(x - center)
    (:func:`quadratic_features`) equals :func:`gaussian_log_density` up to rounding. Choose ``center`` near the
    points (e.g. the data centre): the expanded form loses about eps (|e|^2 + |m_k|^2) / sigma_k^2 in absolute
    accuracy, where the whitened form loses eps |e - m_k|^2 / sigma_k^2.

    Args:
        means: (K, d).
        covariances: (K, d, d), symmetric positive definite.
        center: (d,) origin of e.

    Returns:
        (K, F) weights, F = d (d + 1) / 2 + d + 1.
    """
    K, d = means.shape
    if covariances.shape != (K, d, d) or center.shape != (d,):
        raise ShapeMismatchError(
            f"means {tuple(means.shape)}, covariances {tuple(covariances.shape)} and center {tuple(center.shape)} "
            f"disagree (expected (K, d), (K, d, d), (d,))"
        )
    chol = torch.linalg.cholesky(covariances)
    prec = torch.cholesky_inverse(chol)  # (K, d, d) Sigma^-1
    m = means - center
    pm = (prec @ m.unsqueeze(-1)).squeeze(-1)  # Sigma^-1 m
    const = gaussian_log_normalizer(chol) - 0.5 * (m * pm).sum(-1)
    return quadratic_weights(-0.5 * prec, pm, const)
