"""Sticky Dirichlet transition rows over each sequence's own features (paper eq. 3).

Notation:
    N  sequences, K feature slots
    weights   (..., N, K, K) eta^(i)_jk > 0, unnormalised transition weights, eta_jk ~ Gamma(alpha + kappa delta_jk, 1)
    features  (..., N, K) bool f_i
    pi^(i)_j = (eta^(i)_j * f_i) / sum_k eta^(i)_jk f_ik  ~  Dir(alpha, ..., alpha + kappa, ..., alpha) over f_i.

Keeping eta for every slot pair (not only the owned ones) lets a sequence switch a feature on or off without
redrawing the other rows: the weights of features a sequence does not own are draws from their prior
(Fox, Hughes, Sudderth & Jordan 2014, "Joint modeling of multiple time series via the beta process").
The paper calls alpha "beta"; ``transition_concentration`` is alpha, ``stickiness`` is kappa.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lfd_torch.segmentation.emissions import sample_gamma

__all__ = [
    "prior_shape",
    "sample_transition_weights_prior",
    "transition_matrix",
    "initial_distribution",
    "transition_counts",
    "sample_transition_weights_posterior",
    "dirichlet_log_density_rows",
]


def prior_shape(
    n_features: int, alpha: float | Tensor, kappa: float | Tensor, *, dtype: torch.dtype, device: torch.device | None = None
) -> Tensor:
    """Gamma shapes alpha + kappa delta_jk of the transition weights, (K, K) or (..., K, K).

    ``alpha`` and ``kappa`` are numbers or tensors broadcasting against (..., 1, 1) (e.g. one value per chain).
    """
    return alpha + kappa * torch.eye(n_features, dtype=dtype, device=device)


def sample_transition_weights_prior(
    shape: tuple[int, ...], n_features: int, alpha: float | Tensor, kappa: float | Tensor, generator: torch.Generator,
    *, dtype: torch.dtype = torch.float64, device: torch.device | None = None,
) -> Tensor:
    """Draw eta of shape (*shape, K, K) from the sticky Gamma prior (alpha, kappa broadcast against it)."""
    a = prior_shape(n_features, alpha, kappa, dtype=dtype, device=device).expand(*shape, n_features, n_features)
    return sample_gamma(a.contiguous(), generator)


def transition_matrix(weights: Tensor, features: Tensor) -> Tensor:
    """Row-stochastic transition matrices restricted to owned features.

    Args:
        weights: (..., K, K) eta.
        features: (..., K) bool.

    Returns:
        (..., K, K) pi; rows and columns of features not owned are zero.
    """
    f = features.to(weights.dtype)
    w = weights * f.unsqueeze(-1) * f.unsqueeze(-2)
    total = w.sum(-1, keepdim=True)
    return w / torch.where(total > 0, total, torch.ones_like(total))


def initial_distribution(features: Tensor, dtype: torch.dtype) -> Tensor:
    """(..., K) uniform distribution over each sequence's owned features."""
    f = features.to(dtype)
    return f / f.sum(-1, keepdim=True).clamp_min(1.0)


def transition_counts(states: Tensor, lengths: Tensor, n_features: int) -> Tensor:
    """n_jk: number of j -> k transitions in each sequence.

    Args:
        states: (..., T) long labels (padding arbitrary in 0..K-1).
        lengths: (...) valid samples per sequence.
        n_features: K.

    Returns:
        (..., K, K) counts in the dtype float64.
    """
    T = states.shape[-1]
    valid = torch.arange(1, T, device=states.device) < lengths.unsqueeze(-1)  # transition t-1 -> t valid
    pair = states[..., :-1] * n_features + states[..., 1:]
    counts = torch.zeros(*states.shape[:-1], n_features * n_features, dtype=torch.float64, device=states.device)
    counts.scatter_add_(-1, pair, valid.to(torch.float64))
    return counts.reshape(*states.shape[:-1], n_features, n_features)


def sample_transition_weights_posterior(
    counts: Tensor, features: Tensor, alpha: float | Tensor, kappa: float | Tensor, generator: torch.Generator
) -> Tensor:
    """Conjugate draw of eta given transition counts.

    On the owned block, pi_j ~ Dir(alpha + kappa delta + n_j) and the row total S_j = sum_k eta_jk is independent
    of the data, S_j ~ Gamma(sum_k (alpha + kappa delta_jk), 1); eta_j = S_j pi_j. Entries outside the owned block
    are redrawn from the prior.

    Args:
        counts: (..., K, K) transition counts n_jk (zero outside the owned block).
        features: (..., K) bool.
        alpha, kappa: numbers or tensors broadcasting against (..., 1, 1).
        generator: source of randomness.

    Returns:
        (..., K, K) eta.
    """
    K = counts.shape[-1]
    a0 = prior_shape(K, alpha, kappa, dtype=counts.dtype, device=counts.device)
    f = features.to(counts.dtype)
    block = f.unsqueeze(-1) * f.unsqueeze(-2)
    g = sample_gamma((a0 + counts * block).expand_as(counts).contiguous(), generator)
    g_block = g * block
    pi = g_block / g_block.sum(-1, keepdim=True).clamp_min(torch.finfo(counts.dtype).tiny)
    total_shape = (a0 * block).expand_as(counts).sum(-1)
    total = sample_gamma(torch.where(total_shape > 0, total_shape, torch.ones_like(total_shape)), generator)
    owned = block > 0
    return torch.where(owned, pi * total.unsqueeze(-1), g)


def dirichlet_log_density_rows(pi: Tensor, features: Tensor, alpha: float, kappa: float) -> Tensor:
    """Sum over owned rows of log Dir(pi_j | alpha + kappa delta_j) restricted to owned features.

    Args:
        pi: (..., K, K) transition matrices from :func:`transition_matrix`.
        features: (..., K) bool.

    Returns:
        (...) log densities.
    """
    K = pi.shape[-1]
    f = features.to(pi.dtype)
    block = f.unsqueeze(-1) * f.unsqueeze(-2)
    a = prior_shape(K, alpha, kappa, dtype=pi.dtype, device=pi.device) * block
    log_pi = torch.log(torch.where(block > 0, pi, torch.ones_like(pi)).clamp_min(1e-300))
    row = torch.lgamma(a.sum(-1).clamp_min(1e-300)) - torch.where(block > 0, torch.lgamma(a.clamp_min(1e-300)), torch.zeros_like(a)).sum(-1)
    row = row + ((a - 1.0) * log_pi * block).sum(-1)
    return (row * f).sum(-1)
