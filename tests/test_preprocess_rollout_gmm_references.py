"""Preprocessing, the rollout engine and the mixture kernels (NIW, Gaussian, PC-GMM, DAMM, post-processing) against
independent references: numpy interpolation, closed forms, scipy densities and per-point loops. Each test targets a
behaviour that the rest of the suite let a small code change through (mutation review)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.special
import scipy.stats
import torch

from lfd_torch.data import Demos
from lfd_torch.errors import LfdError, TooFewSamplesError
from lfd_torch.preprocess import Preprocess, dimension_shares, moving_average, savitzky_golay
from lfd_torch.rollout import rollout

F64 = torch.float64


# ---------------------------------------------------------------------------------------------- preprocess
def test_pipeline_refuses_a_screen_threshold_of_one_at_construction() -> None:
    """Preprocess documents screen_threshold in [0, 1) and checks it at construction: 1.0 (which would drop every
    dimension but one) is refused there, the largest float below 1 is accepted."""
    with pytest.raises(LfdError):
        Preprocess(screen_threshold=1.0)
    Preprocess(screen_threshold=float(np.nextafter(1.0, 0.0)))


def test_pipeline_refuses_a_savgol_polyorder_equal_to_a_window_of_three_at_construction() -> None:
    """A Savitzky-Golay polynomial order must be below the window for every window > 1, window 3 included."""
    with pytest.raises(LfdError):
        Preprocess(window=3, polyorder=3)
    Preprocess(window=3, polyorder=2)


@pytest.mark.parametrize("smoother", [moving_average, savitzky_golay])
def test_a_window_one_sample_longer_than_the_shortest_demonstration_is_refused(smoother) -> None:
    """The window may not exceed the shortest demonstration: with demonstrations of 24 and 40 samples, window 25
    raises TooFewSamplesError naming the short one (index 0), window 23 runs."""
    t = np.linspace(0.0, 1.0, 40)
    seqs = [np.stack([t[:24], t[:24] ** 2], 1), np.stack([t, np.sin(t)], 1)]
    demos = Demos.from_sequences(seqs, times=[t[:24], t])
    with pytest.raises(TooFewSamplesError) as info:
        smoother(demos, 25)
    assert info.value.demo_index == 0
    assert smoother(demos, 23).lengths.tolist() == [24, 40]


def test_dimension_shares_of_motionless_demonstrations_are_uniform() -> None:
    """With zero total variance (every position the same point) the shares are 1/d each and still sum to 1, not
    NaN (0/0)."""
    x = np.tile([[1.0, -2.0, 3.0]], (10, 1))
    shares = dimension_shares(Demos.from_sequences([x, x[:7]]))
    assert torch.isfinite(shares).all()
    np.testing.assert_allclose(shares.numpy(), np.full(3, 1.0 / 3.0), rtol=0, atol=1e-15)


# ---------------------------------------------------------------------------------------------- rollout
def test_positions_at_matches_numpy_interp_between_samples() -> None:
    """positions_at(t) is piecewise linear between samples (floor of t / dt, not the nearest sample) and holds the
    last valid state afterwards: compared with np.interp over each row's valid samples at random query times."""
    rng = np.random.default_rng(7)
    x0 = torch.tensor([[1.0, -0.5], [2.0, 0.3], [0.02, 0.0]], dtype=F64)
    A = torch.tensor([[-1.0, 2.0], [-2.0, -1.0]], dtype=F64)
    res = rollout(lambda x: x @ A.T, x0, 0.1, 40, attractor=torch.zeros(2, dtype=F64), position_tol=0.3,
                  velocity_tol=float("inf"))  # fmt: skip
    assert res.lengths.min() < 41  # at least one row stopped early
    q = np.sort(np.concatenate([rng.uniform(0.0, 5.0, 25), [0.0995, 0.2999]]))
    got = res.positions_at(torch.as_tensor(q)).numpy()
    for b in range(3):
        n = int(res.lengths[b])
        tk = 0.1 * np.arange(n)
        for j in range(2):
            ref = np.interp(q, tk, res.positions[b, :n, j].numpy())
            np.testing.assert_allclose(got[b, :, j], ref, rtol=0, atol=1e-12)


def test_to_demos_defaults_the_goal_to_the_mean_final_state() -> None:
    """Without an attractor (neither in the rollout nor passed), to_demos uses the mean of the rows' final states."""
    x0 = torch.tensor([[1.0, 0.0], [0.0, 2.0], [-3.0, 1.0]], dtype=F64)
    res = rollout(lambda x: -0.5 * x + 0.1, x0, 0.05, 20)
    demos = res.to_demos()
    want = np.mean([res.positions[b, -1].numpy() for b in range(3)], axis=0)
    np.testing.assert_allclose(demos.attractor.numpy(), want, rtol=0, atol=1e-14)


