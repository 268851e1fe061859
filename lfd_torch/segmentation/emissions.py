"""Gaussian emissions with a Normal-Inverse-Wishart (NIW) prior (paper eq. 4).

The kernels live in :mod:`lfd_torch.gmm.niw` and :mod:`lfd_torch.gmm.gaussian` (shared with the GMM fitters);
this module only names them for the segmentation code.

Notation:
    K  number of features (hidden states)
    d  state dimension
    mean        (K, d)     mu_k
    covariance  (K, d, d)  Sigma_k
    NIW(m0, kappa0, nu0, Psi0):  Sigma ~ IW(nu0, Psi0),  mu | Sigma ~ N(m0, Sigma / kappa0)
"""

from __future__ import annotations

from lfd_torch.gmm.gaussian import gaussian_log_density
from lfd_torch.gmm.niw import (
    NIWPrior,
    niw_log_density,
    niw_log_marginal_likelihood,
    niw_posterior,
    niw_prior_from_data,
    sample_gamma,
    sample_niw,
    sufficient_statistics,
)

__all__ = [
    "NIWPrior",
    "niw_prior_from_data",
    "niw_posterior",
    "sufficient_statistics",
    "sample_niw",
    "sample_gamma",
    "niw_log_density",
    "gaussian_log_density",
    "niw_log_marginal_likelihood",
]
