"""The segmentation's post-sampler steps against independent references (naive loops, numpy/scipy, closed forms,
hand-worked cases): run-length encoding, the minimum step length, the least-squares velocities and their noise,
path length and the path-length grid, the position-noise fit, the weighted LCS, routes and their alignment, the
subtask-space Gaussians, attractors, end points, the Segmentation API (membership ties, table, split, store checks)
and the fixed segmenters. Every random draw is seeded; float64 throughout.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
import torch
from scipy.optimize import nnls
from scipy.signal import lfilter
from scipy.stats import median_abs_deviation

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, StoreError, TooFewSamplesError
from lfd_torch.segmentation import FixedSegmenter, NoSegmenter, Segmentation, runs
from lfd_torch.segmentation import segmentation as S
from lfd_torch.segmentation.synthetic import multi_step_demos

F64 = torch.float64


# ---------------------------------------------------------------------------------------------- runs, min length
def test_runs_equal_a_python_run_length_loop():
    """Property: ``runs`` gives the maximal runs of equal labels (start, exclusive end, value), as a plain Python
    run-length loop does, on random label sequences (lengths 1-30, few values so runs are long and short)."""
    rng = np.random.default_rng(0)
    for _ in range(200):
        lab = rng.integers(0, 3, size=int(rng.integers(1, 31))).tolist()
        want = []
        for t, v in enumerate(lab):
            if want and want[-1][2] == v:
                want[-1][1] = t + 1
            else:
                want.append([t, t + 1, v])
        starts, ends, values = runs(torch.tensor(lab))
        assert [list(r) for r in zip(starts.tolist(), ends.tolist(), values.tolist())] == want


def test_resolve_min_length_is_the_documented_count():
    """Property (docstring): a whole number >= 1 is that many samples, a fraction f in (0, 1) is ceil(f T) samples,
    never fewer than 3; non-whole numbers >= 1, 0, negatives, NaN, Inf and bools are refused."""
    assert S.resolve_min_length(0.04, 1000) == 40
    assert S.resolve_min_length(0.041, 1000) == 41  # ceil(41.0) and not more
    assert S.resolve_min_length(0.0405, 1000) == 41  # ceil(40.5): rounds up, not to nearest
    assert S.resolve_min_length(0.0401, 1000) == 41
    assert S.resolve_min_length(0.01, 1000) == 10 and S.resolve_min_length(0.01, 100) == 3  # the floor of 3
    assert S.resolve_min_length(0.03, 100) == 3 and S.resolve_min_length(0.031, 100) == 4
    assert S.resolve_min_length(7, 10) == 7 and S.resolve_min_length(7.0, 10) == 7 and S.resolve_min_length(1, 50) == 3
    assert S.resolve_min_length(2, 50) == 3 and S.resolve_min_length(3, 50) == 3
    for bad in (2.5, 1.5, 0, 0.0, -0.1, -3, float("nan"), float("inf"), True, "0.1", None):
        with pytest.raises(InvalidArgumentError):
            S.resolve_min_length(bad, 100)


def test_check_demos_needs_two_minimum_lengths():
    """Property: segmenting needs T >= 2 * min_length samples per demonstration: T = 2 m passes, T = 2 m - 1 raises
    TooFewSamplesError (min_length 5: 10 passes, 9 does not)."""
    x = torch.linspace(0, 1, 10, dtype=F64)[:, None] * torch.tensor([1.0, 2.0], dtype=F64)
    assert S._check_demos([x], 5).n_demos == 1
    with pytest.raises(TooFewSamplesError):
        S._check_demos([x, x[:9]], 5)


# ---------------------------------------------------------------------------------------------- velocities, noise
def _slope_weights(n: int) -> np.ndarray:
    """Weights a with slope = a @ x of the least-squares line through x_0..x_{n-1} at times 0..n-1 (pseudo-inverse
    of the design matrix [1, t])."""
    design = np.column_stack([np.ones(n), np.arange(n, dtype=float)])
    return np.linalg.pinv(design)[1]


def test_scale_velocities_equal_numpy_polyfit_over_each_window():
    """Reference: at every sample t the velocity is the slope (np.polyfit, degree 1) of the positions over the
    window [t - h, t + h] cut at the ends, divided by dt; strides 1, 3 and an explicit half width, random data."""
    rng = np.random.default_rng(1)
    x = rng.standard_normal((37, 3)).cumsum(0)
    for stride, hw, dt in ((3, None, 0.01), (1, None, 0.5), (2, 5, 0.02)):
        h = stride if hw is None else hw
        got = S.scale_velocities(torch.tensor(x), stride, dt, hw).numpy()
        for t in range(37):
            lo, hi = max(0, t - h), min(36, t + h) + 1
            want = np.polyfit(np.arange(lo, hi) * dt, x[lo:hi], 1)[0]
            np.testing.assert_allclose(got[t], want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_velocity_noise_is_the_estimators_variance_under_ar1_noise(rho):
    """Reference: with a the slope weights of each window (pseudo-inverse) and Sigma_ij = sigma^2 rho^|i - j| the
    AR(1) covariance, the slope noise is (a Sigma a)^(1/2) / dt per axis; windows of 3 or more samples (h = 2,
    windows 3..5 at the ends and 5 inside)."""
    sigma, dt, T, h = 0.3, 0.05, 12, 2
    got = S.velocity_noise(sigma, T, h, dt, rho=rho).numpy()
    for t in range(T):
        n = min(T - 1, t + h) - max(0, t - h) + 1
        a = _slope_weights(n)
        cov = sigma**2 * rho ** np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
        np.testing.assert_allclose(got[t], math.sqrt(a @ cov @ a) / dt, rtol=1e-10)


def test_velocity_noise_of_a_two_sample_window_is_that_of_a_difference():
    """Property (docstring formula n (n^2 - 1) / 12): at stride 1 the first velocity is (x_1 - x_0) / dt, whose
    noise under white noise sigma is sqrt(2) sigma / dt, in both the white and the AR(1) branch (rho -> 0)."""
    white = S.velocity_noise(1.0, 10, 1, 1.0)
    ar = S.velocity_noise(1.0, 10, 1, 1.0, rho=1e-12)
    assert float(white[0]) == pytest.approx(math.sqrt(2.0)) and float(ar[0]) == pytest.approx(math.sqrt(2.0))


def test_path_length_of_a_straight_line_is_speed_times_time():
    """Closed form: a motion at constant velocity (3, 4) (speed 5) with zero velocity noise has path length
    5 dt (t + 1) at sample t (the cumulative sum includes the sample's own interval); a velocity whose squared norm
    is below d sigma_v^2 adds no length; dt scales the length."""
    v = torch.tensor([3.0, 4.0], dtype=F64).expand(50, 2)
    for dt in (0.01, 0.2):
        got = S.path_length(v, torch.zeros(50, dtype=F64), dt)
        torch.testing.assert_close(got, 5.0 * dt * torch.arange(1, 51, dtype=F64))
    noisy = S.path_length(v, torch.full((50,), 3.0, dtype=F64), 1.0)  # ||v||^2 = 25 < 2 * 9 + ... -> sqrt(25 - 18)
    torch.testing.assert_close(noisy, math.sqrt(7.0) * torch.arange(1, 51, dtype=F64))
    assert float(S.path_length(v, torch.full((50,), 4.0, dtype=F64), 1.0).abs().max()) == 0.0


def test_path_grid_equals_a_loop_over_the_levels():
    """Reference loop (module docstring, item 3c): n = ceil(T / k) levels (j + 1/2) L / n; each grid sample is the
    first whose path length reaches a level, a sample reached by several levels is kept once with the first; the
    crossing instant is interpolated linearly in path length. Random positive speeds, T = 50, strides 3, 4 and 7."""
    rng = np.random.default_rng(2)
    speed = rng.uniform(0.0, 2.0, 50)
    speed[20:26] = 0.0  # a rest
    speed[30] = 40.0  # one fast sample that covers several levels
    v = torch.tensor(speed)[:, None]
    times = torch.tensor(np.cumsum(rng.uniform(0.5, 1.5, 50)))
    L = np.cumsum(speed * 0.1)
    for k in (3, 4, 7):
        n = math.ceil(50 / k)
        first: dict[int, float] = {}
        for j in range(n):
            level = (j + 0.5) * L[-1] / n
            first.setdefault(next((t for t in range(50) if L[t] >= level), 49), level)
        grid = S.path_grid(v, torch.zeros(50, dtype=F64), k, 0.1)
        assert grid.tolist() == sorted(first)
        inst, lev = S.grid_crossings(v, torch.zeros(50, dtype=F64), k, 0.1, times)
        np.testing.assert_allclose(lev.numpy(), [first[t] for t in sorted(first)], rtol=1e-12)
        for got, t in zip(inst.tolist(), sorted(first)):
            level, tm = first[t], times.numpy()
            want = tm[0] if t == 0 else tm[t - 1] + (level - L[t - 1]) / (L[t] - L[t - 1]) * (tm[t] - tm[t - 1])
            assert got == pytest.approx(want, rel=1e-12)


def test_grid_without_motion_is_every_kth_sample():
    """Property (docstring): with no motion the grid is every k-th sample, its levels the sample indices 0, k, 2k,
    ... and its crossing instants those samples' times."""
    times = torch.tensor(np.cumsum(np.random.default_rng(3).uniform(0.1, 1.0, 23)))
    inst, lev = S.grid_crossings(torch.zeros(23, 2, dtype=F64), torch.zeros(23, dtype=F64), 5, 0.1, times)
    assert S.path_grid(torch.zeros(23, 2, dtype=F64), torch.zeros(23, dtype=F64), 5, 0.1).tolist() == [0, 5, 10, 15, 20]
    assert lev.tolist() == [0.0, 5.0, 10.0, 15.0, 20.0]
    torch.testing.assert_close(inst, times[[0, 5, 10, 15, 20]])


def test_time_at_length_clamps_outside_the_path():
    """Property (docstring): t_0 for levels at or below L_0, t_(T-1) beyond the end of the path (also when the path
    ends with a rest), linear in path length between samples."""
    length = torch.tensor([1.0, 2.0, 4.0, 4.0], dtype=F64)
    times = torch.tensor([10.0, 11.0, 13.0, 20.0], dtype=F64)
    got = S.time_at_length(length, times, torch.tensor([0.0, 1.0, 1.5, 3.0, 4.0, 9.0], dtype=F64))
    assert got.tolist() == pytest.approx([10.0, 10.0, 10.5, 12.0, 13.0, 20.0])
    rising = torch.tensor([1.0, 2.0, 4.0], dtype=F64)
    assert S.time_at_length(rising, times[:3], torch.tensor([7.0], dtype=F64)).tolist() == [13.0]


# ---------------------------------------------------------------------------------------------- position noise
def _ar1_np(rng: np.random.Generator, shape: tuple[int, int], rho: float, sigma: float) -> np.ndarray:
    eta = rng.standard_normal(shape)
    eta[1:] *= math.sqrt(1.0 - rho * rho)
    return sigma * lfilter([1.0], [1.0, -rho], eta, axis=0)


def _noise_model_reference(seqs: list[np.ndarray]) -> tuple[float, float]:
    """The docstring's AR(1) fit written with scipy: robust variances (normal-scaled MAD about 0) of the lag-L second
    differences, L = 1..4; for every rho on 0, 0.01, .., 0.8 non-negative least squares (scipy nnls) of
    sigma^2 2 (1 - rho^L)(3 - rho^L) + S L^4 relative to them; AR(1) only if the best rho lowers the relative residual
    by more than 10.83 * 10 / n (n the number of lag-one second differences), else the white lag-one estimate."""
    def robust_var(L: int) -> float:
        x = np.concatenate([(s[2 * L:] - 2 * s[L:-L] + s[: -2 * L]).ravel() for s in seqs if len(s) > 2 * L])
        return float(median_abs_deviation(x, center=lambda a, axis=None: 0.0, scale="normal")) ** 2

    v = np.array([robust_var(L) for L in (1, 2, 3, 4)])
    white = math.sqrt(v[0] / 6.0)
    lags = np.arange(1.0, 5.0)
    fits = []
    for rho in np.arange(81) * 0.01:
        A = np.column_stack([2 * (1 - rho**lags) * (3 - rho**lags), lags**4]) / v[:, None]
        coef, rnorm = nnls(A, np.ones(4))
        fits.append((rnorm**2, coef, rho))
    k = int(np.argmin([f[0] for f in fits]))
    n = sum(s[2:].size for s in seqs)
    if k > 0 and fits[k][1][0] > 0 and (fits[0][0] - fits[k][0]) / (10.0 / n) > 10.83:
        return math.sqrt(fits[k][1][0]), fits[k][2]
    return white, 0.0


def test_position_noise_of_white_noise_on_a_line_is_its_sigma():
    """Closed form: white noise of standard deviation 0.02 on a straight line (second differences are noise only)
    estimates 0.02 within 5 % (8000 differences); two sequences pool their differences (the estimate of a quiet
    and a loud sequence lies strictly between theirs) and a repeated sequence changes nothing."""
    rng = np.random.default_rng(4)
    line = np.linspace(0, 1, 4001)[:, None] * np.array([1.0, -2.0])
    quiet = torch.tensor(line + 0.02 * rng.standard_normal(line.shape))
    loud = torch.tensor(line + 0.06 * rng.standard_normal(line.shape))
    assert S.position_noise([quiet]) == pytest.approx(0.02, rel=0.05)
    assert S.position_noise([quiet]) < S.position_noise([quiet, loud]) < S.position_noise([loud])
    assert S.position_noise([loud, quiet]) == S.position_noise([quiet, loud])
    assert S.position_noise([quiet, quiet]) == pytest.approx(S.position_noise([quiet]), rel=1e-12)


@pytest.mark.parametrize(("seed", "rho"), [(3, 0.5), (1, 0.4), (0, 0.0), (4, 0.6)])
def test_position_noise_model_equals_a_scipy_nnls_fit(seed, rho):
    """Reference: :func:`_noise_model_reference` (scipy nnls per rho, scipy MAD). 3-D curves of 400 samples with
    AR(1) noise of 1 %: seed 3 / rho 0.5 is detected with a test statistic of about 23, between 10.83 and 3 x 10.83
    (counting rows instead of the 3 axes' differences would keep it white); seed 1 / rho 0.4 stays white (about 7);
    white noise stays white."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 400)[:, None]
    path = np.hstack([np.cos(2 * t), np.sin(3 * t), t**2])
    x = path + _ar1_np(rng, (400, 3), rho, 0.01)
    sigma, rho_hat = S.position_noise_model([torch.tensor(x)])
    want_sigma, want_rho = _noise_model_reference([x])
    assert rho_hat == pytest.approx(want_rho, abs=0.0101)
    assert sigma == pytest.approx(want_sigma, rel=2e-3)  # torch's median is the lower middle value, numpy's the mean
    assert (rho_hat > 0) == {(3, 0.5): True, (1, 0.4): False, (0, 0.0): False, (4, 0.6): True}[(seed, rho)]


# ---------------------------------------------------------------------------------------------- LCS, routes
def _lcs_dp(a: list[int], b: list[int], wa: list[float], wb: list[float]) -> tuple[float, list[tuple[int, int]]]:
    """Plain forward dynamic programme of the weighted LCS (match weight wa_i + wb_j) with its optimal pairs."""
    n, m = len(a), len(b)
    f = [[0.0] * (m + 1) for _ in range(n + 1)]  # f[i][j]: best over a[:i], b[:j]
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            f[i][j] = max(f[i - 1][j], f[i][j - 1])
            if a[i - 1] == b[j - 1]:
                f[i][j] = max(f[i][j], f[i - 1][j - 1] + wa[i - 1] + wb[j - 1])
    pairs, i, j = [], n, m
    while i > 0 and j > 0:
        if a[i - 1] == b[j - 1] and f[i][j] == f[i - 1][j - 1] + wa[i - 1] + wb[j - 1]:
            pairs.append((i - 1, j - 1))
            i, j = i - 1, j - 1
        elif f[i - 1][j] >= f[i][j - 1]:
            i -= 1
        else:
            j -= 1
    return f[n][m], pairs[::-1]


def _random_runs(rng: np.random.Generator, n_states: int = 3, max_len: int = 6) -> tuple[list[int], list[float]]:
    """A run-state sequence (no two equal neighbours) with random run fractions summing to 1."""
    k = int(rng.integers(1, max_len + 1))
    seq = [int(rng.integers(n_states))]
    while len(seq) < k:
        s = int(rng.integers(n_states))
        if s != seq[-1]:
            seq.append(s)
    return seq, rng.dirichlet(np.ones(k)).tolist()


def test_lcs_is_an_optimal_common_subsequence():
    """Reference: the pairs of ``_lcs`` are strictly increasing in both sequences, join equal states, and their
    weight sum (wa_i + wb_j) equals the optimum of a plain dynamic programme, on 300 random pairs."""
    rng = np.random.default_rng(5)
    for _ in range(300):
        (a, wa), (b, wb) = _random_runs(rng, 3, 8), _random_runs(rng, 3, 8)
        pairs = S._lcs(a, b, wa, wb)
        assert all(a[i] == b[j] for i, j in pairs)
        assert all(i2 > i1 and j2 > j1 for (i1, j1), (i2, j2) in zip(pairs, pairs[1:]))
        best, _ = _lcs_dp(a, b, wa, wb)
        assert sum(wa[i] + wb[j] for i, j in pairs) == pytest.approx(best, rel=1e-12, abs=1e-12)


def test_routes_are_the_components_of_the_half_coverage_graph():
    """Reference: two demonstrations are linked when the states of their (unique, random weights) optimal weighted
    LCS cover at least half of each; routes are the connected components (breadth-first search), ordered by their
    first demonstration; 150 random sets of 2-6 demonstrations."""
    rng = np.random.default_rng(6)
    for _ in range(150):
        N = int(rng.integers(2, 7))
        drawn = [_random_runs(rng, 3, 4) for _ in range(N)]
        seqs, fracs = [d[0] for d in drawn], [d[1] for d in drawn]
        adj = {i: set() for i in range(N)}
        for i, j in itertools.combinations(range(N), 2):
            _, pairs = _lcs_dp(seqs[i], seqs[j], fracs[i], fracs[j])
            if sum(fracs[i][p] for p, _ in pairs) >= 0.5 and sum(fracs[j][q] for _, q in pairs) >= 0.5:
                adj[i].add(j)
                adj[j].add(i)
        seen, want = set(), []
        for i in range(N):
            if i in seen:
                continue
            comp, todo = [], [i]
            seen.add(i)
            while todo:
                u = todo.pop()
                comp.append(u)
                for w in adj[u] - seen:
                    seen.add(w)
                    todo.append(w)
            want.append(sorted(comp))
        assert S._routes(seqs, fracs) == want


def test_routes_half_coverage_boundary_and_transitive_links():
    """Hand-worked cases: a shared state covering exactly half of a demonstration links it (at least half); a link
    needs half of EACH demonstration (one covering all of one and 30 % of the other does not); demonstration 0
    linked to 1 and to 2 puts all three in one route although 1 and 2 share nothing."""
    assert S._routes([[0, 1], [0]], [[0.5, 0.5], [1.0]]) == [[0, 1]]
    assert S._routes([[0], [0, 1]], [[1.0], [0.3, 0.7]]) == [[0], [1]]
    assert S._routes([[0, 1], [0], [1]], [[0.5, 0.5], [1.0], [1.0]]) == [[0, 1, 2]]
    assert S._routes([[1], [0, 1], [0]], [[1.0], [0.5, 0.5], [1.0]]) == [[0, 1, 2]]


def test_align_route_keeps_order_and_states_and_starts_from_the_richest():
    """Properties (module docstring): every run of every demonstration maps to a route step of its own state, in
    increasing step order, every step is some run's; the alignment starts from the richest demonstration, so its
    runs are the route's skeleton: (a, d, e) against (a, b, c, e) gives the route (a, d, b, c, e) (hand-worked:
    d, unmatched, joins at its place after a) and the assignments [0, 1, 4], [0, 2, 3, 4]."""
    assert S._align_route([[7, 9, 8], [7, 5, 6, 8]], [[0.3, 0.3, 0.4], [0.25] * 4]) == (
        [7, 9, 5, 6, 8], [[0, 1, 4], [0, 2, 3, 4]])
    rng = np.random.default_rng(7)
    for _ in range(200):
        drawn = [_random_runs(rng, 4, 6) for _ in range(int(rng.integers(1, 5)))]
        seqs, fracs = [d[0] for d in drawn], [d[1] for d in drawn]
        steps, assign = S._align_route(seqs, fracs)
        used = set()
        for seq, a in zip(seqs, assign):
            assert len(a) == len(seq) and [steps[m] for m in a] == seq
            assert all(m2 > m1 for m1, m2 in zip(a, a[1:]))
            used.update(a)
        assert used == set(range(len(steps)))
        richest = max(range(len(seqs)), key=lambda i: len(seqs[i]))
        assert len(steps) >= len(seqs[richest])


# ---------------------------------------------------------------------------------------------- subtask spaces
def _two_demos():
    syn = multi_step_demos(torch.Generator().manual_seed(11), n_demos=2, n_steps=3, samples_per_step=30)
    seqs = syn.demos.sequences()
    return Demos.from_sequences([seqs[0], seqs[1][:-15]], dt=0.01, attractor=syn.demos.attractor)


def test_fixed_segmenter_spaces_are_stretch_gaussians_of_numpy_moments():
    """Reference (module docstring, subtask spaces (a)): every piece of n samples is cut into max(1, n // s)
    consecutive stretches of floor or ceil of n / (their count) samples, s = max(3, ceil(0.04 T)) of the SHORTEST
    demonstration; each Gaussian's mean and covariance are the stretch's (np.cov, bias=True) plus floor * I, floor =
    position noise^2 + 1e-6 trace of the data's covariance (+ eps); each Gaussian belongs to its own step."""
    demos = _two_demos()
    seg = FixedSegmenter([0.3, 0.65])(demos)
    T_min = int(demos.lengths.min())
    s = max(3, math.ceil(0.04 * T_min))
    x_all = np.concatenate([q.numpy() for q in demos.sequences()])
    noise = S.position_noise(demos.sequences())
    floor = noise**2 + 1e-6 * np.trace(np.cov(x_all.T)) + np.finfo(float).eps
    j = 0
    for i, seq in enumerate(demos.sequences()):
        x = seq.numpy()
        for step, a, b in seg.pieces[i].tolist():
            count = max(1, (b - a) // s)
            sizes = {(b - a) // count, -(-(b - a) // count)}
            start = a
            for _ in range(count):
                mu = seg.space_mean[j].numpy()
                size = next(z for z in sizes if np.allclose(x[start : start + z].mean(0), mu, rtol=0, atol=1e-12))
                win = x[start : start + size]
                want = np.cov(win.T, bias=True) + floor * np.eye(2)
                np.testing.assert_allclose(seg.space_covariance[j].numpy(), want, rtol=1e-9, atol=1e-15)
                assert float(seg.space_weights[step, j]) == 1.0
                start, j = start + size, j + 1
            assert start == b
    assert j == seg.space_mean.shape[0]


def test_every_training_sample_lies_in_its_own_steps_space():
    """Property (module docstring, consequence (i)): with boundaries away from the corners (steps that borrow
    samples of their neighbours' legs) every sample x of step m satisfies membership(x)[m]: its most responsible
    Gaussian (a scipy loop over all Gaussians) is in A_m, so log p(x | A_m) is the best density over all Gaussians."""
    from scipy.stats import multivariate_normal

    demos = _two_demos()
    seg = FixedSegmenter([0.22, 0.55])(demos)
    dens = np.stack([multivariate_normal(m.numpy(), c.numpy()).logpdf(np.concatenate([q.numpy() for q in
                     demos.sequences()])) for m, c in zip(seg.space_mean, seg.space_covariance)], -1)
    x = torch.cat(demos.sequences())
    lab = torch.cat(list(seg.labels))
    inside = seg.membership(x)
    assert bool(inside[torch.arange(x.shape[0]), lab].all())
    np.testing.assert_allclose(seg.log_density(x)[torch.arange(x.shape[0]), lab].numpy(), dens.max(-1), rtol=1e-9)


def test_junction_gaussian_is_the_doubt_weighted_moments_shared_by_both_steps():
    """Reference (module docstring, subtask spaces (b)): a junction's Gaussian is the mean and covariance of the
    samples around the switch weighted by their label doubt (np.average / np.cov with aweights, bias=True) plus the
    floor, and it belongs to both steps of the switch; a junction whose doubts are all 0 adds no Gaussian."""
    rng = np.random.default_rng(8)
    x = np.cumsum(rng.standard_normal((40, 2)), 0)
    demos = Demos.from_sequences([torch.tensor(x)], dt=0.1)
    u = rng.uniform(0.0, 1.0, 10)
    pieces = [[(2, 0, 15), (0, 15, 28), (1, 28, 40)]]
    junctions = [[(10, torch.tensor(u)), (25, torch.zeros(6, dtype=F64))]]
    mean, cov, member = S._subtask_spaces(demos, pieces, 3, 5, 0.01, junctions)
    floor = 0.01 + 1e-6 * np.trace(np.cov(x.T)) + np.finfo(float).eps
    n_stretch = 3 + 2 + 2
    assert mean.shape[0] == n_stretch + 1
    np.testing.assert_allclose(mean[-1].numpy(), np.average(x[10:20], axis=0, weights=u), rtol=1e-12)
    np.testing.assert_allclose(cov[-1].numpy(), np.cov(x[10:20].T, aweights=u, bias=True) + floor * np.eye(2),
                               rtol=1e-10)
    assert member[:, -1].tolist() == [1.0, 0.0, 1.0]  # steps 2 (before) and 0 (after), not 1


# ---------------------------------------------------------------------------------------------- assembly, API
def test_attractors_and_end_points_with_unequal_lengths():
    """References: g_m is the mean of the last samples of step m's pieces (a per-piece loop), the last step's is the
    task attractor; ``endpoints`` holds every demonstration's first and LAST VALID sample (not the padding)."""
    rng = np.random.default_rng(9)
    xs = [torch.tensor(rng.standard_normal((n, 2))) for n in (12, 20, 9)]
    demos = Demos.from_sequences(xs, dt=0.1, attractor=torch.tensor([5.0, 5.0], dtype=F64))
    bounds = [[0, 4, 8, 12], [0, 10, 15, 20], [0, 2, 6, 9]]
    seg = S._steps_from_bounds(demos, bounds, {})
    for m in range(2):
        want = sum(xs[i][bounds[i][m + 1] - 1] for i in range(3)) / 3
        torch.testing.assert_close(seg.attractors[m], want)
    torch.testing.assert_close(seg.attractors[2], demos.attractor)
    for i, x in enumerate(xs):
        torch.testing.assert_close(seg.endpoints[i], torch.stack([x[0], x[-1]]))


def test_membership_ties_at_a_shared_gaussian_belong_to_both_steps():
    """Property (module docstring (ii)): where two steps share their best Gaussian their densities tie and the point
    lies in both (p(x | A_m) >= p(x | A_m-)); a point best explained by one step's own Gaussian lies only in it;
    ``other_log_density`` is the max over the other steps (a loop)."""
    base = NoSegmenter()(Demos.from_sequences([torch.linspace(0, 1, 20, dtype=F64)[:, None].expand(20, 2)]))
    seg = dataclasses.replace(
        base, attractors=torch.zeros(3, 2, dtype=F64), step_state=torch.full((3,), -1),
        space_mean=torch.tensor([[0.0, 0.0], [5.0, 5.0], [-5.0, 5.0]], dtype=F64),
        space_covariance=torch.eye(2, dtype=F64).expand(3, 2, 2).clone(),
        space_weights=torch.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64))
    x = torch.tensor([[0.1, -0.2], [5.0, 4.5], [-5.0, 5.0]], dtype=F64)
    assert seg.membership(x).tolist() == [[True, True, False], [True, False, False], [False, False, True]]
    ld = seg.log_density(x)
    for m in range(3):
        torch.testing.assert_close(seg.other_log_density(x)[:, m], torch.stack([ld[:, k] for k in range(3) if k != m],
                                                                               -1).amax(-1))


def test_table_rows_equal_a_loop_over_the_pieces():
    """Hand-worked: FixedSegmenter([0.25, 0.5]) on lengths 40 and 80 gives steps numbered from 1 with 2 pieces each,
    mean start fractions 0, 0.25, 0.5 and mean end fractions (exclusive end / T) 0.25, 0.5, 1."""
    rng = np.random.default_rng(10)
    demos = Demos.from_sequences([torch.tensor(rng.standard_normal((n, 2))).cumsum(0) for n in (40, 80)], dt=0.1)
    rows = FixedSegmenter([0.25, 0.5])(demos).table()
    assert [r["step"] for r in rows] == [1, 2, 3] and [r["n_pieces"] for r in rows] == [2, 2, 2]
    assert [r["mean_start_fraction"] for r in rows] == pytest.approx([0.0, 0.25, 0.5])
    assert [r["mean_end_fraction"] for r in rows] == pytest.approx([0.25, 0.5, 1.0])
    assert [r["route"] for r in rows] == [0, 0, 0]


def test_fixed_segmenter_refuses_equal_boundaries_and_empty_steps():
    """Property (docstring): boundaries must increase strictly (two equal ones are InvalidArgumentError, not an
    empty step), and a boundary that rounds to an empty step is TooFewSamplesError."""
    x = [torch.linspace(0, 1, 10, dtype=F64)[:, None].expand(10, 2).clone()]
    with pytest.raises(InvalidArgumentError):
        FixedSegmenter([0.5, 0.5])
    with pytest.raises(TooFewSamplesError):
        FixedSegmenter([0.02])(x)  # round(0.2) = 0: the first step would be empty
    with pytest.raises(TooFewSamplesError):
        FixedSegmenter([0.5, 0.52])(x)  # both round to 5


def test_split_end_at_attractor_repeats_the_last_interval_and_checks_the_end_points():
    """Property (docstring): with ``end_at_attractor`` the appended sample comes one LAST sampling interval of the
    piece after its last sample (uneven times); split refuses demonstrations that start where the segmented ones do
    but end elsewhere."""
    t = torch.tensor(np.cumsum(np.random.default_rng(12).uniform(0.05, 0.5, 30)))
    x = torch.stack([t, t.square()], -1)
    demos = Demos.from_sequences([x], times=[t])
    seg = FixedSegmenter([0.5])(demos)
    parts = seg.split(demos, end_at_attractor=True)
    for p, (a, b) in zip(parts, ((0, 15), (15, 30))):
        assert float(p.times[0, b - a]) == pytest.approx(float(t[b - 1] + (t[b - 1] - t[b - 2])))
    moved = x.clone()
    moved[-1] += 1.0
    with pytest.raises(ShapeMismatchError):
        seg.split(Demos.from_sequences([moved], times=[t]))


def test_log_density_refuses_non_finite_input_and_from_state_dict_bad_endpoints():
    """Property (docstrings): NaN or Inf input to ``log_density`` is NonFiniteError; a state dict whose end points
    are not (N, 2, d) is StoreError."""
    demos = _two_demos()
    seg = FixedSegmenter([0.5])(demos)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(NonFiniteError):
            seg.log_density(torch.tensor([[0.0, bad]], dtype=F64))
    state = seg.state_dict()
    for ends in (torch.zeros(3, 2, 2, dtype=F64), torch.zeros(2, 3, 2, dtype=F64)):
        with pytest.raises(StoreError):
            Segmentation.from_state_dict(state | {"endpoints": ends})
    assert torch.equal(Segmentation.from_state_dict(state).endpoints, seg.endpoints)


def test_demonstrated_routes_count_the_orders_and_complete_them():
    """Reference (docstring): the distinct step orders of a route's demonstrations, the most demonstrated first
    (ties by first appearance), each completed by the route's last step when it ends before it; hand-worked on a
    4-step route whose demonstrations execute (0, 1, 3), (0, 2, 3), (0, 2) and (0, 2, 3)."""
    x = [torch.linspace(0, 1, 30, dtype=F64)[:, None].expand(30, 2).clone() for _ in range(4)]
    base = FixedSegmenter([0.2, 0.4, 0.6])(x)
    rows = ([[0, 0, 10], [1, 10, 20], [3, 20, 30]], [[0, 0, 10], [2, 10, 20], [3, 20, 30]],
            [[0, 0, 10], [2, 10, 30]], [[0, 0, 10], [2, 10, 20], [3, 20, 30]])
    seg = dataclasses.replace(base, pieces=tuple(torch.tensor(r) for r in rows))
    assert seg.routes == ((0, 1, 2, 3),)
    assert seg.demonstrated_routes == ((0, 2, 3), (0, 1, 3))
    one = dataclasses.replace(base, pieces=tuple(torch.tensor(r) for r in rows[:2] + rows[1:2] + rows[:1]))
    assert one.demonstrated_routes == ((0, 1, 3), (0, 2, 3))  # a tie of two each: first appearance first
