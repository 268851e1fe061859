"""Segmentation kernels against independent references, for properties the other kernel tests leave open.

Each test names the property it checks and its reference: brute-force enumeration of state paths, a naive loop,
scipy.stats densities and means, a closed form computed densely with numpy, quadrature or Monte Carlo with a fixed
seed. They were written to kill mutants of lfd_torch.segmentation.{states,transitions,features,field,dwell} that
the existing tests let survive."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy import stats

from lfd_torch.segmentation.dwell import dwell_mask, dwell_posterior, dwell_prior, posterior_summary
from lfd_torch.segmentation.features import sample_ibp, unique_feature_rate
from lfd_torch.segmentation.field import (
    FieldPrior,
    field_log_density,
    field_log_marginal_likelihood,
    field_mixture_evidence,
    field_mixture_posterior_mean,
    field_observations,
    field_prior,
    field_statistics,
    rotation_field_evidence,
    sample_field,
)
from lfd_torch.segmentation.states import viterbi
from lfd_torch.segmentation.transitions import initial_distribution

F64 = torch.float64


def test_viterbi_equals_brute_force_with_an_informative_start_and_anti_sticky_padding() -> None:
    """viterbi is the argmax over all K^T paths of log p(s, x) (brute-force enumeration), where the initial
    distribution is sharply peaked (it must enter delta_0) and the transitions avoid self-loops (after a sequence's
    end the backpointers must be the identity, or the padding stops repeating the last valid state)."""
    gen = torch.Generator().manual_seed(7)
    B, T, K = 4, 6, 3
    le = torch.randn(B, T, K, generator=gen, dtype=F64)
    init = torch.softmax(6.0 * torch.randn(B, K, generator=gen, dtype=F64), -1)
    P = torch.rand(B, K, K, generator=gen, dtype=F64) + 0.5
    P = P * (1.0 - 0.97 * torch.eye(K, dtype=F64))  # self-transitions about 30x less likely than a switch
    P = P / P.sum(-1, keepdim=True)
    lengths = torch.tensor([6, 3, 2, 1])
    got = viterbi(le, init, P, lengths)
    for b in range(B):
        n = int(lengths[b])
        best, arg = -math.inf, None
        for seq in itertools.product(range(K), repeat=n):
            lp = math.log(float(init[b, seq[0]])) + float(le[b, 0, seq[0]])
            for t in range(1, n):
                lp += math.log(float(P[b, seq[t - 1], seq[t]])) + float(le[b, t, seq[t]])
            if lp > best:
                best, arg = lp, seq
        assert got[b, :n].tolist() == list(arg), b
        assert got[b, n:].tolist() == [arg[-1]] * (T - n), b


def test_initial_distribution_is_uniform_over_the_owned_features() -> None:
    """p(s_0 = k) = 1 / |f_i| on the owned features and 0 elsewhere (naive loop over rows), including a row that
    owns every feature, one that owns a single one, and one that owns none (all zeros, no NaN)."""
    features = torch.tensor([[True, False, True, True, False], [True] * 5, [False, False, False, True, False],
                             [False] * 5])
    got = initial_distribution(features, F64)
    for i in range(features.shape[0]):
        owned = [k for k in range(5) if bool(features[i, k])]
        for k in range(5):
            want = 1.0 / len(owned) if k in owned else 0.0
            assert float(got[i, k]) == pytest.approx(want, abs=1e-15), (i, k)


def test_unique_feature_rate_is_the_mean_number_of_features_only_the_last_row_owns() -> None:
    """Two-parameter IBP: given the other N - 1 rows, a row owns Poisson(gamma c / (c + N - 1)) features no other
    row owns. Monte Carlo with the sequential buffet draw (by exchangeability the last row stands for any row):
    the mean count of columns owned by the last row alone, and the Poisson probability of none."""
    gen = torch.Generator().manual_seed(5)
    mass, conc, N, n = 2.0, 1.5, 4, 4000
    counts = []
    for _ in range(n):
        F = sample_ibp(N, mass, conc, gen)
        counts.append(int((F[-1] & (F[:-1].sum(0) == 0)).sum()))
    rate = unique_feature_rate(mass, conc, N)
    mean = float(np.mean(counts))
    assert mean == pytest.approx(rate, abs=5.0 * math.sqrt(rate / n))
    p0 = math.exp(-rate)
    assert float(np.mean(np.array(counts) == 0)) == pytest.approx(p0, abs=5.0 * math.sqrt(p0 * (1 - p0) / n))
    assert unique_feature_rate(mass, conc, 1) == pytest.approx(mass)  # one row: every feature is its own


def test_field_observations_unbias_the_squared_speed_and_standardise_to_unit_rms() -> None:
    """Reliability w = s^2 / (s^2 + s0^2), s0 = sigma_v / sigma_u, with s^2 estimated as ||v||^2 - d sigma_v^2: for
    velocities v = s u + e, e ~ N(0, sigma_v^2 I), the squared speed recovered from w, s0^2 w / (1 - w), averages
    to the true s^2 (Monte Carlo, fixed seed; a wrong bias correction or s0 instead of s0^2 shifts it by > 10 %).
    The standardised positions have mean 0 and root-mean-square norm 1 (a naive mean over the valid samples)."""
    gen = torch.Generator().manual_seed(3)
    d, T, s_true, sv, su = 3, 20000, 1.0, 0.3, 0.2
    direction = torch.randn(1, T, d, generator=gen, dtype=F64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    v = s_true * direction + sv * torch.randn(1, T, d, generator=gen, dtype=F64)
    x = 3.0 * torch.randn(1, T, d, generator=gen, dtype=F64) + torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    valid = torch.ones(1, T, dtype=torch.bool)
    valid[0, -100:] = False  # padding must not enter the standardisation
    obs = field_observations(x, v, valid, velocity_noise=sv, direction_noise=su)
    w = obs.w[valid]
    s0_sq = (sv / su) ** 2
    recovered = s0_sq * w / (1.0 - w)
    assert float(recovered.mean()) == pytest.approx(s_true**2, abs=0.02)
    xs = obs.z[..., :d][valid]
    torch.testing.assert_close(xs.mean(0), torch.zeros(d, dtype=F64), atol=1e-10, rtol=0)
    assert float(xs.square().sum(-1).mean().sqrt()) == pytest.approx(1.0, abs=1e-10)


@pytest.mark.parametrize("dim,extra", [(2, 2.0), (3, 5.0)])
def test_field_prior_expected_noise_is_the_inverse_wishart_mean(dim: int, extra: float) -> None:
    """E[Psi] under the field prior is direction_noise^2 I (module docstring), the inverse-Wishart mean
    S0 / (nu0 - d - 1) computed by scipy.stats.invwishart."""
    prior = field_prior(dim, direction_noise=0.3, extra_dof=extra)
    mean = stats.invwishart(df=float(prior.dof), scale=prior.scale.numpy()).mean()
    np.testing.assert_allclose(mean, 0.09 * np.eye(dim), rtol=1e-12, atol=1e-14)


def test_field_evidence_with_a_nonzero_prior_mean_is_the_multivariate_t() -> None:
    """MNIW evidence with a nonzero prior mean M0 and a non-diagonal V0 (every prior the package builds has M0 = 0,
    so the M0 terms of the update are otherwise unchecked): for d = 1, u = Z B^T + e, e ~ N(0, Psi W^-1),
    B | Psi ~ N(M0, Psi V0), Psi ~ IW(nu0, S0), the directions are multivariate t with nu0 dof, location Z M0^T and
    shape S0 / nu0 (W^-1 + Z V0 Z^T) (scipy.stats.multivariate_t); the function leaves out the Jacobian
    1/2 sum log w."""
    gen = torch.Generator().manual_seed(2)
    n, p = 8, 3
    m0 = torch.tensor([[0.5, -0.3, 0.8]], dtype=F64)
    a = torch.randn(p, p, generator=gen, dtype=F64)
    v0 = a @ a.T + 0.5 * torch.eye(p, dtype=F64)
    prior = FieldPrior(mean=m0, row_covariance=v0, dof=torch.tensor(4.0, dtype=F64),
                       scale=torch.tensor([[0.3]], dtype=F64))
    z = torch.cat([torch.randn(n, p - 1, generator=gen, dtype=F64), torch.ones(n, 1, dtype=F64)], -1)
    u = torch.randn(n, 1, generator=gen, dtype=F64)
    w = torch.rand(n, generator=gen, dtype=F64) + 0.3
    ev = field_log_marginal_likelihood(prior, *field_statistics(z, u, w, torch.ones(n, 1, dtype=F64)))[0]
    ev = float(ev) + 0.5 * float(torch.log(w).sum())
    Z = z.numpy()
    shape = 0.3 / 4.0 * (np.diag(1.0 / w.numpy()) + Z @ v0.numpy() @ Z.T)
    want = stats.multivariate_t(loc=(Z @ m0.numpy().T)[:, 0], shape=shape, df=4.0).logpdf(u[:, 0].numpy())
    assert ev == pytest.approx(float(want), abs=1e-9)


def test_sample_field_draws_have_the_matrix_normal_mean_and_column_covariance() -> None:
    """B | Psi ~ MN(M, Psi, V): E[B] = M and Cov(B_ij, B_il) = E[Psi_ii] V_jl with E[Psi] = S / (nu - d - 1)
    (Monte Carlo, fixed seed, with a non-diagonal V so that chol(V) and its transpose are told apart)."""
    gen = torch.Generator().manual_seed(9)
    d, p, n, dof = 2, 3, 40000, 40.0
    v = torch.tensor([[1.0, 0.9, 0.3], [0.9, 1.2, 0.5], [0.3, 0.5, 2.0]], dtype=F64)
    mean = torch.tensor([[0.5, -1.0, 0.2], [0.0, 0.3, -0.4]], dtype=F64)
    scale = 0.25 * (dof - d - 1.0) * torch.eye(d, dtype=F64)  # E[Psi] = 0.25 I
    params = FieldPrior(mean=mean.expand(n, d, p), row_covariance=v.expand(n, p, p),
                        dof=torch.tensor(dof, dtype=F64).expand(n), scale=scale.expand(n, d, d))
    b, _ = sample_field(params, gen)
    torch.testing.assert_close(b.mean(0), mean, atol=0.02, rtol=0)
    for i in range(d):
        rows = b[:, i, :] - b[:, i, :].mean(0)
        cov = rows.T @ rows / (n - 1)
        torch.testing.assert_close(cov, 0.25 * v, atol=0.025, rtol=0)


def test_field_log_density_is_the_inverse_wishart_times_the_matrix_normal() -> None:
    """log MNIW(B, Psi | M, V, nu, S) = log IW(Psi | nu, S) + log MN(B | M, Psi, V) with scipy.stats.invwishart and
    scipy.stats.matrix_normal (rows of B covary by Psi, its columns by V), at random points, d = 2 and 3."""
    gen = torch.Generator().manual_seed(4)
    for d in (2, 3):
        p = d + 1
        a = torch.randn(p, p, generator=gen, dtype=F64)
        v = a @ a.T + 0.3 * torch.eye(p, dtype=F64)
        c = torch.randn(d, d, generator=gen, dtype=F64)
        s = c @ c.T + 0.5 * torch.eye(d, dtype=F64)
        params = FieldPrior(mean=torch.randn(d, p, generator=gen, dtype=F64), row_covariance=v,
                            dof=torch.tensor(d + 3.5, dtype=F64), scale=s)
        e = torch.randn(d, d, generator=gen, dtype=F64)
        psi = e @ e.T + 0.2 * torch.eye(d, dtype=F64)
        b = torch.randn(d, p, generator=gen, dtype=F64)
        got = float(field_log_density(b, psi, params))
        want = (stats.invwishart(df=d + 3.5, scale=s.numpy()).logpdf(psi.numpy())
                + stats.matrix_normal(mean=params.mean.numpy(), rowcov=psi.numpy(), colcov=v.numpy()).logpdf(b.numpy()))
        assert got == pytest.approx(float(want), abs=1e-9), d


def test_rotation_posterior_noise_is_the_posterior_mean_of_sigma2_by_quadrature() -> None:
    """The rotation field's E[Psi | u, z] = E[sigma^2 | u, z] I: quadrature over log sigma^2 of the closed-form
    Gaussian marginal N(y; 0, sigma^2 (diag(1 / w) + D L0^-1 D^T)) times the IG(a0, b0) prior (a0 = (nu0 - d - 1) d
    / 2 + 1, mean E[Psi]_11 of the prior), D the design of u_t = [w x2 + b1, -w x1 + b2] written out for d = 2."""
    gen = torch.Generator().manual_seed(12)
    d, n = 2, 9
    prior = field_prior(d, direction_noise=0.2, extra_dof=3.0)
    z = torch.cat([torch.randn(n, d, generator=gen, dtype=F64), torch.ones(n, 1, dtype=F64)], -1)
    u = torch.randn(n, d, generator=gen, dtype=F64) * 0.5
    w = torch.rand(n, generator=gen, dtype=F64) + 0.3
    _, _, psi = rotation_field_evidence(prior, *field_statistics(z, u, w, torch.ones(n, 1, dtype=F64)))
    Zn, wn, y = z.numpy(), w.numpy(), u.reshape(-1).numpy()  # y sample-major: [u_0x, u_0y, u_1x, ...]
    D = np.zeros((n * d, 3))  # columns: rate, offset x, offset y
    D[0::2, 0], D[0::2, 1] = Zn[:, 1], 1.0
    D[1::2, 0], D[1::2, 2] = -Zn[:, 0], 1.0
    v0 = np.diag(prior.row_covariance.numpy())
    L0inv = np.diag([v0[0], v0[-1], v0[-1]])
    A = np.diag(np.repeat(1.0 / wn, d)) + D @ L0inv @ D.T
    quad = float(y @ np.linalg.solve(A, y))
    extra = float(prior.dof) - d - 1.0
    a0 = extra * d / 2.0 + 1.0
    b0 = float(prior.scale[0, 0]) / extra * (a0 - 1.0)
    ls = np.linspace(-12.0, 4.0, 20001)
    s2 = np.exp(ls)
    log_post = -0.5 * n * d * ls - 0.5 * quad / s2 + stats.invgamma(a0, scale=b0).logpdf(s2) + ls
    weight = np.exp(log_post - log_post.max())
    want = float(np.trapezoid(weight * s2, ls) / np.trapezoid(weight, ls))
    assert float(psi[0, 0, 0]) == pytest.approx(want, rel=1e-6)
    assert float(psi[0, 1, 1]) == pytest.approx(want, rel=1e-6) and float(psi[0, 0, 1]) == 0.0


def test_straight_component_posterior_noise_is_the_normal_inverse_wishart_mean() -> None:
    """Under the spike-and-slab prior E[Psi | u] = P(straight) E[Psi | straight] + (1 - P(straight)) E[Psi | affine];
    the straight component, recovered from the mixture, equals the inverse-Wishart mean (scipy.stats.invwishart) of
    the conjugate update on the constant regressor written out densely: Lambda_n = 1 / v + sum w, m = sum w u /
    Lambda_n, S_n = S0 + sum w u u^T - Lambda_n m m^T, nu_n = nu0 + n."""
    gen = torch.Generator().manual_seed(6)
    d, n, rho = 2, 10, 0.5
    prior = field_prior(d, direction_noise=0.3, extra_dof=2.0)
    x = torch.randn(n, d, generator=gen, dtype=F64)
    z = torch.cat([x, torch.ones(n, 1, dtype=F64)], -1)
    u = torch.tensor([0.8, 0.3], dtype=F64) + 0.2 * torch.randn(n, d, generator=gen, dtype=F64) + 0.25 * x.flip(-1)
    w = torch.rand(n, generator=gen, dtype=F64) * 0.5 + 0.5
    st = field_statistics(z, u, w, torch.ones(n, 1, dtype=F64))
    _, log_ps = field_mixture_evidence(prior, *st, rho)
    ps = float(torch.exp(log_ps[0]))
    assert 0.05 < ps < 0.95  # both components matter here
    _, psi = field_mixture_posterior_mean(prior, *st, rho)
    _, psi_affine = field_mixture_posterior_mean(prior, *st, 0.0)
    psi_straight = ((psi[0] - (1.0 - ps) * psi_affine[0]) / ps).numpy()
    un, wn = u.numpy(), w.numpy()
    lam = 1.0 / float(prior.row_covariance[-1, -1]) + wn.sum()
    m = (wn[:, None] * un).sum(0) / lam
    s_n = prior.scale.numpy() + (wn[:, None, None] * un[:, :, None] * un[:, None, :]).sum(0) - lam * np.outer(m, m)
    want = stats.invwishart(df=float(prior.dof) + n, scale=s_n).mean()
    np.testing.assert_allclose(psi_straight, want, rtol=1e-9, atol=1e-12)


def test_dwell_posterior_summary_is_the_normal_inverse_gamma_posterior_mean() -> None:
    """posterior_summary of one labelling: E[mu], E[delta] and sqrt(E[sigma^2]) of the NIG posterior of
    c_t = mu + delta b_t + e_t over the mask, written out densely with numpy from the module docstring's prior
    ((mu, delta) | sigma^2 ~ N(0, 100 sigma^2 I), sigma^2 ~ IG with nu0 = 3, S0 = 0.1): Lambda_n = I / 100 + X^T X,
    m = Lambda_n^-1 X^T c, S_n = S0 + c^T c - m^T Lambda_n m, E[sigma^2] = S_n / (nu0 + n - 2)."""
    gen = torch.Generator().manual_seed(8)
    N, T, D = 2, 25, 3
    lengths = torch.tensor([25, 21])
    mask = dwell_mask(lengths, T, D)
    c = 0.4 * torch.randn(N, T, generator=gen, dtype=F64)
    starts = [[0, 5, 9, 16], [0, 4, 12]]  # runs of at least D points
    phase = torch.zeros(1, N, T, dtype=torch.long)
    for i, ss in enumerate(starts):
        for t in range(T):
            begun = max(s for s in ss if s <= t)
            phase[0, i, t] = min(t - begun, D - 1)
    c[0, 5] += 1.5  # a dwell at a switch
    c[1, 12] += 1.2
    got = posterior_summary(dwell_posterior(dwell_prior(), c, mask, phase))
    X, y = [], []
    for i in range(N):
        for t in range(T):
            if bool(mask[i, t]):
                X.append([1.0, 1.0 if t in starts[i] else 0.0])
                y.append(float(c[i, t]))
    X, y = np.array(X), np.array(y)
    lam = np.eye(2) / 100.0 + X.T @ X
    m = np.linalg.solve(lam, X.T @ y)
    s_n = 0.1 + y @ y - m @ lam @ m
    var = s_n / (3.0 + len(y) - 2.0)
    assert got["dwell_mean"] == pytest.approx(m[0], abs=1e-10)
    assert got["dwell_shift"] == pytest.approx(m[1], abs=1e-10)
    assert got["dwell_noise"] == pytest.approx(math.sqrt(var), rel=1e-10)


def test_rotation_slab_posterior_mean_weights_the_components_by_bayes_rule() -> None:
    """With ``rotation_weight`` r the slab is the mixture (1 - r) affine + r rotation, so its evidence is
    log((1 - r) p_a + r p_r) and its posterior means are the components' means weighted by P(rotation | u) =
    r p_r / ((1 - r) p_a + r p_r) (Bayes' rule written out with math.exp; the affine component's means are the MNIW
    posterior mean M_n and the scipy.stats.invwishart mean of Psi). r is small enough that P(rotation | u) is
    about 1/2 on a noisy arc, where the rotation evidence is about 6 nats above the affine one."""
    from lfd_torch.segmentation.field import field_posterior

    gen = torch.Generator().manual_seed(5)
    prior = field_prior(2, direction_noise=0.2, extra_dof=30.0)
    phi = torch.linspace(0.0, 2.0, 30, dtype=F64)
    x = torch.stack([0.3 * torch.cos(phi), 0.3 * torch.sin(phi)], -1)
    u = torch.stack([-torch.sin(phi), torch.cos(phi)], -1) + 0.1 * torch.randn(30, 2, generator=gen, dtype=F64)
    z = torch.cat([x, torch.ones(30, 1, dtype=F64)], -1)
    st = field_statistics(z, u, torch.full((30,), 0.7, dtype=F64), torch.ones(30, 1, dtype=F64))
    r = 0.003
    ev_a = float(field_log_marginal_likelihood(prior, *st)[0])
    ev_r, mean_r, psi_r = rotation_field_evidence(prior, *st)
    ev_r = float(ev_r[0])
    top = max(ev_a, ev_r)
    slab = top + math.log((1 - r) * math.exp(ev_a - top) + r * math.exp(ev_r - top))
    p_rot = r * math.exp(ev_r - slab)
    assert 0.2 < p_rot < 0.8  # both components matter here
    post = field_posterior(prior, *st)
    mean_a = post.mean[0].numpy()
    psi_a = stats.invwishart(df=float(post.dof[0]), scale=post.scale[0].numpy()).mean()
    ev, _ = field_mixture_evidence(prior, *st, 0.0, rotation_weight=r)
    assert float(ev[0]) == pytest.approx(slab, abs=1e-9)
    mean, psi = field_mixture_posterior_mean(prior, *st, 0.0, rotation_weight=r)
    np.testing.assert_allclose(mean[0].numpy(), (1 - p_rot) * mean_a + p_rot * mean_r[0].numpy(), atol=1e-10)
    np.testing.assert_allclose(psi[0].numpy(), (1 - p_rot) * psi_a + p_rot * psi_r[0].numpy(), atol=1e-10)


def test_prior_transition_weights_are_gamma_alpha_plus_kappa_on_the_diagonal() -> None:
    """eta_jk ~ Gamma(alpha + kappa delta_jk, 1) under the sticky prior: Kolmogorov-Smirnov tests of the diagonal
    and off-diagonal draws against scipy.stats.gamma (alpha and kappa far apart so that a swap is visible)."""
    from lfd_torch.segmentation.transitions import sample_transition_weights_prior

    gen = torch.Generator().manual_seed(13)
    alpha, kappa, K = 0.5, 6.0, 3
    eta = sample_transition_weights_prior((4000,), K, alpha, kappa, gen)
    eye = torch.eye(K, dtype=torch.bool).expand(4000, K, K)
    assert stats.kstest(eta[eye].numpy(), stats.gamma(alpha + kappa).cdf).pvalue > 1e-3
    assert stats.kstest(eta[~eye].numpy(), stats.gamma(alpha).cdf).pvalue > 1e-3


def test_free_transition_counts_skip_the_forced_phase_moves() -> None:
    """With a minimum duration D, only the moves out of a run's last phase (D - 1) are drawn from pi: the counts of
    ``transition_counts`` with ``free_transitions`` equal a naive loop over a labelling that tracks each run's age
    (self-transitions counted only once a run has lasted D points, every switch counted), within the lengths."""
    from lfd_torch.segmentation.transitions import free_transitions, transition_counts

    D, K = 3, 3
    states = torch.tensor([[0, 0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2], [2, 2, 2, 0, 0, 0, 0, 1, 1, 1, 1, 1]])
    lengths = torch.tensor([12, 10])
    phases = torch.zeros_like(states)
    for i in range(2):
        for t in range(1, 12):
            phases[i, t] = min(int(phases[i, t - 1]) + 1, D - 1) if states[i, t] == states[i, t - 1] else 0
    got = transition_counts(states, lengths, K, free_transitions(phases, D))
    want = torch.zeros(2, K, K, dtype=F64)
    for i in range(2):
        age = 1
        for t in range(1, int(lengths[i])):
            a, b = int(states[i, t - 1]), int(states[i, t])
            if a != b or age >= D:
                want[i, a, b] += 1
            age = age + 1 if a == b else 1
    torch.testing.assert_close(got, want)
    assert float(want[0, 0, 0]) == 2.0 and float(want[0, 0, 1]) == 1.0  # the loop counts both kinds
