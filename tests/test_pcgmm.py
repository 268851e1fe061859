"""PC-GMM (ddCRP collapsed Gibbs) and the DAMM-like sampler of lfd_torch.gmm."""

from __future__ import annotations

import itertools
import math
from collections import Counter

import numpy as np
import pytest
import scipy.integrate
import scipy.stats
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from conftest import requires_cuda
from lfd_torch.errors import NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.gmm import GMM, InvalidGMMError, damm_labels, fit_damm, fit_pcgmm, pcgmm_labels
from lfd_torch.gmm.damm import vmf_log_normalizer
from lfd_torch.gmm.niw import NIWPrior, niw_log_marginal_likelihood, sufficient_statistics
from lfd_torch.gmm.pcgmm import _ddcrp_gibbs, _flat_features, _LogMarginal, prior_weights

F64 = torch.float64


def adjusted_rand_index(a: torch.Tensor, b: torch.Tensor) -> float:
    """Hubert & Arabie's ARI from the contingency table (1 = same partition, ~0 = chance)."""
    _, a = torch.unique(a, return_inverse=True)
    _, b = torch.unique(b, return_inverse=True)
    n = a.numel()
    table = torch.zeros(int(a.max()) + 1, int(b.max()) + 1, dtype=F64)
    table.index_put_((a, b), torch.ones(n, dtype=F64), accumulate=True)

    def pairs(t: torch.Tensor) -> float:
        return float((t * (t - 1) / 2).sum())

    index, rows, cols, total = pairs(table), pairs(table.sum(1)), pairs(table.sum(0)), n * (n - 1) / 2
    expected = rows * cols / total
    top = (rows + cols) / 2
    return 1.0 if top == expected else (index - expected) / (top - expected)


