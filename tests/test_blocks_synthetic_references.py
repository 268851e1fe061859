"""Independent references for the block emission (lfd_torch.segmentation.blocks), the emissions' names and the
synthetic generators (lfd_torch.segmentation.synthetic).

The block evidence is checked against a dense Gaussian built from the model of the module docstring: the block
means' noise e (diagonal, var) pushed through the difference matrix of the increments, the coefficients' design
matrix written per axis, and the coefficients integrated out as log N(y; 0, Omega + X Lambda X^T) (scipy). The
generators are checked against the properties their docstrings state, measured on the samples they return.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

import lfd_torch.gmm.gaussian as gmm_gaussian
import lfd_torch.gmm.niw as gmm_niw
import lfd_torch.segmentation.emissions as emissions
from lfd_torch.errors import InvalidArgumentError
from lfd_torch.segmentation.blocks import (
    block_log_evidence,
    block_sequence_terms,
    check_block_variances,
    combine_block_terms,
)
from lfd_torch.segmentation.synthetic import (
    FAMILIES,
    HELD_OUT_FAMILIES,
    SLOWING_FAMILIES,
    curved_steps,
    multi_step_demos,
    out_and_back_steps,
    random_waypoints,
    revisit_steps,
    rounded_steps,
    scoop_steps,
    straight_steps,
    with_correlated_noise,
    with_sampling_rate,
)

F64 = torch.float64


# ============================================================================================ block evidence
def _dense_evidence(xbar, sbar, var, zmid, valid, labels, straight, tol, spread, slopes, seqs=None):
    """log p(y) of one labelling ``labels`` (N, T) by a dense Gaussian: y the increments of the block means of the
    sequences ``seqs`` (all by default), each sequence's noise covariance D V D^T (D its difference matrix over the
    valid points, V = diag(var)), a padded increment a unit-variance zero; then X Lambda X^T of the coefficients
    (shared per state: direction 1/d, field slopes s_k^2, field offset 1; per sequence and state: turn and offset
    omega^2) and the extra variances (curved: (ds tol)^2, across a switch: ds^2); the axes independent."""
    xbar, sbar, var, zmid = (np.asarray(t, dtype=np.float64) for t in (xbar, sbar, var, zmid))
    valid, labels, straight = np.asarray(valid), np.asarray(labels), np.asarray(straight)
    N, T, d = xbar.shape
    M = T - 1
    K = straight.shape[0]
    seqs = list(range(N)) if seqs is None else list(seqs)
    blocks_cov, ys, rows = [], [], []
    for i in seqs:
        n = int(valid[i].sum())
        D = np.zeros((n - 1, n))
        D[np.arange(n - 1), np.arange(n - 1)] = -1.0
        D[np.arange(n - 1), np.arange(1, n)] = 1.0
        om = np.eye(M)
        om[: n - 1, : n - 1] = D @ np.diag(var[i, :n]) @ D.T
        y = np.zeros((M, d))
        y[: n - 1] = D @ xbar[i, :n]
        blocks_cov.append(om)
        ys.append(y)
        rows += [(i, j, j < n - 1) for j in range(M)]
    R = len(rows)
    omega = np.zeros((R, R))
    for q, om in enumerate(blocks_cov):
        omega[q * M:(q + 1) * M, q * M:(q + 1) * M] = om
    y = np.concatenate(ys)
    # columns: per state k: direction, d + 1 field coefficients; per state and sequence: turn, offset
    cols, prior = {}, []

    def col(key, v):
        if key not in cols:
            cols[key] = len(prior)
            prior.append(v)
        return cols[key]

    entries = []
    for r, (i, j, inside) in enumerate(rows):
        if not inside:
            continue
        ds = sbar[i, j + 1] - sbar[i, j]
        a, b = labels[i, j], labels[i, j + 1]
        if a != b:
            omega[r, r] += ds**2
        elif straight[a]:
            entries += [(r, col(("dir", a), 1.0 / d), ds), (r, col(("turn", a, i), spread**2), ds)]
        else:
            for c in range(d + 1):
                entries.append((r, col(("field", a, c), slopes[a] ** 2 if c < d else 1.0), ds * zmid[i, j, c]))
            entries.append((r, col(("off", a, i), spread**2), ds))
            omega[r, r] += (ds * tol) ** 2
    X = np.zeros((R, max(len(prior), 1)))
    for r, c, v in entries:
        X[r, c] += v
    lam = np.diag(prior + [0.0] * (X.shape[1] - len(prior)))
    cov = omega + X @ lam @ X.T
    return float(sum(multivariate_normal(np.zeros(R), cov).logpdf(y[:, a]) for a in range(d)))


def _block_data(seed, N=3, T=12, d=3, short=(0, 2, 4)):
    """Random block means (a random walk), increasing path lengths, variances and midpoint regressors; sequence i
    ``short[i]`` points shorter than T (its padding filled with other random numbers)."""
    g = torch.Generator().manual_seed(seed)
    xbar = (torch.randn(N, T, d, generator=g, dtype=F64) * 0.2).cumsum(1)
    sbar = (0.05 + torch.rand(N, T, generator=g, dtype=F64) * 0.2).cumsum(1)
    var = 0.002 + 0.02 * torch.rand(N, T, generator=g, dtype=F64)
    zmid = torch.cat([torch.randn(N, T - 1, d, generator=g, dtype=F64), torch.ones(N, T - 1, 1, dtype=F64)], -1)
    valid = torch.ones(N, T, dtype=torch.bool)
    for i, k in enumerate(short):
        if k:
            valid[i, T - k:] = False
    return xbar, sbar, var, zmid, valid


def _labellings(T):
    """(4, 3, T) labellings of three sequences over four states and (4, 4) straight flags: straight and curved
    states, a state at one point, a state only one sequence uses, labels in the padding."""
    a = [[0] * 4 + [1] * 4 + [2] * (T - 8), [0] * 3 + [1] * 5 + [2] * (T - 8), [0] * 5 + [1] * 3 + [2] * (T - 8)]
    b = [[3] * 6 + [0] * (T - 6), [1] * 2 + [0] * 7 + [3] * (T - 9), [2] * T]
    c = [[1] * T, [1] * 5 + [2] + [1] * (T - 6), [0] * 4 + [3] * (T - 4)]
    e = [[2] * 3 + [3] * 3 + [0] * 3 + [1] * (T - 9), [3] * (T - 3) + [0] * 3, [1] * 7 + [0] * (T - 7)]
    labels = torch.tensor([a, b, c, e])
    straight = torch.tensor([[True, False, True, False], [False, True, False, True], [True, True, False, False],
                             [False, False, True, True]])
    return labels, straight


@pytest.mark.parametrize("slopes", ["one", "per_state"])
def test_block_evidence_equals_the_dense_gaussian_of_the_increments(slopes):
    """``block_log_evidence`` of each of four labellings (three sequences of different lengths, d = 3, straight and
    curved states, single-point runs, labels in the padding) equals log N(y; 0, Omega + X Lambda X^T) of the dense
    model, Omega built as D diag(var) D^T per sequence (not from its tridiagonal entries); one slope scale for all
    states or one per labelling and state."""
    xbar, sbar, var, zmid, valid = _block_data(0)
    labels, straight = _labellings(xbar.shape[1])
    tol, spread = 0.3, 0.07
    if slopes == "one":
        scale = 1.7
        per = [[scale] * 4] * 4
    else:
        scale = torch.tensor([[0.5, 2.0, 1.0, 3.0], [1.5, 0.7, 4.0, 1.0], [2.5, 0.4, 1.2, 0.9],
                              [0.6, 3.5, 1.1, 2.2]], dtype=F64)
        per = scale.tolist()
    got = block_log_evidence(xbar, sbar, var, zmid, valid, labels, straight, tolerance=tol, spread=spread,
                             slope_scale=scale)
    assert got.shape == (4,) and got.dtype == F64
    for b in range(4):
        ref = _dense_evidence(xbar, sbar, var, zmid, valid, labels[b], straight[b], tol, spread, per[b])
        assert float(got[b]) == pytest.approx(ref, abs=1e-7, rel=1e-10)


def test_block_evidence_without_a_constant_last_regressor():
    """With the last midpoint regressor the constant 1, the own offset's column is the field offset's and
    ``block_sequence_terms`` whitens it once; with any other last regressor (here random, or 0 as a data-blind
    caller passes) the two columns differ and the evidence is still the dense model's."""
    xbar, sbar, var, zmid, valid = _block_data(3, d=2)
    labels, straight = _labellings(xbar.shape[1])
    g = torch.Generator().manual_seed(4)
    for last in (torch.randn(zmid.shape[:-1], generator=g, dtype=F64), torch.zeros(zmid.shape[:-1], dtype=F64)):
        z = torch.cat([zmid[..., :-1], last.unsqueeze(-1)], -1)
        got = block_log_evidence(xbar, sbar, var, z, valid, labels, straight, tolerance=0.3, spread=0.07,
                                 slope_scale=1.4)
        for b in range(4):
            ref = _dense_evidence(xbar, sbar, var, z, valid, labels[b], straight[b], 0.3, 0.07, [1.4] * 4)
            assert float(got[b]) == pytest.approx(ref, abs=1e-7, rel=1e-10)


