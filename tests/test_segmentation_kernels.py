"""Kernels of the BP-GM-HMM against independent references (enumeration, closed forms, scipy, Monte Carlo).

The NIW and Gaussian emission kernels are those of lfd_torch.gmm, tested in test_gmm.py."""

from __future__ import annotations

import collections
import itertools
import math

import numpy as np
import pytest
import torch
from scipy import stats

from lfd_torch.segmentation.features import ibp_log_prior, sample_ibp, shared_log_odds
from lfd_torch.segmentation.states import backward_sample, forward_filter, forward_log_likelihood, used_states, viterbi
from lfd_torch.segmentation.transitions import (
    sample_transition_weights_posterior,
    transition_counts,
    transition_matrix,
)

F64 = torch.float64


def _tiny_hmm(generator: torch.Generator, B: int = 3, T: int = 5, K: int = 3):
    le = torch.randn(B, T, K, generator=generator, dtype=F64) * 3.0
    init = torch.rand(B, K, generator=generator, dtype=F64)
    P = torch.rand(B, K, K, generator=generator, dtype=F64)
    # sequence 1 cannot use state K-1 (not owned), as in the sampler
    le[1, :, K - 1] = -math.inf
    init[1, K - 1] = 0.0
    P[1, :, K - 1] = 0.0
    P[1, K - 1, :] = 0.0
    init = init / init.sum(-1, keepdim=True)
    P = P / P.sum(-1, keepdim=True).clamp_min(1e-300)
    lengths = torch.tensor([T, T - 1, 1][:B])
    return le, init, P, lengths


def _enumerate(le, init, P, lengths):
    """Brute force over all K^T state sequences: log evidence, filtered marginals, posterior over paths."""
    B, T, K = le.shape
    out_ll, out_filt, out_post = [], [], []
    for b in range(B):
        L = int(lengths[b])
        joint = {}
        for seq in itertools.product(range(K), repeat=L):
            p = float(init[b, seq[0]]) * math.exp(float(le[b, 0, seq[0]]))
            for t in range(1, L):
                p *= float(P[b, seq[t - 1], seq[t]]) * math.exp(float(le[b, t, seq[t]]))
            joint[seq] = p
        total = sum(joint.values())
        out_ll.append(math.log(total))
        out_post.append({k: v / total for k, v in joint.items()})
        filt = np.zeros((L, K))
        for t in range(L):  # p(s_t | x_0..t): enumerate prefixes
            pref = {}
            for seq in itertools.product(range(K), repeat=t + 1):
                p = float(init[b, seq[0]]) * math.exp(float(le[b, 0, seq[0]]))
                for u in range(1, t + 1):
                    p *= float(P[b, seq[u - 1], seq[u]]) * math.exp(float(le[b, u, seq[u]]))
                pref[seq] = p
            z = sum(pref.values())
            for seq, p in pref.items():
                filt[t, seq[-1]] += p / z
        out_filt.append(filt)
    return out_ll, out_filt, out_post


def test_forward_likelihood_equals_enumeration(generator):
    le, init, P, lengths = _tiny_hmm(generator)
    ref_ll, ref_filt, _ = _enumerate(le, init, P, lengths)
    torch.testing.assert_close(forward_log_likelihood(le, init, P, lengths), torch.tensor(ref_ll, dtype=F64))
    filtered, ll = forward_filter(le, init, P, lengths)
    torch.testing.assert_close(ll, torch.tensor(ref_ll, dtype=F64))
    for b in range(le.shape[0]):
        L = int(lengths[b])
        torch.testing.assert_close(filtered[b, :L], torch.tensor(ref_filt[b]), atol=1e-10, rtol=1e-9)
        # padding repeats the last valid row
        torch.testing.assert_close(filtered[b, L:], filtered[b, L - 1 : L].expand(le.shape[1] - L, -1))


def test_forward_likelihood_long_sequence_no_underflow(generator):
    # 400 steps of strongly informative emissions: a naive product underflows, the normalised recursion must not.
    le, init, P, lengths = _tiny_hmm(generator, B=2, T=400, K=3)
    le = le * 20.0
    ll = forward_log_likelihood(le, init, P, torch.tensor([400, 399]))
    _, ll2 = forward_filter(le, init, P, torch.tensor([400, 399]))
    assert torch.isfinite(ll).all()
    torch.testing.assert_close(ll, ll2)


def test_backward_sampling_matches_posterior(generator):
    le, init, P, lengths = _tiny_hmm(generator, B=3, T=4, K=3)
    _, _, ref_post = _enumerate(le, init, P, lengths)
    filtered, _ = forward_filter(le, init, P, lengths)
    n = 20000
    draws = backward_sample(filtered.repeat(n, 1, 1), P.repeat(n, 1, 1), lengths.repeat(n), generator)
    draws = draws.reshape(n, 3, -1)
    for b in range(3):
        L = int(lengths[b])
        counts: dict[tuple[int, ...], int] = {}
        for row in draws[:, b, :L].tolist():
            counts[tuple(row)] = counts.get(tuple(row), 0) + 1
        for path, p in ref_post[b].items():
            # 5 binomial standard errors
            assert abs(counts.get(path, 0) / n - p) <= 5.0 * math.sqrt(p * (1 - p) / n) + 1e-9, (b, path)
        assert (draws[:, b, L:] == draws[:, b, L - 1 : L]).all()


def test_transition_posterior_mean(generator):
    K = 3
    features = torch.tensor([True, False, True])
    counts = torch.zeros(K, K, dtype=F64)
    counts[0, 0], counts[0, 2], counts[2, 2] = 5.0, 2.0, 7.0
    n = 20000
    eta = sample_transition_weights_posterior(counts.expand(n, K, K), features.expand(n, K), 1.0, 3.0, generator)
    pi = transition_matrix(eta, features.expand(n, K))
    # Dirichlet posterior means on the owned block {0, 2}
    a = torch.tensor([[1.0 + 3.0 + 5.0, 1.0 + 2.0], [1.0, 1.0 + 3.0 + 7.0]], dtype=F64)
    ref = a / a.sum(-1, keepdim=True)
    got = pi.mean(0)[[0, 2]][:, [0, 2]]
    torch.testing.assert_close(got, ref, atol=0.01, rtol=0)
    assert (pi[:, :, 1] == 0).all() and (pi[:, 1, :] == 0).all()
    # weights outside the owned block keep their prior Gamma(alpha + kappa delta) law
    assert float(eta[:, 1, 1].mean()) == pytest.approx(4.0, rel=0.05)
    # the owned rows' totals are independent of the data: Gamma(sum_k alpha + kappa delta_jk) over the block, here
    # Gamma(2 + 3) for both rows whatever their counts (KS test against scipy)
    for j in (0, 2):
        total = eta[:, j, [0, 2]].sum(-1).numpy()
        assert stats.kstest(total, stats.gamma(5.0).cdf).pvalue > 1e-3, j


