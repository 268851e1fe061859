"""Beta-process feature sharing through the two-parameter Indian buffet process (paper eqs. 1-2).

Notation:
    N   number of sequences
    K   number of feature slots (columns); a column no sequence owns is unused
    F   (..., N, K) bool, F[i, k] = 1 when sequence i owns feature k (the paper's binary vector f_i / q_i)
    gamma  mass of the Beta process (the expected number of features of one sequence)
    c      concentration of the Beta process (the paper's alpha in eq. 1)

Marginalising the Beta process H gives the two-parameter IBP (Griffiths & Ghahramani 2011): given the other
sequences, sequence i owns an existing feature k with probability m_{-i,k} / (c + N - 1) (eq. 2), and owns
Poisson(gamma c / (c + N - 1)) features that no other sequence owns ("unique" features).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
from lfd_torch.utils import check_float, check_generator, check_int

__all__ = [
    "shared_log_odds",
    "unique_feature_rate",
    "ibp_log_prior",
    "sample_ibp",
]


def shared_log_odds(counts_others: Tensor, n_sequences: int, concentration: float) -> Tensor:
    """log p(f_ik = 1 | F_-i) - log p(f_ik = 0 | F_-i) for a feature other sequences own (m_{-i,k} > 0).

    Args:
        counts_others: (...) m_{-i,k}, values in 1..N-1.
        n_sequences: N.
        concentration: c > 0.

    Returns:
        (...) log odds log m - log(c + N - 1 - m).
    """
    m = counts_others.to(torch.get_default_dtype() if not counts_others.is_floating_point() else counts_others.dtype)
    return torch.log(m) - torch.log(concentration + n_sequences - 1.0 - m)


def unique_feature_rate(mass: float, concentration: float, n_sequences: int) -> float:
    """Poisson rate gamma c / (c + N - 1) of the features only one sequence owns."""
    return mass * concentration / (concentration + n_sequences - 1.0)


def ibp_log_prior(features: Tensor, mass: float | Tensor, concentration: float) -> Tensor:
    """log probability of the equivalence class of a binary matrix under the two-parameter IBP.

    p([F]) = (gamma c)^K+ / prod_h K_h! * exp(-gamma sum_{n=1}^N c / (c + n - 1)) * prod_k B(m_k, N - m_k + c),
    where K+ counts owned columns and K_h the columns with identical pattern h (Griffiths & Ghahramani 2011).

    Args:
        features: (..., N, K) bool; columns nobody owns are ignored.
        mass: gamma, a number or (...).
        concentration: c.

    Returns:
        (...) tensor (a scalar for one matrix).

    Raises:
        ShapeMismatchError: ``features`` is not a bool tensor of at least 2 dimensions.
        InvalidArgumentError: ``concentration``, or a number ``mass``, not finite and > 0 (a tensor ``mass`` is the
            sampler's own, not checked: no host synchronisation on its hot path).
    """
    if not isinstance(features, Tensor) or features.dtype != torch.bool or features.ndim < 2:
        got = f"{features.dtype} {tuple(features.shape)}" if isinstance(features, Tensor) else type(features).__name__
        raise ShapeMismatchError(f"features must be a bool tensor (..., N, K), got {got}")
    check_float(concentration, "concentration", low=0.0, low_open=True)
    if not isinstance(mass, Tensor):
        check_float(mass, "mass", low=0.0, low_open=True)
    f = features.to(torch.float64)
    n = f.shape[-2]
    m = f.sum(-2)  # (..., K)
    owned = m > 0
    mass_t = torch.as_tensor(mass, dtype=torch.float64, device=f.device)
    harmonic = sum(concentration / (concentration + j) for j in range(n))
    k_plus = owned.sum(-1).to(torch.float64)
    log_beta = torch.lgamma(m.clamp_min(1.0)) + torch.lgamma(n - m + concentration) - math.lgamma(n + concentration)
    log_beta = (log_beta * owned).sum(-1)
    # K_h!: a column in a group of h identical owned columns adds log(h!) / h, so each group adds log(h!) once
    same = (features.unsqueeze(-1) == features.unsqueeze(-2)).all(-3) & owned.unsqueeze(-1) & owned.unsqueeze(-2)
    h = same.sum(-1).to(torch.float64)  # (..., K)
    log_hist = (torch.where(owned, torch.lgamma(h + 1.0) / h.clamp_min(1.0), torch.zeros_like(h))).sum(-1)
    return k_plus * (torch.log(mass_t) + math.log(concentration)) - log_hist - mass_t * harmonic + log_beta


def sample_ibp(
    n_sequences: int, mass: float, concentration: float, generator: torch.Generator, max_features: int = 10_000
) -> Tensor:
    """Draw a binary matrix from the two-parameter IBP by its sequential (buffet) construction.

    Sequence i owns each existing feature with probability m_k / (c + i) and adds Poisson(gamma c / (c + i)) new
    ones (i = 0..N-1).

    Returns:
        (N, K) bool, columns in order of first appearance.

    Raises:
        InvalidArgumentError: ``generator`` not a torch.Generator; ``n_sequences`` not an integer >= 0; ``mass`` or
            ``concentration`` not finite and > 0; ``max_features`` not an integer >= 1, or exceeded by the draw.
    """
    check_generator(generator, where="sample_ibp")
    check_int(n_sequences, "n_sequences", low=0)
    check_float(mass, "mass", low=0.0, low_open=True)
    check_float(concentration, "concentration", low=0.0, low_open=True)
    check_int(max_features, "max_features", low=1)
    device = generator.device
    counts = torch.zeros(0, dtype=torch.float64, device=device)
    rows: list[Tensor] = []
    for i in range(n_sequences):
        p = counts / (concentration + i)
        own = torch.rand(counts.shape, generator=generator, dtype=torch.float64, device=device) < p
        rate = torch.tensor([mass * concentration / (concentration + i)], dtype=torch.float64, device=device)
        n_new = int(torch.poisson(rate, generator=generator))
        row = torch.cat([own, torch.ones(n_new, dtype=torch.bool, device=device)])
        counts = torch.cat([counts + own.double(), torch.ones(n_new, dtype=torch.float64, device=device)])
        if counts.numel() > max_features:
            raise InvalidArgumentError(f"the IBP draw exceeded max_features = {max_features} features (mass {mass}, "
                                       f"concentration {concentration}): raise max_features or lower the mass")
        rows.append(row)
    k = counts.numel()
    out = torch.zeros(n_sequences, k, dtype=torch.bool, device=device)
    for i, r in enumerate(rows):
        out[i, : r.numel()] = r
    return out
