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

computed once per step (from :func:`~lfd_torch.modulation.pair_factors`): a tick then costs d^2 K (K + 1) / 2
multiply-adds per row (the pairs i <= j; the sum is symmetric) instead of K^2 triangular solves.

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
        self._M, self._K, self._d = M, K, d
        # feature-major constants: every row is evaluated under every step (cheap matrix products), then each row
        # keeps its own step's block with one gather along the leading axis
        self._A_fm = self.A.reshape(M * K * d, d)  # rows (m, k, i): A_k[i, :]
        self._Ag_fm = (self.A @ self.attractors.view(M, 1, d, 1)).reshape(M, K * d, 1)  # A_k g_m
        self._log_pi_fm = self.log_pi.unsqueeze(-1)  # (M, K, 1)
        # entropy: the K (K + 1) / 2 pairs i <= j (the sum is symmetric), an off-diagonal pair counted twice
        I, J = torch.triu_indices(K, K, device=device)
        self._pair_i, self._pair_j = I, J
        Qp = Q[:, I, J].reshape(M, -1, d * d)  # (M, P, d*d)
        self._Q_pairs = Qp.permute(2, 0, 1).contiguous()  # (d*d, M, P)
        self._const_pairs = self._overlap_const.view(M, K, K)[:, I, J] + torch.where(I == J, 0.0, math.log(2.0)).to(**f)

    @staticmethod
    def _own_block(values: Tensor, step: Tensor) -> Tensor:
        """values (M, R, n) -> (R, n): column t taken from block step[t]."""
        return values.gather(0, step.view(1, 1, -1).expand(1, values.shape[1], -1)).squeeze(0)

    def evaluate(self, x: Tensor, step: Tensor, *, entropy: bool) -> tuple[Tensor, Tensor | None]:
        """f_m(x) (B, d) and, if ``entropy``, H2_m(x) (B,) for row-wise steps m = ``step`` (B,)."""
        M, K, d = self._M, self._K, self._d
        n = x.shape[0]
        xt = x.T
        log_n = self._bank.log_density_fm(xt).view(M, K, n)  # every row under every step's Gaussians
        log_w = self._own_block(log_n + self._log_pi_fm, step)  # (K, n)
        Ax = torch.mm(self._A_fm, xt).view(M, K * d, n)
        mu = self._own_block(Ax, step).sub_(self._own_block(self._Ag_fm.expand(M, K * d, n), step)).view(K, d, n)
        gamma = torch.softmax(log_w, dim=0)
        f = (mu * gamma.unsqueeze(1)).sum(0).T  # (n, d)
        h2 = None
        if entropy:
            e = x - self.attractors[step]  # (n, d)
            ee = (e.unsqueeze(-1) * e.unsqueeze(-2)).reshape(n, d * d)
            Qg = self._Q_pairs[:, step]  # (d*d, n, P)
            q = Qg[0] * ee[:, :1]
            for a in range(1, d * d):  # d^2 broadcast multiply-adds: faster than a batched matmul of tiny blocks
                q = q + Qg[a] * ee[:, a : a + 1]
            lw = log_w.T  # (n, K)
            terms = lw[:, self._pair_i] + lw[:, self._pair_j] + self._const_pairs[step] - 0.5 * q
            h2 = -torch.logsumexp(terms, dim=-1)
        return f, h2
