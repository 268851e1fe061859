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

Model selection. :func:`bic` is -2 log L + p log N, which assumes N independent samples. Samples along a
demonstration are strongly autocorrelated (a smooth curve sampled every 20 ms), so the data carry far less
information than N suggests and the plain BIC over-fits K (e.g. K = 9-10 on the 500 samples of one LASA
demonstration). With ``n_effective`` the *effective-sample-size BIC* is used instead,

    BIC_eff = -2 (N_eff / N) log L + p log N_eff,

i.e. the BIC of N_eff independent samples with the same per-sample log-likelihood. :func:`effective_sample_size`
estimates N_eff = sum over sequences of T_s / tau_s, with tau_s the integrated autocorrelation time of sequence
s (Sokal's automatic window, c = 5), taken as the largest over the coordinates (the smallest per-coordinate
effective size, a conservative choice). The plain BIC stays the default (``n_effective=None``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.gmm.model import NOT_GIVEN, GMM, check_samples
from lfd_torch.utils import check_float, check_generator, check_int

__all__ = [
    "fit_em",
    "fit_em_bic",
    "refine_em",
    "kmeans_plus_plus",
    "bic",
    "n_parameters",
    "integrated_autocorrelation_time",
    "effective_sample_size",
]


def _data_scale(x: Tensor) -> Tensor:
    v = x.var(dim=0, unbiased=False).mean() if x.shape[0] > 1 else x.new_tensor(0.0)
    return v if float(v) > 0 else x.new_tensor(1.0)


def _nearest(x: Tensor, centers: Tensor) -> Tensor:
    """(N,) index of the nearest of ``centers`` (K, d) to each of ``x`` (N, d), from the differences themselves: the
    expansion ||a||^2 + ||b||^2 - 2 a.b that ``torch.cdist`` uses for large inputs cancels in float32 when the data
    lie far from the origin relative to their spread (about 1e4 spreads away)."""
    return torch.cdist(x, centers, compute_mode="donot_use_mm_for_euclid_dist").argmin(-1)


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
    check_samples(x, min_samples=1)
    check_int(n_components, "n_components", low=1, high=x.shape[0])
    check_int(n_iter, "n_iter", low=0, high=MAX_ITER)
    check_generator(generator, where="k-means++")
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
    labels = _nearest(x, centers)
    for _ in range(n_iter):
        K = centers.shape[0]
        counts = torch.bincount(labels, minlength=K)
        sums = torch.zeros_like(centers).index_add_(0, labels, x)
        # an emptied centre keeps its position
        new = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None].to(x.dtype), centers)
        new_labels = _nearest(x, new)
        centers = new
        if torch.equal(new_labels, labels):
            break
        labels = new_labels
    # every centre keeps at least its nearest sample, so all K labels are used
    nearest = _nearest(centers, x)
    if nearest.unique().numel() < centers.shape[0]:  # coincident centres (fewer distinct points than K) share a
        taken: list[int] = []  # nearest sample: each centre in turn takes its nearest sample not yet taken
        for c in centers:
            taken.append(next(i for i in torch.argsort(((x - c) ** 2).sum(-1), stable=True).tolist()
                              if i not in taken))
        nearest = torch.tensor(taken, device=x.device)
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
        max_iter: maximum number of EM iterations, in [0, 100000].
        tol: stop when the per-sample penalised log-likelihood improves by less than ``tol``.
        reg_covar: relative covariance regularisation (module docstring).

    Returns:
        (gmm, history): the final mixture and the (n_iter + 1,) per-sample penalised log-likelihood F/N
        of every iterate, starting with ``init`` (non-decreasing up to rounding).
    """
    check_samples(x, min_samples=1)
    if not isinstance(init, GMM):
        raise InvalidArgumentError(f"init must be a GMM, got {type(init).__name__}")
    check_int(max_iter, "max_iter", low=0, high=MAX_ITER)
    check_float(tol, "tol", low=0.0)
    check_float(reg_covar, "reg_covar", low=0.0)
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


#: Bounds that keep the cost of an EM call finite (iterations, restarts, candidate K).
MAX_ITER = 100_000
MAX_RESTARTS = 1_000
MAX_K_CANDIDATES = 1_000


def _check_em_args(
    x: Tensor, n_components: int, *, n_init: int = 1, max_iter: int = 1, tol: float = 0.0, reg_covar: float = 0.0,
    kmeans_iter: int = 1, generator: object = None,
) -> None:  # fmt: skip
    check_samples(x, min_samples=1)
    check_em_hyperparameters(n_components=n_components, n_init=n_init, max_iter=max_iter, tol=tol,
                             reg_covar=reg_covar, kmeans_iter=kmeans_iter)  # fmt: skip
    if x.shape[0] < n_components:
        raise TooFewSamplesError(f"x has {x.shape[0]} samples, they cannot support n_components = {n_components}")
    check_generator(generator, where="EM")


def check_em_hyperparameters(
    *, n_components: object = NOT_GIVEN, k_range: object = NOT_GIVEN, n_init: object, max_iter: object,
    tol: object, reg_covar: object, kmeans_iter: object, n_effective: object = NOT_GIVEN,
) -> None:  # fmt: skip
    """The checks of :func:`fit_em` / :func:`fit_em_bic` on their hyperparameters, without the data (also run by
    :class:`~lfd_torch.gmm.EMFitter` and :class:`~lfd_torch.gmm.EMBICFitter` at construction); the optional ones
    are checked when given.

    Raises:
        TooFewSamplesError: ``n_components`` not an integer >= 1. InvalidArgumentError: another hyperparameter of
            the wrong type or out of range (naming it).
    """
    if n_components is not NOT_GIVEN:
        check_int(n_components, "n_components", low=1, error=TooFewSamplesError)
    if k_range is not NOT_GIVEN:
        _k_candidates(k_range)
    check_int(n_init, "n_init", low=1, high=MAX_RESTARTS)
    check_int(max_iter, "max_iter", low=0, high=MAX_ITER)
    check_int(kmeans_iter, "kmeans_iter", low=0, high=MAX_ITER)
    check_float(tol, "tol", low=0.0)
    check_float(reg_covar, "reg_covar", low=0.0)
    if n_effective is not NOT_GIVEN:
        check_float(n_effective, "n_effective", low=0.0, low_open=True, allow_none=True)


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
        n_components: K >= 1 (cost O(n_init max_iter N K d^2)).
        generator: torch generator on x's device (the only source of randomness).
        n_init: number of k-means++ restarts in [1, 1000]; the one with the highest final objective is kept.
        max_iter: EM iterations per restart, in [0, 100000] (0: the k-means++ / Lloyd initialisation).
        tol: convergence threshold on the per-sample objective.
        reg_covar: relative covariance regularisation (module docstring).
        kmeans_iter: Lloyd iterations after k-means++ seeding.

    Returns:
        The fitted :class:`GMM`, same dtype and device as ``x``.

    Raises:
        ShapeMismatchError, NonFiniteError: malformed ``x``.
        TooFewSamplesError: fewer samples than components.
        InvalidArgumentError: a hyperparameter of the wrong type or out of range, or no generator.

    Precision: the Lloyd step's distances are taken from the differences, so float32 data far from the origin keep
    their clusters (``tests/test_gmm.py::test_kmeans_keeps_clusters_far_from_the_origin_in_float32``).
    """
    _check_em_args(x, n_components, n_init=n_init, max_iter=max_iter, tol=tol, reg_covar=reg_covar,
                   kmeans_iter=kmeans_iter, generator=generator)  # fmt: skip
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
    """Free parameters of a full-covariance GMM: (K - 1) + K d + K d (d + 1) / 2.

    Raises:
        InvalidArgumentError: ``n_components`` or ``dim`` is not an integer >= 1.
    """
    n_components = check_int(n_components, "n_components", low=1)
    dim = check_int(dim, "dim", low=1)
    return (n_components - 1) + n_components * dim + n_components * dim * (dim + 1) // 2


