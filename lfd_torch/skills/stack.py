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

Two evaluations. :meth:`PrimitiveStack.evaluate` (a single control tick, small batches) evaluates every step for
every row and keeps each row's own block. :meth:`PrimitiveStack.evaluate_sorted` (large batches) takes rows sorted by
step and evaluates each step only on its own rows, with exact K_m (no padding), H2 only where asked: since log w_k
and every pair term log w_i + log w_j + log N(mu_i; mu_j, S_i + S_j) are quadratic functions of e = x - g_m, each
step costs one (K_m, F) and one (K_m (K_m + 1) / 2, F) product with the features phi(e) = [e_a e_b, e, 1]. Both
agree to rounding (the expanded quadratic loses about eps |mu_k - g_m|^2 / sigma_k^2 in log w, ~1e-12 relative in f
for LASA-sized data; tested).

Shapes: B rows, M steps, K padded components, d dimension.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from lfd_torch.gmm import GaussianBank
from lfd_torch.gmm.gaussian import LOG_2PI, gaussian_quadratic_weights, quadratic_features, quadratic_weights
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
        # per-step tables of the rows-sorted-by-step evaluation (exact K_m, no padding), in e = x - g_m
        self._groups: list[tuple[Tensor, Tensor, Tensor]] = []
        for m, p in enumerate(primitives):
            k = p.n_components
            lw = gaussian_quadratic_weights(self.means[m, :k], self.covariances[m, :k], self.attractors[m])
            lw[:, -1] += self.log_pi[m, :k]  # (k, F): log pi_k + log N(g_m + e; mu_k, Sigma_k)
            i, j = torch.triu_indices(k, k, device=device)
            zero = torch.zeros((i.numel(), d), **f)
            const = self._overlap_const.view(M, K, K)[m, i, j] + torch.where(i == j, 0.0, math.log(2.0)).to(**f)
            pair = lw[i] + lw[j] + quadratic_weights(-0.5 * Q[m, i, j], zero, const)  # (P_m, F): one term of H2
            self._groups.append((lw, self.A[m, :k].reshape(k * d, d).contiguous(), pair))
        # single-state tables (one step, padded K: one shape for every step), see :meth:`single_tables`
        aff = self._bank._affine.view(M, K, d, d + 1).transpose(1, 2)  # rows (a, k): whitening row a of Gaussian k
        W, b = aff[..., :d].reshape(M, d * K, d), aff[..., d].reshape(M, d * K)
        pad = torch.finfo(dtype).min / 8  # a finite -inf: exp gives 0 all the same, and 0 * pad = 0 in products
        c = torch.where(self.log_pi > -math.inf, self._bank._log_norm.view(M, K) + self.log_pi, pad)
        A = self._A_fm.view(M, K * d, d)
        Qh = -0.5 * self._Q_pairs.permute(1, 2, 0)  # (M, P, d*d)
        S = torch.zeros((I.numel(), K), **f)  # row p adds log w_i + log w_j of pair p
        S.index_put_((torch.arange(I.numel(), device=device), I), torch.ones(I.numel(), **f), accumulate=True)
        S.index_put_((torch.arange(I.numel(), device=device), J), torch.ones(I.numel(), **f), accumulate=True)
        self._single = [(W[m].contiguous(), b[m].contiguous(), c[m].contiguous(), A[m].contiguous(),
                         Qh[m].contiguous(), self._const_pairs[m].contiguous(), S) for m in range(M)]  # fmt: skip

    def single_tables(self, step: int) -> tuple[Tensor, ...]:
        """Tables of step m for one state (the single-state tick, :meth:`SkillEngine.tick_velocity`), padded to K:
        W (d K, d) and b (d K,), whose rows give the whitened offsets sqrt(1/2) L_k^-1 (x - mu_k) (rows (a, k));
        c (K,) log pi_k + the log normaliser (padding: finfo.min / 8, finite so that the pair product below stays
        free of 0 * inf); A (K d, d) the stacked A_k; -Q_ij / 2 (P, d*d) and the constants (P,) of the pairs
        i <= j of :meth:`evaluate`; S (P, K), S log w = log w_i + log w_j of every pair.

        With them log w = c - ||W x + b||^2 (summed over a), f = softmax(log w) . A_k e and
        H2 = -logsumexp(const - e^T Q_ij e / 2 + S log w), e = x - g_m: the formulas of :meth:`evaluate`.
        """
        return self._single[step]

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

    def evaluate_sorted(self, e: Tensor, groups: list[tuple[int, int, int, int]]) -> tuple[Tensor, Tensor]:
        """f_m and H2_m of rows sorted by step, one matrix product per step present (the large-batch path).

        Every log w_k and every pair term of H2 is a quadratic function of e = x - g_m, hence one row of a
        (rows, F) x (F, n) product with the quadratic features phi(e)
        (:func:`lfd_torch.gmm.gaussian.quadratic_features`):

            log w(e) = W_m phi(e),   H2(e) = -logsumexp_{i <= j} (V_m phi(e)),   f = sum_k softmax(log w)_k A_k e,

        with W_m, V_m built at construction (V_m folds log w_i + log w_j, the overlap constant, log 2 for i < j and
        -0.5 e^T Q_ij e of each pair). Equal to :meth:`evaluate` up to rounding (a test checks it).

        Args:
            e: (d, n) feature-major offsets x - g_m of the rows, sorted so that each step's rows are contiguous.
            groups: (m, lo, mid, hi): rows lo:hi are in step m; rows mid:hi also need H2.

        Returns:
            f (d, n) (0 on rows in no group) and H2 (n,) (-inf where not evaluated).
        """
        d, n = e.shape
        phi = quadratic_features(e)  # (F, n)
        f = torch.zeros_like(e)
        h2 = torch.full((n,), -math.inf, dtype=e.dtype, device=e.device)
        for m, lo, mid, hi in groups:
            lw_w, A, pair = self._groups[m]
            k = lw_w.shape[0]
            w = _exp_shifted(torch.mm(lw_w, phi[:, lo:hi]))[0]  # (k, n_m) softmax numerators
            mu = torch.mm(A, e[:, lo:hi]).view(k, d, hi - lo)  # A_k e
            f[:, lo:hi] = (mu * w.unsqueeze(1)).sum(0).div_(w.sum(0))
            if hi > mid:
                t, top = _exp_shifted(torch.mm(pair, phi[:, mid:hi]))
                h2[mid:hi] = t.sum(0).log_().add_(top).neg_()  # -logsumexp over the pairs
        return f, h2


def _exp_shifted(v: Tensor) -> tuple[Tensor, Tensor]:
    """exp(v - max_0 v) in place over the leading axis of a (k, n) tensor, and the (n,) maxima.

    The shifted exponents are clamped at -700 first: exp there is < 1e-304, which cannot change a sum that
    contains exp(0) = 1 (the float64 ulp of 1 is 2.2e-16), while exp of arguments below about -708 (subnormal or
    zero results) runs on a slow path about 20x slower. Done by hand over the leading axis because
    torch.softmax / logsumexp(dim=0) use strided kernels there.
    """
    top = v.amax(0)
    floor = -700.0 if v.dtype == torch.float64 else -80.0  # float32: exp(-80) ~ 1.8e-35 < ulp(1) = 1.2e-7
    return v.sub_(top).clamp_min_(floor).exp_(), top
