"""Multivariate Gaussian log-density, evaluated through Cholesky factors.

    log N(x; mu, Sigma) = -0.5 ||L^-1 (x - mu)||^2 - sum_i log L_ii - 0.5 d log(2 pi),   Sigma = L L^T.

:func:`gaussian_log_normalizer` is the part that does not depend on x; :func:`gaussian_log_density` is the full
density of n points under K Gaussians; :class:`GaussianBank` caches the factors of K fixed Gaussians and evaluates
many points feature-major (the hot path of controllers that query the same Gaussians at every tick). The :class:`~lfd_torch.gmm.model.GMM` caches the normaliser of each
component and whitens points with its cached L^-1.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lfd_torch.errors import ShapeMismatchError

__all__ = ["GaussianBank", "gaussian_log_normalizer", "gaussian_log_density", "LOG_2PI"]

LOG_2PI = math.log(2.0 * math.pi)


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
        ShapeMismatchError: the trailing dimensions of the three arguments disagree.
    """
    d = x.shape[-1]
    if mean.shape[-1] != d or covariance.shape[-2:] != (d, d):
        raise ShapeMismatchError(
            f"samples have dimension {d}, mean {tuple(mean.shape)}, covariance {tuple(covariance.shape)}"
        )
    chol = torch.linalg.cholesky(covariance)  # (..., K, d, d)
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
    """

    def __init__(self, means: Tensor, covariances: Tensor):
        K, d = means.shape
        if covariances.shape != (K, d, d):
            raise ShapeMismatchError(f"covariances must have shape {(K, d, d)}, got {tuple(covariances.shape)}")
        chol = torch.linalg.cholesky(covariances)
        eye = torch.eye(d, dtype=chol.dtype, device=chol.device).expand(K, d, d)
        chol_inv = torch.linalg.solve_triangular(chol, eye, upper=False)
        self.n_components, self.dim = K, d
        self._whiten = chol_inv.reshape(K * d, d)
        self._shift = (chol_inv @ means.unsqueeze(-1)).reshape(K * d, 1)
        self._log_norm = gaussian_log_normalizer(chol).reshape(K, 1)

    def log_density(self, x: Tensor) -> Tensor:
        """(n, K) log N(x_t; mu_k, Sigma_k) of (n, d) points."""
        if x.ndim != 2 or x.shape[-1] != self.dim:
            raise ShapeMismatchError(f"points must have shape (n, {self.dim}), got {tuple(x.shape)}")
        return self.log_density_fm(x.T).T

    def log_density_fm(self, xt: Tensor) -> Tensor:
        """Feature-major form: (d, n) points to a (K, n) tensor of log densities."""
        z = torch.mm(self._whiten, xt).sub_(self._shift).view(self.n_components, self.dim, -1)
        return z.square().sum(1).mul_(-0.5).add_(self._log_norm)
