"""GMM dataclass, EM / EM+BIC, post-processing and the config fitters of lfd_torch.gmm."""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import requires_cuda
from lfd_torch.errors import InvalidArgumentError, LfdError, NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.gmm import (
    GMM,
    DAMMFitter,
    EMBICFitter,
    EMFitter,
    InvalidGMMError,
    NIWPrior,
    PCGMMFitter,
    bic,
    fit_em,
    fit_em_bic,
    gaussian_log_density,
    inverse_wishart_log_density,
    kmeans_plus_plus,
    merge_small_components,
    n_parameters,
    niw_log_density,
    niw_log_marginal_likelihood,
    niw_posterior,
    niw_prior_from_data,
    order_by_attractor,
    refine_em,
    regularize_covariances,
    sample_gamma,
    sample_niw,
    sufficient_statistics,
)

F64 = torch.float64
CONF = Path(__file__).resolve().parents[1] / "conf"


def random_gmm(K: int, d: int, generator: torch.Generator, dtype: torch.dtype = F64) -> GMM:
    w = torch.rand(K, generator=generator, dtype=dtype) + 0.1
    mu = 3 * torch.randn(K, d, generator=generator, dtype=dtype)
    A = torch.randn(K, d, d, generator=generator, dtype=dtype)
    cov = A @ A.transpose(-2, -1) + 0.5 * torch.eye(d, dtype=dtype)
    return GMM(w / w.sum(), mu, cov)