def test_block_sequence_shares_sum_to_the_evidence_of_any_subset_of_sequences():
    """Each sequence's share (``block_sequence_terms``) combined alone is the dense evidence of that sequence alone;
    the shares of all sequences minus one of them (``BlockTerms.add_to`` with sign -1) combined are the dense
    evidence of the others; all of them (``totals``) that of the whole."""
    xbar, sbar, var, zmid, valid = _block_data(1, T=10, d=2, short=(1, 0, 3))
    labels, straight = _labellings(10)
    tol, spread, scale = 0.2, 0.05, 0.8
    terms = block_sequence_terms(xbar, sbar, var, zmid, valid, labels, straight, tolerance=tol, spread=spread,
                                 slope_scale=scale)
    whole = combine_block_terms(*terms.totals(), slope_scale=scale)
    for b in range(4):
        ref = _dense_evidence(xbar, sbar, var, zmid, valid, labels[b], straight[b], tol, spread, [scale] * 4)
        assert float(whole[b]) == pytest.approx(ref, abs=1e-7)
    for i in range(3):
        alone = combine_block_terms(*terms[:, i:i + 1].totals(), slope_scale=scale)
        gram, proj, const = (t.clone() for t in terms.totals())
        terms[:, i].add_to(gram, proj, const, torch.arange(4), sign=-1.0)
        others = combine_block_terms(gram, proj, const, slope_scale=scale)
        for b in range(4):
            ref = _dense_evidence(xbar, sbar, var, zmid, valid, labels[b], straight[b], tol, spread, [scale] * 4,
                                  seqs=[i])
            assert float(alone[b]) == pytest.approx(ref, abs=1e-7)
            ref = _dense_evidence(xbar, sbar, var, zmid, valid, labels[b], straight[b], tol, spread, [scale] * 4,
                                  seqs=[k for k in range(3) if k != i])
            assert float(others[b]) == pytest.approx(ref, abs=1e-7)


