"""Expectation-maximisation for a Gaussian mixture with a fixed number of components, and BIC model selection.

Notation: N samples x (N, d); K components; responsibilities R (N, K).

Regularisation: every M-step sets ``Sigma_k = (S_k + rho I) / n_k`` with S_k the responsibility-weighted
scatter, n_k = sum_n R_nk and ``rho = reg_covar * mean_i Var(x_i)`` (scale-free). This is the exact maximiser
of the *penalised* log-likelihood

    F(theta) = sum_n log sum_k pi_k N(x_n; mu_k, Sigma_k) - (rho / 2) sum_k tr(Sigma_k^-1),

so the EM iterates never decrease F (the quantity recorded in the history, per sample); with the default
``reg_covar = 1e-6`` F differs from the log-likelihood by a negligible amount.

Initialisation: k-means++ seeding (D^2 sampling, Arthur & Vassilvitskii 2007) with the given generator, then
at most ``kmeans_iter`` Lloyd iterations; the best of ``n_init`` restarts (highest final F) is returned.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
from torch import Tensor

from lfd_torch.errors import TooFewSamplesError
from lfd_torch.gmm.model import GMM, check_samples

__all__ = ["fit_em", "fit_em_bic", "refine_em", "kmeans_plus_plus", "bic", "n_parameters"]


def _data_scale(x: Tensor) -> Tensor:
    v = x.var(dim=0, unbiased=False).mean() if x.shape[0] > 1 else x.new_tensor(0.0)
    return v if float(v) > 0 else x.new_tensor(1.0)


def kmeans_plus_plus(x: Tensor, n_components: int, *, generator: torch.Generator, n_iter: int = 10) -> Tensor:
    """k-means++ seeding followed by up to ``n_iter`` Lloyd iterations.

    Args:
        x: (N, d) samples, N >= n_components.
        n_components: K.
        generator: torch generator on x's device.
        n_iter: Lloyd iterations after seeding (0 keeps the seeds).

    Returns:
        (N,) int64 hard labels in 0..K-1 (every label used).
    """
    N = x.shape[0]
    first = int(torch.randint(N, (1,), generator=generator, device=x.device))
    centers = x[first : first + 1]
    d2 = ((x - centers) ** 2).sum(-1)
    for _ in range(1, n_components):
        total = d2.sum()
        if float(total) > 0:
            idx = torch.multinomial(d2 / total, 1, generator=generator)
        else:  # all remaining points coincide with a centre: pick uniformly
            idx = torch.randint(N, (1,), generator=generator, device=x.device)
        centers = torch.cat([centers, x[idx]])
        d2 = torch.minimum(d2, ((x - x[idx]) ** 2).sum(-1))
    labels = torch.cdist(x, centers).argmin(-1)
    for _ in range(n_iter):
        K = centers.shape[0]
        counts = torch.bincount(labels, minlength=K)
        sums = torch.zeros_like(centers).index_add_(0, labels, x)
        # an emptied centre keeps its position
        new = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None].to(x.dtype), centers)
        new_labels = torch.cdist(x, new).argmin(-1)
        centers = new
        if torch.equal(new_labels, labels):
            break
        labels = new_labels
    # every centre keeps at least its nearest sample, so all K labels are used
    nearest = torch.cdist(centers, x).argmin(-1)
    labels = labels.clone()
    labels[nearest] = torch.arange(centers.shape[0], device=x.device)
    return labels


def _m_step(x: Tensor, resp: Tensor, rho: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    N, d = x.shape
    eps = 10 * torch.finfo(x.dtype).eps
    nk = resp.sum(0) + eps  # (K,)
    weights = nk / nk.sum()
    means = (resp.T @ x) / nk[:, None]
    diff = x.unsqueeze(1) - means  # (N, K, d)
    scatter = torch.einsum("nk,nki,nkj->kij", resp, diff, diff)
    eye = torch.eye(d, dtype=x.dtype, device=x.device)
    cov = (scatter + rho * eye) / nk[:, None, None]
    return weights, means, 0.5 * (cov + cov.transpose(-2, -1))


def _objective(gmm: GMM, x: Tensor, rho: Tensor) -> tuple[Tensor, Tensor]:
    """(penalised log-likelihood per sample, responsibilities (N, K))."""
    lp = gmm.log_prob_components(x)
    ll = torch.logsumexp(lp, -1)
    penalty = 0.5 * rho * torch.diagonal(gmm.precisions, dim1=-2, dim2=-1).sum()
    return (ll.sum() - penalty) / x.shape[0], torch.softmax(lp, -1)


def refine_em(
    x: Tensor, init: GMM, *, max_iter: int = 100, tol: float = 1e-6, reg_covar: float = 1e-6
) -> tuple[GMM, Tensor]:
    """Run EM from an initial mixture.

    Args:
        x: (N, d) samples.
        init: starting mixture (same dtype/device as x).
        max_iter: maximum number of EM iterations.
        tol: stop when the per-sample penalised log-likelihood improves by less than ``tol``.
        reg_covar: relative covariance regularisation (module docstring).

    Returns:
        (gmm, history): the final mixture and the (n_iter + 1,) per-sample penalised log-likelihood F/N
        of every iterate, starting with ``init`` (non-decreasing up to rounding).
    """
    check_samples(x, min_samples=1)
    rho = reg_covar * _data_scale(x)
    gmm = init
    f, resp = _objective(gmm, x, rho)
    history = [f]
    for _ in range(max_iter):
        gmm = GMM(*_m_step(x, resp, rho))
        f_new, resp = _objective(gmm, x, rho)
        history.append(f_new)
        if float(f_new - f) < tol:
            break
        f = f_new
    return gmm, torch.stack(history)


def _check_em_args(x: Tensor, n_components: int) -> None:
    check_samples(x, min_samples=1)
    if int(n_components) < 1:
        raise TooFewSamplesError(f"n_components must be >= 1, got {n_components}")
    if x.shape[0] < n_components:
        raise TooFewSamplesError(f"{x.shape[0]} samples cannot support {n_components} components")


def fit_em(
    x: Tensor,
    n_components: int,
    *,
    generator: torch.Generator,
    n_init: int = 1,
    max_iter: int = 100,
    tol: float = 1e-6,
    reg_covar: float = 1e-6,
    kmeans_iter: int = 10,
) -> GMM:
    """Maximum (penalised) likelihood GMM with K = ``n_components`` by EM from k-means++ starts.

    Args:
        x: (N, d) samples, N >= n_components.
        n_components: K >= 1.
        generator: torch generator on x's device (the only source of randomness).
        n_init: number of k-means++ restarts; the one with the highest final objective is kept.
        max_iter: EM iterations per restart.
        tol: convergence threshold on the per-sample objective.
        reg_covar: relative covariance regularisation (module docstring).
        kmeans_iter: Lloyd iterations after k-means++ seeding.

    Returns:
        The fitted :class:`GMM`, same dtype and device as ``x``.

    Raises:
        ShapeMismatchError, NonFiniteError: malformed ``x``.
        TooFewSamplesError: fewer samples than components, or n_components < 1.
    """
    _check_em_args(x, n_components)
    rho = reg_covar * _data_scale(x)
    best: tuple[float, GMM] | None = None
    for _ in range(max(1, int(n_init))):
        labels = kmeans_plus_plus(x, int(n_components), generator=generator, n_iter=kmeans_iter)
        resp = torch.nn.functional.one_hot(labels, int(n_components)).to(x.dtype)
        init = GMM(*_m_step(x, resp, rho))
        gmm, hist = refine_em(x, init, max_iter=max_iter, tol=tol, reg_covar=reg_covar)
        score = float(hist[-1])
        if best is None or score > best[0]:
            best = (score, gmm)
    assert best is not None
    return best[1]


def n_parameters(n_components: int, dim: int) -> int:
    """Free parameters of a full-covariance GMM: (K - 1) + K d + K d (d + 1) / 2."""
    return (n_components - 1) + n_components * dim + n_components * dim * (dim + 1) // 2


def bic(gmm: GMM, x: Tensor) -> float:
    """Bayesian information criterion -2 log L + p log N (lower is better).

    Args:
        gmm: fitted mixture.
        x: (N, d) samples it was fitted to.
    """
    ll = float(gmm.log_prob(x).sum())
    return -2.0 * ll + n_parameters(gmm.n_components, gmm.dim) * math.log(x.shape[0])


def fit_em_bic(
    x: Tensor,
    *,
    k_range: Iterable[int] = range(1, 11),
    generator: torch.Generator,
    n_init: int = 1,
    max_iter: int = 100,
    tol: float = 1e-6,
    reg_covar: float = 1e-6,
    kmeans_iter: int = 10,
) -> GMM:
    """EM for every K in ``k_range`` (K <= N), keeping the fit with the lowest :func:`bic`.

    Args:
        x: (N, d) samples.
        k_range: candidate numbers of components (values above N are skipped).
        generator: torch generator; the candidates are fitted in ascending K with it.
        n_init, max_iter, tol, reg_covar, kmeans_iter: as in :func:`fit_em`.

    Returns:
        The BIC-optimal :class:`GMM`.

    Raises:
        TooFewSamplesError: no admissible K in ``k_range``.
    """
    check_samples(x, min_samples=1)
    ks = sorted({int(k) for k in k_range if 1 <= int(k) <= x.shape[0]})
    if not ks:
        raise TooFewSamplesError(f"no admissible K in k_range for {x.shape[0]} samples")
    best: tuple[float, GMM] | None = None
    for k in ks:
        gmm = fit_em(
            x, k, generator=generator, n_init=n_init, max_iter=max_iter, tol=tol, reg_covar=reg_covar,
            kmeans_iter=kmeans_iter,
        )
        score = bic(gmm, x)
        if best is None or score < best[0]:
            best = (score, gmm)
    assert best is not None
    return best[1]