def blobs(
    centers: list[list[float]], n: int, std: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    c = torch.tensor(centers, dtype=F64)
    lab = torch.arange(len(centers)).repeat_interleave(n)
    return c[lab] + std * torch.randn(lab.shape[0], c.shape[1], generator=generator, dtype=F64), lab


# ---------------------------------------------------------------------------------------------- densities
@pytest.mark.parametrize("d", [1, 2, 3])
def test_log_prob_matches_scipy_mixture(generator: torch.Generator, d: int) -> None:
    gmm = random_gmm(4, d, generator)
    x = 3 * torch.randn(5, 7, d, generator=generator, dtype=F64)
    comps = np.stack(
        [
            float(gmm.weights[k]) * scipy.stats.multivariate_normal(gmm.means[k].numpy(), gmm.covariances[k].numpy())
            .pdf(x.reshape(-1, d).numpy()).reshape(-1)
            for k in range(4)
        ],
        axis=-1,
    )  # fmt: skip
    ref = np.log(comps.sum(-1)).reshape(5, 7)
    torch.testing.assert_close(gmm.log_prob(x), torch.as_tensor(ref), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(
        gmm.log_prob_components(x).reshape(-1, 4), torch.as_tensor(np.log(comps)), rtol=1e-10, atol=1e-10
    )
    assert gmm.log_prob(x).shape == (5, 7)


def test_posterior_sums_to_one_and_equals_naive_loop(generator: torch.Generator) -> None:
    gmm = random_gmm(3, 2, generator)
    x = 4 * torch.randn(50, 2, generator=generator, dtype=F64)
    gamma = gmm.posterior(x)
    torch.testing.assert_close(gamma.sum(-1), torch.ones(50, dtype=F64))
    naive = torch.zeros(50, 3, dtype=F64)
    for n in range(50):
        dens = []
        for k in range(3):
            diff = x[n] - gmm.means[k]
            S = gmm.covariances[k]
            q = diff @ torch.linalg.solve(S, diff)
            norm = math.sqrt(float(torch.det(2 * math.pi * S)))
            dens.append(float(gmm.weights[k]) * math.exp(-0.5 * float(q)) / norm)
        for k in range(3):
            naive[n, k] = dens[k] / sum(dens)
    torch.testing.assert_close(gamma, naive, rtol=1e-10, atol=1e-12)


def test_posterior_stays_normalised_far_from_data(generator: torch.Generator) -> None:
    gmm = random_gmm(3, 2, generator)
    x = torch.tensor([[1e4, -1e4], [1e6, 1e6]], dtype=F64)
    gamma = gmm.posterior(x)
    assert torch.isfinite(gamma).all()
    torch.testing.assert_close(gamma.sum(-1), torch.ones(2, dtype=F64))
    assert (gmm.log_prob(x) < -1e3).all()


def test_sample_moments_monte_carlo(generator: torch.Generator) -> None:
    gmm = random_gmm(2, 2, generator)
    x, labels = gmm.sample(200_000, generator=generator)
    mean = (gmm.weights[:, None] * gmm.means).sum(0)
    second = (gmm.weights[:, None, None] * (gmm.covariances + gmm.means[:, :, None] * gmm.means[:, None, :])).sum(0)
    cov = second - torch.outer(mean, mean)
    scale = float(torch.linalg.eigvalsh(cov).max().sqrt())
    torch.testing.assert_close(x.mean(0), mean, atol=0.02 * scale, rtol=0)
    torch.testing.assert_close(torch.cov(x.T), cov, atol=0.03 * scale**2, rtol=0)
    freq = torch.bincount(labels, minlength=2).to(F64) / labels.numel()
    torch.testing.assert_close(freq, gmm.weights, atol=0.005, rtol=0)


def test_from_labels_is_the_ml_fit_of_each_group(generator: torch.Generator) -> None:
    x = torch.randn(30, 2, generator=generator, dtype=F64)
    labels = torch.tensor([5, 9] * 15)
    gmm = GMM.from_labels(x, labels, reg_covar=0.0)
    for k, lab in enumerate([5, 9]):
        part = x[labels == lab]
        torch.testing.assert_close(gmm.means[k], part.mean(0))
        torch.testing.assert_close(gmm.covariances[k], torch.cov(part.T, correction=0))
    torch.testing.assert_close(gmm.weights, torch.tensor([0.5, 0.5], dtype=F64))


def test_to_and_state_dict_round_trip(generator: torch.Generator) -> None:
    gmm = random_gmm(3, 2, generator)
    g32 = gmm.to(dtype=torch.float32)
    assert g32.dtype == torch.float32 and g32.n_components == 3 and g32.dim == 2 and g32.device.type == "cpu"
    back = GMM.from_state_dict(gmm.state_dict())
    x = torch.randn(10, 2, generator=generator, dtype=F64)
    torch.testing.assert_close(back.log_prob(x), gmm.log_prob(x), rtol=0, atol=0)
    torch.testing.assert_close(g32.log_prob(x.float()), gmm.log_prob(x).float(), rtol=1e-5, atol=1e-5)
    with pytest.raises(ShapeMismatchError):
        GMM.from_state_dict({**gmm.state_dict(), "extra": torch.zeros(1)})
    with pytest.raises(dataclasses.FrozenInstanceError):
        gmm.weights = gmm.weights  # type: ignore[misc]


@requires_cuda
def test_cuda_matches_cpu(generator: torch.Generator) -> None:
    gmm = random_gmm(3, 2, generator)
    x = torch.randn(100, 2, generator=generator, dtype=F64)
    gc = gmm.to(device="cuda")
    torch.testing.assert_close(gc.posterior(x.cuda()).cpu(), gmm.posterior(x))


def test_invalid_parameters_raise_typed_errors() -> None:
    w = torch.tensor([0.5, 0.5], dtype=F64)
    mu = torch.zeros(2, 2, dtype=F64)
    cov = torch.eye(2, dtype=F64).repeat(2, 1, 1)
    GMM(w, mu, cov)  # valid
    with pytest.raises(InvalidGMMError):
        GMM(torch.tensor([1.5, -0.5], dtype=F64), mu, cov)
    with pytest.raises(InvalidGMMError):
        GMM(torch.tensor([0.5, 0.6], dtype=F64), mu, cov)
    bad = cov.clone()
    bad[1] = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)  # indefinite
    with pytest.raises(InvalidGMMError, match="covariance 1"):
        GMM(w, mu, bad)
    asym = cov.clone()
    asym[0, 0, 1] = 0.5
    with pytest.raises(InvalidGMMError, match="symmetric"):
        GMM(w, mu, asym)
    with pytest.raises(NonFiniteError):
        GMM(w, torch.tensor([[0.0, float("nan")], [0.0, 0.0]], dtype=F64), cov)
    with pytest.raises(ShapeMismatchError):
        GMM(w, mu, cov[:, :1, :1])
    with pytest.raises(ShapeMismatchError):
        GMM(w.float(), mu, cov)
    gmm = GMM(w, mu, cov)
    with pytest.raises(ShapeMismatchError):
        gmm.log_prob(torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ShapeMismatchError):
        gmm.log_prob(torch.zeros(4, 2, dtype=torch.float32))
    assert issubclass(InvalidGMMError, LfdError) and issubclass(InvalidGMMError, ValueError)


# ---------------------------------------------------------------------------------------------- EM
@settings(max_examples=15, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), K=st.integers(1, 5), d=st.integers(1, 3),
       reg_covar=st.sampled_from([1e-6, 1.0]))
