"""Bayesian kernels of lfd_torch.gmm (NIW conjugacy, samplers, ddCRP Gibbs, DAMM scores, post-processing) against
independent references: Murphy (2007) closed forms written out in numpy, chains of Student-t predictives
(scipy.stats.multivariate_t), scipy densities and special functions, Monte Carlo moments with 5-sigma tolerances,
exact enumeration of small ddCRP posteriors, and invariances. Every random test is seeded and runs in float64."""

from __future__ import annotations

import itertools
import math
from collections import Counter

import numpy as np
import pytest
import scipy.special
import scipy.stats
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from lfd_torch.gmm import GMM
from lfd_torch.gmm.damm import _Model, _merge_moves, _sample_parameters, _split_moves, _Stats, vmf_log_normalizer
from lfd_torch.gmm.niw import (
    NIWPrior,
    inverse_wishart_log_density,
    log_multigamma,
    niw_log_density,
    niw_log_marginal_likelihood,
    niw_log_marginal_normalizer,
    niw_posterior,
    niw_prior_from_data,
    sample_gamma,
    sample_niw,
    sufficient_statistics,
)
from lfd_torch.gmm.pcgmm import _ddcrp_gibbs, prior_weights
from lfd_torch.gmm.postprocess import merge_small_components, order_by_attractor, regularize_covariances

F64 = torch.float64


# ------------------------------------------------------------------------------------------- references
def _murphy_posterior(m0, k0, nu0, psi0, x):  # type: ignore[no-untyped-def]
    """Murphy (2007) eqs. 250-254 from the centred scatter S and the sample mean xbar."""
    n = x.shape[0]
    xbar = x.mean(0)
    S = (x - xbar).T @ (x - xbar)
    kn = k0 + n
    return (k0 * m0 + n * xbar) / kn, kn, nu0 + n, psi0 + S + (k0 * n / kn) * np.outer(xbar - m0, xbar - m0)


def _student_t_chain(m0, k0, nu0, psi0, x) -> float:  # type: ignore[no-untyped-def]
    """log p(x_1..n) = sum_i log p(x_i | x_<i), each a multivariate Student t (Murphy 2007, eq. 258), with the
    posterior after each point updated by the one-point rank-one form of eqs. 250-254."""
    d = x.shape[1]
    out, m, k, nu, psi = 0.0, np.array(m0, float), float(k0), float(nu0), np.array(psi0, float)
    for xi in x:
        dof = nu - d + 1
        out += scipy.stats.multivariate_t(loc=m, shape=psi * (k + 1) / (k * dof), df=dof).logpdf(xi)
        psi = psi + k / (k + 1) * np.outer(xi - m, xi - m)
        m = (k * m + xi) / (k + 1)
        k, nu = k + 1, nu + 1
    return float(out)


def _prior(m0, k0, nu0, psi0) -> NIWPrior:  # type: ignore[no-untyped-def]
    return NIWPrior(torch.as_tensor(np.asarray(m0, float)), torch.tensor(float(k0), dtype=F64),
                    torch.tensor(float(nu0), dtype=F64), torch.as_tensor(np.asarray(psi0, float)))  # fmt: skip


def _spd(rng: np.random.Generator, d: int) -> np.ndarray:
    B = rng.normal(size=(d, d))
    return B @ B.T + 0.5 * np.eye(d)


def _evidence(prior: NIWPrior, x: np.ndarray) -> float:
    w = torch.ones(x.shape[0], 1, dtype=F64)
    return float(niw_log_marginal_likelihood(prior, *sufficient_statistics(torch.as_tensor(x), w))[0])