def test_block_sequence_terms_with_data_per_labelling():
    """Data with a leading batch dimension (B, N, ...), one set of block means per labelling: each labelling's
    combined shares are the dense evidence of its own data."""
    datas = [_block_data(10 + b, N=2, T=9, d=2, short=(0, 2)) for b in range(3)]
    xbar, sbar, var, zmid, valid = (torch.stack([dt[k] for dt in datas]) for k in range(5))
    valid = valid[0]  # the same lengths
    labels, straight = _labellings(9)
    labels, straight = labels[:3, :2], straight[:3]
    terms = block_sequence_terms(xbar, sbar, var, zmid, valid, labels, straight, tolerance=0.25, spread=0.05,
                                 slope_scale=1.3)
    got = combine_block_terms(*terms.totals(), slope_scale=1.3)
    for b in range(3):
        ref = _dense_evidence(xbar[b], sbar[b], var[b], zmid[b], valid, labels[b], straight[b], 0.25, 0.05, [1.3] * 4)
        assert float(got[b]) == pytest.approx(ref, abs=1e-7)


def test_block_evidence_ignores_finite_padding_values():
    """Padded points (valid False) carry nothing: any finite block mean, path length or variance written there
    leaves the evidence unchanged (module docstring: padded increments are unit-variance zeros)."""
    xbar, sbar, var, zmid, valid = _block_data(2, short=(0, 3, 5))
    labels, straight = _labellings(xbar.shape[1])
    kw = dict(tolerance=0.2, spread=0.05, slope_scale=1.0)
    base = block_log_evidence(xbar, sbar, var, zmid, valid, labels, straight, **kw)
    pad = ~valid
    for fill in (0.0, -3.0, 1e3):
        x2, s2, v2 = xbar.clone(), sbar.clone(), var.clone()
        x2[pad] = fill
        s2[pad] = fill
        v2[pad] = fill
        got = block_log_evidence(x2, s2, v2, zmid, valid, labels, straight, **kw)
        assert torch.allclose(got, base, rtol=0, atol=1e-9)


def test_block_evidence_ignores_nonfinite_padded_variances():
    """A non-finite variance at a padded point is accepted by ``check_block_variances`` (it checks valid blocks
    only), so the evidence must not depend on it either."""
    xbar, sbar, var, zmid, valid = _block_data(2, short=(0, 3, 5))
    labels, straight = _labellings(xbar.shape[1])
    kw = dict(tolerance=0.2, spread=0.05, slope_scale=1.0)
    base = block_log_evidence(xbar, sbar, var, zmid, valid, labels, straight, **kw)
    v2 = var.clone()
    v2[~valid] = float("nan")
    check_block_variances(v2, valid)  # accepted
    got = block_log_evidence(xbar, sbar, v2, zmid, valid, labels, straight, **kw)
    assert torch.allclose(got, base, rtol=0, atol=1e-9)


