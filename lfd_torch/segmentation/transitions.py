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

from lfd_torch.gmm import sample_gamma

__all__ = [
    "prior_shape",
    "sample_transition_weights_prior",
    "transition_matrix",
    "initial_distribution",
    "transition_counts",
    "sample_transition_weights_posterior",
    "dirichlet_log_density_rows",
    "dirichlet_multinomial_log_prob",
    "expand_min_duration",
    "free_transitions",
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


def transition_counts(states: Tensor, lengths: Tensor, n_features: int, free: Tensor | None = None) -> Tensor:
    """n_jk: number of j -> k transitions in each sequence.

    Args:
        states: (..., T) long labels (padding arbitrary in 0..K-1).
        lengths: (...) valid samples per sequence.
        n_features: K.
        free: (..., T - 1) bool, the transitions t-1 -> t drawn from pi (:func:`free_transitions`); None: all.

    Returns:
        (..., K, K) counts in the dtype float64.
    """
    T = states.shape[-1]
    valid = torch.arange(1, T, device=states.device) < lengths.unsqueeze(-1)  # transition t-1 -> t valid
    if free is not None:
        valid = valid & free
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


def _floor(dtype: torch.dtype) -> float:
    """Smallest value a Gamma argument or probability is clamped to before lgamma / log: 1e-300, or the smallest
    normal number of ``dtype`` where that is larger (1e-300 is 0 in float32, and lgamma(0) = inf then turns the
    masked rows of unowned features into inf * 0 = NaN)."""
    return max(1e-300, float(torch.finfo(dtype).tiny))


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
    log_pi = torch.log(torch.where(block > 0, pi, torch.ones_like(pi)).clamp_min(_floor(pi.dtype)))
    row = torch.lgamma(a.sum(-1).clamp_min(_floor(pi.dtype))) - torch.where(block > 0, torch.lgamma(a.clamp_min(_floor(pi.dtype))), torch.zeros_like(a)).sum(-1)
    row = row + ((a - 1.0) * log_pi * block).sum(-1)
    return (row * f).sum(-1)


def dirichlet_multinomial_log_prob(counts: Tensor, features: Tensor, alpha: float | Tensor,
                                   kappa: float | Tensor) -> Tensor:
    """log p(transitions | F) with the sticky rows pi_j ~ Dir(alpha + kappa delta_j) integrated out.

    For every owned row j: log Gamma(A_j) - log Gamma(A_j + n_j) + sum_k [log Gamma(a_jk + n_jk) - log Gamma(a_jk)],
    a_jk = alpha + kappa delta_jk over the owned features, A_j = sum_k a_jk, n_j = sum_k n_jk (the probability of
    one ordered sequence of transitions, not of their counts).

    Args:
        counts: (..., K, K) transition counts n_jk (zero outside the owned block).
        features: (..., K) bool.
        alpha, kappa: numbers or tensors broadcasting against (..., 1, 1).

    Returns:
        (...) log probabilities.
    """
    K = counts.shape[-1]
    f = features.to(counts.dtype)
    block = f.unsqueeze(-1) * f.unsqueeze(-2)
    n = counts * block
    a = prior_shape(K, alpha, kappa, dtype=counts.dtype, device=counts.device) * block
    # log Gamma(a_jk + n_jk) - log Gamma(a_jk) is 0 where n_jk = 0, which is most of the K^2 cells: evaluated only
    # on the counted ones (lgamma over every cell was the bulk of this function's time on a batch of labellings)
    hit = n > 0
    cells = torch.zeros_like(n)
    cells[hit] = torch.lgamma(a[hit] + n[hit]) - torch.lgamma(a[hit])
    rows = (torch.lgamma(a.sum(-1).clamp_min(_floor(counts.dtype))) - torch.lgamma((a + n).sum(-1).clamp_min(_floor(counts.dtype)))
            + cells.sum(-1))
    return (rows * f).sum(-1)


def expand_min_duration(initial: Tensor, transition: Tensor, min_duration: int) -> tuple[Tensor, Tensor]:
    """Initial distribution and transitions of the HMM whose states last at least ``min_duration`` samples.

    Every state k becomes a chain of D = ``min_duration`` phases (k, 0) -> (k, 1) -> ... -> (k, D - 1), index
    k D + r; the first D - 1 moves are forced, and from the last phase the chain follows pi: it stays with pi_kk
    or enters (j, 0) with pi_kj. This is the explicit-duration (semi-Markov) HMM with duration D - 1 + Geometric,
    so a run of a state is never shorter than D samples, except a run cut by the end of the sequence.
    Emissions of all phases of k are those of k (``log_emission.repeat_interleave(D, -1)``).

    Args:
        initial: (..., K).
        transition: (..., K, K) row-stochastic on the usable states.
        min_duration: D >= 1 (1 returns the inputs).

    Returns:
        (..., K D) initial and (..., K D, K D) transition.
    """
    D = int(min_duration)
    if D <= 1:
        return initial, transition
    K = transition.shape[-1]
    lead = transition.shape[:-2]
    P = transition.new_zeros(*lead, K, D, K, D)
    eye = torch.eye(K, dtype=transition.dtype, device=transition.device)
    for r in range(D - 1):
        P[..., :, r, :, r + 1] = eye
    P[..., :, D - 1, :, 0] = transition * (1.0 - eye)
    P[..., :, D - 1, :, D - 1] = transition * eye
    init = initial.new_zeros(*lead, K, D)
    init[..., 0] = initial
    return init.reshape(*lead, K * D), P.reshape(*lead, K * D, K * D)


def free_transitions(phases: Tensor, min_duration: int) -> Tensor:
    """(..., T - 1) bool: transition t-1 -> t was drawn from pi (the phase at t-1 is the last, D - 1)."""
    return phases[..., :-1] == int(min_duration) - 1