# ------------------------------------------------------------------------------------------- NIW closed forms
def test_log_multigamma_matches_scipy() -> None:
    """log Gamma_d(a) equals scipy.special.multigammaln(a, d) for d = 1..5 over a range of a > (d - 1) / 2."""
    for d in range(1, 6):
        a = np.array([0.5 * (d - 1) + 0.01, 0.5 * d + 0.3, 3.7, 11.0, 250.5])
        got = log_multigamma(torch.tensor(a, dtype=F64), d).numpy()
        np.testing.assert_allclose(got, [scipy.special.multigammaln(v, d) for v in a], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("d", [1, 2, 4])
def test_niw_posterior_is_murphys_closed_form_and_sequential(d: int) -> None:
    """niw_posterior from (n, s, Q) equals Murphy (2007) eqs. 250-254 written from the centred scatter, for a
    prior with non-zero mean, kappa0 != 1, a non-diagonal Psi0 and K = 3 states at once; and conjugacy holds:
    updating the posterior after a batch A by a batch B gives the posterior after A u B."""
    rng = np.random.default_rng(10 + d)
    m0, k0, nu0, psi0 = rng.normal(size=d), 0.37, d + 1.5, _spd(rng, d)
    prior = _prior(m0, k0, nu0, psi0)
    x = rng.normal(size=(17, d)) * 1.7 + 2.0
    lab = np.array([0] * 5 + [1] * 8 + [2] * 4)
    rng.shuffle(lab)
    onehot = torch.nn.functional.one_hot(torch.as_tensor(lab), 3).to(F64)
    post = niw_posterior(prior, *sufficient_statistics(torch.as_tensor(x), onehot))
    for k in range(3):
        mn, kn, nun, psin = _murphy_posterior(m0, k0, nu0, psi0, x[lab == k])
        np.testing.assert_allclose(post.mean[k].numpy(), mn, rtol=1e-11, atol=1e-12)
        assert float(post.kappa[k]) == pytest.approx(kn, rel=1e-14)
        assert float(post.dof[k]) == pytest.approx(nun, rel=1e-14)
        np.testing.assert_allclose(post.scale[k].numpy(), psin, rtol=1e-10, atol=1e-10)
    # sequential conjugacy
    xa, xb = x[:9], x[9:]
    one = lambda z: sufficient_statistics(torch.as_tensor(z), torch.ones(z.shape[0], 1, dtype=F64))  # noqa: E731
    pa = niw_posterior(prior, *one(xa))
    pa = NIWPrior(pa.mean[0], pa.kappa[0], pa.dof[0], pa.scale[0])
    pab = niw_posterior(pa, *one(xb))
    pall = niw_posterior(prior, *one(x))
    for f in ("mean", "kappa", "dof", "scale"):
        torch.testing.assert_close(getattr(pab, f), getattr(pall, f), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("d", [1, 2, 3, 4])
def test_niw_evidence_is_a_chain_of_student_t_predictives_and_permutation_invariant(d: int) -> None:
    """niw_log_marginal_likelihood equals the chain rule of one-step Student-t predictives (scipy
    multivariate_t), for a prior with non-zero mean, kappa0 = 2.3 and non-diagonal Psi0 (d = 4 takes the
    generic log-determinant path); it is invariant to permuting the points; and c(n) of
    niw_log_marginal_normalizer equals evidence + nu_n / 2 log|Psi_n| with Psi_n from Murphy's formulas."""
    rng = np.random.default_rng(20 + d)
    m0, k0, nu0, psi0 = rng.normal(size=d), 2.3, d + 0.7, _spd(rng, d)
    prior = _prior(m0, k0, nu0, psi0)
    for n in (1, 2, 7):
        x = rng.normal(size=(n, d)) * 1.3 - 0.4
        ref = _student_t_chain(m0, k0, nu0, psi0, x)
        assert _evidence(prior, x) == pytest.approx(ref, rel=1e-10, abs=1e-10)
        assert _evidence(prior, x[rng.permutation(n)]) == pytest.approx(ref, rel=1e-10, abs=1e-10)
        _, _, nun, psin = _murphy_posterior(m0, k0, nu0, psi0, x)
        c_ref = ref + 0.5 * nun * np.linalg.slogdet(psin)[1]
        c_got = float(niw_log_marginal_normalizer(prior, torch.tensor(float(n), dtype=F64)))
        assert c_got == pytest.approx(c_ref, rel=1e-10, abs=1e-10)


def test_niw_evidence_ratio_is_the_student_t_predictive() -> None:
    """p(x_1..n+1) / p(x_1..n) under NIW is the Student-t posterior predictive at x_{n+1} (Murphy 2007, eq. 258)
    with the posterior parameters from Murphy's closed form (not the chain)."""
    rng = np.random.default_rng(3)
    d = 3
    m0, k0, nu0, psi0 = rng.normal(size=d), 0.6, d + 2.0, _spd(rng, d)
    prior = _prior(m0, k0, nu0, psi0)
    x = rng.normal(size=(6, d))
    xn = rng.normal(size=d) * 2
    mn, kn, nun, psin = _murphy_posterior(m0, k0, nu0, psi0, x)
    dof = nun - d + 1
    ref = scipy.stats.multivariate_t(loc=mn, shape=psin * (kn + 1) / (kn * dof), df=dof).logpdf(xn)
    got = _evidence(prior, np.vstack([x, xn])) - _evidence(prior, x)
    assert got == pytest.approx(ref, rel=1e-10)


def test_inverse_wishart_and_niw_densities_match_scipy_in_three_dimensions() -> None:
    """inverse_wishart_log_density equals scipy.stats.invwishart.logpdf and niw_log_density equals it plus
    scipy's N(mu; m, Sigma / kappa) log density, for d = 3, kappa = 2.5, non-diagonal Psi and a batch of
    (mu, Sigma) with one prior broadcast over it."""
    rng = np.random.default_rng(4)
    d, kappa, nu = 3, 2.5, 6.5
    psi, m = _spd(rng, d), rng.normal(size=d)
    prior = _prior(m, kappa, nu, psi)
    sig = np.stack([_spd(rng, d) for _ in range(4)])
    mu = rng.normal(size=(4, d))
    iw = inverse_wishart_log_density(torch.as_tensor(sig), prior.dof, prior.scale).numpy()
    niw = niw_log_density(torch.as_tensor(mu), torch.as_tensor(sig), prior).numpy()
    for b in range(4):
        ref_iw = scipy.stats.invwishart(df=nu, scale=psi).logpdf(sig[b])
        ref_n = scipy.stats.multivariate_normal(m, sig[b] / kappa).logpdf(mu[b])
        assert iw[b] == pytest.approx(ref_iw, rel=1e-10)
        assert niw[b] == pytest.approx(ref_iw + ref_n, rel=1e-10)


def test_niw_prior_from_data_expected_covariance() -> None:
    """The prior's expected covariance Psi0 / (nu0 - d - 1) is covariance_scale times the diagonal of the unbiased
    data covariance, nu0 = d + 1 + extra_dof, m0 the data mean, kappa0 the pseudo count (numpy reference)."""
    rng = np.random.default_rng(5)
    x = rng.normal(size=(50, 3)) * [1.0, 3.0, 0.2] + 4.0
    p = niw_prior_from_data(torch.as_tensor(x), covariance_scale=0.3, mean_pseudo_count=0.2, extra_dof=1.5)
    d = 3
    assert float(p.dof) == pytest.approx(d + 1 + 1.5)
    np.testing.assert_allclose((p.scale / (p.dof - d - 1)).numpy(), np.diag(0.3 * x.var(0, ddof=1)), rtol=1e-12)
    np.testing.assert_allclose(p.mean.numpy(), x.mean(0), rtol=1e-12)
    assert float(p.kappa) == pytest.approx(0.2)


# ------------------------------------------------------------------------------------------- samplers
def _assert_5sigma(samples: np.ndarray, want: np.ndarray, what: str) -> None:
    """Sample mean over axis 0 within 5 standard errors (plus 1e-12) of the exact expectation, elementwise."""
    n = samples.shape[0]
    mean = samples.mean(0)
    se = samples.std(0, ddof=1) / math.sqrt(n)
    bad = np.abs(mean - want) > 5 * se + 1e-12
    assert not bad.any(), f"{what}: mean {mean} want {want} se {se}"


def test_sample_niw_moments_within_five_sigma() -> None:
    """Draws of sample_niw for two different NIW parameter sets in one batch: E[Sigma] = Psi / (nu - d - 1),
    E[Sigma^-1] = nu Psi^-1 (Wishart mean of the precision), E[mu] = m and E[kappa (mu - m)(mu - m)^T] =
    E[Sigma], each within 5 Monte Carlo standard errors (closed forms: Murphy 2007 / Gelman et al. BDA)."""
    rng = np.random.default_rng(6)
    d, n = 3, 30000
    psis = np.stack([_spd(rng, d), _spd(rng, d)])
    ms = rng.normal(size=(2, d))
    kappas, nus = np.array([0.5, 3.0]), np.array([d + 4.5, d + 9.0])
    idx = np.tile([0, 1], n)
    params = NIWPrior(torch.as_tensor(ms[idx]), torch.as_tensor(kappas[idx]), torch.as_tensor(nus[idx]),
                      torch.as_tensor(psis[idx]))  # fmt: skip
    mu, S = sample_niw(params, torch.Generator().manual_seed(11))
    mu, S = mu.numpy(), S.numpy()
    for b in range(2):
        sel = idx == b
        Sb = S[sel].reshape(-1, d * d)
        ES = psis[b] / (nus[b] - d - 1)
        _assert_5sigma(Sb, ES.reshape(-1), f"E[Sigma] {b}")
        _assert_5sigma(np.linalg.inv(S[sel]).reshape(-1, d * d), (nus[b] * np.linalg.inv(psis[b])).reshape(-1),
                       f"E[Sigma^-1] {b}")  # fmt: skip
        r = mu[sel] - ms[b]
        _assert_5sigma(r, np.zeros(d), f"E[mu] {b}")
        _assert_5sigma(kappas[b] * (r[:, :, None] * r[:, None, :]).reshape(-1, d * d), ES.reshape(-1),
                       f"kappa Cov(mu) {b}")  # fmt: skip


def test_sample_gamma_moments_within_five_sigma() -> None:
    """sample_gamma(a) has E[g] = a, E[g^2] = a (a + 1) and E[log g] = digamma(a) (scipy), within 5 Monte
    Carlo standard errors, for shapes below 1 (boosted branch), at 1 and above."""
    shapes = np.array([0.05, 0.3, 0.8, 1.0, 2.5, 30.0])
    n = 40000
    g = sample_gamma(torch.as_tensor(shapes).repeat(n, 1), torch.Generator().manual_seed(12)).numpy()
    _assert_5sigma(g, shapes, "mean")
    _assert_5sigma(g * g, shapes * (shapes + 1), "second moment")
    _assert_5sigma(np.log(g), scipy.special.digamma(shapes), "E log")


# ------------------------------------------------------------------------------------------- ddCRP (PC-GMM)
def _ddcrp_enumeration(y: np.ndarray, W: np.ndarray, prior: NIWPrior) -> dict[tuple[int, ...], float]:
    """Posterior over partitions of the ddCRP-NIW model by summing prod_i W[i, c_i] prod_T p(y_T) over all M^M
    link graphs, with p(y_T) from the Student-t chain (independent of the library's marginal)."""
    M = y.shape[0]
    m0, k0, nu0, psi0 = (prior.mean.numpy(), float(prior.kappa), float(prior.dof), prior.scale.numpy())
    cache: dict[tuple[int, ...], float] = {}
    post: Counter[tuple[int, ...]] = Counter()
    for links in itertools.product(range(M), repeat=M):
        w = math.prod(W[i, links[i]] for i in range(M))
        if w == 0:
            continue
        _, lab = connected_components(coo_matrix((np.ones(M), (np.arange(M), links)), shape=(M, M)), directed=False)
        key = _key(lab)
        lik = 0.0
        for k in range(lab.max() + 1):
            members = tuple(np.flatnonzero(lab == k))
            if members not in cache:
                cache[members] = _student_t_chain(m0, k0, nu0, psi0, y[list(members)])
            lik += cache[members]
        post[key] += w * math.exp(lik)
    total = sum(post.values())
    return {k: v / total for k, v in post.items()}


def _key(labels: np.ndarray) -> tuple[int, ...]:
    first: dict[int, int] = {}
    return tuple(first.setdefault(int(v), len(first)) for v in labels)


@pytest.mark.parametrize("d", [1, 3])
def test_ddcrp_gibbs_stationary_partitions_match_enumeration(d: int) -> None:
    """Partition frequencies of the collapsed Gibbs chain (after 200 burn-in sweeps) match the exact ddCRP-NIW
    posterior from enumerating all 4^4 link graphs with Student-t-chain marginals, in d = 1 and d = 3 (the
    sampler's written-out determinants), with asymmetric weights, a non-unit self weight and one forbidden
    link; total variation < 0.035. Relabelling the points (permuting y and W together) permutes the posterior."""
    rng = np.random.default_rng(30 + d)
    M = 4
    y = rng.normal(size=(M, d))
    y[:2] += 1.2
    W = rng.uniform(0.1, 1.5, size=(M, M))
    np.fill_diagonal(W, 0.6)
    W[2, 0] = 0.0
    prior = _prior(np.zeros(d), 0.4, d + 1.5, 0.7 * np.eye(d))
    exact = _ddcrp_enumeration(y, W, prior)
    assert len(exact) >= 10 and max(exact.values()) < 0.6
    trace: list[np.ndarray] = []
    _ddcrp_gibbs(y, W, prior, 9000, torch.Generator().manual_seed(d), trace=trace)
    emp = Counter(_key(t) for t in trace[200:])
    tot = sum(emp.values())
    tv = 0.5 * sum(abs(exact.get(k, 0.0) - emp[k] / tot) for k in set(exact) | set(emp))
    assert tv < 0.035, tv
    # relabelling invariance of the reference itself (sanity of the enumeration)
    perm = np.array([2, 0, 3, 1])
    exact_p = _ddcrp_enumeration(y[perm], W[np.ix_(perm, perm)], prior)
    for k, v in exact.items():
        lab = np.asarray(k)[perm]
        assert exact_p[_key(lab)] == pytest.approx(v, rel=1e-9)


def test_prior_weights_against_a_loop() -> None:
    """prior_weights equals exp(-||x_i - x_j|| / l) (1 + cos(v_i, v_j)) off the diagonal (cos = 0 for a zero
    velocity) and alpha on it, computed point by point in numpy."""
    rng = np.random.default_rng(8)
    x = rng.normal(size=(6, 2)) * 2
    v = rng.normal(size=(6, 2))
    v[3] = -v[1]
    v[4] = 0.0
    ls, alpha = 0.7, 2.5
    W = prior_weights(torch.as_tensor(x), torch.as_tensor(v), ls, alpha).numpy()
    for i, j in itertools.product(range(6), repeat=2):
        if i == j:
            want = alpha
        else:
            ni, nj = np.linalg.norm(v[i]), np.linalg.norm(v[j])
            cos = 0.0 if ni == 0 or nj == 0 else v[i] @ v[j] / (ni * nj)
            want = math.exp(-np.linalg.norm(x[i] - x[j]) / ls) * (1 + cos)
        assert W[i, j] == pytest.approx(want, rel=1e-12, abs=1e-15)


# ------------------------------------------------------------------------------------------- DAMM scores
def _damm_model(d: int, alpha: float, kappa: float) -> _Model:
    return _Model(alpha, kappa, _prior(np.zeros(d), 0.8, d + 3.0, 1.5 * np.eye(d)))


def _vmf_marginal(u: np.ndarray, kappa: float, d: int) -> float:
    """log int prod_i C_d(kappa) exp(kappa m . u_i) dm / area(S^{d-1}) = n log C_d(kappa) + log C_d(0)
    - log C_d(kappa |R|), with C_d from scipy's Bessel function: C_d(k) = k^(d/2-1) / ((2 pi)^(d/2) I_{d/2-1}(k))."""
    def log_c(k: float) -> float:
        if k == 0:
            return -(math.log(2) + d / 2 * math.log(math.pi) - scipy.special.gammaln(d / 2))
        nu = d / 2 - 1
        return nu * math.log(k) - d / 2 * math.log(2 * math.pi) - (math.log(scipy.special.ive(nu, k)) + k)

    if u.shape[0] == 0:
        return 0.0
    return u.shape[0] * log_c(kappa) + log_c(0.0) - log_c(kappa * np.linalg.norm(u.sum(0)))


@pytest.mark.parametrize("d", [2, 3])
def test_vmf_log_normalizer_closed_forms(d: int) -> None:
    """log C_2(k) = -log(2 pi I_0(k)) and log C_3(k) = log(k / (4 pi sinh k)) (scipy / math), and C_d(0) is the
    inverse sphere area."""
    for k in (1e-6, 0.3, 2.0, 40.0, 600.0):
        got = float(vmf_log_normalizer(torch.tensor([k], dtype=F64), d)[0])
        if d == 2:
            want = -math.log(2 * math.pi * scipy.special.i0(k)) if k < 500 else -math.log(2 * math.pi) - (
                math.log(scipy.special.i0e(k)) + k)
        else:
            want = math.log(k / (4 * math.pi * math.sinh(k)))
        assert got == pytest.approx(want, rel=1e-9, abs=1e-9)
    area = 2 * math.pi if d == 2 else 4 * math.pi
    assert float(vmf_log_normalizer(torch.tensor([0.0], dtype=F64), d)[0]) == pytest.approx(-math.log(area))


def test_damm_merge_probability_is_the_inverse_chang_fisher_ratio() -> None:
    """The merge move's Hastings ratio is the inverse of Chang & Fisher's (2013) split ratio,
    H_merge = 1 / (alpha Gamma(n_a) Gamma(n_b) / Gamma(n) p(Y_a) p(Y_b) / p(Y)), p the NIW (Student-t chain) times
    vMF (scipy Bessel) marginal: two groups merge with probability min(1, H_merge), estimated over 400 seeds
    within 5 binomial sigma of the closed form."""
    d, alpha, kappa = 2, 0.9, 2.0
    model = _damm_model(d, alpha, kappa)
    rng = np.random.default_rng(9)
    y = rng.normal(size=(7, d)) * 0.8
    lab = np.array([0, 0, 0, 1, 1, 1, 1])
    y[lab == 1] += 2.5
    v = rng.normal(size=(7, d)) + [0.4, 0.2]
    u = v / np.linalg.norm(v, axis=-1, keepdims=True)
    p = model.prior
    ml = lambda s: (_student_t_chain(p.mean.numpy(), float(p.kappa), float(p.dof), p.scale.numpy(), y[s])  # noqa: E731
                    + _vmf_marginal(u[s], kappa, d))
    a, b = lab == 0, lab == 1
    log_h_merge = -(math.log(alpha) + math.lgamma(3) + math.lgamma(4) - math.lgamma(7) + ml(a) + ml(b)
                    - ml(np.ones(7, bool)))
    p_merge = min(1.0, math.exp(log_h_merge))
    assert 0.05 < p_merge < 0.95, p_merge  # the estimate below is informative
    feats = _Stats.features(torch.as_tensor(y), torch.as_tensor(u), torch.ones(7, dtype=torch.bool))
    z = torch.as_tensor(lab)
    st = _Stats.of(feats, z, 2, d)
    n_trials = 400
    merged = sum(_merge_moves(model, z, st, torch.Generator().manual_seed(s))[1] == 1 for s in range(n_trials))
    se = math.sqrt(p_merge * (1 - p_merge) / n_trials)
    assert abs(merged / n_trials - p_merge) < 5 * se, (merged / n_trials, p_merge)


def _principal_halves(z: np.ndarray) -> np.ndarray:
    """Sides of the hyperplane through the mean of the rows of z, normal to their principal axis (numpy eigh)."""
    c = z - z.mean(0)
    axis = np.linalg.eigh(c.T @ c / z.shape[0])[1][:, -1]
    return c @ axis > 0


def test_damm_split_probability_is_the_chang_fisher_ratio_of_the_better_proposal() -> None:
    """From one component, the split move proposes the halves across the principal axis of the positions and of
    the directions (numpy eigh), keeps the one with the larger Chang & Fisher (2013) ratio
    H = alpha Gamma(n_a) Gamma(n_b) / Gamma(n) p(Y_a) p(Y_b) / p(Y) (Student-t chain x scipy-Bessel vMF marginals)
    and accepts it with probability min(1, H): over 400 seeds the split frequency is within 5 binomial sigma
    of that probability, and every accepted split is that partition. alpha = 0.4 so that log alpha matters."""
    d, alpha, kappa = 2, 0.4, 2.0
    model = _damm_model(d, alpha, kappa)
    rng = np.random.default_rng(21)
    y = rng.normal(size=(8, d)) * 0.8
    y[4:] += [3.0, 0.0]
    v = rng.normal(size=(8, d)) + [0.4, 0.2]
    u = v / np.linalg.norm(v, axis=-1, keepdims=True)
    p = model.prior
    ml = lambda s: (_student_t_chain(p.mean.numpy(), float(p.kappa), float(p.dof), p.scale.numpy(), y[s])  # noqa: E731
                    + _vmf_marginal(u[s], kappa, d))
    best, best_side = -math.inf, None
    for side in (_principal_halves(y), _principal_halves(u)):
        na, nb = int(side.sum()), int((~side).sum())
        h = (math.log(alpha) + math.lgamma(na) + math.lgamma(nb) - math.lgamma(8) + ml(side) + ml(~side)
             - ml(np.ones(8, bool)))
        if h > best:
            best, best_side = h, side
    p_split = min(1.0, math.exp(best))
    assert 0.05 < p_split < 0.95, p_split
    yt, ut = torch.as_tensor(y), torch.as_tensor(u)
    feats = _Stats.features(yt, ut, torch.ones(8, dtype=torch.bool))
    z0 = torch.zeros(8, dtype=torch.long)
    st = _Stats.of(feats, z0, 1, d)
    n_trials, n_split = 400, 0
    for s in range(n_trials):
        z, K = _split_moves(model, feats, yt, ut, z0, st, torch.Generator().manual_seed(s))
        if K > 1:
            n_split += 1
            assert _key(z.numpy()) == _key(best_side.astype(int))
    se = math.sqrt(p_split * (1 - p_split) / n_trials)
    assert abs(n_split / n_trials - p_split) < 5 * se, (n_split / n_trials, p_split)


def test_damm_log_posterior_is_crp_plus_marginals_up_to_a_constant() -> None:
    """_Model.log_posterior(partition) - sum_T [log p(Y_T)] equals K log alpha + sum_T lgamma(n_T) plus a constant
    (the CRP's Ewens probability alpha^K prod Gamma(n_T) Gamma(alpha) / Gamma(alpha + N)), with the marginals
    from the Student-t chain and the scipy-Bessel vMF marginal."""
    d, alpha, kappa = 3, 1.7, 4.0
    model = _damm_model(d, alpha, kappa)
    rng = np.random.default_rng(12)
    y = rng.normal(size=(6, d))
    v = rng.normal(size=(6, d))
    u = v / np.linalg.norm(v, axis=-1, keepdims=True)
    feats = _Stats.features(torch.as_tensor(y), torch.as_tensor(u), torch.ones(6, dtype=torch.bool))
    p = model.prior
    diffs = []
    for part in ([0] * 6, [0, 0, 1, 1, 2, 2], [0, 1, 2, 3, 4, 5], [0, 1, 1, 1, 1, 0]):
        lab = np.asarray(part)
        K = lab.max() + 1
        got = float(model.log_posterior(_Stats.of(feats, torch.as_tensor(lab), int(K), d)))
        ref = K * math.log(alpha)
        for k in range(K):
            s = lab == k
            ref += math.lgamma(s.sum()) + _vmf_marginal(u[s], kappa, d)
            ref += _student_t_chain(p.mean.numpy(), float(p.kappa), float(p.dof), p.scale.numpy(), y[s])
        diffs.append(got - ref)
    np.testing.assert_allclose(diffs, diffs[0], rtol=0, atol=1e-9)


def test_damm_split_moves_are_label_permutation_equivariant() -> None:
    """Relabelling the components of the current state (same partition, different ids) does not change which
    points a split move separates under the same generator seed (as a partition)."""
    d = 2
    model = _damm_model(d, 1.0, 5.0)
    g = torch.Generator().manual_seed(3)
    y = torch.cat([0.1 * torch.randn(40, d, generator=g, dtype=F64) + c for c in (-1.0, 1.0)])
    y = torch.cat([y, 0.1 * torch.randn(30, d, generator=g, dtype=F64) + torch.tensor([5.0, 0.0], dtype=F64)])
    v = torch.tensor([1.0, 0.3], dtype=F64) + 0.05 * torch.randn(110, d, generator=g, dtype=F64)
    u = v / v.norm(dim=-1, keepdim=True)
    feats = _Stats.features(y, u, torch.ones(110, dtype=torch.bool))
    z = torch.cat([torch.zeros(80, dtype=torch.long), torch.ones(30, dtype=torch.long)])
    out = []
    for zz in (z, 1 - z):
        zn, K = _split_moves(model, feats, y, u, zz, _Stats.of(feats, zz, 2, d), torch.Generator().manual_seed(0))
        out.append(_key(zn.numpy()))
    assert out[0] == out[1]
    assert len(set(out[0])) == 3  # the two blobs of component 0 were split, component 1 kept


# ------------------------------------------------------------------------------------------- post-processing
def test_merge_small_components_threshold_and_relabelling_invariance() -> None:
    """A cluster of exactly min_size points is kept and one of min_size - 1 is merged into the cluster with the
    nearest mean (numpy reference); the resulting partition does not depend on the label ids."""
    rng = np.random.default_rng(13)
    centres = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [9.0, 1.0]])
    sizes = [6, 5, 4, 2]
    lab = np.repeat(np.arange(4), sizes)
    x = centres[lab] + 0.1 * rng.normal(size=(lab.size, 2))
    out = merge_small_components(torch.as_tensor(x), torch.as_tensor(lab), 4).numpy()
    assert _key(out) == _key(np.where(lab == 3, 1, lab))
    for perm in ([3, 2, 1, 0], [1, 3, 0, 2]):
        lab_p = np.asarray(perm)[lab]
        out_p = merge_small_components(torch.as_tensor(x), torch.as_tensor(lab_p), 4).numpy()
        assert _key(out_p) == _key(out)
    # min_size 5: the 4-point cluster is merged as well, into the nearest mean of the kept clusters (0 or 1)
    out5 = merge_small_components(torch.as_tensor(x), torch.as_tensor(lab), 5).numpy()
    means = np.stack([x[lab == k].mean(0) for k in (0, 1)])
    want = lab.copy()
    for i in np.flatnonzero(lab >= 2):
        want[i] = int(np.argmin(np.linalg.norm(means - x[i], axis=1)))
    assert _key(out5) == _key(want)