def test_check_block_variances_rejects_every_bad_valid_variance():
    """A valid block's variance that is 0, negative, NaN or +inf raises InvalidArgumentError naming ``var``."""
    valid = torch.ones(2, 6, dtype=torch.bool)
    valid[1, 4:] = False
    ok = torch.full((2, 6), 0.01, dtype=F64)
    check_block_variances(ok, valid)
    for bad in (0.0, -0.01, float("nan"), float("inf")):
        v = ok.clone()
        v[1, 2] = bad
        with pytest.raises(InvalidArgumentError, match="var"):
            check_block_variances(v, valid)


# ============================================================================================ emissions
def test_emissions_names_are_the_gmm_kernels():
    """``lfd_torch.segmentation.emissions`` only names the NIW and Gaussian kernels of ``lfd_torch.gmm``: every
    name of its ``__all__`` is the very object of the same name there, and none is missing."""
    want = {"NIWPrior", "niw_prior_from_data", "niw_posterior", "sufficient_statistics", "sample_niw",
            "sample_gamma", "niw_log_density", "gaussian_log_density", "niw_log_marginal_likelihood"}
    assert set(emissions.__all__) == want
    for name in want:
        source = gmm_gaussian if name == "gaussian_log_density" else gmm_niw
        assert getattr(emissions, name) is getattr(source, name), name


# ============================================================================================ generators
def _turn(u, v):
    """Angle between the rows of u and v, degrees."""
    c = (u * v).sum(-1) / (u.norm(dim=-1) * v.norm(dim=-1))
    return torch.rad2deg(torch.acos(c.clamp(-1.0, 1.0)))


def _leg_counts(syn, i):
    """Samples of each leg of demonstration i: leg m runs from its corner sample to the next corner's (exclusive),
    the last leg to the final sample (inclusive, it ends on the goal)."""
    n = int(syn.demos.lengths[i])
    bounds = [0] + syn.switch_times[i].tolist() + [n - 1]
    return [b - a for a, b in zip(bounds[:-1], bounds[1:])]


_DRAWS = {}


def _draws(name, seeds=range(12), n_demos=3):
    """Cached draws of a family over several seeds."""
    key = (name, tuple(seeds), n_demos)
    if key not in _DRAWS:
        table = {**FAMILIES, **SLOWING_FAMILIES, **HELD_OUT_FAMILIES}
        _DRAWS[key] = [table[name](torch.Generator().manual_seed(1000 + s), n_demos) for s in seeds]
    return _DRAWS[key]


@pytest.mark.parametrize("name,lo,hi,rule", [("straight_dwell_2d", 150.0, 200.0, "sqrt"),
                                             ("curved_const_3d", 130.0, 170.0, "linear"),
                                             ("revisit_slow_2d", 130.0, 170.0, "linear"),
                                             ("out_and_back_dwell_2d", 150.0, 200.0, "sqrt")])
def test_leg_sample_counts_follow_the_time_base(name, lo, hi, rule):
    """Module docstring, time base: a leg of arc length L gets n_nom sqrt(L / L_g) samples (dwelling) or n_nom L / L_g
    (constant speed; the slowing timing follows it too), n_nom in [lo, hi] per case, each demonstration's durations
    scaled by [0.85, 1.15] and each leg's by a further [0.9, 1.1]. So q_m = n_m / rule(L_m / L_g) lies in
    [0.85 * 0.9 lo, 1.15 * 1.1 hi]; two legs of one demonstration differ by at most 1.1 / 0.9; one leg in two
    demonstrations by at most 1.15 * 1.1 / (0.85 * 0.9); and across draws the leg factors do vary."""
    within, across, lows, highs = [], [], [], []
    for syn in _draws(name):
        L = syn.leg_lengths
        g = math.exp(float(L.log().mean()))
        r = (L / g).sqrt() if rule == "sqrt" else L / g
        n = torch.tensor([_leg_counts(syn, i) for i in range(syn.demos.n_demos)], dtype=F64)
        keep = (n > 20).all(0)  # legs above the max(20, .) floor in every demonstration
        lo_q, hi_q = ((n - 0.5) / r)[:, keep], ((n + 0.5) / r)[:, keep]  # q up to the rounding of n
        lows.append(float(hi_q.min()))
        highs.append(float(lo_q.max()))
        within.append(float((lo_q.amax(1) / hi_q.amin(1)).max()))
        across.append(float((lo_q.amax(0) / hi_q.amin(0)).max()))
    assert min(lows) >= 0.85 * 0.9 * lo and max(highs) <= 1.15 * 1.1 * hi
    assert max(within) <= 1.1 / 0.9 and max(within) > 1.08  # leg factors present, within their range
    assert max(across) <= 1.15 * 1.1 / (0.85 * 0.9)