def test_transition_counts_respect_lengths():
    s = torch.tensor([[0, 0, 1, 1, 2], [2, 1, 1, 0, 0]])
    c = transition_counts(s, torch.tensor([5, 3]), 3)
    ref0 = torch.zeros(3, 3, dtype=F64)
    ref0[0, 0], ref0[0, 1], ref0[1, 1], ref0[1, 2] = 1, 1, 1, 1
    ref1 = torch.zeros(3, 3, dtype=F64)
    ref1[2, 1], ref1[1, 1] = 1, 1
    torch.testing.assert_close(c, torch.stack([ref0, ref1]))


def test_used_states_matches_a_naive_loop():
    """used_states: the states each row uses on its valid samples, against a loop over rows and samples (padding
    labels, which may name any state, must not count; leading batch dims and a broadcast mask)."""
    g = torch.Generator().manual_seed(3)
    K = 6
    labels = torch.randint(0, K, (4, 3, 9), generator=g)
    valid = torch.rand(4, 3, 9, generator=g) > 0.4
    expected = torch.zeros(4, 3, K, dtype=torch.bool)
    for b, i, t in itertools.product(range(4), range(3), range(9)):
        if valid[b, i, t]:
            expected[b, i, labels[b, i, t]] = True
    assert torch.equal(used_states(labels, valid, K), expected)
    shared = valid[0]  # (3, 9) one mask for every batch element
    assert torch.equal(used_states(labels, shared, K), used_states(labels, shared.expand(4, 3, 9), K))
    assert not used_states(labels, torch.zeros(3, 9, dtype=torch.bool), K).any()


def test_ibp_prior_predictive(generator):
    # Row i owns Poisson(gamma) features marginally; K+ has mean gamma * sum_n c / (c + n - 1).
    mass, conc, N = 2.0, 1.5, 4
    draws = [sample_ibp(N, mass, conc, generator) for _ in range(3000)]
    per_row = torch.tensor([float(f.sum(1).float().mean()) for f in draws])
    k_plus = torch.tensor([float(f.shape[1]) for f in draws])
    assert float(per_row.mean()) == pytest.approx(mass, rel=0.05)
    assert float(k_plus.mean()) == pytest.approx(mass * sum(conc / (conc + n) for n in range(N)), rel=0.05)
    # the closed-form log prior of the equivalence class is consistent with the sequential draw for N = 1:
    # K ~ Poisson(gamma) and [F] is determined by K, so p([F]) = Poisson(K; gamma)
    one = torch.ones(1, 3, dtype=torch.bool)
    assert float(ibp_log_prior(one, mass, conc)) == pytest.approx(stats.poisson(mass).logpmf(3), rel=1e-10)