def test_regularize_covariances_and_order_by_attractor_against_numpy() -> None:
    """regularize_covariances floors eigenvalues at max(ratio * lambda_max, min_eig) keeping eigenvectors (numpy
    eigh reference); order_by_attractor sorts components by increasing ||mu_k - g||."""
    rng = np.random.default_rng(14)
    d, K = 3, 4
    Q = np.stack([np.linalg.qr(rng.normal(size=(d, d)))[0] for _ in range(K)])
    lam = np.array([[1e-4, 0.5, 2.0], [1.0, 1.1, 1.2], [1e-6, 1e-5, 3.0], [0.02, 0.3, 0.9]])
    cov = Q @ (lam[:, :, None] * np.swapaxes(Q, 1, 2))
    means = rng.normal(size=(K, d)) * 3
    gmm = GMM(torch.full((K,), 1.0 / K, dtype=F64), torch.as_tensor(means), torch.as_tensor(cov))
    out = regularize_covariances(gmm, 0.05, min_eig=0.03).covariances.numpy()
    floor = np.maximum(0.05 * lam[:, -1:], 0.03)
    want = Q @ (np.maximum(lam, floor)[:, :, None] * np.swapaxes(Q, 1, 2))
    np.testing.assert_allclose(out, want, rtol=1e-9, atol=1e-12)
    g = rng.normal(size=d)
    ordered = order_by_attractor(gmm, torch.as_tensor(g))
    np.testing.assert_allclose(ordered.means.numpy(), means[np.argsort(np.linalg.norm(means - g, axis=1))])


