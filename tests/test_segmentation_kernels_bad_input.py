"""Segmentation kernels on hard or bad input: underflow in the forward recursion, float32 Dirichlet densities,
NIW prior validation, argument checks of the HMM kernels, the IBP prior, synthetic demonstrations and ``runs``."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError
from lfd_torch.segmentation.states import ffbs, forward_filter, forward_log_likelihood, viterbi
from lfd_torch.segmentation.transitions import dirichlet_log_density_rows


def _brute_force(le: torch.Tensor, init: torch.Tensor, P: torch.Tensor, length: int) -> tuple[float, torch.Tensor]:
    """log p(x) and the posterior marginal of s_0 by enumerating every state sequence (float64)."""
    le, init, P = le.double(), init.double(), P.double()
    K = le.shape[-1]
    terms, firsts = [], []
    for s in itertools.product(range(K), repeat=length):
        lp = torch.log(init[s[0]]) + le[0, s[0]]
        for t in range(1, length):
            lp = lp + torch.log(P[s[t - 1], s[t]]) + le[t, s[t]]
        terms.append(float(lp))
        firsts.append(s[0])
    terms_t = torch.tensor(terms, dtype=torch.float64)
    total = torch.logsumexp(terms_t, 0)
    post0 = torch.zeros(K, dtype=torch.float64)
    post0.index_add_(0, torch.tensor(firsts), torch.exp(terms_t - total))
    return float(total), post0


# ---------------------------------------------------------------------------- 1. underflow of a single state
@pytest.mark.xfail(strict=True, reason="known limitation of states._forward (module docstring): a single state that "
                   "underflows while the others keep the mass is lost; the log-space redo that fixes it made the "
                   "sampler's Geweke test fail, not understood yet")
@pytest.mark.parametrize("dtype,le", [
    (torch.float64, [[0.0, -800.0], [-700.0, 0.0], [-700.0, 0.0]]),
    (torch.float32, [[0.0, -110.0], [-95.0, 0.0], [-95.0, 0.0]]),
])
def test_forward_keeps_a_state_whose_scaled_probability_underflows(dtype, le):
    """Property: the forward log likelihood equals brute-force enumeration when one state falls far (but not
    everywhere) behind the best one, and ffbs draws s_0 from its exact posterior (which favours the lagging state)."""
    le_t = torch.tensor([le], dtype=dtype)
    init = torch.tensor([[0.5, 0.5]], dtype=dtype)
    P = torch.eye(2, dtype=dtype)[None]
    lengths = torch.tensor([3])
    ref, post0 = _brute_force(le_t[0], init[0], P[0], 3)
    got = float(forward_log_likelihood(le_t, init, P, lengths)[0])
    assert got == pytest.approx(ref, rel=1e-5)
    _, ll = forward_filter(le_t, init, P, lengths)
    assert float(ll[0]) == pytest.approx(ref, rel=1e-5)
    assert float(post0[1]) > 0.99
    g = torch.Generator().manual_seed(0)
    draws = ffbs(le_t.expand(64, 3, 2), init.expand(64, 2), P.expand(64, 2, 2), lengths.expand(64), g)
    assert bool((draws[:, 0] == 1).all())


@pytest.mark.xfail(strict=True, reason="known limitation of states._forward (module docstring): a single state that "
                   "underflows while the others keep the mass is lost; the log-space redo that fixes it made the "
                   "sampler's Geweke test fail, not understood yet")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_forward_matches_brute_force_on_random_small_models(dtype):
    """Property: forward_log_likelihood equals the enumeration over all K^T sequences (K, T <= 3), with wide log
    emission spreads (some beyond the underflow margin), ragged lengths, and in half the rows sticky (identity)
    transitions where state 1 lags beyond the margin at t = 0 and state 0 lags at every later sample."""
    g = torch.Generator().manual_seed(1)
    scale = 400.0 if dtype == torch.float64 else 60.0
    lag0, lag = (800.0, 700.0) if dtype == torch.float64 else (110.0, 95.0)
    for K, T in [(2, 3), (3, 3), (3, 2)]:
        B = 6
        le = (torch.rand(B, T, K, generator=g, dtype=torch.float64) * -2.5 * scale).to(dtype)
        init = torch.rand(B, K, generator=g, dtype=torch.float64) + 0.1
        init = (init / init.sum(-1, keepdim=True)).to(dtype)
        P = torch.rand(B, K, K, generator=g, dtype=torch.float64) + 0.05
        P = (P / P.sum(-1, keepdim=True)).to(dtype)
        lengths = torch.randint(1, T + 1, (B,), generator=g)
        le[:3, 0, 1] = le[:3, 0, 0] - lag0
        le[:3, 1:, 0] = le[:3, 1:, 1] - lag
        P[:3] = torch.eye(K, dtype=dtype)
        lengths[:3] = T
        got = forward_log_likelihood(le, init, P, lengths)
        for b in range(B):
            ref, _ = _brute_force(le[b], init[b], P[b], int(lengths[b]))
            assert float(got[b]) == pytest.approx(ref, rel=1e-5, abs=1e-3)


# ---------------------------------------------------------------------------- 2. float32 Dirichlet densities
def test_dirichlet_log_density_rows_float32_matches_float64_with_unowned_features():
    """Property: with a feature nobody owns, the float32 density is finite and equals the float64 one to float32
    precision (1e-300 clamps are 0 in float32, lgamma(0) = inf, inf * 0 = NaN)."""
    g = torch.Generator().manual_seed(2)
    pi = torch.rand(3, 3, generator=g, dtype=torch.float64)
    pi[:, 2] = 0.0
    pi = pi / pi.sum(-1, keepdim=True)
    pi[2] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    features = torch.tensor([True, True, False])
    ref = dirichlet_log_density_rows(pi, features, 1.0, 5.0)
    got = dirichlet_log_density_rows(pi.float(), features, 1.0, 5.0)
    assert torch.isfinite(got)
    assert float(got) == pytest.approx(float(ref), rel=1e-5)


# ---------------------------------------------------------------------------- 3. NIW prior validation
from lfd_torch.gmm.niw import NIWPrior, niw_log_marginal_likelihood, niw_prior_from_data  # noqa: E402


def _niw(**kw):
    f = dict(mean=torch.zeros(2, dtype=torch.float64), kappa=torch.tensor(1.0, dtype=torch.float64),
             dof=torch.tensor(4.0, dtype=torch.float64), scale=torch.eye(2, dtype=torch.float64))
    f.update(kw)
    return NIWPrior(**f)


@pytest.mark.parametrize("field,value,error", [
    ("scale", -torch.eye(2, dtype=torch.float64), InvalidArgumentError),
    ("scale", torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64), InvalidArgumentError),
    ("scale", torch.tensor([[1.0, math.nan], [math.nan, 1.0]], dtype=torch.float64), NonFiniteError),
    ("mean", torch.tensor([0.0, math.inf], dtype=torch.float64), NonFiniteError),
    ("mean", torch.zeros(2), ShapeMismatchError),  # float32 among float64 fields
    ("kappa", torch.ones(3, dtype=torch.float64), None),  # batch (3,) against scale batch (2,) below
    ("mean", torch.zeros(0, dtype=torch.float64), ShapeMismatchError),
])
def test_niw_prior_rejects_improper_parameters(field, value, error):
    """Property: NIWPrior accepts only a proper prior (finite, one dtype, d >= 1, broadcasting batch shapes,
    symmetric positive definite scale), naming the field."""
    if error is None:
        with pytest.raises(ShapeMismatchError, match="broadcast"):
            _niw(kappa=value, scale=torch.eye(2, dtype=torch.float64).expand(2, 2, 2))
        return
    kw = {field: value}
    if field == "mean" and value.shape == (0,):
        kw["scale"] = torch.zeros(0, 0, dtype=torch.float64)
        kw["dof"] = torch.tensor(1.0, dtype=torch.float64)
    with pytest.raises(error):
        _niw(**kw)


def test_niw_log_marginal_likelihood_rejects_bad_counts_and_shapes():
    """Property: negative / NaN counts and statistics of the wrong shape raise typed errors instead of returning 0
    or broadcasting."""
    prior = _niw()
    sums, outer = torch.zeros(3, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64).expand(3, 2, 2)
    for counts in (torch.tensor([1.0, -1.0, 2.0], dtype=torch.float64),
                   torch.tensor([1.0, math.nan, 2.0], dtype=torch.float64)):
        with pytest.raises(InvalidArgumentError, match="counts"):
            niw_log_marginal_likelihood(prior, counts, sums, outer)
    with pytest.raises(ShapeMismatchError, match="sums"):
        niw_log_marginal_likelihood(prior, torch.ones(3, dtype=torch.float64), torch.zeros(1, 2, dtype=torch.float64),
                                    outer)


def test_niw_prior_from_constant_data_is_proper():
    """Property: constant data give a finite, positive definite scale (a floored variance), so the marginal
    likelihood of a point under the prior is finite."""
    for value in (3.0, 0.0):
        prior = niw_prior_from_data(torch.full((10, 2), value, dtype=torch.float64))
        assert bool(torch.linalg.cholesky_ex(prior.scale)[1] == 0)
        assert float(torch.linalg.eigvalsh(prior.scale).min()) > torch.finfo(torch.float64).tiny * 1e6
        assert bool(torch.isfinite(torch.logdet(prior.scale)))
    x = torch.zeros(10, 2, dtype=torch.float64)
    ll = niw_log_marginal_likelihood(prior, torch.ones(1, dtype=torch.float64), x[:1], (x[0, :, None] * x[0])[None])
    assert bool(torch.isfinite(ll).all())


# ---------------------------------------------------------------------------- 4. arguments of the HMM kernels
def _hmm(B=2, T=4, K=3, dtype=torch.float64):
    g = torch.Generator().manual_seed(4)
    le = torch.randn(B, T, K, generator=g, dtype=dtype)
    init = torch.full((B, K), 1.0 / K, dtype=dtype)
    P = torch.full((B, K, K), 1.0 / K, dtype=dtype)
    return le, init, P, torch.full((B,), T, dtype=torch.long)


def _bad_hmm_cases():
    le, init, P, n = _hmm()
    nan_le = le.clone()
    nan_le[0, 1, 1] = math.nan
    inf_le = le.clone()
    inf_le[1, 0, 0] = math.inf
    return [
        ("lengths 0", (le, init, P, torch.tensor([0, 4])), InvalidArgumentError),
        ("lengths negative", (le, init, P, torch.tensor([-1, 4])), InvalidArgumentError),
        ("lengths > T", (le, init, P, torch.tensor([5, 4])), InvalidArgumentError),
        ("lengths list", (le, init, P, [4, 4]), ShapeMismatchError),
        ("lengths float", (le, init, P, n.double()), InvalidArgumentError),
        ("NaN emission", (nan_le, init, P, n), NonFiniteError),
        ("+Inf emission", (inf_le, init, P, n), NonFiniteError),
        ("not row-stochastic", (le, init, P * 2, n), InvalidArgumentError),
        ("negative initial", (le, init * torch.tensor([3.0, -1.0, -1.0], dtype=torch.float64), P, n),
         InvalidArgumentError),
        ("T = 0", (le[:, :0], init, P, n), ShapeMismatchError),
        ("K = 0", (le[..., :0], init[:, :0], P[:, :0, :0], n), ShapeMismatchError),
        ("mixed dtype", (le, init.float(), P, n), ShapeMismatchError),
    ]


@pytest.mark.parametrize("kernel", ["forward_log_likelihood", "forward_filter", "ffbs", "viterbi"])
def test_hmm_kernels_reject_bad_arguments(kernel):
    """Property: every public HMM kernel raises a typed lfd_torch error naming the argument for out-of-range
    lengths, NaN / +Inf log emissions, non-stochastic transitions, negative initial, empty T or K, a list of
    lengths and mixed dtypes, instead of silently wrong numbers or raw IndexError / AttributeError."""
    fn = {"forward_log_likelihood": forward_log_likelihood, "forward_filter": forward_filter, "viterbi": viterbi,
          "ffbs": lambda *a: ffbs(*a, torch.Generator().manual_seed(0))}[kernel]
    for label, args, error in _bad_hmm_cases():
        with pytest.raises(error):
            fn(*args)
        with pytest.raises(error) as info:
            fn(*args)
        assert any(w in str(info.value) for w in ("log_emission", "initial", "transition", "lengths")), label


def test_ffbs_and_backward_sample_require_a_generator():
    """Property: ffbs / backward_sample need an explicit torch.Generator (None would silently use the global RNG)."""
    from lfd_torch.segmentation.states import backward_sample
    le, init, P, n = _hmm()
    for gen in (None, 0):
        with pytest.raises(InvalidArgumentError, match="generator"):
            ffbs(le, init, P, n, gen)
        filtered, _ = forward_filter(le, init, P, n)
        with pytest.raises(InvalidArgumentError, match="generator"):
            backward_sample(filtered, P, n, gen)


# ---------------------------------------------------------------------------- 5-7. IBP, synthetic data, runs
def test_ibp_functions_reject_bad_arguments_and_keep_valid_values():
    """Property: ibp_log_prior and sample_ibp raise typed errors naming the argument (integer features, whose
    {0, 2} entries gave +inf; mass or concentration <= 0, which gave NaN or ZeroDivisionError; no generator; an
    exceeded max_features), and a valid call still equals the direct formula for a 2 x 2 matrix."""
    from lfd_torch.segmentation import ibp_log_prior, sample_ibp

    g = torch.Generator().manual_seed(0)
    F = torch.tensor([[True, False], [True, True]])
    # direct: K+ = 2, one column per pattern; m = (2, 1), N = 2, gamma = 2, c = 1, H = c/c + c/(c+1) = 1.5
    gam, c = 2.0, 1.0
    direct = 2 * math.log(gam * c) - gam * 1.5 + sum(
        math.lgamma(m) + math.lgamma(2 - m + c) - math.lgamma(2 + c) for m in (2, 1))
    assert float(ibp_log_prior(F, gam, c)) == pytest.approx(direct, rel=1e-12)
    with pytest.raises(ShapeMismatchError, match="features"):
        ibp_log_prior(F.long() * 2, gam, c)
    with pytest.raises(InvalidArgumentError, match="mass"):
        ibp_log_prior(F, 0.0, c)
    with pytest.raises(InvalidArgumentError, match="concentration"):
        ibp_log_prior(F, gam, -1.0)
    with pytest.raises(InvalidArgumentError, match="generator"):
        sample_ibp(3, gam, c, None)
    with pytest.raises(InvalidArgumentError, match="concentration"):
        sample_ibp(3, gam, 0.0, g)
    with pytest.raises(InvalidArgumentError, match="max_features"):
        sample_ibp(50, 50.0, c, g, max_features=5)


def test_multi_step_demos_checks_and_records_its_noise():
    """Property: multi_step_demos records the noise it adds (SyntheticSteps.noise was always 0.0) and rejects
    settings it silently altered or misreported (samples_per_step <= 0 became 4; timing_jitter >= 1 gives
    non-positive leg factors; 1-D waypoints; no generator); the same seed gives the same data."""
    from lfd_torch.segmentation import multi_step_demos

    a = multi_step_demos(torch.Generator().manual_seed(3), noise=0.05)
    b = multi_step_demos(torch.Generator().manual_seed(3), noise=0.05)
    assert a.noise == 0.05 and torch.equal(a.demos.positions, b.demos.positions)
    g = torch.Generator().manual_seed(0)
    for kw, name in [({"samples_per_step": 0}, "samples_per_step"), ({"timing_jitter": 2.0}, "timing_jitter"),
                     ({"noise": -0.1}, "noise"), ({"n_demos": 0}, "n_demos")]:
        with pytest.raises(InvalidArgumentError, match=name):
            multi_step_demos(g, **kw)
    with pytest.raises(ShapeMismatchError, match="waypoints"):
        multi_step_demos(g, waypoints=torch.zeros(3, dtype=torch.float64))
    with pytest.raises(InvalidArgumentError, match="generator"):
        multi_step_demos(None)


def test_runs_rejects_non_sequences_and_matches_a_loop():
    """Reference: a plain loop over the labels; empty, 0-d, 2-D and float labels raise ShapeMismatchError (a raw
    IndexError before)."""
    from lfd_torch.segmentation import runs

    labels = torch.tensor([2, 2, 0, 0, 0, 1, 2, 2])
    starts, ends, values = runs(labels)
    loop, start = [], 0
    for t in range(1, len(labels) + 1):
        if t == len(labels) or labels[t] != labels[t - 1]:
            loop.append((start, t, int(labels[start])))
            start = t
    assert list(zip(starts.tolist(), ends.tolist(), values.tolist())) == loop
    for bad in (torch.tensor([], dtype=torch.long), torch.tensor(3), torch.zeros(2, 2, dtype=torch.long),
                torch.tensor([0.0, 1.0])):
        with pytest.raises(ShapeMismatchError, match="labels"):
            runs(bad)


def test_sampler_run_checks_its_arguments():
    """Property: BetaProcessHMMSampler.run names the bad argument: a min_duration that is not an integer in
    [1, shortest sequence] (0 and -2 gave raw errors, 2.7 was truncated, 1000 with T = 33 ran for over ten minutes),
    a NaN speed_floor (raw LinAlgError), mixed dtypes (raw RuntimeError), no generator, NaN velocities."""
    from lfd_torch.segmentation import BetaProcessHMMSampler

    g = torch.Generator().manual_seed(0)
    x = [torch.randn(33, 2, generator=g, dtype=torch.float64).cumsum(0)]
    v = [torch.randn(33, 2, generator=g, dtype=torch.float64)]
    sampler = BetaProcessHMMSampler(n_chains=1, n_iterations=2)
    for bad in (0, -2, 2.7, 1000):
        with pytest.raises(InvalidArgumentError, match="min_duration"):
            sampler.run(x, v, g, min_duration=bad)
    with pytest.raises(InvalidArgumentError, match="speed_floor"):
        sampler.run(x, v, g, speed_floor=float("nan"))
    with pytest.raises(ShapeMismatchError, match="dtype"):
        sampler.run(x, [v[0].float()], g)
    with pytest.raises(InvalidArgumentError, match="generator"):
        sampler.run(x, v, 0)
    nan_v = [v[0].clone()]
    nan_v[0][3, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="velocities"):
        sampler.run(x, nan_v, g)
    assert sampler.run(x, v, torch.Generator().manual_seed(1), min_duration=2).states.shape == (1, 33)