def integrated_autocorrelation_time(y: Tensor, *, window_factor: float = 5.0) -> Tensor:
    """Integrated autocorrelation time tau = 1 + 2 sum_{t >= 1} rho(t) of each column of a time series.

    The autocorrelation rho is estimated by FFT (biased estimator, mean removed) and summed up to Sokal's
    automatic window, the smallest M with M >= ``window_factor`` tau(M) (Sokal 1997; the rule of emcee).

    Args:
        y: (T, d) samples in time order (or (T,)).
        window_factor: c of the window rule (> 0).

    Returns:
        (d,) tau per column, in [1, T] (1 for a constant column or T = 1).
    """
    if not window_factor > 0:
        raise InvalidArgumentError(f"window_factor must be positive, got {window_factor}")
    y = y.reshape(y.shape[0], -1)
    T = y.shape[0]
    if T < 2:
        return torch.ones(y.shape[1], dtype=y.dtype, device=y.device)
    z = y - y.mean(0)
    f = torch.fft.rfft(z, n=2 * T, dim=0)
    acov = torch.fft.irfft(f * f.conj(), n=2 * T, dim=0)[:T]  # (T, d)
    var = acov[0]
    constant = var <= 0
    rho = acov / torch.where(constant, torch.ones_like(var), var)
    taus = 2.0 * torch.cumsum(rho, 0) - 1.0  # tau(M) = 1 + 2 sum_{t=1..M} rho(t)
    lags = torch.arange(T, dtype=y.dtype, device=y.device)[:, None]
    ok = lags >= window_factor * taus
    ok[-1] = True  # no window found: use all lags
    window = ok.to(torch.int8).argmax(0)
    tau = taus.gather(0, window[None]).squeeze(0)
    return torch.where(constant, torch.ones_like(tau), tau.clamp(1.0, float(T)))


