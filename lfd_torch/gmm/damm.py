"""Directionality-aware mixture (DAMM-like; after Sun, Gao, Li & Figueroa, RA-L 2024), fitted by a parallel
uncollapsed Gibbs sampler with split/merge moves.

Model (N samples; positions y_i standardised, unit directions u_i = x_dot_i / ||x_dot_i||):

    z_i ~ Cat(pi),  pi ~ Dirichlet process (concentration ``alpha``),
    y_i | z_i = k ~ N(mu_k, Sigma_k),   (mu_k, Sigma_k) ~ NIW(0, kappa0, Psi0, nu0),
    u_i | z_i = k ~ vMF(m_k, ``kappa``),  m_k ~ uniform on the unit sphere.

Samples with zero velocity carry no direction and only enter the position term.

Sampler (one iteration, every step a batched tensor operation over all samples / components):
    1. parameters given labels: pi ~ Dir(n_1..n_K); (mu_k, Sigma_k) from their NIW posterior (Bartlett
       decomposition); m_k from its vMF posterior vMF(R_k / |R_k|, kappa |R_k|), R_k = sum of u_i in k,
       drawn with the tangent-space Gaussian approximation (exact as kappa |R_k| -> infinity; kappa |R_k| is
       in the hundreds for trajectory data).
    2. labels given parameters: ALL z_i at once by Gumbel-max on log pi_k + log N(y_i) + kappa m_k . u_i.
    3. split moves (every component in parallel): two deterministic proposals per component, halves across
       the principal axis of its positions and halves across the principal axis of its direction scatter;
       the better one is accepted with probability min(1, H), where H is the Hastings ratio of Chang &
       Fisher (NIPS 2013) for the DP mixture with the parameters integrated out,
       H_split = alpha Gamma(n_a) Gamma(n_b) / Gamma(n) * p(Y_a) p(Y_b) / p(Y),
       p(.) the NIW marginal of the positions times the vMF marginal of the directions.
       Because the proposals are deterministic, this is a stochastic search rather than an exact MH move.
    4. merge moves: all pairs scored with H_merge = 1 / H_split(pair); accepted greedily (best first, each
       component in at most one merge) with probability min(1, H_merge).
K therefore starts at 1 and is inferred. The labels with the highest collapsed log posterior (CRP prior +
marginal likelihoods) over the iterations are kept; clusters smaller than ``min_cluster_size`` are merged
into the nearest one and the GMM on positions is the maximum-likelihood fit of that partition.

All random numbers come from ``generator`` (Gamma variates by Marsaglia-Tsang from its normals/uniforms). The NIW
kernels (posterior, marginal, draws) and the Gaussian log-density are those of :mod:`lfd_torch.gmm.niw` and
:mod:`lfd_torch.gmm.gaussian`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from lfd_torch.gmm.gaussian import gaussian_log_density
from lfd_torch.errors import ShapeMismatchError
from lfd_torch.gmm.model import NOT_GIVEN, GMM, InvalidGMMError, _gmm_from_dense_labels, check_samples
from lfd_torch.gmm.niw import (
    NIWPrior,
    _niw_posterior_unchecked,
    _sample_gamma_unchecked,
    niw_log_marginal_likelihood,
    sample_niw,
)
from lfd_torch.gmm.postprocess import merge_small_components
from lfd_torch.utils import check_float, check_generator, check_int

__all__ = ["fit_damm", "damm_labels", "DAMMResult", "vmf_log_normalizer"]

MIN_SAMPLES_DAMM = 3

#: Bound on the sampler iterations (keeps the cost of a call finite).
MAX_ITERATIONS = 10_000


@dataclass(frozen=True)
class DAMMResult:
    """Outcome of the sampler.

    Attributes:
        labels: (N,) int64 final clusters 0..K-1 (after merging small clusters).
        log_posterior: (n_iter,) collapsed log posterior (up to a constant) after every iteration.
        n_components: (n_iter,) K after every iteration.
    """

    labels: Tensor
    log_posterior: Tensor
    n_components: Tensor


def vmf_log_normalizer(kappa: Tensor, d: int) -> Tensor:
    """log C_d(kappa) of the von Mises-Fisher density C_d(kappa) exp(kappa m . u) on the unit sphere in R^d.

    Closed forms for d = 2 (via the scaled Bessel function i0e) and d = 3; kappa = 0 gives the uniform
    density 1 / area(S^{d-1}).

    Args:
        kappa: (...,) concentrations >= 0.
        d: ambient dimension (2 or 3 exactly; otherwise scipy's ive on the CPU).
    """
    k = kappa
    if d == 1:
        raise InvalidGMMError("directions need d >= 2")
    if d == 2:
        return -math.log(2 * math.pi) - (torch.log(torch.special.i0e(k)) + k)
    if d == 3:
        small = k < 1e-8
        ks = torch.where(small, torch.ones_like(k), k)
        # log sinh(k) = k + log(1 - exp(-2k)) - log 2
        val = torch.log(ks) - math.log(4 * math.pi) - (ks + torch.log1p(-torch.exp(-2 * ks)) - math.log(2))
        return torch.where(small, torch.full_like(k, -math.log(4 * math.pi)), val)
    import numpy as np
    from scipy.special import gammaln, ive

    nu = d / 2 - 1
    kn = k.detach().cpu().numpy()
    with np.errstate(divide="ignore", invalid="ignore"):
        val = nu * np.log(kn) - d / 2 * math.log(2 * math.pi) - (np.log(ive(nu, kn)) + kn)
    area = math.log(2) + d / 2 * math.log(math.pi) - float(gammaln(d / 2))
    val = np.where(kn < 1e-8, -area, val)
    return torch.as_tensor(val, dtype=k.dtype, device=k.device)


class _Stats:
    """Sufficient statistics per group, from rows of the per-sample feature matrix
    [1, y (d), y y^T (d*d), has_dir, u (d), u u^T (d*d)]: counts n (G,), sums s (G, d), scatter Q (G, d, d),
    direction counts nd (G,), resultants R (G, d), direction scatter U (G, d, d)."""

    def __init__(self, table: Tensor, d: int):
        self.table = table
        G = table.shape[0]
        o = 0
        self.n = table[:, o]
        o += 1
        self.s = table[:, o : o + d]
        o += d
        self.Q = table[:, o : o + d * d].reshape(G, d, d)
        o += d * d
        self.nd = table[:, o]
        o += 1
        self.R = table[:, o : o + d]
        o += d
        self.U = table[:, o : o + d * d].reshape(G, d, d)

    @staticmethod
    def features(y: Tensor, u: Tensor, has_dir: Tensor) -> Tensor:
        N, d = y.shape
        return torch.cat(
            [
                torch.ones(N, 1, dtype=y.dtype, device=y.device), y, (y.unsqueeze(-1) * y.unsqueeze(-2)).reshape(N, -1),
                has_dir.to(y.dtype).unsqueeze(-1), u, (u.unsqueeze(-1) * u.unsqueeze(-2)).reshape(N, -1),
            ],
            dim=1,
        )  # fmt: skip

    @classmethod
    def of(cls, feats: Tensor, labels: Tensor, n_groups: int, d: int) -> _Stats:
        table = torch.zeros(n_groups, feats.shape[1], dtype=feats.dtype, device=feats.device)
        return cls(table.index_add_(0, labels, feats), d)


class _Model:
    """Hyperparameters and collapsed marginals."""

    def __init__(self, alpha: float, kappa: float, prior: NIWPrior):
        self.d, self.alpha, self.kappa, self.prior = prior.dim, alpha, kappa, prior
        self.log_c_kappa = float(vmf_log_normalizer(torch.tensor([kappa], dtype=torch.float64), self.d)[0])
        self.log_c_0 = float(vmf_log_normalizer(torch.tensor([0.0], dtype=torch.float64), self.d)[0])

    def log_marginal(self, st: _Stats) -> Tensor:
        """Positions (NIW) times directions (vMF with uniform prior on the mean) log marginal, (G,)."""
        pos = niw_log_marginal_likelihood(self.prior, st.n, st.s, st.Q)
        rn = torch.linalg.vector_norm(st.R, dim=-1)
        dirs = st.nd * self.log_c_kappa + self.log_c_0 - vmf_log_normalizer(self.kappa * rn, self.d)
        return pos + torch.where(st.nd > 0, dirs, torch.zeros_like(dirs))

    def log_posterior(self, st: _Stats) -> Tensor:
        """Collapsed log posterior (CRP partition prior + marginals) of a partition with all groups used."""
        K = st.n.shape[0]
        return K * math.log(self.alpha) + torch.lgamma(st.n).sum() + self.log_marginal(st).sum()


def _sample_parameters(
    model: _Model, st: _Stats, generator: torch.Generator
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(log pi (K,), mu (K, d), Sigma (K, d, d), m (K, d)) drawn given the labels."""
    K, d = st.s.shape
    f = dict(dtype=st.s.dtype, device=st.s.device)
    g = _sample_gamma_unchecked(st.n, generator)
    log_pi = torch.log(g.clamp_min(1e-300)) - torch.log(g.sum())
    mu, cov = sample_niw(_niw_posterior_unchecked(model.prior, st.n, st.s, st.Q), generator)
    # mean direction: tangent-space Gaussian approximation of vMF(R/|R|, kappa |R|)
    rn = torch.linalg.vector_norm(st.R, dim=-1, keepdim=True)
    mhat = torch.where(rn > 0, st.R / rn.clamp_min(1e-300), torch.zeros_like(st.R))
    xi = torch.randn(K, d, generator=generator, **f)
    xi = xi - (xi * mhat).sum(-1, keepdim=True) * mhat
    m = mhat + xi / torch.sqrt(model.kappa * rn.clamp_min(1e-300))
    m = torch.where(rn > 0, m / torch.linalg.vector_norm(m, dim=-1, keepdim=True).clamp_min(1e-300), m * 0)
    return log_pi, mu, cov, m


def _sample_labels(
    y: Tensor, u: Tensor, params: tuple[Tensor, Tensor, Tensor, Tensor], kappa: float, generator: torch.Generator
) -> Tensor:
    """All labels at once by Gumbel-max: (N,) int64."""
    log_pi, mu, cov, m = params
    logits = log_pi + gaussian_log_density(y, mu, cov) + kappa * (u @ m.T)
    gumbel = -torch.log(-torch.log(torch.rand(logits.shape, dtype=y.dtype, device=y.device, generator=generator)
                                   .clamp_min(1e-300)))
    return torch.argmax(logits + gumbel, dim=-1)


def _relabel(z: Tensor) -> tuple[Tensor, int]:
    _, dense = torch.unique(z, return_inverse=True)
    return dense, int(dense.max()) + 1


def _split_moves(
    model: _Model, feats: Tensor, y: Tensor, u: Tensor, z: Tensor, st: _Stats, generator: torch.Generator
) -> tuple[Tensor, int]:
    """Propose one split per component (two candidates each), accept in parallel. ``st``: stats of z."""
    K, d = st.s.shape
    n = st.n
    mean = st.s / n.clamp_min(1)[:, None]
    cov = st.Q / n.clamp_min(1)[:, None, None] - mean.unsqueeze(-1) * mean.unsqueeze(-2)
    rmean = st.R / st.nd.clamp_min(1)[:, None]
    dcov = st.U / st.nd.clamp_min(1)[:, None, None] - rmean.unsqueeze(-1) * rmean.unsqueeze(-2)
    axes = torch.linalg.eigh(torch.cat([cov, dcov]))[1][..., -1]  # principal axes (2K, d)
    side_pos = ((y - mean[z]) * axes[:K][z]).sum(-1) > 0
    side_dir = ((u - rmean[z]) * axes[K:][z]).sum(-1) > 0
    quad = _Stats.of(feats, 4 * z + 2 * side_pos.long() + side_dir.long(), 4 * K, d).table.reshape(K, 2, 2, -1)
    halves = torch.cat([quad.sum(2), quad.sum(1)])  # (2K, 2, p): position split, then direction split
    sub = _Stats(halves.reshape(4 * K, -1), d)
    ml = model.log_marginal(sub).reshape(2 * K, 2)
    na, nb = sub.n.reshape(2 * K, 2).unbind(-1)
    ml_parent = model.log_marginal(st).repeat(2)
    n2 = n.repeat(2)
    h = (math.log(model.alpha) + torch.lgamma(na.clamp_min(1)) + torch.lgamma(nb.clamp_min(1))
         - torch.lgamma(n2.clamp_min(1)) + ml[:, 0] + ml[:, 1] - ml_parent)
    h = torch.where((na > 0) & (nb > 0), h, torch.full_like(h, -math.inf))
    use_dir = h[K:] > h[:K]
    best = torch.where(use_dir, h[K:], h[:K])
    accept = torch.log(torch.rand(K, dtype=y.dtype, device=y.device, generator=generator)) < best
    if not bool(accept.any()):
        return z, K
    side = torch.where(use_dir[z], side_dir, side_pos)
    new_id = K + torch.cumsum(accept.long(), 0) - 1
    z = torch.where(accept[z] & side, new_id[z], z)
    return _relabel(z)


def _merge_moves(
    model: _Model, z: Tensor, st: _Stats, generator: torch.Generator
) -> tuple[Tensor, int]:
    """Score every pair for a merge; accept greedily, best first, each component at most once."""
    K = st.n.shape[0]
    if K < 2:
        return z, K
    ml = model.log_marginal(st)
    ia, ib = torch.triu_indices(K, K, offset=1, device=z.device)
    merged = _Stats(st.table[ia] + st.table[ib], st.s.shape[1])
    log_h = (-math.log(model.alpha) + torch.lgamma(merged.n) - torch.lgamma(st.n[ia]) - torch.lgamma(st.n[ib])
             + model.log_marginal(merged) - ml[ia] - ml[ib])
    log_u = torch.log(torch.rand(log_h.shape, dtype=log_h.dtype, device=z.device, generator=generator))
    ok = log_u < log_h
    if not bool(ok.any()):
        return z, K
    order = torch.argsort(log_h, descending=True)
    target = torch.arange(K, device=z.device)
    taken: set[int] = set()
    pairs = torch.stack([ia, ib], -1)[order[ok[order]]].tolist()
    for a, b in pairs:
        if a in taken or b in taken:
            continue
        taken.update((a, b))
        target[b] = a
    return _relabel(target[z])


def check_damm_hyperparameters(
    *, alpha: float, kappa: float, kappa0: float, nu0_offset: float, psi_scale: float, n_iter: int,
    min_cluster_size: int | None, reg_covar: object = NOT_GIVEN,
) -> None:  # fmt: skip
    """The checks of :func:`damm_labels` / :func:`fit_damm` on their hyperparameters (also run by
    :class:`~lfd_torch.gmm.DAMMFitter` at construction); ``reg_covar`` is checked when given.

    Raises:
        InvalidGMMError: naming the first hyperparameter of the wrong type or out of range.
    """
    if reg_covar is not NOT_GIVEN:
        check_float(reg_covar, "reg_covar", low=0.0, error=InvalidGMMError)
    for name, v in (("alpha", alpha), ("kappa", kappa), ("kappa0", kappa0), ("nu0_offset", nu0_offset),
                    ("psi_scale", psi_scale)):
        check_float(v, name, low=0.0, low_open=True, error=InvalidGMMError)
    check_int(n_iter, "n_iter", low=1, high=MAX_ITERATIONS, error=InvalidGMMError)
    check_int(min_cluster_size, "min_cluster_size", low=1, allow_none=True, error=InvalidGMMError)


def damm_labels(
    x: Tensor,
    x_dot: Tensor,
    *,
    generator: torch.Generator,
    alpha: float = 1.0,
    kappa: float = 5.0,
    kappa0: float = 1.0,
    nu0_offset: float = 10.0,
    psi_scale: float = 1.0,
    n_iter: int = 20,
    min_cluster_size: int | None = None,
) -> DAMMResult:
    """Cluster labels of the DAMM-like sampler (see the module docstring).

    Args:
        x: (N, d) positions (data units), d >= 2.
        x_dot: (N, d) velocities.
        generator: torch generator on x's device.
        alpha: DP concentration (> 0).
        kappa: vMF concentration of the directions within a component (> 0; larger splits more by direction).
        kappa0, nu0_offset, psi_scale: NIW prior on standardised positions (as in :mod:`~lfd_torch.gmm.pcgmm`).
        n_iter: sampler iterations in [1, 10000] (each: parameters, labels, splits, merges; O(N K d^2)).
        min_cluster_size: clusters smaller than this are merged into the nearest one (None: max(3, 1 % of N)).

    Returns:
        :class:`DAMMResult`.
    """
    if x_dot is None:
        raise ShapeMismatchError("x_dot (N, d) velocities are required, got None")
    check_samples(x, x_dot, min_samples=MIN_SAMPLES_DAMM)
    check_generator(generator, where="DAMM")
    check_damm_hyperparameters(alpha=alpha, kappa=kappa, kappa0=kappa0, nu0_offset=nu0_offset, psi_scale=psi_scale,
                               n_iter=n_iter, min_cluster_size=min_cluster_size)  # fmt: skip
    N, d = x.shape
    if d < 2:
        raise InvalidGMMError("DAMM needs d >= 2 (directions live on the unit sphere)")
    xx = x.detach().to(torch.float64)
    vv = x_dot.detach().to(torch.float64)
    scale = float(xx.std(0, unbiased=False).pow(2).mean().sqrt())
    y = (xx - xx.mean(0)) / (scale if scale > 0 else 1.0)
    speed = torch.linalg.vector_norm(vv, dim=-1, keepdim=True)
    has_dir = speed.squeeze(-1) > 0
    u = torch.where(speed > 0, vv / speed.clamp_min(1e-300), torch.zeros_like(vv))
    nu0 = d + float(nu0_offset)
    f64 = dict(dtype=torch.float64, device=x.device)
    prior = NIWPrior(
        mean=torch.zeros(d, **f64), kappa=torch.tensor(float(kappa0), **f64), dof=torch.tensor(nu0, **f64),
        scale=torch.eye(d, **f64) * max(nu0 - d - 1.0, 1e-3) * float(psi_scale) ** 2,
    )  # fmt: skip
    model = _Model(float(alpha), float(kappa), prior)
    feats = _Stats.features(y, u, has_dir)
    z = torch.zeros(N, dtype=torch.long, device=x.device)
    K = 1
    st = _Stats.of(feats, z, K, d)
    lp_hist, k_hist = [], []
    best_lp, best_z = -math.inf, z
    for _ in range(int(n_iter)):
        z, K = _split_moves(model, feats, y, u, z, st, generator)
        st = _Stats.of(feats, z, K, d)
        z2, K2 = _merge_moves(model, z, st, generator)
        if K2 != K:
            z, K = z2, K2
            st = _Stats.of(feats, z, K, d)
        params = _sample_parameters(model, st, generator)
        z, K = _relabel(_sample_labels(y, u, params, model.kappa, generator))
        st = _Stats.of(feats, z, K, d)
        lp = float(model.log_posterior(st))
        lp_hist.append(lp)
        k_hist.append(K)
        if lp > best_lp:
            best_lp, best_z = lp, z
    min_size = max(3, math.ceil(0.01 * N)) if min_cluster_size is None else int(min_cluster_size)
    labels = merge_small_components(xx, best_z, max(1, min_size))
    return DAMMResult(
        labels=labels,
        log_posterior=torch.tensor(lp_hist, dtype=torch.float64),
        n_components=torch.tensor(k_hist),
    )


def fit_damm(
    x: Tensor,
    x_dot: Tensor,
    *,
    generator: torch.Generator,
    alpha: float = 1.0,
    kappa: float = 5.0,
    kappa0: float = 1.0,
    nu0_offset: float = 10.0,
    psi_scale: float = 1.0,
    n_iter: int = 20,
    min_cluster_size: int | None = None,
    reg_covar: float = 1e-3,
) -> GMM:
    """Fit the DAMM-like mixture and return its GMM on positions; K is inferred.

    Args:
        x: (N, d) positions (data units), N >= 3, d >= 2.
        x_dot: (N, d) velocities.
        generator: torch generator on x's device.
        alpha, kappa, kappa0, nu0_offset, psi_scale, n_iter, min_cluster_size: see :func:`damm_labels`.
        reg_covar: relative diagonal loading of the final covariances (times the mean data variance).

    Returns:
        :class:`GMM` with x's dtype and device.

    Raises:
        ShapeMismatchError, NonFiniteError, TooFewSamplesError: malformed input.
        InvalidGMMError: invalid hyperparameters or d < 2.
    """
    check_float(reg_covar, "reg_covar", low=0.0, error=InvalidGMMError)
    res = damm_labels(
        x, x_dot, generator=generator, alpha=alpha, kappa=kappa, kappa0=kappa0, nu0_offset=nu0_offset,
        psi_scale=psi_scale, n_iter=n_iter, min_cluster_size=min_cluster_size,
    )  # fmt: skip
    return _gmm_from_dense_labels(x, res.labels.to(x.device), reg_covar)