def z_field(n: int, generator: torch.Generator, width: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Three adjacent linear regimes (a 'Z'): rightwards along the top, diagonally down-left, rightwards
    along the bottom; n samples per regime spread uniformly along it, velocities of 20 units/s with noise."""
    starts = torch.tensor([[0.0, 10.0], [10.0, 10.0], [0.0, 0.0]], dtype=F64)
    ends = torch.tensor([[10.0, 10.0], [0.0, 0.0], [10.0, 0.0]], dtype=F64)
    lab = torch.arange(3).repeat_interleave(n)
    t = torch.rand(3 * n, 1, generator=generator, dtype=F64)
    seg = ends[lab] - starts[lab]
    u = seg / seg.norm(dim=-1, keepdim=True)
    normal = torch.stack([-u[:, 1], u[:, 0]], -1)
    x = starts[lab] + t * seg + width * torch.randn(3 * n, 1, generator=generator, dtype=F64) * normal
    x_dot = 20 * (u + 0.1 * torch.randn(3 * n, 2, generator=generator, dtype=F64))
    return x, x_dot, lab


def test_adjusted_rand_index_reference_values() -> None:
    a = torch.tensor([0, 0, 1, 1, 2, 2])
    assert adjusted_rand_index(a, a) == 1.0
    assert adjusted_rand_index(a, torch.tensor([5, 5, 3, 3, 9, 9])) == 1.0
    # hand-computed: contingency [[2,0],[1,1],[0,2]] -> index 2, rows 3, cols 6, total 15 -> (2-1.2)/(4.5-1.2)
    assert adjusted_rand_index(a, torch.tensor([0, 0, 0, 1, 1, 1])) == pytest.approx(0.8 / 3.3)


# ---------------------------------------------------------------------------------------------- NIW marginal
def _pcgmm_prior(d: int, c: float, kappa0: float = 1.0, nu0_offset: float = 2.0) -> NIWPrior:
    """The prior form the sampler uses: mean 0, scale c I."""
    return NIWPrior(torch.zeros(d, dtype=F64), torch.tensor(kappa0, dtype=F64), torch.tensor(d + nu0_offset, dtype=F64),
                    c * torch.eye(d, dtype=F64))  # fmt: skip


@pytest.mark.parametrize("d", [1, 2, 3, 4])
def test_sampler_marginal_equals_the_niw_kernel(d: int) -> None:
    """The sampler's float fast path (tabulated c(n), written-out determinant) is the shared NIW kernel; the
    kernel itself is checked against Student-t predictives in test_gmm.py."""
    rng = np.random.default_rng(d)
    prior = _pcgmm_prior(d, 0.8, kappa0=0.7, nu0_offset=3.0)
    lm = _LogMarginal(prior, 20)
    y = rng.normal(size=(9, d)) + 0.5
    feats = _flat_features(y)
    groups = [slice(0, 4), slice(4, 9), slice(0, 9)]
    onehot = torch.zeros(9, 3, dtype=F64)
    for k, g in enumerate(groups):
        onehot[g, k] = 1.0
    ref = niw_log_marginal_likelihood(prior, *sufficient_statistics(torch.tensor(y), onehot))
    for k, g in enumerate(groups):
        assert lm(feats[g].sum(0).tolist()) == pytest.approx(float(ref[k]), rel=1e-12)
    assert lm.merged(feats[:4].sum(0).tolist(), feats[4:].sum(0).tolist()) == pytest.approx(float(ref[2]), rel=1e-12)
    np.testing.assert_allclose(lm.batch(np.stack([feats[g].sum(0) for g in groups])), ref.numpy(), rtol=1e-12)


# ---------------------------------------------------------------------------------------------- ddCRP sampler
def _partition_key(labels: np.ndarray) -> tuple[int, ...]:
    first: dict[int, int] = {}
    return tuple(first.setdefault(int(v), len(first)) for v in labels)


def test_ddcrp_gibbs_matches_exact_posterior_by_enumeration() -> None:
    """Partition frequencies of a long chain equal the posterior from enumerating all M^M link graphs."""
    rng = np.random.default_rng(1)
    M, d = 4, 2
    y = rng.normal(size=(M, d))
    y[:2] += 1.5
    W = rng.uniform(0.1, 1.0, size=(M, M))
    np.fill_diagonal(W, 0.4)
    W[0, 3] = 0.0  # a forbidden link (opposite velocities)
    prior = _pcgmm_prior(d, 0.5)
    lm = _LogMarginal(prior, 2 * M)
    feats = _flat_features(y)
    exact: Counter[tuple[int, ...]] = Counter()
    for links in itertools.product(range(M), repeat=M):
        w = math.prod(W[i, links[i]] for i in range(M))
        if w == 0:
            continue
        _, lab = connected_components(coo_matrix((np.ones(M), (np.arange(M), links)), shape=(M, M)), directed=False)
        loglik = sum(lm(feats[lab == k].sum(0).tolist()) for k in range(lab.max() + 1))
        exact[_partition_key(lab)] += w * math.exp(loglik)
    total = sum(exact.values())
    trace: list[np.ndarray] = []
    _ddcrp_gibbs(y, W, prior, 8000, torch.Generator().manual_seed(0), trace=trace)
    empirical = Counter(_partition_key(t) for t in trace)
    keys = set(exact) | set(empirical)
    tv = 0.5 * sum(abs(exact[k] / total - empirical[k] / len(trace)) for k in keys)
    assert len(exact) > 5
    assert tv < 0.03, tv


def test_prior_weights() -> None:
    x = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]], dtype=F64)
    v = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 3.0]], dtype=F64)
    W = prior_weights(x, v, 2.0, 0.3)
    assert W[0, 0] == 0.3 and W[0, 1] == 0.0  # opposite velocities cannot link
    assert float(W[0, 2]) == pytest.approx(math.exp(-1.0) * 1.0)
    assert float(W[1, 2]) == pytest.approx(math.exp(-math.sqrt(5) / 2))


# ---------------------------------------------------------------------------------------------- recovery
def test_pcgmm_recovers_three_linear_regimes() -> None:
    """On samples that fill each regime uniformly, a length scale of the regime size and a prior with the weight
    of 10 observations recover the three regimes. (The defaults are chosen for trajectory data, where they split
    the uniformly filled straight regimes of this field: see the module docstring of lfd_torch.gmm.pcgmm.)"""
    ks, aris = [], []
    for seed in range(5):
        g = torch.Generator().manual_seed(100 + seed)
        x, x_dot, lab = z_field(150, g)
        rms = float((x - x.mean(0)).pow(2).sum(-1).mean().sqrt())
        res = pcgmm_labels(x, x_dot, generator=g, length_scale=2.0 * rms, nu0_offset=10.0)
        ks.append(int(res.labels.max()) + 1)
        aris.append(adjusted_rand_index(res.labels, lab))
    assert sum(k == 3 for k in ks) >= 3, ks
    assert float(np.median(aris)) > 0.85, aris


def z_trajectories(n_demos: int, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n_demos`` noisy demonstrations of a 'Z' path (right, diagonally down-left, right; legs of 100 units),
    ``n`` samples per leg at constant speed 20 units/s: samples lie along curves, as in LASA."""
    corners = torch.tensor([[0.0, 100.0], [100.0, 100.0], [0.0, 0.0], [100.0, 0.0]], dtype=F64)
    xs, vs, labs = [], [], []
    for _ in range(n_demos):
        offset = 3.0 * torch.randn(4, 2, generator=generator, dtype=F64)
        offset[-1] = 0.0  # common end point
        c = corners + offset
        for leg in range(3):
            t = torch.linspace(0.0, 1.0, n + 1, dtype=F64)[:-1, None]
            seg = c[leg + 1] - c[leg]
            xs.append(c[leg] + t * seg + 0.3 * torch.randn(n, 2, generator=generator, dtype=F64))
            vs.append((20.0 * seg / seg.norm()).expand(n, 2))
            labs.append(torch.full((n,), leg))
    return torch.cat(xs), torch.cat(vs), torch.cat(labs)


def test_pcgmm_default_clusters_are_physically_consistent_on_trajectories() -> None:
    """Default hyperparameters on trajectory data: clusters stay within one linear regime up to the corners
    (purity >= 0.85; measured 0.89-0.98 over seeds, against 0.81-0.87 with the short length scale and the former
    strong prior nu0_offset = 10), regimes are split but not shattered (3 <= K <= 12; 7 measured), and the default
    length scale is 0.25 x the RMS radius."""
    from lfd_torch.gmm.pcgmm import LENGTH_SCALE_FACTOR, default_length_scale

    for seed in range(3):
        g = torch.Generator().manual_seed(400 + seed)
        x, x_dot, lab = z_trajectories(4, 150, g)
        res = pcgmm_labels(x, x_dot, generator=g)
        rms = float((x[res.sample_index] - x[res.sample_index].mean(0)).pow(2).sum(-1).mean().sqrt())
        assert res.length_scale == pytest.approx(LENGTH_SCALE_FACTOR * rms, rel=1e-12)
        assert default_length_scale(x) == pytest.approx(0.25 * float((x - x.mean(0)).pow(2).sum(-1).mean().sqrt()))
        K = int(res.labels.max()) + 1
        assert 3 <= K <= 12, K
        counts = torch.zeros(K, 3, dtype=F64).index_put_((res.labels, lab), torch.ones(lab.numel(), dtype=F64),
                                                         accumulate=True)  # fmt: skip
        purity = float(counts.max(1).values.sum() / lab.numel())
        assert purity >= 0.85, (seed, K, purity)


def test_damm_recovers_three_linear_regimes() -> None:
    ks, aris = [], []
    for seed in range(5):
        g = torch.Generator().manual_seed(200 + seed)
        x, x_dot, lab = z_field(200, g)
        res = damm_labels(x, x_dot, generator=g)
        ks.append(int(res.labels.max()) + 1)
        aris.append(adjusted_rand_index(res.labels, lab))
    assert sum(k == 3 for k in ks) >= 4, ks
    assert min(aris) > 0.8 and float(np.median(aris)) > 0.95, aris


def test_damm_keeps_a_single_gaussian_regime_whole() -> None:
    """Split/merge must not over-split: one elongated Gaussian moving in one direction is one component."""
    for seed in range(3):
        g = torch.Generator().manual_seed(300 + seed)
        x = torch.randn(400, 2, generator=g, dtype=F64) * torch.tensor([3.0, 1.0], dtype=F64)
        x_dot = torch.tensor([1.0, 0.0], dtype=F64) + 0.1 * torch.randn(400, 2, generator=g, dtype=F64)
        res = damm_labels(x, x_dot, generator=g)
        assert int(res.labels.max()) + 1 == 1
        assert res.n_components[-1] == 1


def test_position_only_bic_is_not_enough_on_the_field() -> None:
    """Sanity of the benchmark field: velocities carry information that positions alone do not."""
    from lfd_torch.gmm import fit_em_bic

    g = torch.Generator().manual_seed(100)
    x, x_dot, lab = z_field(150, g)
    em = fit_em_bic(x, k_range=range(1, 9), generator=g)
    damm = fit_damm(x, x_dot, generator=g)
    ari_em = adjusted_rand_index(em.posterior(x).argmax(-1), lab)
    ari_damm = adjusted_rand_index(damm.posterior(x).argmax(-1), lab)
    assert ari_damm > ari_em


@pytest.mark.parametrize("fit", [fit_pcgmm, fit_damm])
def test_fit_is_reproducible_and_returns_a_valid_gmm(fit) -> None:  # type: ignore[no-untyped-def]
    x, x_dot, _ = z_field(80, torch.Generator().manual_seed(5))
    a = fit(x, x_dot, generator=torch.Generator().manual_seed(11))
    b = fit(x, x_dot, generator=torch.Generator().manual_seed(11))
    assert isinstance(a, GMM) and a.dtype == F64 and a.dim == 2
    for k in ("weights", "means", "covariances"):
        assert torch.equal(a.state_dict()[k], b.state_dict()[k])
    # float32 input: same dtype out
    c = fit(x.float(), x_dot.float(), generator=torch.Generator().manual_seed(11))
    assert c.dtype == torch.float32


def test_pcgmm_coarsening_labels_every_sample() -> None:
    x, x_dot, lab = z_field(200, torch.Generator().manual_seed(6))
    res = pcgmm_labels(x, x_dot, generator=torch.Generator().manual_seed(0), max_points=150)
    assert res.labels.shape == (600,)
    assert res.sample_index.numel() == 150
    assert res.log_posterior.shape == (20,) and torch.isfinite(res.log_posterior).all()
    full = pcgmm_labels(x[::4], x_dot[::4], generator=torch.Generator().manual_seed(0), max_points=None, n_iter=3)
    assert full.sample_index.numel() == 150


def test_small_clusters_are_merged() -> None:
    x, x_dot, _ = z_field(100, torch.Generator().manual_seed(7))
    res = damm_labels(x, x_dot, generator=torch.Generator().manual_seed(0), min_cluster_size=60)
    counts = torch.bincount(res.labels)
    assert (counts >= 60).all()


# ---------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("fit", [fit_pcgmm, fit_damm])
def test_bad_input_raises_typed_errors(fit, generator: torch.Generator) -> None:  # type: ignore[no-untyped-def]
    x, x_dot, _ = z_field(20, generator)
    nan_x = x.clone()
    nan_x[3, 1] = float("nan")
    with pytest.raises(NonFiniteError):
        fit(nan_x, x_dot, generator=generator)
    inf_v = x_dot.clone()
    inf_v[0, 0] = float("inf")
    with pytest.raises(NonFiniteError):
        fit(x, inf_v, generator=generator)
    with pytest.raises(ShapeMismatchError):
        fit(x, x_dot[:-1], generator=generator)
    with pytest.raises(ShapeMismatchError):
        fit(x, x_dot.float(), generator=generator)
    with pytest.raises(TooFewSamplesError):
        fit(x[:2], x_dot[:2], generator=generator)
    with pytest.raises(InvalidGMMError):
        fit(x, x_dot, generator=generator, alpha=0.0)
    with pytest.raises(InvalidGMMError):
        fit(x, x_dot, generator=generator, n_iter=0)


def test_damm_needs_two_dimensions(generator: torch.Generator) -> None:
    x = torch.randn(20, 1, generator=generator, dtype=F64)
    with pytest.raises(InvalidGMMError):
        fit_damm(x, x.clone(), generator=generator)


def test_pcgmm_invalid_length_scale(generator: torch.Generator) -> None:
    x, x_dot, _ = z_field(20, generator)
    with pytest.raises(InvalidGMMError):
        fit_pcgmm(x, x_dot, generator=generator, length_scale=-1.0)


# ---------------------------------------------------------------------------------------------- DAMM kernels
@pytest.mark.parametrize("d", [2, 3, 4])
def test_vmf_normaliser_integrates_to_one(d: int) -> None:
    for kappa in (0.0, 0.5, 7.0, 60.0):
        log_c = float(vmf_log_normalizer(torch.tensor([kappa], dtype=F64), d)[0])
        # integral over the sphere of exp(kappa cos theta): area(S^{d-2}) * int_0^pi exp(k cos t) sin^{d-2} t dt
        area = 2 * math.pi ** ((d - 1) / 2) / math.gamma((d - 1) / 2)
        def integrand(t: float, kappa: float = kappa) -> float:
            return math.exp(kappa * (math.cos(t) - 1)) * math.sin(t) ** (d - 2)

        val, _ = scipy.integrate.quad(integrand, 0, math.pi)
        assert log_c + math.log(area * val) + kappa == pytest.approx(0.0, abs=1e-8)


@requires_cuda
def test_damm_and_pcgmm_accept_cuda_tensors() -> None:
    x, x_dot, _ = z_field(60, torch.Generator().manual_seed(8))
    g = torch.Generator(device="cuda").manual_seed(0)
    for fit in (fit_damm, fit_pcgmm):
        gmm = fit(x.cuda(), x_dot.cuda(), generator=g)
        assert gmm.device.type == "cuda"
        assert torch.isfinite(gmm.log_prob(x.cuda())).all()


@pytest.mark.parametrize("name", ["PCGMMFitter", "DAMMFitter", "EMFitter", "EMBICFitter"])
def test_fitters_require_a_generator(name) -> None:
    import lfd_torch.gmm as gmm
    from lfd_torch.errors import InvalidArgumentError

    x = torch.randn(50, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    with pytest.raises(InvalidArgumentError, match="generator"):
        getattr(gmm, name)()(x, x, generator=None)


def test_merge_small_components_against_a_loop() -> None:
    """A cluster of exactly min_size points is kept; smaller ones go point by point to the nearest kept mean
    (written out); labels are renumbered densely in the kept clusters' order; with no cluster large enough the
    largest (the first of equal ones) is kept."""
    from lfd_torch.gmm.postprocess import merge_small_components

    x = torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1],  # cluster 0: 3 points (= min_size, kept)
                      [5.0, 5.0], [5.1, 5.0], [5.0, 5.1], [5.1, 5.1],  # cluster 1: 4 points (kept)
                      [1.0, 1.0], [4.0, 4.2]], dtype=torch.float64)  # clusters 2 and 3: 1 point each  # fmt: skip
    labels = torch.tensor([0, 0, 0, 1, 1, 1, 1, 2, 3])
    out = merge_small_components(x, labels, 3)
    means = torch.stack([x[:3].mean(0), x[3:7].mean(0)])
    want = labels.clone()
    for n in (7, 8):
        want[n] = int(torch.argmin(((x[n] - means) ** 2).sum(-1)))
    assert out.tolist() == want.tolist() == [0, 0, 0, 1, 1, 1, 1, 0, 1]
    assert merge_small_components(x, torch.tensor([2, 2, 0, 0, 1, 1, 3, 3, 3]), 5).tolist() == [0] * 9