def test_corner_jitter_is_two_percent_of_the_shorter_adjacent_leg():
    """Module docstring: each demonstration offsets its corners (the start too, not the goal) by Gaussian jitter of
    2 % of the shorter adjacent leg; the corner sample of the clean path is that jittered corner. The offsets divided
    by that scale have a standard deviation of 0.02 (pooled over draws); the goal is exactly the waypoint."""
    z = []
    for syn in _draws("straight_const_3d", range(15), 4):
        W, L = syn.waypoints, syn.leg_lengths
        M = syn.n_steps
        scale = [float(L[0])] + [float(min(L[m - 1], L[m])) for m in range(1, M)]
        for i in range(syn.demos.n_demos):
            n = int(syn.demos.lengths[i])
            at = [0] + syn.switch_times[i].tolist()
            p = syn.clean[i]
            for m, t in enumerate(at):
                z.append((p[t] - W[m]) / scale[m])
            assert torch.allclose(p[n - 1], W[-1], rtol=0, atol=1e-12)
    z = torch.cat(z)
    assert abs(float(z.std()) / 0.02 - 1.0) < 0.12, float(z.std())


@pytest.mark.parametrize("name", ["straight_dwell_3d", "scoop_const_3d", "revisit_slow_2d"])
def test_noise_is_white_at_the_stated_fraction_of_the_measured_span(name):
    """Module docstring: white position noise of 0.3-1 % of the span (drawn per case), the span the diagonal of the
    bounding box of the noise-free demonstrations: the span recomputed from the clean samples equals ``span``, the
    residuals' standard deviation is ``noise`` and noise / span lies in [0.003, 0.01], varying across cases; the
    residuals are uncorrelated in time."""
    fractions = []
    for syn in _draws(name, range(8)):
        cl = torch.cat([syn.clean[i, : int(n)] for i, n in enumerate(syn.demos.lengths.tolist())])
        span = float((cl.amax(0) - cl.amin(0)).norm())
        assert syn.span == pytest.approx(span, rel=1e-12)
        res = [syn.demos.positions[i, : int(n)] - syn.clean[i, : int(n)] for i, n in enumerate(syn.demos.lengths.tolist())]
        flat = torch.cat(res).reshape(-1)
        assert float(flat.std()) == pytest.approx(syn.noise, rel=0.08)
        lag = torch.cat([(r[1:] * r[:-1]).reshape(-1) for r in res]).mean() / flat.var()
        assert abs(float(lag)) < 0.08
        fractions.append(syn.noise / span)
    assert 0.003 <= min(fractions) and max(fractions) <= 0.01 and max(fractions) - min(fractions) > 0.002


def test_family_ranges_of_legs_and_corners():
    """Module docstring: 3-5 legs (each count occurs), nominal corner angles in [30, 150] degrees covering most of
    it, leg lengths within a factor 5 of each other."""
    Ms, angles = set(), []
    for s in range(25):
        syn = straight_steps(torch.Generator().manual_seed(s), n_demos=1, dim=3)
        W = syn.waypoints
        legs = W[1:] - W[:-1]
        Ms.add(syn.n_steps)
        angles.append(_turn(legs[:-1], legs[1:]))
        assert float(syn.leg_lengths.max() / syn.leg_lengths.min()) <= 5.0 + 1e-9
        assert torch.allclose(legs.norm(dim=-1), syn.leg_lengths)
    angles = torch.cat(angles)
    assert Ms == {3, 4, 5}
    assert float(angles.min()) >= 30.0 - 1e-6 and float(angles.max()) <= 150.0 + 1e-6
    assert float(angles.min()) < 40.0 and float(angles.max()) > 140.0


def _bends(syn, i):
    """Tangent turn along each leg of demonstration i at constant speed: the chords of a circular arc traversed in n
    equal steps have the arc's tangent at the steps' midpoints, so the first and last chord turn by bend (n - 1) / n."""
    step = syn.clean[i, : int(syn.demos.lengths[i])].diff(dim=0)
    bounds = [0] + syn.switch_times[i].tolist() + [int(syn.demos.lengths[i]) - 1]
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        n = b - a
        out.append(float(_turn(step[a], step[b - 1])) * n / (n - 1))
    return out