# ------------------------------------------------------------------------------------------- documented priors
def test_pcgmm_and_damm_build_the_documented_niw_prior(monkeypatch: pytest.MonkeyPatch) -> None:
    """Both fitters run on standardised positions (centred, overall RMS std 1) under NIW(0, kappa0, d + nu0_offset,
    (nu0 - d - 1) psi_scale^2 I), i.e. a prior mean cluster covariance psi_scale^2 I (module docstrings); the
    prior is captured where the samplers receive it and checked against those formulas."""
    import lfd_torch.gmm.damm as damm_mod
    import lfd_torch.gmm.pcgmm as pcgmm_mod

    seen: dict[str, tuple] = {}
    real_gibbs, real_model = pcgmm_mod._ddcrp_gibbs, damm_mod._Model

    def gibbs(y, weights, prior, n_iter, generator, trace=None):  # type: ignore[no-untyped-def]
        seen["pcgmm"] = (y, prior)
        return real_gibbs(y, weights, prior, n_iter, generator, trace)

    class Model(real_model):  # type: ignore[misc, valid-type]
        def __init__(self, alpha: float, kappa: float, prior: NIWPrior) -> None:
            seen["damm"] = (None, prior)
            super().__init__(alpha, kappa, prior)

    monkeypatch.setattr(pcgmm_mod, "_ddcrp_gibbs", gibbs)
    monkeypatch.setattr(damm_mod, "_Model", Model)
    rng = np.random.default_rng(15)
    x = torch.as_tensor(rng.normal(size=(40, 3)) * [3.0, 1.0, 0.5] + 7.0)
    v = torch.as_tensor(rng.normal(size=(40, 3)))
    kw = dict(kappa0=0.3, nu0_offset=4.5, psi_scale=0.7, n_iter=1)
    pcgmm_mod.pcgmm_labels(x, v, generator=torch.Generator().manual_seed(0), max_points=None, **kw)
    damm_mod.damm_labels(x, v, generator=torch.Generator().manual_seed(0), **kw)
    d = 3
    for name in ("pcgmm", "damm"):
        y, prior = seen[name]
        np.testing.assert_allclose(prior.mean.numpy(), np.zeros(d), atol=0)
        assert float(prior.kappa) == pytest.approx(0.3)
        assert float(prior.dof) == pytest.approx(d + 4.5)
        np.testing.assert_allclose((prior.scale / (prior.dof - d - 1)).numpy(), 0.49 * np.eye(d), rtol=1e-12)
    y = np.asarray(seen["pcgmm"][0])
    np.testing.assert_allclose(y.mean(0), 0.0, atol=1e-12)
    assert float(np.sqrt(y.var(0).mean())) == pytest.approx(1.0, rel=1e-12)


