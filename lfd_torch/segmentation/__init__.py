"""BP-GM-HMM adaptive segmentation (paper Sec. III-A/B, eqs. 1-4, Table I, Fig. 2).

Notation:
    N demonstrations x^(i) of shape (T_i, d); K features (hidden states) shared through a Beta process;
    F (N, K) binary feature matrix f_i; eta^(i) (K, K) sticky transition weights; (mu_k, Sigma_k) Gaussian
    emissions with a Normal-Inverse-Wishart prior; s^(i) (T_i,) state sequences.
    Steps m = 1..M: ordered pieces shared by all demonstrations, attractors g_m (M, d), subtask spaces A_m with
    log p(x | A_m) of shape (..., M).

Entry points: :func:`segment` (or the config-friendly :class:`BPGMHMMSegmenter`) -> :class:`Segmentation`;
:class:`FixedSegmenter` and :class:`NoSegmenter` for ablations. Kernels: :mod:`.emissions`, :mod:`.features`,
:mod:`.transitions`, :mod:`.states`; the MCMC in :mod:`.sampler`; plotting in :mod:`.plot`; synthetic data with
known switch points in :mod:`.synthetic`.
"""

from lfd_torch.segmentation.emissions import (
    NIWPrior,
    gaussian_log_density,
    niw_log_density,
    niw_log_marginal_likelihood,
    niw_posterior,
    niw_prior_from_data,
    sample_niw,
    sufficient_statistics,
)
from lfd_torch.segmentation.features import ibp_log_prior, sample_ibp
from lfd_torch.segmentation.sampler import BetaProcessHMMSampler, SamplerResult
from lfd_torch.segmentation.segmentation import (
    BPGMHMMSegmenter,
    FixedSegmenter,
    NoSegmenter,
    Segmentation,
    SegmentationWarning,
    runs,
    segment,
)
from lfd_torch.segmentation.states import backward_sample, ffbs, forward_filter, forward_log_likelihood
from lfd_torch.segmentation.synthetic import SyntheticSteps, multi_step_demos

__all__ = [
    "segment",
    "Segmentation",
    "SegmentationWarning",
    "BPGMHMMSegmenter",
    "FixedSegmenter",
    "NoSegmenter",
    "runs",
    "BetaProcessHMMSampler",
    "SamplerResult",
    "NIWPrior",
    "niw_prior_from_data",
    "niw_posterior",
    "niw_log_density",
    "niw_log_marginal_likelihood",
    "sample_niw",
    "sufficient_statistics",
    "gaussian_log_density",
    "ibp_log_prior",
    "sample_ibp",
    "forward_log_likelihood",
    "ffbs",
    "forward_filter",
    "backward_sample",
    "SyntheticSteps",
    "multi_step_demos",
]