def test_curved_legs_bend_by_30_to_90_degrees():
    """Module docstring: every curved leg turns its tangent smoothly by 30-90 degrees (measured on the constant-speed
    clean path), covering the range across draws."""
    bends = []
    for syn in _draws("curved_const_2d", range(10), 2):
        for i in range(syn.demos.n_demos):
            bends += _bends(syn, i)
    assert 30.0 - 0.5 <= min(bends) and max(bends) <= 90.0 + 0.5
    assert min(bends) < 40.0 and max(bends) > 80.0


def test_out_and_back_lengths_and_corners():
    """``out_and_back_steps``: the back leg is 0.5-1 of the out leg, the other corners turn by 30-150 degrees
    (nominal), the reversal by 180."""
    fr, others = [], []
    for s in range(20):
        syn = out_and_back_steps(torch.Generator().manual_seed(s), n_demos=1, dim=2)
        L, W = syn.leg_lengths, syn.waypoints
        fr.append(float(L[2] / L[1]))
        legs = W[1:] - W[:-1]
        t = _turn(legs[:-1], legs[1:])
        assert float(t[1]) > 179.9
        others += [float(t[0])] + ([float(t[2])] if syn.n_steps == 4 else [])
    assert 0.5 <= min(fr) and max(fr) <= 1.0 and max(fr) - min(fr) > 0.3
    assert 30.0 - 1e-6 <= min(others) and max(others) <= 150.0 + 1e-6


def test_revisit_geometry():
    """``revisit_steps``: leg 3's line crosses leg 1 at 30-70 % of it, at 45-135 degrees to it; every nominal corner
    turns by 30-150 degrees."""
    for s in range(25):
        syn = revisit_steps(torch.Generator().manual_seed(s), n_demos=1, dim=2)
        W = syn.waypoints.numpy()
        u, c = W[1] - W[0], W[3] - W[2]
        # W0 + t u = W2 + r c
        t, _ = np.linalg.solve(np.stack([u, -c], 1), W[2] - W[0])
        assert 0.3 - 1e-9 <= t <= 0.7 + 1e-9, t
        crossing = float(_turn(torch.tensor(u), torch.tensor(c)))
        assert 45.0 - 1e-6 <= crossing <= 135.0 + 1e-6
        legs = torch.tensor(W[1:] - W[:-1])
        t = _turn(legs[:-1], legs[1:])
        assert float(t.min()) >= 30.0 - 1e-6 and float(t.max()) <= 150.0 + 1e-6


def test_scoop_geometry():
    """``scoop_steps``: approach 0.8-1.2 long descending at 20-45 degrees; hook chord 0.25-0.4 approaches forward and
    up to 5 % higher, bending by 120-170 degrees; transfer chord 1.2-1.8 approaches horizontally within +-100 degrees
    of forward and within +-0.1 approaches in height, bending by 70-120 degrees (bends measured on the clean path at
    constant speed)."""
    for syn in _draws("scoop_const_3d", range(15), 1):
        W = syn.waypoints
        a, h, t = W[1] - W[0], W[2] - W[1], W[3] - W[2]
        La = float(a.norm())
        assert 0.8 <= La <= 1.2
        assert 20.0 - 1e-6 <= math.degrees(math.asin(-float(a[2]) / La)) <= 45.0 + 1e-6
        assert 0.25 - 1e-9 <= float(h[:2].norm()) / La <= 0.4 + 1e-9 and 0.0 <= float(h[2]) / La <= 0.05 + 1e-9
        assert float(_turn(h[:2], a[:2])) < 1e-4  # forward
        assert 1.2 - 1e-9 <= float(t[:2].norm()) / La <= 1.8 + 1e-9 and abs(float(t[2])) / La <= 0.1 + 1e-9
        assert float(_turn(t[:2], a[:2])) <= 100.0 + 1e-6
        _, hook, transfer = _bends(syn, 0)
        assert 120.0 - 0.5 <= hook <= 170.0 + 0.5 and 70.0 - 0.5 <= transfer <= 120.0 + 0.5


def test_slowing_blend_spans_its_range():
    """Module docstring: the slowing timing's lam is drawn per case in [0.3, 0.8]; the speed at a leg's ends is
    1 - lam of its mean. Over draws the measured lam stays in the range and covers most of it."""
    lams = []
    for s in range(40):
        syn = SLOWING_FAMILIES["straight_slow_2d"](torch.Generator().manual_seed(s), 1)
        n = int(syn.demos.lengths[0])
        speed = syn.clean[0, :n].diff(dim=0).norm(dim=-1)
        bounds = [0] + syn.switch_times[0].tolist() + [n - 1]
        ends = [float(speed[a]) / float(speed[a:b].mean()) for a, b in zip(bounds[:-1], bounds[1:])]
        lams.append(1.0 - sum(ends) / len(ends))
    assert 0.3 - 0.02 <= min(lams) and max(lams) <= 0.8 + 0.02
    assert min(lams) < 0.4 and max(lams) > 0.7