def test_a_hook_push_of_a_stopped_row_forgets_its_earlier_stop() -> None:
    """A row that the hook displaces after it stopped is reactivated and its earlier stop forgotten (module
    docstring): pushed far away near the end of the run, it cannot stop again, so it ends not converged with all
    n_steps + 1 samples, exactly as the same push given as a Disturbance."""
    from lfd_torch.rollout import Disturbance

    g = torch.zeros(2, dtype=F64)
    x0 = torch.tensor([[0.5, 0.0], [0.3, 0.1]], dtype=F64)
    push = torch.tensor([5.0, 0.0], dtype=F64)

    def hook(k, x, active):
        return x + push * torch.tensor([[1.0], [0.0]], dtype=F64) if k == 95 else None

    kw = dict(attractor=g, position_tol=0.05, velocity_tol=0.2)
    base = rollout(lambda x: -2.0 * x, x0, 0.05, 100, **kw)
    assert bool(base.converged.all()) and int(base.lengths.max()) < 95
    res = rollout(lambda x: -2.0 * x, x0, 0.05, 100, hook=hook, **kw)
    ref = rollout(lambda x: -2.0 * x, x0, 0.05, 100,
                  disturbances=[Disturbance(95, push, rows=[0])], **kw)  # fmt: skip
    assert res.converged.tolist() == [False, True] and res.lengths.tolist() == [101, int(base.lengths[1])]
    assert torch.equal(res.lengths, ref.lengths) and torch.equal(res.converged, ref.converged)


# ---------------------------------------------------------------------------------------------- PC-GMM coarsening
def _stub_sampler(monkeypatch, calls: list) -> None:
    """Replace the Gibbs sampler by one that puts every retained sample in its own table (records its input)."""
    import lfd_torch.gmm.pcgmm as pcgmm

    def fake(y, weights, prior, n_iter, generator, trace=None):
        calls.append(y.shape[0])
        M = y.shape[0]
        return np.arange(M), np.zeros(n_iter), np.full(n_iter, M)

    monkeypatch.setattr(pcgmm, "_ddcrp_gibbs", fake)


def test_pcgmm_coarsening_keeps_at_most_max_points_every_ceil_n_over_max_th_sample(monkeypatch) -> None:
    """max_points bounds the samples the sampler runs on: N = 1000 and max_points = 300 keep every
    ceil(1000 / 300) = 4th sample (250 of them), never more than 300."""
    from lfd_torch.gmm.pcgmm import pcgmm_labels

    calls: list = []
    _stub_sampler(monkeypatch, calls)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(1000, 2, generator=g, dtype=F64).cumsum(0)
    v = torch.randn(1000, 2, generator=g, dtype=F64)
    res = pcgmm_labels(x, v, generator=g, max_points=300, n_iter=1, min_cluster_size=1)
    assert calls == [250]
    assert torch.equal(res.sample_index, torch.arange(0, 1000, math.ceil(1000 / 300)))


def test_pcgmm_retained_samples_keep_the_sampler_label_even_when_duplicated(monkeypatch) -> None:
    """After coarsening, the retained samples keep the sampler's own labels; only the others take the label of their
    most similar retained sample. Two retained samples at the same point with the same direction (a still tail
    repeats its end point) but in different sampler tables stay apart."""
    from lfd_torch.gmm.pcgmm import pcgmm_labels

    calls: list = []
    _stub_sampler(monkeypatch, calls)
    g = torch.Generator().manual_seed(2)
    x = torch.randn(40, 2, generator=g, dtype=F64).cumsum(0)
    v = torch.randn(40, 2, generator=g, dtype=F64)
    x[[30, 32, 34]] = x[30].clone()  # duplicated retained samples (stride 2)
    v[[30, 32, 34]] = v[30].clone()
    res = pcgmm_labels(x, v, generator=g, max_points=20, n_iter=1, min_cluster_size=1)
    assert calls == [20]
    assert res.labels[res.sample_index].tolist() == list(range(20))
    # every other sample takes the label of the retained sample with the largest similarity (a per-point loop)
    xs, vs = x[res.sample_index], v[res.sample_index]
    for i in range(1, 40, 2):
        cos = (v[i] @ vs.T) / (v[i].norm() * vs.norm(dim=-1))
        score = torch.exp(-(x[i] - xs).norm(dim=-1) / res.length_scale) * (1 + cos)
        assert int(res.labels[i]) == int(torch.argmax(score)), i