def test_em_objective_never_decreases(seed: int, K: int, d: int, reg_covar: float) -> None:
    """EM is the exact MAP ascent of the penalised objective: at a large ``reg_covar`` (1.0, where the penalty
    0.5 rho tr(Sigma^-1) and the M-step's (S + rho I) / n_k matter) as at the default."""
    g = torch.Generator().manual_seed(seed)
    x = torch.cat([torch.randn(40, d, generator=g, dtype=F64) * (1 + k) + 3 * k for k in range(3)])
    init = fit_em(x, K, generator=g, max_iter=0, reg_covar=reg_covar)  # k-means++ start, no EM step
    gmm, hist = refine_em(x, init, max_iter=60, tol=0.0, reg_covar=reg_covar)
    steps = hist[1:] - hist[:-1]
    assert (steps >= -1e-9 * hist.abs().max()).all(), steps.min()
    assert hist.shape[0] >= 2 and torch.isfinite(hist).all()


def test_em_keeps_the_best_restart() -> None:
    """With n_init restarts the returned fit scores at least as well as each restart alone (the same generator
    draws restart r's k-means++ seeds after r - 1 earlier restarts)."""
    x, _ = blobs([[0, 0], [3, 0], [0, 3], [3, 3]], 30, 1.0, torch.Generator().manual_seed(2))

    def score(gmm) -> float:
        return float(refine_em(x, gmm, max_iter=0)[1][-1])

    g = torch.Generator().manual_seed(3)
    singles = [score(fit_em(x, 4, generator=g, n_init=1)) for _ in range(6)]
    best = score(fit_em(x, 4, generator=torch.Generator().manual_seed(3), n_init=6))
    assert max(singles) - min(singles) > 1e-3  # the restarts differ, so keeping the worst would show
    assert best >= max(singles) - 1e-6 * abs(max(singles)), (best, singles)


def test_em_repeats_exactly_under_the_same_seed() -> None:
    x, _ = blobs([[0, 0], [5, 5], [0, 6]], 80, 1.0, torch.Generator().manual_seed(1))
    a = fit_em(x, 3, generator=torch.Generator().manual_seed(7), n_init=2)
    b = fit_em(x, 3, generator=torch.Generator().manual_seed(7), n_init=2)
    for k in ("weights", "means", "covariances"):
        assert torch.equal(a.state_dict()[k], b.state_dict()[k])