def effective_sample_size(x: Tensor, groups: Tensor | None = None, *, window_factor: float = 5.0) -> float:
    """Effective number of independent samples of time series, N_eff = sum_s T_s / max_i tau_{s,i}.

    Args:
        x: (N, d) samples; within each group in time order.
        groups: optional (N,) int sequence index of every sample (e.g. the demonstration); None: one sequence.
        window_factor: see :func:`integrated_autocorrelation_time`.

    Returns:
        N_eff in [number of sequences, N].

    Raises:
        ShapeMismatchError, NonFiniteError, TooFewSamplesError: malformed ``x`` or ``groups``.
        InvalidArgumentError: ``window_factor`` <= 0.
    """
    check_samples(x, min_samples=1)
    if groups is None:
        groups = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
    if groups.shape != (x.shape[0],):
        raise ShapeMismatchError(f"groups must have shape ({x.shape[0]},), got {tuple(groups.shape)}")
    total = 0.0
    for gid in torch.unique(groups):
        seq = x[groups == gid]
        tau = integrated_autocorrelation_time(seq, window_factor=window_factor)
        total += seq.shape[0] / float(tau.max())
    return total


def bic(gmm: GMM, x: Tensor, *, n_effective: float | None = None) -> float:
    """Bayesian information criterion -2 log L + p log N (lower is better), or its effective-sample-size form.

    Args:
        gmm: fitted mixture.
        x: (N, d) samples it was fitted to.
        n_effective: optional effective sample size N_eff (0 < N_eff <= N, e.g. :func:`effective_sample_size`):
            returns -2 (N_eff / N) log L + p log N_eff (module docstring). None: the plain BIC.

    Raises:
        InvalidArgumentError: ``gmm`` is not a GMM, or ``n_effective`` not a number in (0, N].
        TooFewSamplesError, ShapeMismatchError, NonFiniteError: ``x`` is not a finite (N, d) tensor with N >= 1.
    """
    if not isinstance(gmm, GMM):
        raise InvalidArgumentError(f"gmm must be a GMM, got {type(gmm).__name__}")
    check_samples(x, min_samples=1)
    check_float(n_effective, "n_effective", low=0.0, low_open=True, allow_none=True)
    ll = float(gmm.log_prob(x).sum())
    p = n_parameters(gmm.n_components, gmm.dim)
    N = x.shape[0]
    if n_effective is None:
        return -2.0 * ll + p * math.log(N)
    n_eff = float(n_effective)
    if not 0 < n_eff <= N * (1 + 1e-12):
        raise InvalidArgumentError(f"n_effective must be in (0, N = {N}], got {n_effective}")
    return -2.0 * (n_eff / N) * ll + p * math.log(n_eff)


