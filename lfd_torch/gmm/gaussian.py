"""Multivariate Gaussian log-density, evaluated through Cholesky factors.

    log N(x; mu, Sigma) = -0.5 ||L^-1 (x - mu)||^2 - sum_i log L_ii - 0.5 d log(2 pi),   Sigma = L L^T.

:func:`gaussian_log_normalizer` is the part that does not depend on x; :func:`gaussian_log_density` is the full
density of n points under K Gaussians. The :class:`~lfd_torch.gmm.model.GMM` caches the normaliser of each
component and whitens points with its cached L^-1.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lfd_torch.errors import ShapeMismatchError

__all__ = ["gaussian_log_normalizer", "gaussian_log_density", "LOG_2PI"]

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