def test_em_recovers_separated_clusters(generator: torch.Generator) -> None:
    centers = [[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]
    x, _ = blobs(centers, 300, 1.0, generator)
    gmm = fit_em(x, 3, generator=generator, n_init=3)
    order = torch.argsort(gmm.means[:, 0] + 2 * gmm.means[:, 1])
    torch.testing.assert_close(gmm.means[order], torch.tensor(centers, dtype=F64)[[0, 1, 2]], atol=0.2, rtol=0)
    for k in range(3):
        torch.testing.assert_close(gmm.covariances[k], torch.eye(2, dtype=F64), atol=0.25, rtol=0)
    torch.testing.assert_close(gmm.weights, torch.full((3,), 1 / 3, dtype=F64), atol=0.02, rtol=0)


@pytest.mark.parametrize("true_k", [1, 3, 4])
def test_bic_picks_the_true_k(true_k: int) -> None:
    centers = [[0.0, 0.0], [12.0, 0.0], [0.0, 12.0], [12.0, 12.0]][:true_k]
    x, _ = blobs(centers, 150, 1.0, torch.Generator().manual_seed(3))
    gmm = fit_em_bic(x, k_range=range(1, 8), generator=torch.Generator().manual_seed(4), n_init=2)
    assert gmm.n_components == true_k


def test_bic_formula(generator: torch.Generator) -> None:
    x, _ = blobs([[0, 0]], 100, 1.0, generator)
    gmm = fit_em(x, 2, generator=generator)
    assert n_parameters(2, 2) == 1 + 4 + 6
    assert bic(gmm, x) == pytest.approx(-2 * float(gmm.log_prob(x).sum()) + 11 * math.log(100))


def test_kmeans_plus_plus_uses_every_label(generator: torch.Generator) -> None:
    x, _ = blobs([[0, 0], [3, 3]], 20, 0.5, generator)
    labels = kmeans_plus_plus(x, 7, generator=generator)
    assert labels.shape == (40,)
    assert set(labels.tolist()) == set(range(7))


def test_em_bad_input_raises_typed_errors(generator: torch.Generator) -> None:
    x = torch.randn(10, 2, generator=generator, dtype=F64)
    with pytest.raises(NonFiniteError):
        fit_em(torch.cat([x, torch.full((1, 2), float("nan"), dtype=F64)]), 2, generator=generator)
    with pytest.raises(TooFewSamplesError):
        fit_em(x[:2], 3, generator=generator)
    with pytest.raises(TooFewSamplesError):
        fit_em(x, 0, generator=generator)
    with pytest.raises(ShapeMismatchError):
        fit_em(x[:, 0], 1, generator=generator)
    with pytest.raises(TooFewSamplesError):
        fit_em_bic(x[:2], k_range=[5, 6], generator=generator)


# ---------------------------------------------------------------------------------------------- post-processing
def test_order_by_attractor(generator: torch.Generator) -> None:
    gmm = random_gmm(5, 2, generator)
    g = torch.tensor([1.0, -2.0], dtype=F64)
    out = order_by_attractor(gmm, g)
    dist = torch.linalg.vector_norm(out.means - g, dim=-1)
    assert (dist[1:] >= dist[:-1]).all()
    x = torch.randn(20, 2, generator=generator, dtype=F64)
    torch.testing.assert_close(out.log_prob(x), gmm.log_prob(x))
    with pytest.raises(ShapeMismatchError):
        order_by_attractor(gmm, torch.zeros(3, dtype=F64))


def test_regularize_covariances_floors_thin_clusters() -> None:
    R = torch.tensor([[math.cos(0.3), -math.sin(0.3)], [math.sin(0.3), math.cos(0.3)]], dtype=F64)
    thin = R @ torch.diag(torch.tensor([100.0, 1e-4], dtype=F64)) @ R.T
    fat = torch.diag(torch.tensor([4.0, 2.0], dtype=F64))
    gmm = GMM(torch.tensor([0.5, 0.5], dtype=F64), torch.zeros(2, 2, dtype=F64), torch.stack([thin, fat]))
    out = regularize_covariances(gmm, min_eig_ratio=1e-2)
    ev, vec = torch.linalg.eigh(out.covariances[0])
    torch.testing.assert_close(ev, torch.tensor([1.0, 100.0], dtype=F64))
    torch.testing.assert_close((vec.T @ R).abs(), torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=F64), atol=1e-10, rtol=0)
    torch.testing.assert_close(out.covariances[1], fat)  # already well conditioned: unchanged
    out_abs = regularize_covariances(gmm, min_eig_ratio=0.0, min_eig=3.0)
    assert float(torch.linalg.eigvalsh(out_abs.covariances[1]).min()) == pytest.approx(3.0)
    with pytest.raises(InvalidGMMError):
        regularize_covariances(gmm, min_eig_ratio=2.0)