def _k_candidates(k_range: Iterable[int]) -> list[int]:
    """The sorted distinct candidates of ``k_range`` (the checks of :func:`check_k_range` that need no data)."""
    if isinstance(k_range, (str, bytes)) or not isinstance(k_range, Iterable):
        raise InvalidArgumentError(f"k_range must be an iterable of integers >= 1, got {k_range!r}")
    if isinstance(k_range, range) and len(k_range) > MAX_K_CANDIDATES or (
        isinstance(k_range, Sequence) and len(k_range) > MAX_K_CANDIDATES
    ):
        raise InvalidArgumentError(f"k_range has {len(k_range)} candidates, at most {MAX_K_CANDIDATES} are allowed")
    ks = sorted({check_int(k, "k_range entry", low=1) for k in k_range})
    if len(ks) > MAX_K_CANDIDATES:
        raise InvalidArgumentError(f"k_range has {len(ks)} candidates, at most {MAX_K_CANDIDATES} are allowed")
    return ks


def check_k_range(k_range: Iterable[int], n_samples: int) -> list[int]:
    """The sorted distinct candidates K of ``k_range`` that N = ``n_samples`` samples support (K <= N).

    Raises:
        InvalidArgumentError: not an iterable of integers >= 1, or more than 1000 candidates.
        TooFewSamplesError: no candidate K <= N.
    """
    ks = [k for k in _k_candidates(k_range) if k <= n_samples]
    if not ks:
        raise TooFewSamplesError(f"no candidate K in k_range = {k_range!r} is <= the {n_samples} samples")
    return ks


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
    n_effective: float | None = None,
) -> GMM:
    """EM for every K in ``k_range`` (K <= N), keeping the fit with the lowest :func:`bic`.

    Args:
        x: (N, d) samples.
        k_range: candidate numbers of components, integers >= 1, at most 1000 (values above N are skipped).
        generator: torch generator; the candidates are fitted in ascending K with it.
        n_init, max_iter, tol, reg_covar, kmeans_iter: as in :func:`fit_em`.
        n_effective: optional effective sample size for the effective-sample-size BIC (module docstring);
            None (default) uses the plain BIC.

    Returns:
        The BIC-optimal :class:`GMM`.

    Raises:
        TooFewSamplesError: no admissible K in ``k_range``.
        InvalidArgumentError: a hyperparameter of the wrong type or out of range (``n_effective`` included, checked
            before any fit).
    """
    check_samples(x, min_samples=1)
    ks = check_k_range(k_range, x.shape[0])
    check_float(n_effective, "n_effective", low=0.0, low_open=True, allow_none=True)
    best: tuple[float, GMM] | None = None
    for k in ks:
        gmm = fit_em(
            x, k, generator=generator, n_init=n_init, max_iter=max_iter, tol=tol, reg_covar=reg_covar,
            kmeans_iter=kmeans_iter,
        )
        score = bic(gmm, x, n_effective=n_effective)
        if best is None or score < best[0]:
            best = (score, gmm)
    assert best is not None
    return best[1]