def test_damm_mixing_weights_are_dirichlet_of_the_counts() -> None:
    """Step 1 of the DAMM sampler draws pi ~ Dirichlet(n_1..n_K) (module docstring): for counts (1, 3, 6) the
    Monte Carlo means of pi_k over 1500 draws are within 5 sigma of n_k / N, and of pi_k^2 within 5 sigma of
    n_k (n_k + 1) / (N (N + 1))."""
    d = 2
    model = _damm_model(d, 1.0, 5.0)
    rng = np.random.default_rng(16)
    y = torch.as_tensor(rng.normal(size=(10, d)))
    v = rng.normal(size=(10, d))
    u = torch.as_tensor(v / np.linalg.norm(v, axis=-1, keepdims=True))
    lab = torch.as_tensor(np.repeat([0, 1, 2], [1, 3, 6]))
    st = _Stats.of(_Stats.features(y, u, torch.ones(10, dtype=torch.bool)), lab, 3, d)
    g = torch.Generator().manual_seed(17)
    pis = np.stack([np.exp(_sample_parameters(model, st, g)[0].numpy()) for _ in range(1500)])
    n = np.array([1.0, 3.0, 6.0])
    _assert_5sigma(pis, n / 10, "E[pi]")
    _assert_5sigma(pis**2, n * (n + 1) / 110, "E[pi^2]")


