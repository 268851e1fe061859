"""EM, the GMM and the argument checks of lfd_torch.utils against independent references (per-sample loops with
scipy.stats, numpy M-steps, closed forms, boundary values). Every test is seeded and float64."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats
import torch

from lfd_torch.errors import (
    InvalidArgumentError,
    NonFiniteError,
    ShapeMismatchError,
    SolverError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.gmm import GMM, InvalidGMMError, bic, fit_em, kmeans_plus_plus, n_parameters, refine_em
from lfd_torch.gmm.em import check_k_range
from lfd_torch.gmm.model import check_samples
from lfd_torch.utils import (
    check_choice,
    check_cost,
    check_float,
    check_generator,
    check_int,
    check_path,
    check_tensor,
    safe_magnitude,
    solver_errors,
)

F64 = torch.float64


def _random_gmm(K: int, d: int, seed: int) -> GMM:
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.2, 1.0, K)
    mu = 2.0 * rng.standard_normal((K, d))
    A = rng.standard_normal((K, d, d))
    cov = A @ A.transpose(0, 2, 1) + 0.3 * np.eye(d)
    return GMM(torch.tensor(w / w.sum()), torch.tensor(mu), torch.tensor(cov))


def _data(seed: int, d: int = 2, n_per: int = 25) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0] * d, [3.0] * d, [0.0] * (d - 1) + [4.0]])
    # anisotropic spread per cluster so the covariances are not all alike
    scales = rng.uniform(0.4, 1.5, (3, d))
    return np.concatenate([c + s * rng.standard_normal((n_per, d)) for c, s in zip(centres, scales)])


def _np_e_step(x: np.ndarray, w: np.ndarray, mu: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, float]:
    """Responsibilities and total log-likelihood by a per-sample loop over scipy densities."""
    N, K = x.shape[0], w.shape[0]
    R = np.zeros((N, K))
    ll = 0.0
    for n in range(N):
        dens = np.array([w[k] * scipy.stats.multivariate_normal(mu[k], cov[k]).pdf(x[n]) for k in range(K)])
        R[n] = dens / dens.sum()
        ll += math.log(dens.sum())
    return R, ll


def _np_m_step(x: np.ndarray, R: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted means and covariances (S_k + rho I) / n_k component by component."""
    N, d = x.shape
    K = R.shape[1]
    nk = R.sum(0)
    w = nk / N
    mu = np.zeros((K, d))
    cov = np.zeros((K, d, d))
    for k in range(K):
        mu[k] = (R[:, k : k + 1] * x).sum(0) / nk[k]
        S = np.zeros((d, d))
        for n in range(N):
            S += R[n, k] * np.outer(x[n] - mu[k], x[n] - mu[k])
        cov[k] = (S + rho * np.eye(d)) / nk[k]
    return w, mu, cov


def _np_objective(x: np.ndarray, w, mu, cov, rho: float) -> float:
    _, ll = _np_e_step(x, w, mu, cov)
    pen = 0.5 * rho * sum(np.trace(np.linalg.inv(c)) for c in cov)
    return (ll - pen) / x.shape[0]


def _params(g: GMM):
    return g.weights.numpy(), g.means.numpy(), g.covariances.numpy()