def test_merge_small_components() -> None:
    x = torch.tensor([[0.0], [0.1], [0.2], [10.0], [10.1], [10.2], [9.0], [0.5]], dtype=F64)
    labels = torch.tensor([0, 0, 0, 1, 1, 1, 2, 3])
    out = merge_small_components(x, labels, min_size=2)
    assert out.tolist() == [0, 0, 0, 1, 1, 1, 1, 0]


# ---------------------------------------------------------------------------------------------- configs
@pytest.mark.parametrize(
    "name, cls", [("pcgmm", PCGMMFitter), ("damm", DAMMFitter), ("em", EMFitter), ("em_bic", EMBICFitter)]
)
def test_gmm_configs_match_fitter_fields_and_run(name: str, cls: type, generator: torch.Generator) -> None:
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF / "gmm"), version_base="1.3"):
        cfg = compose(config_name=name)
    keys = set(OmegaConf.to_container(cfg)) - {"_target_"}
    assert keys == {f.name for f in dataclasses.fields(cls)}
    fitter = instantiate(cfg)
    assert isinstance(fitter, cls)
    assert fitter == cls()  # the yaml repeats the defaults
    x, _ = blobs([[0, 0], [8, 0]], 60, 1.0, generator)
    noise = 0.1 * torch.randn(120, 2, generator=generator, dtype=F64)
    x_dot = torch.tensor([1.0, 0.0], dtype=F64).repeat(120, 1) + noise
    gmm = fitter(x, x_dot, generator=generator)
    assert isinstance(gmm, GMM) and gmm.dim == 2


# ---------------------------------------------------------------------------------------------- kernels
# lfd_torch.gmm.gaussian and lfd_torch.gmm.niw, shared with lfd_torch.segmentation: each against an independent
# reference (scipy, the closed form written out in numpy, a chain of Student-t predictives, moments).
@pytest.mark.parametrize("d", [1, 2, 3])
def test_gaussian_log_density_matches_scipy(generator: torch.Generator, d: int) -> None:
    B, n, K = 2, 5, 3
    x = 2 * torch.randn(B, n, d, generator=generator, dtype=F64)
    mean = torch.randn(B, K, d, generator=generator, dtype=F64)
    A = torch.randn(B, K, d, d, generator=generator, dtype=F64)
    cov = A @ A.transpose(-2, -1) + 0.3 * torch.eye(d, dtype=F64)
    got = gaussian_log_density(x, mean, cov)
    assert got.shape == (B, n, K)
    for b, k in itertools.product(range(B), range(K)):
        ref = scipy.stats.multivariate_normal(mean[b, k].numpy(), cov[b, k].numpy()).logpdf(x[b].numpy())
        np.testing.assert_allclose(got[b, :, k].numpy(), np.reshape(ref, n), rtol=1e-10)
    # parameters broadcast over the leading dimensions of the samples; dtype follows the input
    torch.testing.assert_close(gaussian_log_density(x, mean[0], cov[0])[1], gaussian_log_density(x[1], mean[0], cov[0]))
    assert gaussian_log_density(x.float(), mean.float(), cov.float()).dtype == torch.float32
    with pytest.raises(ShapeMismatchError):
        gaussian_log_density(x, mean[..., :0], cov)


def _reference_niw_posterior(m0, k0, nu0, psi0, x):  # type: ignore[no-untyped-def]
    """Murphy (2007) eqs. 250-254 written out in numpy, from the centred scatter."""
    n = x.shape[0]
    xbar = x.mean(0)
    S = (x - xbar).T @ (x - xbar)
    kn = k0 + n
    mn = (k0 * m0 + n * xbar) / kn
    psin = psi0 + S + (k0 * n / kn) * np.outer(xbar - m0, xbar - m0)
    return mn, kn, nu0 + n, psin