def test_ibp_log_prior_batched_matches_a_naive_formula():
    """Reference: the IBP equivalence-class formula evaluated column by column in plain Python (patterns counted in a
    dict), for a batch of random matrices with repeated and unowned columns; the batched call equals the loop."""
    gen = torch.Generator().manual_seed(3)
    N, K, c = 4, 7, 1.5
    F = torch.rand(6, N, K, generator=gen) < 0.4
    F[:, :, 1] = F[:, :, 0]  # a repeated pattern
    F[:, :, 2] = False  # a column nobody owns
    mass = torch.tensor([0.5, 1.0, 2.0, 3.0, 4.0, 5.0], dtype=F64)
    ref = []
    for b in range(F.shape[0]):
        cols = [tuple(F[b, :, k].tolist()) for k in range(K) if F[b, :, k].any()]
        hist = collections.Counter(cols)
        out = len(cols) * (math.log(float(mass[b])) + math.log(c)) - float(mass[b]) * sum(c / (c + j) for j in range(N))
        out -= sum(math.lgamma(h + 1) for h in hist.values())
        for col in cols:
            m = sum(col)
            out += math.lgamma(m) + math.lgamma(N - m + c) - math.lgamma(N + c)
        ref.append(out)
    got = ibp_log_prior(F, mass, c)
    torch.testing.assert_close(got, torch.tensor(ref, dtype=F64), rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(torch.stack([ibp_log_prior(F[b], mass[b], c) for b in range(6)]), got)


def test_shared_log_odds_matches_ibp_conditional():
    m = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    N, c = 4, 1.5
    p = m / (c + N - 1)
    torch.testing.assert_close(shared_log_odds(m, N, c), torch.log(p / (1 - p)))


def _log_space_forward(le, init, P, lengths):
    """Naive log-space forward algorithm (logsumexp over K^2 terms per step), one sequence at a time."""
    out = []
    for b in range(le.shape[0]):
        L = int(lengths[b])
        log_a = torch.log(init[b]) + le[b, 0]
        logP = torch.log(P[b])
        for t in range(1, L):
            log_a = torch.logsumexp(log_a.unsqueeze(-1) + logP, dim=0) + le[b, t]
        out.append(torch.logsumexp(log_a, 0))
    return torch.stack(out)


def test_forward_likelihood_finite_with_tiny_transition_probabilities():
    # alternating emissions with switch probability 1e-100: every step costs ~ log(1e-100), so a recursion that
    # normalises only every few steps underflows to 0/0 = NaN; the true log evidence is finite
    T = 9
    le = torch.full((2, T, 2), -1000.0, dtype=F64)
    le[:, torch.arange(T) % 2 == 0, 0] = 0.0
    le[:, torch.arange(T) % 2 == 1, 1] = 0.0
    P = torch.tensor([[1 - 1e-100, 1e-100], [1e-100, 1 - 1e-100]], dtype=F64).expand(2, 2, 2).contiguous()
    init = torch.full((2, 2), 0.5, dtype=F64)
    lengths = torch.tensor([T, 6])
    ll = forward_log_likelihood(le, init, P, lengths)
    assert torch.isfinite(ll).all(), ll
    torch.testing.assert_close(ll, _log_space_forward(le, init, P, lengths))
    torch.testing.assert_close(ll, forward_filter(le, init, P, lengths)[1])
    # a sample no usable state explains: -inf, never NaN, in both recursions
    le[0, 3] = -math.inf
    ll = forward_log_likelihood(le, init, P, lengths)
    filtered, ll_f = forward_filter(le, init, P, lengths)
    assert ll[0] == -math.inf and ll_f[0] == -math.inf and torch.isfinite(ll[1])
    assert not torch.isnan(filtered).any()


def test_forward_likelihood_exact_through_a_subnormal_step():
    # a step whose whole mass is subnormal (a switch of probability 1e-310 that the emissions force): the recursion
    # normalises by the smallest normal number there, and the next step's factor carries the rest, so the log
    # evidence still equals the log-space reference (about -713.8 nats for that switch)
    T = 6
    le = torch.full((2, T, 2), -1000.0, dtype=F64)
    le[:, :3, 0] = 0.0
    le[:, 3:, 1] = 0.0
    P = torch.tensor([[1 - 1e-310, 1e-310], [1e-310, 1 - 1e-310]], dtype=F64).expand(2, 2, 2).contiguous()
    init = torch.tensor([[1.0, 0.0], [0.5, 0.5]], dtype=F64)
    lengths = torch.tensor([T, 5])
    ll = forward_log_likelihood(le, init, P, lengths)
    assert torch.isfinite(ll).all(), ll
    torch.testing.assert_close(ll, _log_space_forward(le, init, P, lengths), rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(forward_filter(le, init, P, lengths)[1], ll)


def test_segmentation_package_creates_tensors_on_an_explicit_device():
    # every factory call (torch.tensor/zeros/ones/arange/full/eye/empty/rand*/linspace) names its device, so that
    # nothing silently lands on the CPU next to CUDA data (a CPU query of torch.searchsorted once broke CUDA runs)
    import ast
    from pathlib import Path

    import lfd_torch.gmm.gaussian
    import lfd_torch.gmm.niw
    import lfd_torch.segmentation as pkg

    factories = {"tensor", "zeros", "ones", "arange", "full", "eye", "empty", "rand", "randn", "randint", "linspace"}
    missing = []
    kernels = [Path(lfd_torch.gmm.niw.__file__), Path(lfd_torch.gmm.gaussian.__file__)]  # the emission kernels
    for path in sorted(Path(pkg.__file__).parent.glob("*.py")) + kernels:
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in factories
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"
                and not any(k.arg == "device" for k in node.keywords)
            ):  # fmt: skip
                missing.append(f"{path.name}:{node.lineno} torch.{node.func.attr}")
    assert not missing, missing


@pytest.mark.parametrize("dof", [None, 4.0])
def test_additive_field_likelihood_against_scipy_and_at_rest(generator, dof):
    """field_log_likelihood_additive is the Student t / Gaussian density with scale Psi_k + sigma_u^2 (1/w - 1) I
    (scipy reference); it equals the sampler's Psi_k / w form when Psi_k = sigma_u^2 I; and as w -> 0 the ratio
    of two states' densities tends to 1 (a sample at rest carries no evidence), where the Psi_k / w form keeps
    (|Psi_b| / |Psi_a|)^(1/2)."""
    from lfd_torch.segmentation.field import field_log_likelihood, field_log_likelihood_additive

    d, n, K, su = 3, 6, 2, 0.2
    z = torch.cat([torch.randn(n, d, generator=generator, dtype=F64), torch.ones(n, 1, dtype=F64)], -1)
    u = torch.randn(n, d, generator=generator, dtype=F64)
    w = torch.rand(n, generator=generator, dtype=F64) * 0.9 + 0.05
    b = torch.randn(K, d, d + 1, generator=generator, dtype=F64) * 0.3
    a = torch.randn(K, d, d, generator=generator, dtype=F64) * 0.1
    psi = a @ a.transpose(-1, -2) + 0.02 * torch.eye(d, dtype=F64)
    got = field_log_likelihood_additive(z, u, w, b, psi, dof, direction_noise=su)
    for t in range(n):
        for k in range(K):
            cov = (psi[k] + su**2 * (1 / w[t] - 1) * torch.eye(d, dtype=F64)).numpy()
            mean = (b[k] @ z[t]).numpy()
            ref = (stats.multivariate_normal(mean, cov).logpdf(u[t].numpy()) if dof is None
                   else stats.multivariate_t(mean, cov, df=dof).logpdf(u[t].numpy()))  # fmt: skip
            assert got[t, k].item() == pytest.approx(ref, rel=1e-9, abs=1e-9)
    iso = (su**2 * torch.eye(d, dtype=F64)).expand(K, d, d)
    torch.testing.assert_close(field_log_likelihood_additive(z, u, w, b, iso, dof, direction_noise=su),
                               field_log_likelihood(z, u, w, b, iso, dof))  # fmt: skip
    rest = torch.full((n,), 1e-7, dtype=F64)
    add = field_log_likelihood_additive(z, u, rest, b, psi, dof, direction_noise=su)
    assert (add[:, 0] - add[:, 1]).abs().max().item() < 1e-4
    scaled = field_log_likelihood(z, u, rest, b, psi, dof)
    half = 0.5 * (torch.logdet(psi[1]) - torch.logdet(psi[0]))
    torch.testing.assert_close(scaled[:, 0] - scaled[:, 1], half.expand(n), atol=1e-4, rtol=0)


def test_correlated_tolerance_is_the_stacked_ar1_gaussian(generator):
    """The correlated tolerance (``correlated_tolerance_observations``) against its model written out: the density of
    a run, its samples seen in the views of their ages, equals the density of the stacked directions,
    N(vec(B z_t), (R + diag(r)) (x) Psi) with R_ts = rho^|t - s| / (1 - rho^2) the AR(1) deviation and r_t = c'_t /
    s_i^2 the white noise in units of Psi (scipy), with and without velocity noise and a floor, for runs that start
    anywhere and as long as the filter's memory; longer runs forget the oldest samples; a direction with no
    information (w = 0) does not reset the deviation; rho = 0 and another scale sigma is the additive white model
    with tolerance sigma; rho = 0 and sigma = sigma_u returns the observations as they are."""
    from lfd_torch.errors import InvalidArgumentError
    from lfd_torch.segmentation.field import (
        FieldObservations,
        correlated_tolerance_observations,
        correlated_tolerance_prior,
        field_log_likelihood,
        field_log_likelihood_additive,
        field_prior,
    )

    d, n, rho, su, memory = 2, 7, 0.8, 0.2, 6
    z = torch.cat([torch.randn(1, n, d, generator=generator, dtype=F64), torch.ones(1, n, 1, dtype=F64)], -1)
    u = torch.randn(1, n, d, generator=generator, dtype=F64)
    b = torch.randn(1, d, d + 1, generator=generator, dtype=F64) * 0.3
    a = torch.randn(1, d, d, generator=generator, dtype=F64) * 0.1
    psi = a @ a.transpose(-1, -2) + 0.02 * torch.eye(d, dtype=F64)
    mean = (z[0] @ b[0].T).reshape(-1).numpy()
    t = torch.arange(n, dtype=F64)
    ar = rho ** (t[:, None] - t[None, :]).abs() / (1 - rho**2)

    def run_density(views, lo: int, hi: int) -> float:  # samples lo..hi-1 as one run: sample t in view t - lo
        return sum(field_log_likelihood(*views[min(k - lo, memory)], b, psi)[0, k, 0].item() for k in range(lo, hi))

    def stacked(cov: Tensor, lo: int, hi: int) -> float:
        return stats.multivariate_normal(mean[lo * d: hi * d], torch.kron(cov[lo:hi, lo:hi], psi[0]).numpy()).logpdf(
            u[0, lo:hi].reshape(-1).numpy())

    sigma, tau = 0.15, 0.03
    w = torch.rand(1, n, generator=generator, dtype=F64) * 0.9 + 0.05
    for w_, sc, fl in ((torch.ones(1, n, dtype=F64), su, 0.0), (w, su, 0.0), (w, sigma, tau)):
        obs = FieldObservations(z=z, u=u, w=w_, centre=torch.zeros(d, dtype=F64), radius=torch.tensor(1.0, dtype=F64))
        views = correlated_tolerance_observations(obs, rho, su, sc, fl, memory=memory)
        assert len(views) == memory + 1
        c = su**2 * (1.0 / w_[0] - 1.0) + fl**2
        cov = ar + torch.diag(c / ((1 - rho**2) * sc**2))
        for lo, hi in ((0, n), (3, n), (1, 4)):  # runs of up to memory + 1 samples: exact
            assert run_density(views, lo, hi) == pytest.approx(stacked(cov, lo, hi), rel=1e-10)
    # a longer run: beyond the memory a sample is predicted from the last `memory` samples only
    short = correlated_tolerance_observations(obs, rho, su, sigma, tau, memory=2)
    lead = sum(field_log_likelihood(*short[min(k, 2)], b, psi)[0, k, 0].item() for k in range(3))
    assert lead == pytest.approx(stacked(cov, 0, 3), rel=1e-10)
    torch.testing.assert_close(short[2][0][0, 3:], views[2][0][0, 3:])  # same view as with a longer memory
    # no information at sample 2: the filter predicts through it, so sample 3 still depends on samples 0 and 1
    dark = FieldObservations(z=z, u=u, w=torch.cat([w[:, :2], torch.zeros(1, 1, dtype=F64), w[:, 3:]], 1),
                             centre=obs.centre, radius=obs.radius)
    v3 = correlated_tolerance_observations(dark, rho, su, memory=memory)[3]
    assert v3[2][0, 2] == 0.0  # the dark sample itself carries no weight
    assert not torch.allclose(v3[1][0, 3], u[0, 3])  # ...but the prediction of sample 3 is not reset
    # rho = 0, scale sigma: the additive white model u ~ N(B z, sigma^2 I + c_t I) in every view
    obs_w = FieldObservations(z=z, u=u, w=w, centre=obs.centre, radius=obs.radius)
    iso = (sigma**2 * torch.eye(d, dtype=F64))[None]
    for view in correlated_tolerance_observations(obs_w, 0.0, su, sigma, memory=3):
        torch.testing.assert_close(field_log_likelihood(*view, b, iso),
                                   field_log_likelihood_additive(z, u, w, b, iso, direction_noise=su))
    # the white floor tau adds tau^2 to the white noise
    start = correlated_tolerance_observations(obs_w, 0.0, su, sigma, tau)[0]
    torch.testing.assert_close(field_log_likelihood(*start, b, iso),
                               field_log_likelihood_additive(z, u, w, b, iso + tau**2 * torch.eye(d, dtype=F64),
                                                             direction_noise=su))
    same = correlated_tolerance_observations(obs_w, 0.0, su)
    assert all(v is same[0] for v in same) and same[0][0] is z and same[0][1] is u and torch.equal(same[0][2], w)
    with pytest.raises(InvalidArgumentError, match="memory"):
        correlated_tolerance_observations(obs_w, rho, su, memory=0)
    # the prior: E[Psi] and V0 scaled so that the prior of B (Psi (x) V0) is unchanged
    prior = field_prior(d, direction_noise=su)
    scaled = correlated_tolerance_prior(prior, rho, sigma / su)
    f = (sigma / su) ** 2 * (1 - rho**2)
    torch.testing.assert_close(scaled.scale, prior.scale * f)
    torch.testing.assert_close(scaled.row_covariance * scaled.scale[0, 0], prior.row_covariance * prior.scale[0, 0])


def test_field_marginal_likelihood_is_the_chib_identity(generator):
    """MNIW evidence = likelihood x prior / posterior at any (B, Psi) (exact for a conjugate model)."""
    from lfd_torch.segmentation.field import (
        FieldPrior, field_log_density, field_log_likelihood, field_log_marginal_likelihood, field_posterior,
        field_prior, field_statistics, sample_field,
    )  # fmt: skip

    d, n = 3, 25
    prior = field_prior(d, direction_noise=0.3, extra_dof=5.0)
    z = torch.cat([torch.randn(n, d, generator=generator, dtype=F64), torch.ones(n, 1, dtype=F64)], -1)
    u = torch.randn(n, d, generator=generator, dtype=F64)
    w = torch.rand(n, generator=generator, dtype=F64) + 0.2
    stats = field_statistics(z, u, w, torch.ones(n, 1, dtype=F64))
    evidence = field_log_marginal_likelihood(prior, *stats)[0] + 0.5 * d * torch.log(w).sum()
    post = field_posterior(prior, *stats)
    post = FieldPrior(post.mean[0], post.row_covariance[0], post.dof[0], post.scale[0])
    for _ in range(3):
        b, psi = sample_field(post, generator)
        chib = field_log_likelihood(z, u, w, b[None], psi[None]).sum() + field_log_density(b, psi, prior)
        chib = chib - field_log_density(b, psi, post)
        assert float(evidence) == pytest.approx(float(chib), abs=1e-8)
    empty = field_log_marginal_likelihood(prior, *field_statistics(z, u, w, torch.zeros(n, 1, dtype=F64)))
    assert float(empty) == 0.0


def test_field_prior_slope_scale_is_the_slope_standard_deviation(generator):
    """Monte Carlo over prior draws: the slope entries of B have standard deviation ``slope_scale`` (E[Psi] =
    direction_noise^2 I, V0 slope block slope_scale^2 / direction_noise^2), the offsets 1; slope_scale=1 is the
    plain prior V0 = I / direction_noise^2, and a scale <= 0 is refused."""
    from lfd_torch.errors import InvalidArgumentError
    from lfd_torch.segmentation.field import FieldPrior, field_prior, sample_field

    d, n = 2, 40000
    plain = field_prior(d, direction_noise=0.3, extra_dof=30.0)
    assert torch.equal(plain.row_covariance, torch.eye(d + 1, dtype=F64) / 0.3**2)
    for scale in (0.5, 3.0):
        prior = field_prior(d, direction_noise=0.3, extra_dof=30.0, slope_scale=scale)
        batch = FieldPrior(prior.mean.expand(n, -1, -1), prior.row_covariance.expand(n, -1, -1),
                           prior.dof.expand(n), prior.scale.expand(n, -1, -1))
        b, _ = sample_field(batch, generator)
        sd = b.std(0)  # (d, p)
        torch.testing.assert_close(sd[:, :d], torch.full((d, d), scale, dtype=F64), rtol=0.03, atol=0)
        torch.testing.assert_close(sd[:, d], torch.ones(d, dtype=F64), rtol=0.03, atol=0)
    with pytest.raises(InvalidArgumentError, match="slope_scale"):
        field_prior(d, slope_scale=0.0)


def test_dirichlet_multinomial_transitions_against_scipy(generator):
    """Sticky rows integrated out: the DM pmf of the row counts over the multinomial coefficient, owned block only."""
    from lfd_torch.segmentation.transitions import dirichlet_multinomial_log_prob

    K, alpha, kappa = 4, 1.3, 7.0
    feats = torch.tensor([True, True, False, True])
    counts = torch.randint(0, 6, (K, K), generator=generator).to(F64)
    out = float(dirichlet_multinomial_log_prob(counts, feats, alpha, kappa))
    own = [0, 1, 3]
    ref = 0.0
    for j in own:
        n = counts[j, own].numpy()
        a = np.array([alpha + kappa * (k == j) for k in own])
        coef = math.lgamma(n.sum() + 1) - sum(math.lgamma(v + 1) for v in n)
        ref += stats.dirichlet_multinomial.logpmf(n, a, int(n.sum())) - coef
    assert out == pytest.approx(ref, abs=1e-9)
    # batched: per-element hyperparameters and features, each equal to its own scalar call
    counts_b = torch.randint(0, 3, (3, K, K), generator=generator).to(F64)
    feats_b = torch.rand(3, K, generator=generator) > 0.3
    alphas, kappas = torch.tensor([0.5, 1.3, 4.0], dtype=F64), torch.tensor([0.0, 7.0, 2.5], dtype=F64)
    batched = dirichlet_multinomial_log_prob(counts_b, feats_b, alphas.view(3, 1, 1), kappas.view(3, 1, 1))
    for b in range(3):
        single = dirichlet_multinomial_log_prob(counts_b[b], feats_b[b], float(alphas[b]), float(kappas[b]))
        assert float(batched[b]) == pytest.approx(float(single), abs=1e-12)


def test_viterbi_matches_brute_force_enumeration_with_padding():
    """viterbi against the argmax of log p(s, x) over all K^T sequences (T = 6, K = 3, some transitions 0);
    padding repeats the last valid state."""
    import itertools

    gen = torch.Generator().manual_seed(11)
    B, T, K = 3, 6, 3
    le = torch.randn(B, T, K, generator=gen, dtype=torch.float64) * 2.0
    init = torch.rand(B, K, generator=gen, dtype=torch.float64) + 0.1
    init = init / init.sum(-1, keepdim=True)
    P = torch.rand(B, K, K, generator=gen, dtype=torch.float64) + 0.05
    P[0, 0, 2] = 0.0  # a forbidden move
    P = P / P.sum(-1, keepdim=True)
    lengths = torch.tensor([6, 4, 1])
    got = viterbi(le, init, P, lengths)
    for b in range(B):
        n = int(lengths[b])
        best, arg = -math.inf, None
        for seq in itertools.product(range(K), repeat=n):
            lp = math.log(init[b, seq[0]]) + float(le[b, 0, seq[0]])
            for t in range(1, n):
                a = float(P[b, seq[t - 1], seq[t]])
                lp += (math.log(a) if a > 0 else -math.inf) + float(le[b, t, seq[t]])
            if lp > best:
                best, arg = lp, seq
        assert got[b, :n].tolist() == list(arg)
        assert got[b, n:].tolist() == [arg[-1]] * (T - n)


def _directions_near_a_field(gen, n, slope):
    """n directions (d = 2) near a constant one plus ``slope`` times the flipped positions, weights in [0.5, 1):
    regressors z (n, 3), directions u (n, 2), weights w (n,) and their one-state statistics."""
    from lfd_torch.segmentation.field import field_statistics

    x = torch.randn(n, 2, generator=gen, dtype=F64)
    z = torch.cat([x, torch.ones(n, 1, dtype=F64)], -1)
    u = torch.tensor([0.8, 0.3], dtype=F64) + 0.1 * torch.randn(n, 2, generator=gen, dtype=F64) + slope * x.flip(-1)
    w = torch.rand(n, generator=gen, dtype=F64) * 0.5 + 0.5
    return z, u, w, field_statistics(z, u, w, torch.ones(n, 1, dtype=F64))


def _spike_and_slab_draws(gen, prior, row_covariance, rho):
    """M fields and noises from the MNIW of ``prior`` with row covariance (M, p, p), the slope set to 0 with
    probability rho: the draws, the straight mask (M,)."""
    from lfd_torch.segmentation.field import FieldPrior, sample_field

    M, d = row_covariance.shape[0], prior.mean.shape[-2]
    draws = FieldPrior(prior.mean.expand(M, d, d + 1), row_covariance, prior.dof.expand(M), prior.scale.expand(M, d, d))
    b, noise = sample_field(draws, gen)
    straight = torch.rand(M, generator=gen, dtype=F64) < rho
    b = torch.where(straight[:, None, None], torch.cat([torch.zeros_like(b[..., :-1]), b[..., -1:]], -1), b)
    return b, noise, straight


def test_straight_or_affine_field_evidence_and_posterior_against_monte_carlo():
    """Spike-and-slab field prior (straight with probability rho, else affine): the evidence against the mean
    likelihood of 400,000 prior draws (a quarter of them with the slope set to 0 for rho = 0.25), P(straight | u)
    and the posterior-mean field against the same draws weighted by their likelihood (self-normalised importance
    sampling); the straight evidence is the affine one in the limit of a zero-variance slope prior."""
    from lfd_torch.segmentation.field import (
        FieldPrior, field_log_likelihood, field_log_marginal_likelihood, field_mixture_evidence,
        field_mixture_posterior_mean, field_prior, straight_field_prior,
    )  # fmt: skip

    gen = torch.Generator().manual_seed(4)
    d, n, rho, M = 2, 4, 0.25, 400_000
    prior = field_prior(d, direction_noise=0.6, extra_dof=4.0)
    z, u, w, stats = _directions_near_a_field(gen, n, 0.2)
    ev, log_ps = field_mixture_evidence(prior, *stats, rho)
    mean, psi = field_mixture_posterior_mean(prior, *stats, rho)
    b, noise, straight = _spike_and_slab_draws(gen, prior, prior.row_covariance.expand(M, d + 1, d + 1), rho)
    loglik = field_log_likelihood(z, u, w, b, noise).sum(0)  # (M,)
    mc = torch.logsumexp(loglik, 0) - math.log(M)
    assert float(ev[0] + 0.5 * d * torch.log(w).sum()) == pytest.approx(float(mc), abs=0.03)
    weights = torch.softmax(loglik, 0)
    assert float(torch.exp(log_ps[0])) == pytest.approx(float(weights[straight].sum()), abs=0.02)
    torch.testing.assert_close(mean[0], (weights[:, None, None] * b).sum(0), atol=0.03, rtol=0)
    torch.testing.assert_close(psi[0], (weights[:, None, None] * noise).sum(0), atol=0.03, rtol=0)
    # the straight model is the affine one whose slope prior variance tends to 0 (V0 is diagonal here)
    v0 = prior.row_covariance.clone()
    v0[:d, :d] = torch.eye(d, dtype=F64) * 1e-12
    narrow = FieldPrior(prior.mean, v0, prior.dof, prior.scale)
    counts, szz, suz, suu = stats
    ev_s = field_log_marginal_likelihood(straight_field_prior(prior), counts, szz[..., -1:, -1:], suz[..., -1:], suu)
    assert float(field_log_marginal_likelihood(narrow, *stats)[0]) == pytest.approx(float(ev_s[0]), abs=1e-4)
    ev_a = field_log_marginal_likelihood(prior, *stats)
    mix = torch.logaddexp(math.log(rho) + ev_s, math.log1p(-rho) + ev_a)
    assert float(ev[0]) == pytest.approx(float(mix[0]), abs=1e-12)


def test_two_slope_scales_evidence_and_posterior_against_monte_carlo():
    """With ``wide`` the affine slab is an equal mixture of two slope scales: the evidence, P(straight | u) and the
    posterior-mean field and noise against Monte Carlo draws from that prior (straight with probability rho, else
    scale 1 or 3 with probability 1/2 each); with ``wide`` equal to ``prior`` nothing changes."""
    from lfd_torch.segmentation.field import (
        field_log_likelihood, field_log_marginal_likelihood, field_mixture_evidence, field_mixture_posterior_mean,
        field_prior, straight_field_prior,
    )  # fmt: skip

    gen = torch.Generator().manual_seed(4)
    d, n, rho, M = 2, 3, 0.25, 1_000_000
    prior = field_prior(d, direction_noise=0.6, extra_dof=4.0)
    wide = field_prior(d, direction_noise=0.6, extra_dof=4.0, slope_scale=3.0)
    z, u, w, stats = _directions_near_a_field(gen, n, 0.6)
    ev, log_ps = field_mixture_evidence(prior, *stats, rho, wide)
    mean, psi = field_mixture_posterior_mean(prior, *stats, rho, wide)
    pick_wide = torch.rand(M, generator=gen, dtype=F64) < 0.5
    row_cov = torch.where(pick_wide[:, None, None], wide.row_covariance, prior.row_covariance)
    b, noise, straight = _spike_and_slab_draws(gen, prior, row_cov, rho)
    loglik = field_log_likelihood(z, u, w, b, noise).sum(0)  # (M,)
    mc = torch.logsumexp(loglik, 0) - math.log(M)
    weights = torch.softmax(loglik, 0)
    se = float(weights.square().sum().sqrt())  # relative standard error of the estimate of p(u | z), 1 / sqrt(ESS)
    assert se < 0.05
    assert float(ev[0] + 0.5 * d * torch.log(w).sum()) == pytest.approx(float(mc), abs=4 * se)
    assert float(torch.exp(log_ps[0])) == pytest.approx(float(weights[straight].sum()), abs=0.02)
    torch.testing.assert_close(mean[0], (weights[:, None, None] * b).sum(0), atol=0.05, rtol=0)
    torch.testing.assert_close(psi[0], (weights[:, None, None] * noise).sum(0), atol=0.05, rtol=0)
    # exactly rho p_straight + (1 - rho) (p_1 + p_3) / 2 of the single-scale evidences
    counts, szz, suz, suu = stats
    ev_s = field_log_marginal_likelihood(straight_field_prior(prior), counts, szz[..., -1:, -1:], suz[..., -1:], suu)
    ev_1, ev_3 = field_log_marginal_likelihood(prior, *stats), field_log_marginal_likelihood(wide, *stats)
    mix = torch.logaddexp(math.log(rho) + ev_s, math.log1p(-rho) - math.log(2.0) + torch.logaddexp(ev_1, ev_3))
    assert float(ev[0]) == pytest.approx(float(mix[0]), abs=1e-12)
    assert abs(float(ev_1[0] - ev_3[0])) > 0.5  # the two scales are told apart by these data
    for got, ref in zip(field_mixture_evidence(prior, *stats, rho, prior), field_mixture_evidence(prior, *stats, rho)):
        torch.testing.assert_close(got, ref, atol=1e-12, rtol=0)


def test_demo_offset_statistics_against_scipy_and_the_augmented_regression(generator):
    """Every sequence's own offset Delta_i ~ N(0, v Psi) integrated out: (1) for fixed (B, Psi) the sequence's
    likelihood is the Gaussian with covariance Psi kron (W^-1 + v 1 1^T) over its stacked samples (scipy); (2) the
    evidence equals the MNIW evidence of the regression with one more offset column per sequence, of prior
    variance v (the same model written as a larger conjugate regression)."""
    from lfd_torch.segmentation.field import (
        FieldPrior, demo_offset_statistics, field_log_marginal_likelihood, field_prior, field_statistics,
    )  # fmt: skip

    d, N, T, v = 3, 3, 9, 2.5
    p = d + 1
    prior = field_prior(d, direction_noise=0.3, extra_dof=4.0)
    z = torch.cat([torch.randn(N, T, d, generator=generator, dtype=F64), torch.ones(N, T, 1, dtype=F64)], -1)
    u = torch.randn(N, T, d, generator=generator, dtype=F64)
    w = torch.rand(N, T, generator=generator, dtype=F64) + 0.2
    labels = torch.ones(N, T, 1, dtype=F64)
    labels[0, :2] = 0.0  # sequence 0 visits the state less often
    (counts, szz, suz, suu), extra = demo_offset_statistics(*field_statistics(z, u, w, labels), v)
    assert counts.shape == (1,) and szz.shape == (1, p, p) and extra.shape == (1,)
    # (1) the conditional likelihood of all sequences at a fixed field and noise
    b = torch.randn(d, p, generator=generator, dtype=F64)
    a = torch.randn(d, d, generator=generator, dtype=F64)
    psi = a @ a.T + 0.5 * torch.eye(d, dtype=F64)
    ours = (extra[0] - 0.5 * counts[0] * (d * math.log(2 * math.pi) + torch.logdet(psi))
            + 0.5 * d * (torch.log(w) * labels[..., 0]).sum())
    pinv = torch.linalg.inv(psi)
    quad = suu[0] - suz[0] @ b.T - b @ suz[0].T + b @ szz[0] @ b.T
    ours = ours - 0.5 * torch.trace(pinv @ quad)
    reference = 0.0
    for i in range(N):
        keep = labels[i, :, 0] > 0
        n_i = int(keep.sum())
        rows = torch.diag(1.0 / w[i, keep]) + v * torch.ones(n_i, n_i, dtype=F64)
        mean = (z[i, keep] @ b.T).reshape(-1)  # sample-major stacking: cov = rows kron psi
        cov = torch.kron(rows, psi)
        reference += stats.multivariate_normal(mean.numpy(), cov.numpy()).logpdf(u[i, keep].reshape(-1).numpy())
    assert float(ours) == pytest.approx(reference, abs=1e-8)
    # (2) the evidence against the augmented conjugate regression
    evidence = field_log_marginal_likelihood(prior, counts, szz, suz, suu)[0] + extra[0]
    za = torch.zeros(N, T, p + N, dtype=F64)
    za[..., :p] = z
    for i in range(N):
        za[i, :, p + i] = 1.0
    va = torch.zeros(p + N, p + N, dtype=F64)
    va[:p, :p] = prior.row_covariance
    va[p:, p:] = v * torch.eye(N, dtype=F64)
    augmented = FieldPrior(torch.zeros(d, p + N, dtype=F64), va, prior.dof, prior.scale)
    flat = field_statistics(za.reshape(N * T, -1), u.reshape(N * T, d), w.reshape(N * T), labels.reshape(N * T, 1))
    assert float(evidence) == pytest.approx(float(field_log_marginal_likelihood(augmented, *flat)[0]), abs=1e-8)
    # v = 0 is the plain pooled statistics
    plain = field_statistics(z.reshape(N * T, p), u.reshape(N * T, d), w.reshape(N * T), labels.reshape(N * T, 1))
    zero, extra0 = demo_offset_statistics(*field_statistics(z, u, w, labels), 0.0)
    for x, y in zip(zero, plain):
        torch.testing.assert_close(x, y)
    assert float(extra0.abs().max()) == 0.0


def test_demo_offsets_let_two_turned_demonstrations_share_one_straight_field(generator):
    """Two demonstrations of one straight leg whose directions differ by 0.3 rad, seen with a tight tolerance
    (0.05 rad): one shared field must explain the difference with its tolerance, so two fields (one per
    demonstration) have the higher evidence; with each demonstration's own offset (v = 16, about 0.2 rad) the shared
    field wins, while for one demonstration the offsets change the evidence by less than a nat."""
    from lfd_torch.segmentation.field import (
        demo_offset_statistics, field_mixture_evidence, field_prior, field_statistics,
    )  # fmt: skip

    d, T = 2, 40
    prior = field_prior(d, direction_noise=0.05, extra_dof=30.0)
    s = torch.linspace(-1.0, 1.0, T, dtype=F64)
    z, u = [], []
    for angle, shift in ((-0.15, -0.1), (0.15, 0.1)):
        direction = torch.tensor([math.cos(angle), math.sin(angle)], dtype=F64)
        x = s.unsqueeze(-1) * direction + torch.tensor([0.0, shift], dtype=F64)
        z.append(torch.cat([x, torch.ones(T, 1, dtype=F64)], -1))
        noisy = direction + 0.02 * torch.randn(T, d, generator=generator, dtype=F64)
        u.append(noisy / noisy.norm(dim=-1, keepdim=True))
    z, u, w = torch.stack(z), torch.stack(u), torch.ones(2, T, dtype=F64)
    one = torch.ones(2, T, 1, dtype=F64)

    def shared(v):
        stats, extra = demo_offset_statistics(*field_statistics(z, u, w, one), v)
        return float(field_mixture_evidence(prior, *stats, 0.5)[0][0] + extra[0])

    separate = sum(float(field_mixture_evidence(prior, *field_statistics(z[i], u[i], w[i], one[i]), 0.5)[0][0])
                   for i in range(2))
    assert shared(0.0) < separate < shared(16.0)
    single = [demo_offset_statistics(*field_statistics(z[:1], u[:1], w[:1], one[:1]), v) for v in (0.0, 16.0)]
    evidences = [float(field_mixture_evidence(prior, *st, 0.5)[0][0] + ex[0]) for st, ex in single]
    assert abs(evidences[1] - evidences[0]) < 1.0


def _rotation_reference(prior, z, u, w, d):
    """log p(u | z, rotation) by quadrature over sigma^2 of the Gaussian marginal N(y; 0, sigma^2 (diag(1 / w) +
    Z L0^-1 Z^T)) (theta integrated out in closed form), y the stacked directions, less d / 2 sum log w (the
    Jacobian the callers add)."""
    from lfd_torch.segmentation.field import _rotation_map

    n = z.shape[0]
    G = _rotation_map(d, F64, torch.device("cpu"))
    Z = torch.stack([torch.kron(z[t].unsqueeze(0), torch.eye(d, dtype=F64)) @ G for t in range(n)]).reshape(n * d, -1)
    v0 = torch.diagonal(prior.row_covariance)
    n_rates = d * (d - 1) // 2
    pv = torch.cat([v0[:1].expand(n_rates), v0[-1:].expand(d)])
    shape = torch.diag((1.0 / w).repeat_interleave(d)) + Z @ torch.diag(pv) @ Z.T
    extra = float(prior.dof) - d - 1.0
    a0 = extra * d / 2.0 + 1.0
    b0 = float(prior.scale[0, 0]) / extra * (a0 - 1.0)
    y = u.reshape(-1).numpy()
    cov = shape.numpy()
    log_s2 = np.linspace(-10.0, 3.0, 1301)  # quadrature in log sigma^2
    dens = [stats.multivariate_normal(np.zeros(n * d), math.exp(ls) * cov).logpdf(y)
            + stats.invgamma(a0, scale=b0).logpdf(math.exp(ls)) + ls for ls in log_s2]
    dens = np.array(dens)
    top = dens.max()
    integral = top + math.log(np.trapezoid(np.exp(dens - top), log_s2))
    return integral - 0.5 * d * float(torch.log(w).sum())


@pytest.mark.parametrize("d", [2, 3])
def test_rotation_field_evidence_against_quadrature_and_skew_mean(d):
    """:func:`rotation_field_evidence` is the normal-inverse-gamma marginal likelihood of u_t = W z_t + b + noise
    (W skew): against a quadrature over sigma^2 of the closed-form Gaussian marginal, with random weighted data; its
    posterior-mean slope is skew-symmetric; on a noise-free circular arc it recovers R / r."""
    from lfd_torch.segmentation.field import field_prior, field_statistics, rotation_field_evidence

    g = torch.Generator().manual_seed(11 + d)
    prior = field_prior(d, direction_noise=0.2, extra_dof=3.0)
    n = 9
    z = torch.cat([torch.randn(n, d, generator=g, dtype=F64), torch.ones(n, 1, dtype=F64)], -1)
    u = torch.randn(n, d, generator=g, dtype=F64) * 0.5
    w = torch.rand(n, generator=g, dtype=F64) + 0.3
    stats_ = field_statistics(z, u, w, torch.ones(n, 1, dtype=F64))
    ev, mean, psi = rotation_field_evidence(prior, *stats_)
    assert float(ev[0]) == pytest.approx(_rotation_reference(prior, z, u, w, d), abs=2e-3)
    slope = mean[0, :, :d]
    assert torch.allclose(slope, -slope.T, atol=1e-12) and float(slope.abs().max()) > 0
    assert torch.allclose(psi[0], psi[0, 0, 0] * torch.eye(d, dtype=F64))
    # a noise-free quarter circle of radius 0.5 about c in the first two coordinates: u = R (x - c) / r
    phi = torch.linspace(0.0, math.pi / 2, 40, dtype=F64)
    c = torch.tensor([0.2, -0.1] + [0.3] * (d - 2), dtype=F64)
    x = c.expand(40, d).clone()
    x[:, 0] += 0.5 * torch.cos(phi)
    x[:, 1] += 0.5 * torch.sin(phi)
    tangent = torch.zeros(40, d, dtype=F64)
    tangent[:, 0], tangent[:, 1] = -torch.sin(phi), torch.cos(phi)
    zc = torch.cat([x, torch.ones(40, 1, dtype=F64)], -1)
    _, mean, _ = rotation_field_evidence(prior, *field_statistics(zc, tangent, torch.ones(40, dtype=F64),
                                                                  torch.ones(40, 1, dtype=F64)))
    pred = zc @ mean[0].T
    assert float((pred - tangent).abs().max()) < 0.02
    assert float(mean[0, 1, 0]) == pytest.approx(2.0, rel=0.05)  # the rate 1 / r, up to the prior's shrinkage


def test_rotation_slab_raises_an_arc_and_not_a_corner():
    """With ``rotation_weight`` 0.5 the slab evidence of a circular arc rises above the affine one (one rate where
    the affine field needs two slope entries), while that of two straight legs meeting at a corner (no single
    rotation) is the affine evidence times 0.5: the component favours a true arc, not a merge."""
    from lfd_torch.segmentation.field import field_mixture_evidence, field_prior, field_statistics

    g = torch.Generator().manual_seed(5)
    prior = field_prior(2, direction_noise=0.2, extra_dof=30.0)

    def gain(x, u):
        z = torch.cat([x, torch.ones(x.shape[0], 1, dtype=F64)], -1)
        u = u + 0.05 * torch.randn(u.shape, generator=g, dtype=F64)
        st = field_statistics(z, u, torch.full((x.shape[0],), 0.7, dtype=F64), torch.ones(x.shape[0], 1, dtype=F64))
        affine = field_mixture_evidence(prior, *st, 0.0)[0]
        mixed = field_mixture_evidence(prior, *st, 0.0, rotation_weight=0.5)[0]
        return float(mixed - affine)

    phi = torch.linspace(0.0, 2.0, 30, dtype=F64)  # a 115 degree arc of radius 0.3
    arc = torch.stack([0.3 * torch.cos(phi), 0.3 * torch.sin(phi)], -1)
    assert gain(arc, torch.stack([-torch.sin(phi), torch.cos(phi)], -1)) > 5.0
    s = torch.linspace(0.0, 1.0, 15, dtype=F64).unsqueeze(-1)
    legs = torch.cat([s * torch.tensor([1.0, 0.0], dtype=F64), torch.tensor([1.0, 0.0]) + s * torch.tensor([0.0, 1.0])])
    dirs = torch.cat([torch.tensor([[1.0, 0.0]]).expand(15, 2), torch.tensor([[0.0, 1.0]]).expand(15, 2)]).to(F64)
    assert gain(legs, dirs) == pytest.approx(math.log(0.5), abs=0.05)


def test_rotation_weight_is_a_probability_below_one():
    from lfd_torch.errors import InvalidArgumentError
    from lfd_torch.segmentation.sampler import BetaProcessHMMSampler

    assert BetaProcessHMMSampler(rotation_weight=0.5).rotation_weight == 0.5
    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(InvalidArgumentError, match="rotation_weight"):
            BetaProcessHMMSampler(rotation_weight=bad)


def test_dirichlet_rows_log_density_against_scipy() -> None:
    """Sum over the owned rows j of log Dir(pi_j over the owned features | alpha + kappa delta_j), against
    scipy.stats.dirichlet, for two feature sets in one batch."""
    from lfd_torch.segmentation.transitions import dirichlet_log_density_rows

    rng = np.random.default_rng(4)
    K, alpha, kappa = 5, 0.7, 3.0
    features = torch.tensor([[True, False, True, True, False], [True, True, True, True, True]])
    pi = torch.zeros(2, K, K, dtype=torch.float64)
    want = np.zeros(2)
    for b in range(2):
        own = np.flatnonzero(features[b].numpy())
        for j in own:
            shape = alpha + kappa * (own == j)
            row = rng.dirichlet(shape)
            pi[b, j, own] = torch.from_numpy(row)
            want[b] += stats.dirichlet.logpdf(row, shape)
    got = dirichlet_log_density_rows(pi, features, alpha, kappa)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-10)
