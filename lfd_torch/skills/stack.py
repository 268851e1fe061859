"""All primitives of a library evaluated at once, each row with its own step (the engine's hot path).

B robots in different steps would otherwise need one primitive call per step present at every tick (a Python
loop over steps, 10-20 small kernels each). Instead the parameters of the M primitives are padded to K = max_m K_m
components (padding: weight 0, i.e. log pi = -inf, identity covariances, A = 0) and gathered per row, and the
package's own kernels are evaluated with those per-row parameters:

    log w_k(x) = log pi_k + log N(x; mu_k, Sigma_k)          (lfd_torch.gmm.GaussianBank over all M K Gaussians)
    f(x)       = sum_k softmax_k(log w) A_k (x - g)           (as StablePrimitive.__call__)
    H2(x)      = mixture_renyi_entropy(log w, A_k (x - g), S_k)   (lfd_torch.modulation.entropy; the pair
                 factors of S_i + S_j are computed once per step and gathered per row)

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
from lfd_torch.modulation import mixture_renyi_entropy, pair_factors

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
        self._pair_inv, self._pair_half_log_det = pair_factors(self.S)  # (M, K, K, d, d), (M, K, K)
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
            factors = (self._pair_inv[step], self._pair_half_log_det[step])
            h2 = mixture_renyi_entropy(log_w, mu, self.S[step], factors=factors)
        return f, h2
