"""Normal-inverse-Wishart conjugate prior: marginal likelihoods of clusters from sufficient statistics.

A cluster of n points y_i in R^d is summarised by (n, s = sum y_i, Q = sum y_i y_i^T). With the prior
mu ~ N(mu0, Sigma / kappa0), Sigma ~ IW(Psi0, nu0), the log marginal likelihood is (Murphy 2007, eq. 266)

    log p(Y) = -n d / 2 log pi + log Gamma_d(nu_n / 2) - log Gamma_d(nu0 / 2)
               + nu0 / 2 log|Psi0| - nu_n / 2 log|Psi_n| + d / 2 (log kappa0 - log kappa_n),

kappa_n = kappa0 + n, nu_n = nu0 + n, Psi_n = Psi0 + Q + kappa0 mu0 mu0^T - kappa_n mu_n mu_n^T,
mu_n = (kappa0 mu0 + s) / kappa_n. Everything here is float64 numpy: it serves the sequential samplers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln

__all__ = ["NIWPrior"]


@dataclass(frozen=True)
class NIWPrior:
    """NIW hyperparameters in the coordinates of the statistics (mu0 (d,), Psi0 (d, d))."""

    mu0: np.ndarray
    kappa0: float
    nu0: float
    psi0: np.ndarray

    @property
    def dim(self) -> int:
        return self.mu0.shape[0]

    def tables(self, n_max: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-count constants c(n) for n = 0..n_max, and log kappa_n, so that
        log p(Y) = c(n) - nu_n / 2 log|Psi_n|."""
        d = self.dim
        n = np.arange(n_max + 1, dtype=np.float64)
        nu_n = self.nu0 + n
        j = np.arange(d, dtype=np.float64)
        lmvg = gammaln(nu_n[:, None] / 2 - j / 2).sum(1)
        lmvg0 = gammaln(self.nu0 / 2 - j / 2).sum()
        logdet0 = np.linalg.slogdet(self.psi0)[1]
        log_kn = np.log(self.kappa0 + n)
        const = (
            -n * d / 2 * math.log(math.pi) + lmvg - lmvg0 + self.nu0 / 2 * logdet0
            + d / 2 * (math.log(self.kappa0) - log_kn)
        )
        return const, log_kn

    def psi_n(self, n: np.ndarray, s: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Posterior scale matrices Psi_n for stacked statistics n (...,), s (..., d), Q (..., d, d)."""
        kn = self.kappa0 + n
        m0 = self.kappa0 * self.mu0
        num = m0 + s  # kappa_n mu_n
        return (
            self.psi0 + Q + self.kappa0 * np.outer(self.mu0, self.mu0)
            - num[..., :, None] * num[..., None, :] / kn[..., None, None]
        )

    def log_marginal(self, n: np.ndarray, s: np.ndarray, Q: np.ndarray, const: np.ndarray) -> np.ndarray:
        """log p(Y) for stacked statistics; ``const`` from :meth:`tables`; n must be integer-valued."""
        P = self.psi_n(n, s, Q)
        if self.dim == 2:
            logdet = np.log(P[..., 0, 0] * P[..., 1, 1] - P[..., 0, 1] * P[..., 1, 0])
        else:
            logdet = np.linalg.slogdet(P)[1]
        ni = n.astype(np.int64)
        return const[ni] - (self.nu0 + n) / 2 * logdet


def niw_log_marginal_torch(n, s, Q, *, kappa0: float, nu0: float, psi0):  # type: ignore[no-untyped-def]
    """Batched torch version of the NIW log marginal likelihood with prior mean mu0 = 0.

    Args:
        n: (...,) counts (float tensor).
        s: (..., d) sums.
        Q: (..., d, d) sums of outer products.
        kappa0, nu0: scalar hyperparameters.
        psi0: (d, d) tensor.

    Returns:
        (...,) log p(Y); exactly 0 where n == 0.
    """
    import torch

    d = s.shape[-1]
    kn = kappa0 + n
    nn = nu0 + n
    P = psi0 + Q - s.unsqueeze(-1) * s.unsqueeze(-2) / kn[..., None, None]
    logdet = torch.linalg.slogdet(P)[1]
    logdet0 = torch.linalg.slogdet(psi0)[1]
    out = (
        -n * d / 2 * math.log(math.pi)
        + torch.special.multigammaln(nn / 2, d)
        - torch.special.multigammaln(torch.as_tensor(nu0 / 2, dtype=n.dtype, device=n.device), d)
        + nu0 / 2 * logdet0
        - nn / 2 * logdet
        + d / 2 * (math.log(kappa0) - torch.log(kn))
    )
    return torch.where(n > 0, out, torch.zeros_like(out))