def test_rounded_fillet_validation_and_noise_drawn_per_case():
    """``rounded_steps``: a fillet range reaching 0.5 is rejected; the noise fraction is drawn per case in
    [0.003, 0.01] (it varies across seeds)."""
    with pytest.raises(InvalidArgumentError, match="fillet"):
        rounded_steps(torch.Generator().manual_seed(0), fillet=(0.1, 0.5))
    fr = [HELD_OUT_FAMILIES["rounded_const_2d"](torch.Generator().manual_seed(s), 1) for s in range(6)]
    fr = [syn.noise / syn.span for syn in fr]
    assert 0.003 <= min(fr) and max(fr) <= 0.01 and max(fr) - min(fr) > 0.001


def test_with_correlated_noise_is_stationary_ar1_at_the_scaled_level():
    """``with_correlated_noise``: the residuals over the clean path, divided by scale * noise, have unit variance at
    every instant (t = 0 included: stationary), lag-one correlation rho; ``noise`` is the new level; the clean path is
    kept; the same generator seed gives the same draw; rho outside [0, 1) and scale <= 0 are rejected."""
    syn = FAMILIES["straight_const_2d"](torch.Generator().manual_seed(4), 4)
    rho, scale = 0.8, 0.5
    first, rest, lag = [], [], []
    for s in range(60):
        out = with_correlated_noise(syn, rho, torch.Generator().manual_seed(s), scale=scale)
        assert out.noise == pytest.approx(scale * syn.noise) and out.clean is syn.clean
        for i, n in enumerate(out.demos.lengths.tolist()):
            e = (out.demos.positions[i, :n] - syn.clean[i, :n]) / (scale * syn.noise)
            first.append(e[0])
            rest.append(e[1:])
            lag.append((e[1:] * e[:-1]).mean() / (e * e).mean())
    first, rest = torch.cat(first), torch.cat(rest).reshape(-1)
    assert abs(float(first.std()) - 1.0) < 0.12 and abs(float(rest.std()) - 1.0) < 0.1
    assert abs(float(torch.stack(lag).mean()) - rho) < 0.03
    a = with_correlated_noise(syn, rho, torch.Generator().manual_seed(9))
    b = with_correlated_noise(syn, rho, torch.Generator().manual_seed(9))
    assert torch.equal(a.demos.positions, b.demos.positions)
    for bad in (1.0, -0.1):
        with pytest.raises(InvalidArgumentError, match="rho"):
            with_correlated_noise(syn, bad, torch.Generator().manual_seed(0))
    with pytest.raises(InvalidArgumentError, match="scale"):
        with_correlated_noise(syn, 0.5, torch.Generator().manual_seed(0), scale=0.0)


@pytest.mark.parametrize("rate", [37.0, 100.0, 250.0])
def test_with_sampling_rate_interpolates_and_moves_the_switches(rate):
    """``with_sampling_rate``: the new clean samples are the linear interpolation (numpy's ``interp``) of the old
    clean path at instants k / rate over the same duration (the last new instant at or before the old last one, the
    next after it); a switch is the first new sample at or after its corner's instant; white noise of the same
    standard deviation; dt = 1 / rate; determinism per seed."""
    syn = FAMILIES["curved_const_2d"](torch.Generator().manual_seed(2), 3)
    out = with_sampling_rate(syn, rate, torch.Generator().manual_seed(5))
    again = with_sampling_rate(syn, rate, torch.Generator().manual_seed(5))
    assert torch.equal(out.demos.positions, again.demos.positions)
    assert float(out.demos.times[0, 1] - out.demos.times[0, 0]) == pytest.approx(1.0 / rate)
    res = []
    for i in range(3):
        n, m = int(syn.demos.lengths[i]), int(out.demos.lengths[i])
        old_t = np.arange(n) * 0.01
        new_t = np.arange(m) / rate
        assert new_t[-1] <= old_t[-1] + 1e-9 < (m / rate) + 1e-12
        old = syn.clean[i, :n].numpy()
        ref = np.stack([np.interp(new_t, old_t, old[:, a]) for a in range(old.shape[1])], 1)
        assert np.allclose(out.clean[i, :m].numpy(), ref, atol=1e-10)
        corner_t = syn.switch_times[i].numpy() * 0.01
        sw = out.switch_times[i].numpy()
        assert (new_t[sw] >= corner_t - 1e-9).all() and (new_t[sw - 1] < corner_t - 1e-9).all()
        res.append(out.demos.positions[i, :m] - out.clean[i, :m])
    assert float(torch.cat(res).std()) == pytest.approx(syn.noise, rel=0.1)
    for bad in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(InvalidArgumentError, match="rate"):
            with_sampling_rate(syn, bad, torch.Generator().manual_seed(0))
    with pytest.raises(InvalidArgumentError, match="samples"):
        with_sampling_rate(syn, 0.1, torch.Generator().manual_seed(0))