# ---------------------------------------------------------------------------------------------- collapsed scores
def _damm_prior(d: int, nu0_offset: float = 10.0) -> NIWPrior:
    """The NIW prior damm_labels builds (standardised coordinates, psi_scale 1)."""
    nu0 = d + nu0_offset
    return NIWPrior(torch.zeros(d, dtype=F64), torch.tensor(1.0, dtype=F64), torch.tensor(nu0, dtype=F64),
                    torch.eye(d, dtype=F64) * (nu0 - d - 1.0))  # fmt: skip


def _sphere_quadrature(d: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes m (P, d) on the unit sphere and weights (P,) of quadrature for the surface measure (weights sum to
    area(S^{d-1})): the trapezoid rule on the circle (d = 2), Gauss-Legendre in cos(theta) x trapezoid in phi on
    S^2 (d = 3)."""
    if d == 2:
        th = torch.arange(4000, dtype=F64) * (2 * math.pi / 4000)
        return torch.stack([th.cos(), th.sin()], -1), torch.full((4000,), 2 * math.pi / 4000, dtype=F64)
    t, wt = np.polynomial.legendre.leggauss(200)
    phi = torch.arange(400, dtype=F64) * (2 * math.pi / 400)
    ct = torch.as_tensor(t, dtype=F64)[:, None].expand(200, 400)
    st = (1 - ct**2).sqrt()
    m = torch.stack([st * phi.cos(), st * phi.sin(), ct], -1).reshape(-1, 3)
    w = (torch.as_tensor(wt, dtype=F64)[:, None] * (2 * math.pi / 400)).expand(200, 400).reshape(-1)
    return m, w


def _vmf_direction_log_marginal(u: torch.Tensor, kappa: float) -> float:
    """log of the integral over the unit mean m (uniform prior) of prod_i C_d(kappa) exp(kappa m . u_i), by
    quadrature; C_d(kappa) itself is the reciprocal of the quadrature of exp(kappa m . e_1). Empty u gives 0."""
    d = u.shape[-1]
    m, w = _sphere_quadrature(d)
    log_c = -float(torch.logsumexp(torch.log(w) + kappa * m[:, 0], 0))
    if u.shape[0] == 0:
        return 0.0
    log_area = math.log(float(w.sum()))
    return u.shape[0] * log_c + float(torch.logsumexp(torch.log(w) + kappa * (m @ u.sum(0)), 0)) - log_area


@pytest.mark.parametrize("d", [2, 3])
def test_damm_direction_marginal_equals_quadrature_over_the_sphere(d: int) -> None:
    """_Model.log_marginal minus the NIW position marginal is the vMF direction marginal with a uniform prior on the
    mean direction, log int prod_i C_d(kappa) exp(kappa m . u_i) dm / area(S^{d-1}) (quadrature over the circle /
    sphere); samples with zero velocity and groups without directions contribute nothing."""
    from lfd_torch.gmm.damm import _Model, _Stats

    g = torch.Generator().manual_seed(31 + d)
    kappa = 2.5
    y = torch.randn(9, d, generator=g, dtype=F64)
    v = torch.randn(9, d, generator=g, dtype=F64) + 0.8
    v[2] = 0.0  # no direction
    v[7:] = 0.0  # group 2: no directions at all
    speed = v.norm(dim=-1, keepdim=True)
    has_dir = speed.squeeze(-1) > 0
    u = torch.where(speed > 0, v / speed.clamp_min(1e-300), torch.zeros_like(v))
    labels = torch.tensor([0, 0, 0, 0, 1, 1, 1, 2, 2])
    prior = _damm_prior(d)
    model = _Model(0.7, kappa, prior)
    st = _Stats.of(_Stats.features(y, u, has_dir), labels, 3, d)
    onehot = torch.nn.functional.one_hot(labels, 3).to(F64)
    pos = niw_log_marginal_likelihood(prior, *sufficient_statistics(y, onehot))
    got = model.log_marginal(st) - pos
    for k in range(3):
        sel = (labels == k) & has_dir
        want = _vmf_direction_log_marginal(u[sel], kappa)
        assert float(got[k]) == pytest.approx(want, abs=1e-8), (k, float(got[k]), want)
    assert float(got[2]) == 0.0


def _crp_log_prob(labels: list[int], alpha: float) -> float:
    """log CRP probability of a partition (in order of first appearance), by seating the customers one by one."""
    sizes: dict[int, int] = {}
    out = 0.0
    for i, k in enumerate(labels):
        out += math.log((alpha if k not in sizes else sizes[k]) / (alpha + i))
        sizes[k] = sizes.get(k, 0) + 1
    return out


def test_damm_log_posterior_differences_equal_crp_prior_plus_marginals() -> None:
    """Differences of _Model.log_posterior between partitions of the same data equal those of the CRP partition
    probability (sequential seating) plus the NIW position and (quadrature) vMF direction marginals of the groups."""
    from lfd_torch.gmm.damm import _Model, _Stats

    g = torch.Generator().manual_seed(7)
    d, alpha, kappa = 2, 0.7, 3.0
    y = torch.randn(7, d, generator=g, dtype=F64)
    v = torch.randn(7, d, generator=g, dtype=F64) + torch.tensor([1.0, 0.5], dtype=F64)
    v[4] = 0.0
    speed = v.norm(dim=-1, keepdim=True)
    has_dir = speed.squeeze(-1) > 0
    u = torch.where(speed > 0, v / speed.clamp_min(1e-300), torch.zeros_like(v))
    prior = _damm_prior(d)
    model = _Model(alpha, kappa, prior)
    feats = _Stats.features(y, u, has_dir)
    partitions = [
        [0, 0, 0, 0, 0, 0, 0], [0, 0, 0, 1, 1, 1, 1], [0, 1, 1, 1, 1, 1, 1], [0, 1, 0, 2, 1, 2, 0],
        [0, 1, 2, 3, 4, 5, 6], [0, 0, 1, 1, 1, 1, 2], [0, 1, 0, 0, 0, 0, 0],
    ]  # fmt: skip
    got, want = [], []
    for part in partitions:
        lab = torch.tensor(part)
        K = int(lab.max()) + 1
        got.append(float(model.log_posterior(_Stats.of(feats, lab, K, d))))
        ref = _crp_log_prob(part, alpha)
        for k in range(K):
            sel = lab == k
            ref += float(niw_log_marginal_likelihood(prior, *sufficient_statistics(y[sel], torch.ones(int(sel.sum()), 1,
                                                                                                     dtype=F64)))[0])
            ref += _vmf_direction_log_marginal(u[sel & has_dir], kappa)
        want.append(ref)
    diffs_got = np.asarray(got) - got[0]
    diffs_want = np.asarray(want) - want[0]
    np.testing.assert_allclose(diffs_got, diffs_want, rtol=0, atol=1e-8)


def test_damm_split_move_accepts_clear_splits_and_rejects_a_single_blob() -> None:
    """One split move on two far-apart tight clusters of 100 samples under one label splits them exactly
    (log Hastings ratio about +70 under damm_labels' prior, so accepted with probability 1) for every generator
    seed; on one tight blob (ratio << 1) it never splits."""
    from lfd_torch.gmm.damm import _Model, _Stats, _split_moves

    d = 2
    model = _Model(1.0, 5.0, _damm_prior(d))
    n_split = {"pair": 0, "blob": 0}
    for seed in range(10):
        g = torch.Generator().manual_seed(500 + seed)
        truth = torch.arange(2).repeat_interleave(100)
        centres = torch.tensor([[-1.0, 0.3], [1.0, -0.3]], dtype=F64)
        for case in ("pair", "blob"):
            y = 0.1 * torch.randn(200, d, generator=g, dtype=F64) + (centres[truth] if case == "pair" else 0.0)
            v = torch.tensor([1.0, 0.2], dtype=F64) + 0.1 * torch.randn(200, d, generator=g, dtype=F64)
            u = v / v.norm(dim=-1, keepdim=True)
            feats = _Stats.features(y, u, torch.ones(200, dtype=torch.bool))
            z0 = torch.zeros(200, dtype=torch.long)
            z, K = _split_moves(model, feats, y, u, z0, _Stats.of(feats, z0, 1, d), g)
            n_split[case] += int(K > 1)
            if case == "pair" and K == 2:
                assert adjusted_rand_index(z, truth) == 1.0
    assert n_split == {"pair": 10, "blob": 0}, n_split


def test_ddcrp_recorded_log_posterior_is_the_joint_of_links_and_tables() -> None:
    """The per-sweep score of the ddCRP sampler is log prod_i W[i, c_i] + sum over tables of the NIW log marginal.
    With links allowed only to oneself or to the previous point (a chain), the links are read off the tables
    (c_i = i - 1 iff i and i - 1 share a table), so the score is recomputed from the traced tables; the returned
    MAP table is the traced table with the highest score."""
    rng = np.random.default_rng(3)
    M, d = 8, 2
    y = rng.normal(size=(M, d))
    y[4:] += 1.2
    W = np.zeros((M, M))
    W[np.arange(1, M), np.arange(M - 1)] = rng.uniform(0.2, 3.0, size=M - 1)
    np.fill_diagonal(W, 0.35)
    prior = _pcgmm_prior(d, 0.5)
    trace: list[np.ndarray] = []
    best, lp_hist, nt_hist = _ddcrp_gibbs(y, W, prior, 60, torch.Generator().manual_seed(4), trace=trace)
    assert len(trace) == 60 and len({_partition_key(t) for t in trace}) > 3
    yt = torch.as_tensor(y)
    want = []
    for table in trace:
        links = [i - 1 if i > 0 and table[i] == table[i - 1] else i for i in range(M)]
        log_prior = sum(math.log(W[i, c]) for i, c in enumerate(links))
        _, dense = np.unique(table, return_inverse=True)
        onehot = torch.nn.functional.one_hot(torch.as_tensor(dense), int(dense.max()) + 1).to(F64)
        want.append(log_prior + float(niw_log_marginal_likelihood(prior, *sufficient_statistics(yt, onehot)).sum()))
        assert nt_hist[len(want) - 1] == dense.max() + 1
    np.testing.assert_allclose(lp_hist, want, rtol=1e-10, atol=1e-10)
    assert _partition_key(best) == _partition_key(trace[int(np.argmax(want))])