def test_niw_posterior_closed_form(generator: torch.Generator) -> None:
    x = torch.randn(40, 3, generator=generator, dtype=F64) * torch.tensor([1.0, 2.0, 0.5], dtype=F64) + 1.0
    prior = niw_prior_from_data(x, covariance_scale=0.3, mean_pseudo_count=0.5, extra_dof=2.0)
    labels = torch.randint(2, (40,), generator=generator)
    onehot = torch.nn.functional.one_hot(labels, 2).to(F64)
    post = niw_posterior(prior, *sufficient_statistics(x, onehot))
    for k in range(2):
        xk = x[labels == k].numpy()
        mn, kn, nun, psin = _reference_niw_posterior(
            prior.mean.numpy(), float(prior.kappa), float(prior.dof), prior.scale.numpy(), xk
        )
        np.testing.assert_allclose(post.mean[k].numpy(), mn, rtol=1e-12)
        np.testing.assert_allclose(float(post.kappa[k]), kn)
        np.testing.assert_allclose(float(post.dof[k]), nun)
        np.testing.assert_allclose(post.scale[k].numpy(), psin, rtol=1e-10, atol=1e-12)


def test_niw_and_inverse_wishart_log_densities_match_scipy(generator: torch.Generator) -> None:
    x = torch.randn(30, 2, generator=generator, dtype=F64)
    prior = niw_prior_from_data(x, covariance_scale=0.2, extra_dof=3.0)
    for _ in range(3):
        mu, S = sample_niw(prior, generator)
        ref_iw = scipy.stats.invwishart(df=float(prior.dof), scale=prior.scale.numpy()).logpdf(S.numpy())
        assert float(inverse_wishart_log_density(S, prior.dof, prior.scale)) == pytest.approx(ref_iw, rel=1e-10)
        ref = ref_iw + scipy.stats.multivariate_normal(prior.mean.numpy(), S.numpy() / float(prior.kappa)).logpdf(
            mu.numpy()
        )
        assert float(niw_log_density(mu, S, prior)) == pytest.approx(ref, rel=1e-10)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_niw_marginal_equals_chain_of_student_t_predictives(d: int) -> None:
    rng = np.random.default_rng(d)
    kappa0, nu0 = 0.7, d + 3.0
    B = rng.normal(size=(d, d))
    psi0 = B @ B.T + np.eye(d)
    mu0 = rng.normal(size=d)
    y = rng.normal(size=(6, d))
    # reference: p(y_1..n) = prod_i p(y_i | y_<i), each a multivariate Student t (Murphy 2007, eq. 258)
    ref, mu, kap, nu, psi = 0.0, mu0.copy(), kappa0, nu0, psi0.copy()
    for yi in y:
        dof = nu - d + 1
        ref += scipy.stats.multivariate_t(loc=mu, shape=psi * (kap + 1) / (kap * dof), df=dof).logpdf(yi)
        mu_new = (kap * mu + yi) / (kap + 1)
        psi = psi + kap / (kap + 1) * np.outer(yi - mu, yi - mu)
        mu, kap, nu = mu_new, kap + 1, nu + 1
    prior = NIWPrior(torch.tensor(mu0), torch.tensor(kappa0, dtype=F64), torch.tensor(nu0, dtype=F64),
                     torch.tensor(psi0))  # fmt: skip
    # two states: all six points, and none (exactly 0)
    weights = torch.tensor([[1.0, 0.0]] * 6, dtype=F64)
    got = niw_log_marginal_likelihood(prior, *sufficient_statistics(torch.tensor(y), weights))
    assert float(got[0]) == pytest.approx(ref, rel=1e-10)
    assert float(got[1]) == 0.0