def test_multi_step_demos_corner_arrival_goal_and_timing():
    """``multi_step_demos``: the corner is the last sample of its leg and the switch the first sample after it;
    the goal is common (not jittered); each leg has samples_per_step times a factor in [1 - j, 1 + j] (the first leg
    one more, its start); noise 0 gives the exact path."""
    W = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=F64)
    syn = multi_step_demos(torch.Generator().manual_seed(0), n_demos=6, waypoints=W, waypoint_jitter=0.0, noise=0.0,
                           samples_per_step=50, timing_jitter=0.2, profile="constant")
    counts = []
    for i in range(6):
        n = int(syn.demos.lengths[i])
        p = syn.demos.positions[i, :n]
        sw = syn.switch_times[i]
        assert torch.allclose(p[sw - 1], W[1:-1], atol=1e-12) and not torch.allclose(p[sw], W[1:-1])
        bounds = [0] + sw.tolist() + [n]
        c = [b - a for a, b in zip(bounds[:-1], bounds[1:])]
        counts += [c[0] - 1] + c[1:]
    assert 40 <= min(counts) and max(counts) <= 60 and max(counts) - min(counts) > 8
    syn = multi_step_demos(torch.Generator().manual_seed(1), n_demos=4, waypoints=W, waypoint_jitter=0.1, noise=0.0)
    for i in range(4):
        assert torch.allclose(syn.demos.positions[i, int(syn.demos.lengths[i]) - 1], W[-1], atol=1e-12)


def test_random_waypoints_turns_and_leg_lengths():
    """``random_waypoints``: consecutive legs turn by 50-140 degrees (defaults) and leg lengths lie in [0.7, 1.3],
    the first waypoint at the origin."""
    turns, lengths = [], []
    for s in range(20):
        W = random_waypoints(5, 3, torch.Generator().manual_seed(s))
        assert torch.equal(W[0], torch.zeros(3, dtype=F64))
        legs = W[1:] - W[:-1]
        turns.append(_turn(legs[:-1], legs[1:]))
        lengths.append(legs.norm(dim=-1))
    turns, lengths = torch.cat(turns), torch.cat(lengths)
    assert float(turns.min()) >= 50.0 - 1e-6 and float(turns.max()) <= 140.0 + 1e-6
    assert float(lengths.min()) >= 0.7 and float(lengths.max()) <= 1.3


def test_rounded_fillets_span_their_fraction_of_the_shorter_leg():
    """``rounded_steps``: corner m is rounded by the arc tangent to both legs at f_m times the shorter adjacent leg
    from the corner, f_m in [0.05, 0.25]. Measured at constant speed: two consecutive chords inside the arc turn by
    2 asin(c / 2R) (c the chord), which gives R; the tangent length R tan(theta / 2) over the shorter nominal leg is
    f_m up to the corner jitter (10 % allowed); across draws f covers most of the range."""
    fs = []
    for s in range(12):
        syn = HELD_OUT_FAMILIES["rounded_const_2d"](torch.Generator().manual_seed(s), 2)
        L = syn.leg_lengths
        for i in range(syn.demos.n_demos):
            n = int(syn.demos.lengths[i])
            step = syn.clean[i, :n].diff(dim=0)
            turn = torch.deg2rad(_turn(step[:-1], step[1:]))  # turn[t]: between step t and step t + 1
            sw = syn.switch_times[i].tolist()
            mids = [0] + [(a + b) // 2 for a, b in zip([0] + sw, sw + [n - 1])][1:-1] + [n - 2]
            for m, (a, b) in enumerate(zip(mids[:-1], mids[1:])):
                t = a + int(turn[a:b].argmax())
                R = float(step[t].norm()) / (2.0 * math.sin(float(turn[t]) / 2.0))
                theta = math.radians(float(syn.corner_angles[i, m]))
                fs.append(R * math.tan(theta / 2.0) / float(min(L[m], L[m + 1])))
    assert 0.05 / 1.1 <= min(fs) and max(fs) <= 0.25 * 1.1, (min(fs), max(fs))
    assert min(fs) < 0.08 and max(fs) > 0.22