# ---------------------------------------------------------------------------------------------- EM
@pytest.mark.parametrize("reg_covar", [1e-6, 0.5])
def test_refine_em_iterates_equal_a_scipy_loop_em(reg_covar: float) -> None:
    """Three EM iterations (E-step: per-sample scipy densities; M-step: weighted numpy means and (S + rho I) / n_k
    with rho = reg_covar * mean per-dimension variance) and the history of F/N reproduce refine_em exactly."""
    x = _data(0, d=2)
    init = _random_gmm(3, 2, seed=1)
    rho = reg_covar * x.var(0).mean()
    w, mu, cov = _params(init)
    hist_ref = [_np_objective(x, w, mu, cov, rho)]
    for _ in range(3):
        R, _ = _np_e_step(x, w, mu, cov)
        w, mu, cov = _np_m_step(x, R, rho)
        hist_ref.append(_np_objective(x, w, mu, cov, rho))
    gmm, hist = refine_em(torch.tensor(x), init, max_iter=3, tol=0.0, reg_covar=reg_covar)
    assert hist.shape == (4,)
    np.testing.assert_allclose(hist.numpy(), hist_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(gmm.weights.numpy(), w, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(gmm.means.numpy(), mu, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(gmm.covariances.numpy(), cov, rtol=1e-8, atol=1e-10)


def test_refine_em_three_dimensional_single_step() -> None:
    """One EM step in d = 3 with K = 2 against the scipy/numpy reference (catches axis swaps that d = 2 hides)."""
    rng = np.random.default_rng(5)
    x = rng.standard_normal((40, 3)) @ np.array([[1.0, 0.3, 0.0], [0.0, 2.0, 0.5], [0.0, 0.0, 0.7]]) + [1, -2, 3]
    init = _random_gmm(2, 3, seed=6)
    init = GMM(init.weights, init.means + torch.tensor([1.0, -2.0, 3.0], dtype=F64), init.covariances)
    rho = 1e-2 * x.var(0).mean()
    R, _ = _np_e_step(x, *_params(init))
    w, mu, cov = _np_m_step(x, R, rho)
    gmm, _ = refine_em(torch.tensor(x), init, max_iter=1, tol=0.0, reg_covar=1e-2)
    np.testing.assert_allclose(gmm.weights.numpy(), w, rtol=1e-9)
    np.testing.assert_allclose(gmm.means.numpy(), mu, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(gmm.covariances.numpy(), cov, rtol=1e-8, atol=1e-10)


def test_constant_data_regularise_with_unit_scale() -> None:
    """Zero-spread data: the scale of rho falls back to 1, so one component fitted to N identical points has
    covariance reg_covar * I / N (and a single sample likewise reg_covar * I)."""
    x = torch.full((4, 2), 3.0, dtype=F64)
    init = GMM(torch.ones(1, dtype=F64), torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64)[None])
    gmm, _ = refine_em(x, init, max_iter=1, tol=0.0, reg_covar=0.2)
    torch.testing.assert_close(gmm.covariances[0], 0.2 * torch.eye(2, dtype=F64) / 4, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(gmm.means[0], torch.tensor([3.0, 3.0], dtype=F64))
    gmm1, _ = refine_em(x[:1], init, max_iter=1, tol=0.0, reg_covar=0.2)
    torch.testing.assert_close(gmm1.covariances[0], 0.2 * torch.eye(2, dtype=F64), rtol=1e-9, atol=1e-12)


def test_refine_em_stopping_rule_and_monotone_history() -> None:
    """The history is non-decreasing; with tolerance tol the run stops at the first iteration whose gain over the
    previous iterate is below tol (naive scan of a tol = 0 run), and max_iter = 0 returns init untouched."""
    x = torch.tensor(_data(2, d=2))
    init = _random_gmm(3, 2, seed=3)
    _, full = refine_em(x, init, max_iter=40, tol=0.0)
    gains = (full[1:] - full[:-1]).tolist()
    assert min(gains) >= -1e-12 * float(full.abs().max())
    for tol in (1e-1, 1e-2, 1e-3, 1e-4):
        stop = next((i for i, g in enumerate(gains) if g < tol), None)
        assert stop is not None and stop >= 1, (tol, gains)
        _, hist = refine_em(x, init, max_iter=40, tol=tol)
        assert hist.shape[0] == stop + 2, (tol, stop, hist.shape)
        torch.testing.assert_close(hist, full[: stop + 2], rtol=0, atol=0)
    _, huge = refine_em(x, init, max_iter=40, tol=1e9)
    assert huge.shape == (2,)
    g0, h0 = refine_em(x, init, max_iter=0)
    assert g0 is init and h0.shape == (1,)
    _, capped = refine_em(x, init, max_iter=5, tol=0.0)
    assert capped.shape == (6,)


def test_fit_em_with_no_iteration_is_the_m_step_of_the_kmeans_partition() -> None:
    """fit_em(max_iter=0) returns the regularised ML mixture of the k-means++ labels drawn with the same seed:
    weights n_k / N, group means, covariances (S_k + rho I) / n_k."""
    x = _data(4, d=2)
    labels = kmeans_plus_plus(torch.tensor(x), 3, generator=torch.Generator().manual_seed(11)).numpy()
    gmm = fit_em(torch.tensor(x), 3, generator=torch.Generator().manual_seed(11), max_iter=0, reg_covar=0.1)
    R = np.eye(3)[labels]
    w, mu, cov = _np_m_step(x, R, 0.1 * x.var(0).mean())
    np.testing.assert_allclose(gmm.weights.numpy(), w, rtol=1e-9)
    np.testing.assert_allclose(gmm.means.numpy(), mu, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(gmm.covariances.numpy(), cov, rtol=1e-8, atol=1e-12)


def test_kmeans_converged_labels_are_a_lloyd_fixed_point() -> None:
    """After enough Lloyd iterations on separated blobs every sample's label is its nearest group mean (brute-force
    numpy distances), and all K labels are used."""
    x = _data(7, d=2, n_per=30)
    labels = kmeans_plus_plus(torch.tensor(x), 3, generator=torch.Generator().manual_seed(1), n_iter=100).numpy()
    assert set(labels.tolist()) == {0, 1, 2}
    centres = np.stack([x[labels == k].mean(0) for k in range(3)])
    d2 = ((x[:, None, :] - centres[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(d2.argmin(1), labels)
    # n_iter = 0 keeps the seeds: the seeds are samples, each sample is labelled by its nearest seed
    lab0 = kmeans_plus_plus(torch.tensor(x), 3, generator=torch.Generator().manual_seed(1), n_iter=0).numpy()
    assert set(lab0.tolist()) == {0, 1, 2}
    with pytest.raises(InvalidArgumentError, match="n_components"):
        kmeans_plus_plus(torch.tensor(x), x.shape[0] + 1, generator=torch.Generator())
    kmeans_plus_plus(torch.tensor(x), x.shape[0], generator=torch.Generator().manual_seed(0))  # K = N allowed


def test_n_parameters_and_bic_closed_forms() -> None:
    """p = (K - 1) + K d + K d (d + 1) / 2 by counting; BIC and the effective-sample-size BIC by their formulas."""
    for K in range(1, 5):
        for d in range(1, 5):
            count = (K - 1) + K * d + K * sum(range(1, d + 1))
            assert n_parameters(K, d) == count
    gmm = _random_gmm(2, 3, seed=8)
    x = torch.tensor(np.random.default_rng(9).standard_normal((30, 3)))
    ll = sum(float(gmm.log_prob(x[i])) for i in range(30))
    p = n_parameters(2, 3)
    assert bic(gmm, x) == pytest.approx(-2 * ll + p * math.log(30), rel=1e-12)
    assert bic(gmm, x, n_effective=7.5) == pytest.approx(-2 * (7.5 / 30) * ll + p * math.log(7.5), rel=1e-12)
    assert bic(gmm, x, n_effective=30) == pytest.approx(bic(gmm, x), rel=1e-12)
    for bad in (0, -1.0, 31):
        with pytest.raises(InvalidArgumentError, match="n_effective"):
            bic(gmm, x, n_effective=bad)


def test_check_k_range_sorts_dedupes_and_filters() -> None:
    """Candidates are sorted, distinct, <= N; none admissible is TooFewSamplesError; bad entries are typed."""
    assert check_k_range([4, 2, 2, 9, 1], 5) == [1, 2, 4]
    assert check_k_range(range(1, 4), 3) == [1, 2, 3]
    with pytest.raises(TooFewSamplesError):
        check_k_range([6, 7], 5)
    with pytest.raises(InvalidArgumentError):
        check_k_range([0, 1], 5)
    with pytest.raises(InvalidArgumentError):
        check_k_range("123", 5)
    with pytest.raises(InvalidArgumentError):
        check_k_range(range(1, 1002), 5000)
    assert len(check_k_range(range(1, 1001), 5000)) == 1000


def test_em_argument_checks_name_the_argument() -> None:
    """Hyperparameter checks of fit_em / refine_em: boundaries accepted, one past them rejected, naming the argument."""
    x = torch.tensor(_data(1, d=2))
    g = torch.Generator().manual_seed(0)
    init = _random_gmm(2, 2, seed=0)
    refine_em(x, init, max_iter=0, tol=0.0, reg_covar=0.0)
    for kw, bad in (("max_iter", -1), ("tol", -1e-9), ("reg_covar", -1e-9), ("max_iter", 100_001)):
        with pytest.raises(InvalidArgumentError, match=kw):
            refine_em(x, init, **{kw: bad})
    with pytest.raises(InvalidArgumentError, match="init"):
        refine_em(x, "gmm")  # type: ignore[arg-type]
    for kw, bad in (("n_init", 0), ("n_init", 1001), ("kmeans_iter", -1), ("max_iter", -1), ("tol", -1.0)):
        with pytest.raises(InvalidArgumentError, match=kw):
            fit_em(x, 2, generator=g, **{kw: bad})
    with pytest.raises(InvalidArgumentError, match="generator"):
        fit_em(x, 2, generator=None)  # type: ignore[arg-type]
    fit_em(x[:2], 2, generator=g, max_iter=1)  # N == K allowed


# ---------------------------------------------------------------------------------------------- GMM
def test_zero_weight_component_is_valid_and_gets_no_responsibility() -> None:
    """Weights may be 0 (only negatives are invalid): that component's joint log density is -inf and its
    responsibility 0, while the mixture density equals the other component's scipy density."""
    w = torch.tensor([1.0, 0.0], dtype=F64)
    mu = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=F64)
    cov = torch.stack([torch.eye(2, dtype=F64), 2 * torch.eye(2, dtype=F64)])
    gmm = GMM(w, mu, cov)
    x = torch.tensor([[0.5, -0.2], [1.0, 1.0]], dtype=F64)
    lpc = gmm.log_prob_components(x)
    assert torch.isneginf(lpc[:, 1]).all()
    torch.testing.assert_close(gmm.posterior(x), torch.tensor([[1.0, 0.0], [1.0, 0.0]], dtype=F64))
    ref = scipy.stats.multivariate_normal(np.zeros(2), np.eye(2)).logpdf(x.numpy())
    np.testing.assert_allclose(gmm.log_prob(x).numpy(), ref, rtol=1e-12)


def test_weight_sum_and_symmetry_tolerances() -> None:
    """sum(w) within 1e-6 of 1 and relative asymmetry within 1e-5 are accepted; beyond them InvalidGMMError."""
    mu = torch.zeros(2, 2, dtype=F64)
    cov = torch.eye(2, dtype=F64).repeat(2, 1, 1)
    GMM(torch.tensor([0.5, 0.5 + 5e-7], dtype=F64), mu, cov)
    GMM(torch.tensor([0.5, 0.5 - 5e-7], dtype=F64), mu, cov)
    for bad in (0.5 + 2e-6, 0.5 - 2e-6):
        with pytest.raises(InvalidGMMError, match="sum to 1"):
            GMM(torch.tensor([0.5, bad], dtype=F64), mu, cov)
    w = torch.tensor([0.5, 0.5], dtype=F64)
    ok = cov.clone()
    ok[1, 0, 1] = 5e-6
    GMM(w, mu, ok)
    bad_cov = cov.clone()
    bad_cov[1, 0, 1] = 2e-5
    with pytest.raises(InvalidGMMError, match="symmetric"):
        GMM(w, mu, bad_cov)
    with pytest.raises(ShapeMismatchError, match="weights"):
        GMM(torch.tensor([1.0], dtype=F64), mu, cov)
    with pytest.raises(ShapeMismatchError, match="means"):
        GMM(w, torch.zeros(2, 0, dtype=F64), cov)
    with pytest.raises(ShapeMismatchError, match="covariances"):
        GMM(w, mu, cov.to(torch.float32))


def test_precisions_cholesky_and_mahalanobis_against_numpy() -> None:
    """precisions = inv(Sigma_k), L L^T = Sigma_k with L lower, and the squared Mahalanobis distance by a loop."""
    gmm = _random_gmm(3, 3, seed=12)
    S = gmm.covariances.numpy()
    np.testing.assert_allclose(gmm.precisions.numpy(), np.linalg.inv(S), rtol=1e-9, atol=1e-10)
    L = gmm.cholesky.numpy()
    np.testing.assert_allclose(L @ L.transpose(0, 2, 1), S, rtol=1e-10, atol=1e-12)
    assert np.allclose(np.triu(L, 1), 0)
    x = np.random.default_rng(13).standard_normal((6, 3))
    m = gmm.mahalanobis_sq(torch.tensor(x)).numpy()
    for n in range(6):
        for k in range(3):
            diff = x[n] - gmm.means[k].numpy()
            assert m[n, k] == pytest.approx(diff @ np.linalg.solve(S[k], diff), rel=1e-9)


def test_sample_per_component_moments_and_labels() -> None:
    """Samples labelled k follow N(mu_k, Sigma_k): per-label mean and covariance (Monte Carlo, 40k draws), label
    frequencies; n = 0 gives empty outputs; bad n is a typed error naming n."""
    gmm = _random_gmm(2, 3, seed=14)
    x, lab = gmm.sample(40_000, generator=torch.Generator().manual_seed(15))
    assert x.shape == (40_000, 3) and lab.dtype == torch.int64
    for k in range(2):
        xs = x[lab == k].numpy()
        scale = float(np.linalg.eigvalsh(gmm.covariances[k].numpy()).max())
        np.testing.assert_allclose(xs.mean(0), gmm.means[k].numpy(), atol=0.05 * math.sqrt(scale))
        np.testing.assert_allclose(np.cov(xs.T), gmm.covariances[k].numpy(), atol=0.06 * scale)
    freq = np.bincount(lab.numpy(), minlength=2) / 40_000
    np.testing.assert_allclose(freq, gmm.weights.numpy(), atol=0.01)
    for bad in (-1, 2.0, True):
        with pytest.raises(InvalidArgumentError, match="n must"):
            gmm.sample(bad, generator=torch.Generator())  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError, match="generator"):
        gmm.sample(3, generator=None)  # type: ignore[arg-type]


def test_from_labels_regularisation_and_order() -> None:
    """from_labels orders components by sorted label value and adds reg_covar * mean variance to each diagonal."""
    rng = np.random.default_rng(16)
    x = rng.standard_normal((12, 2))
    labels = torch.tensor([7, 3] * 6)
    gmm = GMM.from_labels(torch.tensor(x), labels, reg_covar=0.3)
    reg = 0.3 * x.var(0).mean()
    for k, lab in enumerate([3, 7]):
        part = x[labels.numpy() == lab]
        np.testing.assert_allclose(gmm.means[k].numpy(), part.mean(0), rtol=1e-12)
        np.testing.assert_allclose(gmm.covariances[k].numpy(), np.cov(part.T, bias=True) + reg * np.eye(2),
                                   rtol=1e-10)  # fmt: skip
    with pytest.raises(ShapeMismatchError, match="labels"):
        GMM.from_labels(torch.tensor(x), labels[:5])


def test_check_samples_boundaries() -> None:
    """check_samples: d = 0, too few rows, x_dot of other shape / dtype, non-finite x_dot, all typed."""
    x = torch.zeros(3, 2, dtype=F64)
    check_samples(x, min_samples=3)
    with pytest.raises(TooFewSamplesError, match="at least 4"):
        check_samples(x, min_samples=4)
    with pytest.raises(ShapeMismatchError, match="d >= 1"):
        check_samples(torch.zeros(3, 0, dtype=F64))
    with pytest.raises(ShapeMismatchError, match="x_dot"):
        check_samples(x, torch.zeros(3, 3, dtype=F64))
    with pytest.raises(ShapeMismatchError, match="x_dot"):
        check_samples(x, torch.zeros(3, 2, dtype=torch.float32))
    with pytest.raises(NonFiniteError, match="x_dot"):
        check_samples(x, torch.full((3, 2), float("inf"), dtype=F64))
    with pytest.raises(ShapeMismatchError, match="pos"):
        check_samples(torch.zeros(3, dtype=F64), name="pos")


# ---------------------------------------------------------------------------------------------- utils
def test_check_int_boundaries_and_types() -> None:
    """Inclusive [low, high]; bools and floats rejected, numpy ints accepted; the error class and name are used."""
    assert check_int(3, "k", low=3, high=3) == 3
    assert check_int(np.int64(5), "k", low=0) == 5 and type(check_int(np.int64(5), "k")) is int
    assert check_int(None, "k", allow_none=True) is None
    for bad in (2, 4):
        with pytest.raises(InvalidArgumentError, match=r"k must be an integer in \[3, 3\]"):
            check_int(bad, "k", low=3, high=3)
    for bad in (True, 2.0, "2", None):
        with pytest.raises(InvalidArgumentError, match="k must"):
            check_int(bad, "k")
    with pytest.raises(TooFewSamplesError, match="k must"):
        check_int(0, "k", low=1, error=TooFewSamplesError)


def test_check_float_boundaries_and_types() -> None:
    """Closed and open bounds exactly at the limit, NaN/Inf, allow_inf, scalar tensors, bools, allow_none."""
    assert check_float(0.0, "t", low=0.0) == 0.0 and check_float(1, "t", high=1) == 1.0
    with pytest.raises(InvalidArgumentError, match=r"t must be a finite number in \(0.0, inf\]"):
        check_float(0.0, "t", low=0.0, low_open=True)
    with pytest.raises(InvalidArgumentError, match="t must"):
        check_float(1.0, "t", high=1.0, high_open=True)
    assert check_float(0.999, "t", high=1.0, high_open=True) == 0.999
    for bad in (-1e-300, ):
        with pytest.raises(InvalidArgumentError):
            check_float(bad, "t", low=0.0)
    with pytest.raises(InvalidArgumentError):
        check_float(1.0 + 1e-12, "t", high=1.0)
    for bad in (float("nan"), float("inf"), True, "1.0", None, torch.ones(2)):
        with pytest.raises(InvalidArgumentError, match="t must"):
            check_float(bad, "t")
    assert check_float(float("inf"), "t", allow_inf=True) == math.inf
    with pytest.raises(InvalidArgumentError):
        check_float(float("nan"), "t", allow_inf=True)
    assert check_float(torch.tensor(2.5, dtype=F64), "t") == 2.5 and check_float(np.float32(0.5), "t") == 0.5
    assert check_float(None, "t", allow_none=True) is None
    with pytest.raises(ShapeMismatchError):
        check_float(-1.0, "t", low=0.0, error=ShapeMismatchError)


def test_check_tensor_rules() -> None:
    """dtype/device, rank, last dimension, finiteness and the overflow bound max**0.25 (value at the bound kept)."""
    assert safe_magnitude(F64) == pytest.approx(np.finfo(np.float64).max ** 0.25, rel=1e-15)
    assert safe_magnitude(torch.float32) == pytest.approx(float(np.finfo(np.float32).max) ** 0.25, rel=1e-12)
    x = torch.zeros(4, 3, dtype=F64)
    assert check_tensor(x, "x", ndim=2, last_dim=3, dtype=F64, device=x.device) is x
    for kwargs, err, pat in (
        (dict(ndim=3), ShapeMismatchError, "x must have 3 dimensions"),
        (dict(min_ndim=3), ShapeMismatchError, "x must have >= 3"),
        (dict(last_dim=2), ShapeMismatchError, "last dimension d = 2"),
        (dict(dtype=torch.float32), ShapeMismatchError, "x is torch.float64"),
        (dict(min_rows=5), TooFewSamplesError, "x has 4 samples"),
    ):
        with pytest.raises(err, match=pat):
            check_tensor(x, "x", **kwargs)
    check_tensor(x, "x", min_rows=4, min_ndim=2)
    for bad in (torch.zeros(2, dtype=torch.int64), torch.zeros(2, dtype=torch.float16), np.zeros(2)):
        with pytest.raises(ShapeMismatchError, match="x"):
            check_tensor(bad, "x")
    lim = safe_magnitude(F64)
    check_tensor(torch.tensor([lim, -lim], dtype=F64), "x")
    with pytest.raises(NonFiniteError, match="x contains"):
        check_tensor(torch.tensor([lim * (1 + 1e-12)], dtype=F64), "x")
    check_tensor(torch.tensor([lim * 2], dtype=F64), "x", bounded=False)
    with pytest.raises(NonFiniteError):
        check_tensor(torch.tensor([float("nan")], dtype=F64), "x")
    check_tensor(torch.tensor([float("nan")], dtype=F64), "x", finite=False)


def test_small_checks_choice_generator_cost_path_solver() -> None:
    """check_choice / check_generator / check_cost (size == limit passes) / check_path / solver_errors."""
    assert check_choice("a", "mode", ["a", "b"]) == "a"
    with pytest.raises(UnknownNameError, match="mode"):
        check_choice("c", "mode", ["a", "b"])
    with pytest.raises(UnknownNameError):
        check_choice(1, "mode", ["a", "b"])
    g = torch.Generator()
    assert check_generator(g) is g
    with pytest.raises(InvalidArgumentError, match="EM needs gen=torch.Generator"):
        check_generator(3, "gen", where="EM")
    check_cost("n", 10.0, 10.0, "samples")
    with pytest.raises(InvalidArgumentError, match="n implies"):
        check_cost("n", 10.5, 10.0, "samples")
    assert str(check_path("a/b.txt")) == "a/b.txt"
    for bad in ("", b"a", 3, None):
        with pytest.raises(InvalidArgumentError, match="out must be a file path"):
            check_path(bad, "out")
    with pytest.raises(SolverError, match="inverse failed") as info:
        with solver_errors("inverse"):
            raise RuntimeError("singular")
    assert isinstance(info.value.__cause__, RuntimeError)
    with pytest.raises(TooFewSamplesError):
        with solver_errors("inverse"):
            raise TooFewSamplesError("kept")
    with pytest.raises(KeyError):
        with solver_errors("inverse"):
            raise KeyError("other")


# ---------------------------------------------------------------------------------------------- real bugs found
def test_sample_zero_draws_gives_empty_outputs() -> None:
    """n = 0 is inside the documented range [0, 10^8]: empty (0, d) samples and (0,) labels (torch.multinomial
    refuses to draw none; the review found the RuntimeError)."""
    gmm = _random_gmm(2, 3, seed=14)
    x0, l0 = gmm.sample(0, generator=torch.Generator().manual_seed(0))
    assert x0.shape == (0, 3) and x0.dtype == gmm.dtype and l0.shape == (0,) and l0.dtype == torch.long


def test_check_tensor_unbounded_still_rejects_inf() -> None:
    """finite=True, bounded=False: Inf and NaN still raise NonFiniteError (|inf| <= inf let Inf through), while a
    huge finite value passes."""
    for bad in (float("inf"), -float("inf"), float("nan")):
        with pytest.raises(NonFiniteError):
            check_tensor(torch.tensor([1.0, bad], dtype=F64), "x", bounded=False)
    check_tensor(torch.tensor([1e300], dtype=F64), "x", bounded=False)


def test_stopping_rule_is_strict_at_a_fixed_point() -> None:
    """The rule is 'gain < tol' (strict): with K = 1 EM reaches its fixed point after one step, the later gains are
    exactly 0, so tol = 0 runs all max_iter iterations, while any tol > 0 stops right after the first zero gain."""
    x = torch.tensor(_data(3, d=2))
    init = GMM(torch.ones(1, dtype=F64), torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64)[None])
    _, hist = refine_em(x, init, max_iter=5, tol=0.0)
    assert hist.shape == (6,)
    assert torch.equal(hist[2:], hist[1].expand(4))  # zero gains after the first step
    _, hist_tol = refine_em(x, init, max_iter=5, tol=1e-300)
    assert hist_tol.shape == (3,)


def test_kmeans_plus_plus_seeds_one_centre_per_far_group() -> None:
    """D^2 seeding uses the distance to the nearest chosen seed: for three tight groups 100 spreads apart the
    chance of a second seed in an occupied group is ~1e-8, so with n_iter = 0 the labels are the groups, for every
    seed of the generator (a rule that only looked at the last seed would revisit the first group half the time)."""
    rng = np.random.default_rng(21)
    centres = np.array([[0.0, 0.0], [100.0, 0.0], [50.0, 86.6]])
    group = np.repeat(np.arange(3), 10)
    x = torch.tensor(centres[group] + 0.01 * rng.standard_normal((30, 2)))
    for seed in range(30):
        lab = kmeans_plus_plus(x, 3, generator=torch.Generator().manual_seed(seed), n_iter=0).numpy()
        # a bijection between labels and groups
        assert len({(int(a), int(b)) for a, b in zip(lab, group)}) == 3 and len(set(lab.tolist())) == 3, seed


def test_kmeans_plus_plus_uses_every_label_with_duplicate_points() -> None:
    """N >= K but fewer distinct points than K: the docstring still promises all K labels (coincident centres shared
    one nearest sample, and [[0, 0] x 3, [1, 1]] with K = 3 gave [0, 0, 0, 2])."""
    for x, K in ((torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [1.0, 1.0]], dtype=F64), 3),
                 (torch.zeros(5, 2, dtype=F64), 3), (torch.tensor([[0.0], [0.0], [2.0], [2.0], [2.0]], dtype=F64), 4)):
        for seed in range(5):
            lab = kmeans_plus_plus(x, K, generator=torch.Generator().manual_seed(seed))
            assert set(lab.tolist()) == set(range(K)), (x.tolist(), seed, lab.tolist())


def test_lfd_runtime_errors_pass_through_solver_errors_and_device_rule() -> None:
    """A package error that is also a RuntimeError (CertificationError) leaves solver_errors unchanged, not
    re-wrapped as SolverError; check_tensor rejects a tensor on another device (the meta device) by name."""
    from lfd_torch.errors import CertificationError

    err = CertificationError("mine")
    with pytest.raises(CertificationError) as info:
        with solver_errors("inverse"):
            raise err
    assert info.value is err and not isinstance(info.value, SolverError)
    meta = torch.zeros(3, 2, dtype=F64, device="meta")
    with pytest.raises(ShapeMismatchError, match="meta"):
        check_tensor(meta, "x", dtype=F64, device=torch.device("cpu"))