def test_sample_niw_moments(generator: torch.Generator) -> None:
    prior = NIWPrior(
        mean=torch.tensor([1.0, -2.0], dtype=F64), kappa=torch.tensor(2.0, dtype=F64), dof=torch.tensor(7.0, dtype=F64),
        scale=torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64),
    )  # fmt: skip
    n = 40000
    batch = NIWPrior(prior.mean.expand(n, 2), prior.kappa, prior.dof, prior.scale.expand(n, 2, 2))
    mu, S = sample_niw(batch, generator)
    torch.testing.assert_close(S.mean(0), prior.scale / (7.0 - 2 - 1), rtol=0.03, atol=0.01)
    torch.testing.assert_close(mu.mean(0), prior.mean, rtol=0, atol=0.02)
    # Cov(mu) = E[Sigma] / kappa
    torch.testing.assert_close(torch.cov(mu.T), prior.scale / 4.0 / 2.0, rtol=0.05, atol=0.01)


def test_sample_gamma_distribution(generator: torch.Generator) -> None:
    shapes = [0.3, 1.0, 4.5, 40.0, 500.0]
    a = torch.tensor(shapes, dtype=F64).repeat(50_000, 1)
    g = sample_gamma(a, generator)
    assert (g > 0).all()
    for j, shape in enumerate(shapes):
        assert float(g[:, j].mean()) == pytest.approx(shape, rel=0.02)
        assert float(g[:, j].var()) == pytest.approx(shape, rel=0.06)
        assert scipy.stats.kstest(g[:, j].numpy(), scipy.stats.gamma(shape).cdf).pvalue > 1e-3
    def draw() -> torch.Tensor:
        return sample_gamma(a[:10], torch.Generator().manual_seed(3))

    assert torch.equal(draw(), draw())  # reproducible through the generator alone


def test_gaussian_bank_matches_the_density_kernel() -> None:
    from lfd_torch.gmm import GaussianBank, gaussian_log_density

    gen = torch.Generator().manual_seed(0)
    for d in (1, 2, 3):
        K = 7
        mean = torch.randn(K, d, generator=gen, dtype=torch.float64)
        L = torch.randn(K, d, d, generator=gen, dtype=torch.float64)
        cov = L @ L.transpose(-1, -2) + 0.1 * torch.eye(d, dtype=torch.float64)
        x = 3 * torch.randn(50, d, generator=gen, dtype=torch.float64)
        bank = GaussianBank(mean, cov)
        assert torch.allclose(bank.log_density(x), gaussian_log_density(x, mean, cov), rtol=1e-12, atol=1e-10)
        assert torch.allclose(bank.log_density(x.T.contiguous().T), bank.log_density(x))  # non-contiguous input


# ------------------------------------------------------------------------------- effective-sample-size BIC
def ar1(phi: float, T: int, generator: torch.Generator) -> torch.Tensor:
    e = torch.randn(T, generator=generator, dtype=F64)
    y = torch.zeros(T, dtype=F64)
    for t in range(1, T):
        y[t] = phi * y[t - 1] + e[t]
    return y


def test_autocorrelation_time_of_white_noise_and_ar1(generator: torch.Generator) -> None:
    from lfd_torch.gmm.em import integrated_autocorrelation_time

    white = torch.randn(4000, 3, generator=generator, dtype=F64)
    assert (integrated_autocorrelation_time(white) - 1).abs().max() < 0.2
    tau = float(integrated_autocorrelation_time(ar1(0.9, 20000, generator))[0])
    assert tau == pytest.approx((1 + 0.9) / (1 - 0.9), rel=0.15)  # 19
    assert float(integrated_autocorrelation_time(torch.ones(50, 1, dtype=F64))[0]) == 1.0


