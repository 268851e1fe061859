"""Disturbance modulation of a stable primitive (paper Sec. IV, eqs 8-21; NOTES sec. 4).

Notation (symbols, shapes, units; batch shape (...)):
    d                   state dimension; K number of primitive components
    x                   (..., d)      position (data units, LASA: mm)
    g                   (d,)          attractor g_m of the primitive
    f = f(x)            (..., d)      unmodulated primitive velocity (units/s)
    e_g                 (..., d)      (x - g)/||x - g||, first column of the orthonormal W(x) (eq. 11); 0 at x = g
    c                   (...)         e_g^T f = [W^T f]_1 (units/s)
    D                   diag(d1, d, ..., d); M = W D W^T = d I + (d1 - d) e_g e_g^T; M f = d f + (d1 - d) c e_g
    log_p_own           (...)         log p(x|A_m), own subtask space
    log_p_other         (...)         log p(x|A_m-), largest density of the other subtask spaces
    lambda_limit        float >= 1    cap of the large-scale factor (eq. 13)
    s                   (...)         max(min(lambda_limit, p(x|A_m-)/p(x|A_m)), 1), in [1, lambda_limit]
    H2                  (...)         quadratic Renyi entropy of the velocity mixture (eqs 14-16, NOTES 4a/4b)
    H2_ref              scalar        threshold H2(x_r) (default: max / quantile of H2 over the training states)
    lambda_ss           (...)         min(1, exp(H2_ref - H2)), in [0, 1] (eq. 18)
    kappa               float         ``radial_floor`` of the c = 0 rule: a = max(|c|, kappa ||f||)
    S_k                 (K, d, d)     velocity covariance of component k: the primitive's
                                      ``velocity_covariances`` (units/s)^2
    branch              (...)         int8 :class:`Branch` per sample

Modules: :mod:`~lfd_torch.modulation.entropy` (H2), :mod:`~lfd_torch.modulation.matrix` (closed-form W D W^T),
:mod:`~lfd_torch.modulation.factors` (eqs 13, 18), :mod:`~lfd_torch.modulation.policy` (branches, the c = 0 rule,
the stability analysis, :class:`Modulation`).
"""

from lfd_torch.modulation.entropy import (
    VelocityMixture,
    mixture_renyi_entropy,
    pair_factors,
    pairwise_log_overlap,
    reference_entropy,
    renyi_entropy,
    velocity_mixture,
)
from lfd_torch.modulation.factors import large_scale_factor, large_scale_gain, small_scale_factor
from lfd_torch.modulation.matrix import GoalDirection, goal_direction, modulate, modulation_matrix, radial_component
from lfd_torch.modulation.policy import (
    DEFAULT_LAMBDA_LIMIT,
    DEFAULT_RADIAL_FLOOR,
    MODULATION_MODES,
    Branch,
    Modulation,
    ModulationResult,
    modulated_velocity,
    modulated_velocity_single,
    modulated_velocity_unchecked,
)

__all__ = [
    "DEFAULT_LAMBDA_LIMIT",
    "DEFAULT_RADIAL_FLOOR",
    "MODULATION_MODES",
    "Branch",
    "GoalDirection",
    "Modulation",
    "ModulationResult",
    "VelocityMixture",
    "goal_direction",
    "large_scale_factor",
    "large_scale_gain",
    "mixture_renyi_entropy",
    "modulate",
    "modulated_velocity",
    "modulated_velocity_single",
    "modulated_velocity_unchecked",
    "modulation_matrix",
    "pair_factors",
    "pairwise_log_overlap",
    "radial_component",
    "reference_entropy",
    "renyi_entropy",
    "small_scale_factor",
    "velocity_mixture",
]