# ---------------------------------------------------------------------------------------------- DAMM moves
def _damm_model(alpha: float):
    from lfd_torch.gmm.damm import _Model
    from lfd_torch.gmm.niw import NIWPrior

    d, nu0 = 2, 12.0
    prior = NIWPrior(torch.zeros(d, dtype=F64), torch.tensor(1.0, dtype=F64), torch.tensor(nu0, dtype=F64),
                     torch.eye(d, dtype=F64) * (nu0 - d - 1.0))  # fmt: skip
    return _Model(alpha, 5.0, prior)


def _two_groups(seed: int, separated: bool):
    g = torch.Generator().manual_seed(seed)
    truth = torch.arange(2).repeat_interleave(100)
    centres = torch.tensor([[-1.0, 0.3], [1.0, -0.3]], dtype=F64)
    y = 0.1 * torch.randn(200, 2, generator=g, dtype=F64) + (centres[truth] if separated else 0.0)
    v = torch.tensor([1.0, 0.2], dtype=F64) + 0.1 * torch.randn(200, 2, generator=g, dtype=F64)
    return y, v / v.norm(dim=-1, keepdim=True), truth, g


def test_damm_split_acceptance_grows_with_alpha() -> None:
    """The split Hastings ratio carries a factor alpha (Chang & Fisher): alpha = 1e300 (log alpha = +691) accepts a
    split of one structureless blob, alpha = 1e-300 rejects even the split of two far-apart clusters (whose ratio at
    alpha = 1 is only about e^70)."""
    from lfd_torch.gmm.damm import _Stats, _split_moves

    for seed in range(3):
        for separated, alpha, want_k in ((False, 1e300, 2), (True, 1e-300, 1)):
            y, u, _, g = _two_groups(700 + seed, separated)
            feats = _Stats.features(y, u, torch.ones(200, dtype=torch.bool))
            z0 = torch.zeros(200, dtype=torch.long)
            _, K = _split_moves(_damm_model(alpha), feats, y, u, z0, _Stats.of(feats, z0, 1, 2), g)
            assert K == want_k, (seed, separated, alpha)


def test_damm_merge_acceptance_falls_with_alpha() -> None:
    """The merge Hastings ratio is 1 / H_split, so it carries 1 / alpha: alpha = 1e-300 merges two far-apart
    clusters, alpha = 1e300 keeps two random halves of one blob apart."""
    from lfd_torch.gmm.damm import _merge_moves, _Stats

    for seed in range(3):
        for separated, alpha, want_k in ((True, 1e-300, 1), (False, 1e300, 2)):
            y, u, truth, g = _two_groups(800 + seed, separated)
            z = truth if separated else torch.randperm(200, generator=g) % 2
            feats = _Stats.features(y, u, torch.ones(200, dtype=torch.bool))
            _, K = _merge_moves(_damm_model(alpha), z, _Stats.of(feats, z, 2, 2), g)
            assert K == want_k, (seed, separated, alpha)


# ---------------------------------------------------------------------------------------------- post-processing
def test_regularize_covariances_accepts_ratio_one_and_makes_covariances_isotropic() -> None:
    """min_eig_ratio lies in [0, 1] (inclusive): at 1 every eigenvalue is raised to the largest one, so each
    covariance becomes lambda_max I (lambda_max from numpy's eigvalsh)."""
    from lfd_torch.gmm import GMM
    from lfd_torch.gmm.postprocess import regularize_covariances

    rng = np.random.default_rng(4)
    R = rng.normal(size=(3, 2, 2))
    cov = R @ R.transpose(0, 2, 1) + 0.1 * np.eye(2)
    gmm = GMM(torch.full((3,), 1 / 3, dtype=F64), torch.as_tensor(rng.normal(size=(3, 2))), torch.as_tensor(cov))
    out = regularize_covariances(gmm, min_eig_ratio=1.0)
    want = np.linalg.eigvalsh(cov)[:, -1][:, None, None] * np.eye(2)
    np.testing.assert_allclose(out.covariances.numpy(), want, rtol=1e-12, atol=1e-12)


def test_merge_small_components_keeps_one_cluster_when_the_largest_are_tied() -> None:
    """When no cluster reaches min_size, only one cluster (the largest; the first of tied ones) is kept, so every
    point ends in a single cluster even if two clusters share the largest count."""
    from lfd_torch.gmm.postprocess import merge_small_components

    x = torch.tensor([[0.0, 0.0], [0.1, 0.0], [5.0, 5.0], [5.1, 5.0], [2.0, 2.0]], dtype=F64)
    out = merge_small_components(x, torch.tensor([0, 0, 1, 1, 2]), 5)
    assert out.tolist() == [0, 0, 0, 0, 0]