def test_damm_merge_moves_take_the_best_pair_and_each_component_once() -> None:
    """Merge moves are accepted greedily, best Chang & Fisher ratio first, each component in at most one merge
    (module docstring): three overlapping groups whose pairwise H_merge (Student-t chain x scipy-Bessel vMF
    marginals) are all >> 1 end as exactly two clusters, the top-scoring pair merged, for every seed."""
    d, alpha, kappa = 2, 1.0, 2.0
    model = _damm_model(d, alpha, kappa)
    rng = np.random.default_rng(22)
    lab = np.repeat([0, 1, 2], 12)
    y = 0.3 * rng.normal(size=(36, d)) + np.array([[0.0, 0.0], [0.25, 0.0], [0.08, 0.0]])[lab]
    v = rng.normal(size=(36, d)) * 0.2 + [1.0, 0.0]
    u = v / np.linalg.norm(v, axis=-1, keepdims=True)
    p = model.prior
    ml = lambda s: (_student_t_chain(p.mean.numpy(), float(p.kappa), float(p.dof), p.scale.numpy(), y[s])  # noqa: E731
                    + _vmf_marginal(u[s], kappa, d))
    log_h = {}
    for a, b in ((0, 1), (0, 2), (1, 2)):
        sa, sb = lab == a, lab == b
        log_h[(a, b)] = -(math.log(alpha) + 2 * math.lgamma(12) - math.lgamma(24) + ml(sa) + ml(sb) - ml(sa | sb))
    assert min(log_h.values()) > 3.0, log_h  # every pair is accepted (probability > 0.95 each)
    best = max(log_h, key=log_h.get)
    want = np.where(lab == best[1], best[0], lab)
    feats = _Stats.features(torch.as_tensor(y), torch.as_tensor(u), torch.ones(36, dtype=torch.bool))
    z = torch.as_tensor(lab)
    st = _Stats.of(feats, z, 3, d)
    for s in range(20):
        zn, K = _merge_moves(model, z, st, torch.Generator().manual_seed(s))
        assert K == 2 and _key(zn.numpy()) == _key(want), (s, K, log_h)