def test_effective_sample_size_sums_sequences_and_is_conservative(generator: torch.Generator) -> None:
    from lfd_torch.gmm.em import effective_sample_size, integrated_autocorrelation_time

    a = torch.stack([ar1(0.9, 5000, generator), torch.randn(5000, generator=generator, dtype=F64)], -1)
    b = torch.randn(3000, 2, generator=generator, dtype=F64)
    n_a = effective_sample_size(a)
    assert n_a == pytest.approx(5000 / float(integrated_autocorrelation_time(a).max()))  # the slowest column
    assert n_a < 5000 / 10
    groups = torch.cat([torch.zeros(5000, dtype=torch.long), torch.ones(3000, dtype=torch.long)])
    assert effective_sample_size(torch.cat([a, b]), groups) == pytest.approx(n_a + effective_sample_size(b))
    with pytest.raises(ShapeMismatchError):
        effective_sample_size(a, groups)


def test_effective_bic_formula_and_selection(generator: torch.Generator) -> None:
    x, _ = blobs([[0, 0]], 100, 1.0, generator)
    gmm = fit_em(x, 2, generator=generator)
    assert bic(gmm, x, n_effective=100) == pytest.approx(bic(gmm, x))
    ll = float(gmm.log_prob(x).sum())
    assert bic(gmm, x, n_effective=10) == pytest.approx(-2 * 0.1 * ll + 11 * math.log(10))
    with pytest.raises(InvalidArgumentError):
        bic(gmm, x, n_effective=0)
    with pytest.raises(InvalidArgumentError):
        bic(gmm, x, n_effective=101)
    # a smooth curve sampled densely: the plain BIC keeps adding components, the effective one does not
    t = torch.linspace(0, 1, 400, dtype=F64)
    curve = torch.stack([torch.cos(3 * t), torch.sin(5 * t)], -1)
    curve = curve + 0.01 * torch.randn(400, 2, generator=generator, dtype=F64)
    from lfd_torch.gmm.em import effective_sample_size

    n_eff = effective_sample_size(curve)
    assert n_eff < 40
    plain = fit_em_bic(curve, k_range=range(1, 9), generator=torch.Generator().manual_seed(0))
    eff = fit_em_bic(curve, k_range=range(1, 9), generator=torch.Generator().manual_seed(0), n_effective=n_eff)
    assert eff.n_components < plain.n_components


def test_kmeans_keeps_clusters_far_from_the_origin_in_float32():
    """Two clusters 1 apart with spread 0.05, moved 1e4 and 1e5 from the origin: float32 k-means still separates them
    (distances from the differences; the expanded ||a||^2 + ||b||^2 - 2 a.b lost them at 1e4)."""
    g = torch.Generator().manual_seed(0)
    a = torch.randn(200, 2, generator=g, dtype=torch.float64) * 0.05
    x = torch.cat([a[:100], a[100:] + torch.tensor([1.0, 0.0], dtype=torch.float64)])
    truth = torch.cat([torch.zeros(100), torch.ones(100)]).long()
    for offset in (1e4, 1e5):
        labels = kmeans_plus_plus((x + offset).float(), 2, generator=torch.Generator().manual_seed(1))
        assert torch.equal(labels, truth) or torch.equal(labels, 1 - truth)


def test_niw_prior_from_data_expects_a_share_of_the_data_variance() -> None:
    """E[Sigma] = scale / (dof - d - 1) of the prior is covariance_scale x the data's unbiased per-axis variance
    (numpy, ddof=1); a flat axis gets 1e-6 of the largest variance; mean, kappa and dof as documented."""
    x = torch.randn(30, 3, generator=torch.Generator().manual_seed(2), dtype=F64) * torch.tensor([1.0, 3.0, 0.0],
                                                                                                  dtype=F64)
    prior = niw_prior_from_data(x, covariance_scale=0.2, mean_pseudo_count=0.5, extra_dof=4.0)
    var = x.numpy().var(0, ddof=1)
    var[2] = 1e-6 * var.max()
    expected_cov = prior.scale / (prior.dof - 3 - 1)
    np.testing.assert_allclose(expected_cov.numpy(), np.diag(0.2 * var), rtol=1e-12, atol=0)
    assert float(prior.dof) == 3 + 1 + 4.0 and float(prior.kappa) == 0.5
    np.testing.assert_allclose(prior.mean.numpy(), x.numpy().mean(0), rtol=1e-12, atol=1e-15)
