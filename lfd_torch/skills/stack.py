"""All primitives of a library evaluated at once, each row with its own step (the engine's hot path).

B robots in different steps would otherwise need one primitive call per step present at every tick (a Python
loop over steps, 10-20 small kernels each). Instead the parameters of the M primitives are padded to K = max_m K_m
components (padding: weight 0, i.e. log pi = -inf, identity covariances, A = 0) and gathered per row, and the
package's own kernels are evaluated with those per-row parameters:

    log w_k(x) = log pi_k + log N(x; mu_k, Sigma_k)          (lfd_torch.gmm.GaussianBank over all M K Gaussians)
    f(x)       = sum_k softmax_k(log w) A_k (x - g)           (as StablePrimitive.__call__)
    H2(x)      = -log sum_ij w_i w_j N(mu_i; mu_j, S_i + S_j)   (lfd_torch.modulation.entropy)

For H2 the stack uses that the component means mu_k = A_k e (e = x - g) are linear in e, so the pairwise squared
Mahalanobis distance is a quadratic form with a constant matrix,

    (mu_i - mu_j)^T (S_i + S_j)^-1 (mu_i - mu_j) = e^T Q_ij e,   Q_ij = (A_i - A_j)^T (S_i + S_j)^-1 (A_i - A_j),

computed once per step (from :func:`~lfd_torch.modulation.pair_factors`): a tick then costs d^2 K^2 multiply-adds
per row instead of K^2 triangular solves.

A padded component has w = 0 and contributes nothing to f or H2. Tests check f and H2 against each primitive's own
evaluation.

Shapes: B rows, M steps, K padded components, d dimension.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from lfd_torch.gmm import GaussianBank
from lfd_torch.gmm.gaussian import LOG_2PI
from lfd_torch.modulation import pair_factors

__all__ = ["PrimitiveStack"]


class PrimitiveStack:
    """Padded parameters of the M primitives of a library (module docstring).

    Attributes:
        log_pi: (M, K) log mixture weights (-inf on padding).
        means, covariances: (M, K, d) and (M, K, d, d) position Gaussians.
        A: (M, K, d, d) system matrices; attractors: (M, d); S: (M, K, d, d) velocity covariances.
    """

    def __init__(self, primitives: list[Any], *, dtype: torch.dtype, device: torch.device):
        M = len(primitives)
        d = primitives[0].dim
        K = max(p.n_components for p in primitives)
        f = {"dtype": dtype, "device": device}
        eye = torch.eye(d, **f)
        self.log_pi = torch.full((M, K), -math.inf, **f)
        self.means = torch.zeros((M, K, d), **f)
        self.covariances = eye.repeat(M, K, 1, 1)
        self.A = torch.zeros((M, K, d, d), **f)
        self.S = eye.repeat(M, K, 1, 1)
        self.attractors = torch.stack([p.attractor.to(**f) for p in primitives])
        for m, p in enumerate(primitives):
            k = p.n_components
            self.log_pi[m, :k] = p.gmm.weights.to(**f).log()
            self.means[m, :k] = p.gmm.means.to(**f)
            self.covariances[m, :k] = p.gmm.covariances.to(**f)
            self.A[m, :k] = p.A.to(**f)
            self.S[m, :k] = p.velocity_covariances.to(**f)
        L_inv, half_log_det = pair_factors(self.S)  # (M, K, K, d, d), (M, K, K)
        dA = self.A.unsqueeze(2) - self.A.unsqueeze(1)  # (M, K, K, d, d): A_i - A_j
        W = L_inv @ dA
        Q = W.transpose(-2, -1) @ W  # (M, K, K, d, d)
        self._Q = Q.reshape(M, K * K, d * d).transpose(1, 2).contiguous()  # (M, d*d, K*K)
        self._overlap_const = (-half_log_det - 0.5 * d * LOG_2PI).reshape(M, K * K)
        self._bank = GaussianBank(self.means.reshape(M * K, d), self.covariances.reshape(M * K, d, d))
        self._M, self._K = M, K

    def evaluate(self, x: Tensor, step: Tensor, *, entropy: bool) -> tuple[Tensor, Tensor | None]:
        """f_m(x) (B, d) and, if ``entropy``, H2_m(x) (B,) for row-wise steps m = ``step`` (B,)."""
        n = x.shape[0]
        log_n = self._bank.log_density(x).view(n, self._M, self._K)  # every row under every step's Gaussians
        log_w = self.log_pi[step] + log_n[torch.arange(n, device=x.device), step]
        e = x - self.attractors[step]  # (B, d)
        mu = torch.einsum("bkij,bj->bki", self.A[step], e)  # (B, K, d): A_k (x - g)
        gamma = torch.softmax(log_w, dim=-1)
        f = torch.einsum("bk,bki->bi", gamma, mu)
        h2 = None
        if entropy:
            d = x.shape[-1]
            ee = (e.unsqueeze(-1) * e.unsqueeze(-2)).reshape(n, d * d)
            Qg = self._Q[step]  # (n, d*d, K*K)
            q = Qg[:, 0] * ee[:, :1]
            for i in range(1, d * d):  # d^2 broadcast multiply-adds: faster than a batched matmul of tiny blocks
                q = q + Qg[:, i] * ee[:, i : i + 1]
            terms = (log_w.unsqueeze(-1) + log_w.unsqueeze(-2)).reshape(n, -1) + self._overlap_const[step] - 0.5 * q
            h2 = -torch.logsumexp(terms, dim=-1)
        return f, h2