@pytest.mark.parametrize("name", ["PCGMMFitter", "DAMMFitter"])
def test_velocity_fitters_refuse_missing_velocities_with_an_argument_error(name: str) -> None:
    """The fitters that need velocities raise InvalidArgumentError (their documented check) when x_dot is None."""
    import lfd_torch.gmm.fitters as fitters
    from lfd_torch.errors import InvalidArgumentError

    x = torch.randn(30, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    with pytest.raises(InvalidArgumentError):
        getattr(fitters, name)()(x, None, generator=torch.Generator().manual_seed(0))


# ---------------------------------------------------------------------------------------------- argument checks
def test_rollout_argument_checks_follow_the_documented_ranges() -> None:
    """Documented ranges: disturbance steps are integers >= 0 (not bools); positions_at times >= 0; x0 needs at least
    one dimension; compact_below in [0, 1]; can_stop and hook_until need a hook."""
    from lfd_torch.errors import InvalidArgumentError, NonFiniteError
    from lfd_torch.rollout import Disturbance

    with pytest.raises(InvalidArgumentError):
        Disturbance(steps=-1, value=[1.0, 0.0])
    with pytest.raises(InvalidArgumentError):
        Disturbance(steps=True, value=[1.0, 0.0])
    x0 = torch.ones(2, 2, dtype=F64)
    res = rollout(lambda x: -x, x0, 0.1, 5)
    with pytest.raises(NonFiniteError):
        res.positions_at(torch.tensor([0.1, -0.5], dtype=F64))
    with pytest.raises(TooFewSamplesError):
        rollout(lambda x: -x, torch.ones(2, 0, dtype=F64), 0.1, 5)
    with pytest.raises(InvalidArgumentError):
        rollout(lambda x: -x, x0, 0.1, 5, compact_below=1.5)
    g = torch.zeros(2, dtype=F64)
    with pytest.raises(InvalidArgumentError):
        rollout(lambda x: -x, x0, 0.1, 5, attractor=g, can_stop=lambda k: torch.ones(2, dtype=torch.bool))
    with pytest.raises(InvalidArgumentError):
        rollout(lambda x: -x, x0, 0.1, 5, attractor=g, hook_until=3)


def test_preprocess_steps_refuse_out_of_range_arguments() -> None:
    """subsample needs a stride >= 1 and trim_still_tail tolerances >= 0 (typed errors, not a division by zero)."""
    from lfd_torch.errors import InvalidArgumentError
    from lfd_torch.preprocess import estimate_velocities, subsample, trim_still_tail

    t = np.linspace(0.0, 1.0, 20)
    demos = estimate_velocities(Demos.from_sequences([np.stack([t, t**2], 1)], times=[t], attractor=np.ones(2)))
    with pytest.raises(InvalidArgumentError):
        subsample(demos, 0)
    with pytest.raises(InvalidArgumentError):
        trim_still_tail(demos, -1.0, 1.0)


def test_gmm_helpers_refuse_out_of_range_arguments() -> None:
    """niw_prior_from_data needs N >= 2 and extra_dof > 0; PC-GMM max_points lies in [3, 10000];
    order_by_attractor refuses a non-finite goal; regularize_covariances needs min_eig >= 0."""
    from lfd_torch.errors import InvalidArgumentError, NonFiniteError
    from lfd_torch.gmm import GMM
    from lfd_torch.gmm.niw import niw_prior_from_data
    from lfd_torch.gmm.pcgmm import pcgmm_labels
    from lfd_torch.gmm.postprocess import order_by_attractor, regularize_covariances

    gen = torch.Generator().manual_seed(0)
    x = torch.randn(20, 2, generator=gen, dtype=F64)
    with pytest.raises(TooFewSamplesError):
        niw_prior_from_data(x[:1])
    with pytest.raises(InvalidArgumentError):
        niw_prior_from_data(x, extra_dof=0.0)
    with pytest.raises(InvalidArgumentError):
        pcgmm_labels(x, x, generator=gen, max_points=2, n_iter=1)
    gmm = GMM(torch.full((2,), 0.5, dtype=F64), x[:2], torch.eye(2, dtype=F64).expand(2, 2, 2).clone())
    with pytest.raises(NonFiniteError):
        order_by_attractor(gmm, torch.tensor([float("nan"), 0.0], dtype=F64))
    with pytest.raises(InvalidArgumentError):
        regularize_covariances(gmm, min_eig=-1.0)


def test_sample_gamma_draws_stay_positive_for_tiny_shapes() -> None:
    """Gamma draws are floored at the smallest positive normal number: for shape 1e-4 the boost U^(1/a) underflows to
    0 for most draws, yet every returned value is >= finfo.tiny (so log pi stays finite)."""
    from lfd_torch.gmm.niw import sample_gamma

    out = sample_gamma(torch.full((2000,), 1e-4, dtype=F64), torch.Generator().manual_seed(5))
    assert bool((out >= torch.finfo(F64).tiny).all())
