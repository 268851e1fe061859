"""Gaussian mixture models on positions, used as the scheduling functions gamma_k(x) of LPV-DS.

Notation:
    N  samples, d state dimension, K components
    x      (N, d)  positions (data units, e.g. mm)
    x_dot  (N, d)  velocities (data units per second)
    GMM: weights (K,), means (K, d), covariances (K, d, d)

Modules:
    gaussian     the Gaussian log-density kernel (:func:`gaussian_log_density`, :func:`gaussian_log_normalizer`,
                 :class:`GaussianBank` for fixed Gaussians queried at every tick)
    niw          the Normal-inverse-Wishart kernels (prior, posterior, marginal likelihood, density, draws), shared
                 with :mod:`lfd_torch.segmentation`
    model        the :class:`GMM` dataclass (densities, posteriors, state dicts)
    em           EM with k-means++ starts (:func:`fit_em`) and BIC model selection (:func:`fit_em_bic`)
    pcgmm        PC-GMM: ddCRP prior with position/direction similarity, collapsed Gibbs (:func:`fit_pcgmm`)
    damm         DAMM-like directional mixture, parallel Gibbs with split/merge (:func:`fit_damm`)
    postprocess  :func:`order_by_attractor`, :func:`regularize_covariances`, :func:`merge_small_components`
    fitters      config-friendly callables ``fitter(x, x_dot, generator=...) -> GMM`` (conf/gmm/*.yaml)
"""

from lfd_torch.gmm.damm import DAMMResult, damm_labels, fit_damm
from lfd_torch.gmm.em import bic, fit_em, fit_em_bic, kmeans_plus_plus, n_parameters, refine_em
from lfd_torch.gmm.fitters import DAMMFitter, EMBICFitter, EMFitter, PCGMMFitter
from lfd_torch.gmm.gaussian import GaussianBank, gaussian_log_density, gaussian_log_normalizer
from lfd_torch.gmm.model import GMM, InvalidGMMError, check_samples
from lfd_torch.gmm.niw import (
    NIWPrior,
    inverse_wishart_log_density,
    log_multigamma,
    niw_log_density,
    niw_log_marginal_likelihood,
    niw_log_marginal_normalizer,
    niw_posterior,
    niw_prior_from_data,
    sample_gamma,
    sample_niw,
    sufficient_statistics,
)
from lfd_torch.gmm.pcgmm import PCGMMResult, fit_pcgmm, pcgmm_labels
from lfd_torch.gmm.postprocess import merge_small_components, order_by_attractor, regularize_covariances

__all__ = [
    "GMM",
    "InvalidGMMError",
    "check_samples",
    "fit_em",
    "fit_em_bic",
    "refine_em",
    "kmeans_plus_plus",
    "bic",
    "n_parameters",
    "fit_pcgmm",
    "pcgmm_labels",
    "PCGMMResult",
    "fit_damm",
    "damm_labels",
    "DAMMResult",
    "order_by_attractor",
    "regularize_covariances",
    "merge_small_components",
    "PCGMMFitter",
    "DAMMFitter",
    "EMFitter",
    "EMBICFitter",
    "GaussianBank",
    "gaussian_log_density",
    "gaussian_log_normalizer",
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
