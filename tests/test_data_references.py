"""Data loading, finite differences, preprocessing, MNIST strokes and the rollout engine against independent
references: naive loops, numpy / scipy (``np.gradient``, ``np.interp``, the LASA ``.mat`` files read with
``scipy.io.loadmat``), closed forms and synthetic images whose skeleton is known.

Each test is named by the property it checks and kills at least one mutant of the code that the rest of the
suite let through (the docstrings say which property and which reference). Nothing here reads ``../shared``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch

from lfd_torch.data import Demos, load_lasa
from lfd_torch.data.finite_difference import finite_difference
from lfd_torch.data.lasa import lasa_data_dir
from lfd_torch.data.mnist import extract_stroke, stroke_trajectory
from lfd_torch.errors import InvalidArgumentError, TooFewSamplesError
from lfd_torch.preprocess import (
    Preprocess,
    estimate_velocities,
    moving_average,
    resample,
    savitzky_golay,
    screen_dimensions,
    smooth,
    subsample,
    trim_still_tail,
)
from lfd_torch.rollout import Disturbance, rollout


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _odd_extend(x: np.ndarray, h: int) -> np.ndarray:
    """Point reflection past both ends: x[-k] = 2 x[0] - x[k], x[L-1+k] = 2 x[L-1] - x[L-1-k]."""
    head = 2 * x[0] - x[1 : h + 1][::-1]
    tail = 2 * x[-1] - x[-h - 1 : -1][::-1]
    return np.concatenate([head, x, tail])


def _naive_filter(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Symmetric kernel over the odd extension, one window at a time."""
    w = len(kernel)
    ext = _odd_extend(x, w // 2)
    return np.stack([(kernel[:, None] * ext[t : t + w]).sum(0) for t in range(len(x))])


def _ragged(seed: int, lengths: tuple[int, ...], d: int = 2) -> Demos:
    g = _gen(seed)
    seqs = [torch.randn(n, d, generator=g, dtype=torch.float64).cumsum(0).numpy() for n in lengths]
    times = [np.cumsum(0.05 + 0.1 * torch.rand(n, generator=g, dtype=torch.float64).numpy()) for n in lengths]
    return Demos.from_sequences(seqs, times=times)


# ---------------------------------------------------------------------------------------------- finite differences
def test_backward_and_forward_differences_match_a_naive_loop() -> None:
    """Backward: (x[k] - x[k-1]) / (t[k] - t[k-1]), zero at the first valid sample; forward: (x[k+1] - x[k]) / dt,
    zero at the last; zero on padding. Reference: a per-sample Python loop on a non-uniform grid with garbage in
    the padding."""
    g = _gen(0)
    lengths = torch.tensor([9, 5])
    t = torch.rand(2, 9, generator=g, dtype=torch.float64).add(0.1).cumsum(1)
    x = torch.randn(2, 9, 3, generator=g, dtype=torch.float64)
    back = finite_difference(x, t, lengths, scheme="backward")
    fwd = finite_difference(x, t, lengths, scheme="forward")
    for i, n in enumerate(lengths.tolist()):
        ref_b, ref_f = np.zeros((9, 3)), np.zeros((9, 3))
        for k in range(n):
            if k > 0:
                ref_b[k] = (x[i, k] - x[i, k - 1]).numpy() / float(t[i, k] - t[i, k - 1])
            if k < n - 1:
                ref_f[k] = (x[i, k + 1] - x[i, k]).numpy() / float(t[i, k + 1] - t[i, k])
        np.testing.assert_allclose(back[i].numpy(), ref_b, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(fwd[i].numpy(), ref_f, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------- LASA
def test_lasa_positions_times_and_velocities_are_the_mat_file_fields() -> None:
    """load_lasa gives the shipped pos / t / vel fields (pos and vel transposed to (1000, 2), mm and mm/s, no
    re-estimated velocities, no swapped axes), names ``<shape>/<i>`` from 0 and the attractor exactly (0, 0).
    Reference: the .mat file read here with scipy.io.loadmat."""
    demos = load_lasa("Angle")
    raw = scipy.io.loadmat(lasa_data_dir() / "Angle.mat")["demos"][0]
    for i, d in enumerate(raw):
        np.testing.assert_array_equal(demos.positions[i].numpy(), np.asarray(d["pos"][0, 0], dtype=np.float64).T)
        np.testing.assert_array_equal(demos.velocities[i].numpy(), np.asarray(d["vel"][0, 0], dtype=np.float64).T)
        np.testing.assert_array_equal(demos.times[i].numpy(), np.asarray(d["t"][0, 0], dtype=np.float64).ravel())
    assert demos.names == tuple(f"Angle/{i}" for i in range(7))
    assert demos.attractor.tolist() == [0.0, 0.0]


# ---------------------------------------------------------------------------------------------- smoothing
def test_a_window_as_long_as_the_shortest_demonstration_is_accepted() -> None:
    """Smoothing needs window <= every length (not <): a window equal to the shortest demonstration works and
    equals the naive windowed mean / Savitzky-Golay sum over the point-reflected extension (numpy loop with
    scipy.signal.savgol_coeffs)."""
    import scipy.signal

    demos = _ragged(1, (9, 14))
    ma = moving_average(demos, 9)
    sg = savitzky_golay(demos, 9, 2)
    coeffs = scipy.signal.savgol_coeffs(9, 2)
    for i, seq in enumerate(demos.sequences()):
        x = seq.numpy()
        np.testing.assert_allclose(ma.sequences()[i].numpy(), _naive_filter(x, np.full(9, 1 / 9)), atol=1e-12)
        np.testing.assert_allclose(sg.sequences()[i].numpy(), _naive_filter(x, coeffs), atol=1e-10)
    with pytest.raises(TooFewSamplesError):
        moving_average(demos, 11)


def test_an_even_window_is_rejected_as_not_odd() -> None:
    """An even window has no centre: both smoothers refuse it with an error that says the window must be odd
    (not some later shape error)."""
    demos = _ragged(2, (20, 25))
    for fn in (moving_average, savitzky_golay):
        with pytest.raises(InvalidArgumentError, match="odd"):
            fn(demos, 4)


# ---------------------------------------------------------------------------------------------- resampling
def test_time_resampling_velocities_are_central_differences_of_the_resampled_positions() -> None:
    """After resample(), velocities are second-order central differences of the new positions on the new time
    grid, first-order at the ends. Reference: numpy.gradient(positions, times, axis=0)."""
    demos = _ragged(3, (30, 21))
    for mode in ("time", "arc_length"):
        out = resample(demos, 17, mode)
        for i in range(2):
            ref = np.gradient(out.positions[i].numpy(), out.times[i].numpy(), axis=0)
            np.testing.assert_allclose(out.velocities[i].numpy(), ref, rtol=1e-10, atol=1e-10)


def test_arc_length_resampling_keeps_the_end_time_of_a_still_tail() -> None:
    """Arc-length resampling interpolates the time stamps along the path; the last sample keeps the demonstration's
    last time stamp even when the path ends with samples standing still (a repeated abscissa), and inside the
    moving part the times are numpy.interp of the time stamps over the cumulative path length."""
    move = np.stack([np.linspace(0.0, 3.0, 13), np.linspace(0.0, 1.0, 13) ** 2], 1)
    x = np.concatenate([move, np.repeat(move[-1:], 5, 0)])
    t = np.cumsum(np.full(len(x), 0.1))
    out = resample(Demos.from_sequences([x], times=[t]), 9, "arc_length")
    assert float(out.times[0, -1]) == pytest.approx(t[-1], abs=1e-12)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(move, axis=0), axis=1))])
    q = np.linspace(0.0, s[-1], 9)
    np.testing.assert_allclose(out.times[0, 1:-1].numpy(), np.interp(q[1:-1], s, t[:13]), atol=1e-12)
    for j in range(2):
        np.testing.assert_allclose(out.positions[0, :, j].numpy(), np.interp(q, s, move[:, j]), atol=1e-12)


def test_arc_length_resampling_refuses_a_demonstration_without_path_length() -> None:
    """A demonstration that never moves has no arc-length parametrisation: TooFewSamplesError naming it (index
    1), not a silent constant resampling."""
    still = np.ones((6, 2))
    moving = np.stack([np.linspace(0, 1, 6), np.zeros(6)], 1)
    demos = Demos.from_sequences([moving, still])
    with pytest.raises(TooFewSamplesError, match="zero path length"):
        resample(demos, 5, "arc_length")
    assert resample(demos, 5, "time").lengths.tolist() == [5, 5]


# ---------------------------------------------------------------------------------------------- sub-sampling
def test_subsampling_to_exactly_three_samples_is_allowed() -> None:
    """MIN_SAMPLES = 3 samples is enough: 9 samples by a stride of 4 keep 0, 4, 8 (x[::4] with the end) and do not
    raise; 5 samples by 4 keep only 2 and raise. Reference: numpy slicing."""
    demos = _ragged(4, (9, 9))
    out = subsample(demos, 4)
    assert out.lengths.tolist() == [3, 3]
    for i, seq in enumerate(demos.sequences()):
        np.testing.assert_array_equal(out.sequences()[i].numpy(), seq.numpy()[[0, 4, 8]])
    with pytest.raises(TooFewSamplesError):
        subsample(_ragged(4, (5, 9)), 4)


# ---------------------------------------------------------------------------------------------- screening
def test_screening_keeps_the_largest_dimension_when_every_share_is_below_the_threshold() -> None:
    """At least one dimension survives: variances 9 and 4 (shares 9/13, 4/13) under a threshold of 0.9 keep
    dimension 0 only. Reference: shares computed by numpy var."""
    s = np.tile([1.0, -1.0], 10)
    x = np.stack([3 * s, 2 * s], 1)
    demos = Demos.from_sequences([x], attractor=np.zeros(2))
    shares = x.var(0) / x.var(0).sum()
    assert (shares < 0.9).all()
    out, kept = screen_dimensions(demos, 0.9, return_kept=True)
    assert kept.tolist() == [0] and out.dim == 1
    np.testing.assert_array_equal(out.positions[0].numpy(), x[:, :1])


def test_screening_a_leading_dimension_keeps_the_matching_attractor_and_velocity_entries() -> None:
    """Dropping dimension 0 (and not the last one) keeps positions, velocities and attractor entries 1 and 2 of
    the original set (numpy column indexing as the reference)."""
    g = _gen(5)
    loud = torch.randn(25, 2, generator=g, dtype=torch.float64).cumsum(0).numpy() * 10
    x = np.concatenate([1e-6 * np.ones((25, 1)), loud], 1)
    demos = Demos.from_sequences([x], attractor=np.array([7.0, 1.0, 2.0]))
    out, kept = screen_dimensions(demos, 0.01, return_kept=True)
    assert kept.tolist() == [1, 2]
    assert out.attractor.tolist() == [1.0, 2.0]
    np.testing.assert_array_equal(out.positions[0].numpy(), x[:, 1:])
    np.testing.assert_array_equal(out.velocities[0].numpy(), demos.velocities[0, :, 1:].numpy())


# ---------------------------------------------------------------------------------------------- trimming
def test_trimming_counts_a_sample_at_exactly_the_position_tolerance_as_still() -> None:
    """A sample *within* position_tol of the attractor (distance == tol exactly, at rest) is still: the tail that
    rests at distance 1 from the goal with position_tol = 1 is cut after its first sample. Reference: a naive
    loop with inclusive comparisons."""
    move = np.stack([np.linspace(5.0, 1.0, 9), np.zeros(9)], 1)
    x = np.concatenate([move, np.repeat(move[-1:], 6, 0)])
    v = np.zeros_like(x)
    v[:8, 0] = -2.0  # moving, then exactly at rest from sample 8 on
    demos = Demos.from_sequences([x], velocities=[v], attractor=np.zeros(2))
    out = trim_still_tail(demos, position_tol=1.0, velocity_tol=0.5)
    still = (np.linalg.norm(x, axis=1) <= 1.0) & (np.linalg.norm(v, axis=1) <= 0.5)
    last_moving = max(k for k in range(len(x)) if not still[k])
    assert int(out.lengths[0]) == last_moving + 2 == 9


def test_trimming_a_demonstration_that_is_still_throughout_keeps_three_samples() -> None:
    """A demonstration resting at the goal from its first sample keeps MIN_SAMPLES = 3 samples (not 1), and a
    moving one beside it is unaffected."""
    rest = np.zeros((8, 2))
    move = np.stack([np.linspace(4.0, 0.0, 8), np.zeros(8)], 1)
    demos = estimate_velocities(Demos.from_sequences([rest, move], attractor=np.zeros(2)))
    out = trim_still_tail(demos, position_tol=0.1, velocity_tol=0.1)
    assert out.lengths.tolist() == [3, 8]


def test_trimming_measures_the_speed_as_the_euclidean_norm() -> None:
    """Still means ||v|| <= velocity_tol with the Euclidean norm over every dimension: a tail resting at the goal
    in x but drifting in y at 1 per second is not still under velocity_tol = 0.5 (numpy norm as the reference)."""
    move = np.stack([np.linspace(4.0, 0.0, 9), np.zeros(9)], 1)
    x = np.concatenate([move, np.zeros((5, 2))])
    v = np.zeros_like(x)
    v[:8, 0] = -0.5 / 0.1
    v[9:12, 1] = 1.0  # y drift, position still at the goal within the tolerance
    demos = Demos.from_sequences([x], velocities=[v], dt=0.1, attractor=np.zeros(2))
    out = trim_still_tail(demos, position_tol=0.1, velocity_tol=0.5)
    still = (np.linalg.norm(x, axis=1) <= 0.1) & (np.linalg.norm(v, axis=1) <= 0.5)
    last_moving = max(k for k in range(len(x)) if not still[k])
    assert last_moving == 11 and int(out.lengths[0]) == last_moving + 2


# ---------------------------------------------------------------------------------------------- pipeline
def test_pipeline_equals_its_steps_called_by_hand() -> None:
    """Preprocess runs resample(n_samples, resample_mode) -> smooth(window, smoothing, polyorder) ->
    velocities(velocity_scheme) -> trim(position_tol, velocity_tol) -> screen(threshold) -> subsample(step), each
    with its own field. Reference: the documented step functions called one by one with the same arguments;
    every field is set to a non-default value that changes the result."""
    g = _gen(6)
    seqs = []
    for n in (40, 33):
        walk = torch.randn(n, 3, generator=g, dtype=torch.float64).cumsum(0).numpy()
        walk[:, 2] *= 1e-4  # a quiet third dimension for the screening
        walk = walk - walk[-1]
        seqs.append(np.concatenate([walk, np.repeat(walk[-1:], 6, 0)]))
    demos = Demos.from_sequences(seqs, dt=0.1, attractor=np.zeros(3))
    cases = [
        dict(smoothing="savgol", window=7, polyorder=2, velocity_scheme="forward"),
        dict(smoothing="moving_average", window=5, n_samples=31, resample_mode="arc_length"),
        dict(smoothing="none", velocity_scheme="backward", trim_position_tol=0.0, trim_velocity_tol=50.0,
             screen_threshold=0.05, subsample_step=2),
        dict(smoothing="none", trim_position_tol=50.0, trim_velocity_tol=0.0),
    ]  # fmt: skip
    for kw in cases:
        p = Preprocess(**kw)
        ref = demos
        if p.n_samples is not None:
            ref = resample(ref, p.n_samples, p.resample_mode)
        if p.smoothing != "none":
            ref = smooth(ref, p.window, p.smoothing, p.polyorder)
        ref = estimate_velocities(ref, p.velocity_scheme)
        if p.trim_position_tol is not None:
            ref = trim_still_tail(ref, p.trim_position_tol, p.trim_velocity_tol)
        if p.screen_threshold is not None:
            ref = screen_dimensions(ref, p.screen_threshold)
        ref = subsample(ref, p.subsample_step)
        out = p(demos)
        assert out.lengths.tolist() == ref.lengths.tolist(), kw
        torch.testing.assert_close(out.positions, ref.positions, rtol=0, atol=0)
        torch.testing.assert_close(out.velocities, ref.velocities, rtol=0, atol=0)
        torch.testing.assert_close(out.times, ref.times, rtol=0, atol=0)
    # each choice matters: the defaults give something else
    base = Preprocess(smoothing="none")(demos)
    assert not torch.equal(Preprocess(smoothing="none", velocity_scheme="forward")(demos).velocities, base.velocities)
    sg3 = Preprocess(window=7, polyorder=3)(demos).positions
    # (orders 2k and 2k + 1 give the same centred Savitzky-Golay weights: compare 3 with 4, not with 2)
    assert not torch.allclose(Preprocess(window=7, polyorder=4)(demos).positions, sg3, rtol=0, atol=1e-9)
    assert not torch.equal(Preprocess(smoothing="moving_average", window=7)(demos).positions, sg3)
    assert Preprocess(smoothing="none", screen_threshold=0.05)(demos).dim == 2


def test_given_velocities_are_refused_after_resampling_or_smoothing_and_kept_otherwise() -> None:
    """velocity_scheme='given' keeps the loaded velocities bit for bit when no step moved the positions, and is an
    error once resampling or smoothing changed them (the given labels would no longer match)."""
    demos = load_lasa("Sine")
    kept = Preprocess(smoothing="none", velocity_scheme="given")(demos)
    assert torch.equal(kept.velocities, demos.velocities)
    with pytest.raises(InvalidArgumentError, match="given"):
        Preprocess(smoothing="none", n_samples=100, velocity_scheme="given")(demos)
    with pytest.raises(InvalidArgumentError, match="given"):
        Preprocess(window=5, velocity_scheme="given")(demos)


# ---------------------------------------------------------------------------------------------- rollout
def _naive_rollout(
    f: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, dt: float, n: int, g: np.ndarray, p_tol: float,
    v_tol: float, kicks: dict[int, np.ndarray], gate: Callable[[int], bool] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Euler, one row and one sample at a time, by the module docstring: kicks displace and reactivate every row at
    their sample, a row stops at the first sample k with ||x - g|| < p_tol and ||v|| < v_tol (and gate(k)), and is
    frozen (zero velocity) until the next kick."""
    B, d = x0.shape
    X, V = np.zeros((B, n + 1, d)), np.zeros((B, n + 1, d))
    L = np.full(B, n + 1)
    for b in range(B):
        x, active, stop = x0[b].copy(), True, None
        for k in range(n + 1):
            if k in kicks:
                x, active, stop = x + kicks[k][b], True, None
            X[b, k] = x
            if not active:
                continue
            v = f(x)
            V[b, k] = v
            if np.linalg.norm(x - g) < p_tol and np.linalg.norm(v) < v_tol and (gate is None or gate(k)):
                active, stop = False, k
            else:
                x = x + dt * v
        L[b] = n + 1 if stop is None else stop + 1
    return X, V, L


def test_a_push_due_at_a_synchronisation_step_after_every_row_stopped_is_applied() -> None:
    """Every row stops at sample 0 (it starts at the goal); a push scheduled at sample 8 = check_every must still
    act (the early finish may only happen when no push is pending at or after the current sample). Reference: a
    naive per-row Euler loop of the documented stopping rule."""
    g = np.zeros(2)
    x0 = np.array([[0.0, 0.0], [1e-4, 0.0]])
    push = np.array([1.0, -0.5])
    kw = dict(attractor=torch.zeros(2, dtype=torch.float64), position_tol=0.01, velocity_tol=0.01)
    for check_every in (1, 4, 8):
        res = rollout(lambda x: -x, torch.tensor(x0), 0.1, 60, check_every=check_every,
                      disturbances=Disturbance(steps=8, value=push), **kw)  # fmt: skip
        X, V, L = _naive_rollout(lambda x: -x, x0, 0.1, 60, g, 0.01, 0.01, {8: np.tile(push, (2, 1))})
        assert res.lengths.tolist() == L.tolist(), check_every
        np.testing.assert_allclose(res.positions.numpy(), X, rtol=0, atol=1e-12)
        np.testing.assert_allclose(res.velocities.numpy(), V, rtol=0, atol=1e-12)


def test_a_hook_may_still_displace_at_its_last_sample_hook_until() -> None:
    """hook_until is the last sample at which the hook may displace: with every row stopped before it and the
    synchronisation falling on that very sample, the hook is still called there and its push acts. Reference: the
    same push as a scheduled Disturbance (equal by the module docstring)."""
    x0 = torch.tensor([[0.0, 0.0], [2e-3, 0.0]], dtype=torch.float64)
    kw = dict(attractor=torch.zeros(2, dtype=torch.float64), position_tol=0.01, velocity_tol=0.01, check_every=8)
    delta = torch.tensor([0.5, 0.25], dtype=torch.float64)
    calls: list[int] = []

    def hook(k: int, x: torch.Tensor, active: torch.Tensor) -> torch.Tensor | None:
        calls.append(k)
        return x + delta if k == 8 else None

    res = rollout(lambda x: -x, x0, 0.1, 80, hook=hook, hook_until=8, **kw)
    ref = rollout(lambda x: -x, x0, 0.1, 80, disturbances=Disturbance(steps=8, value=delta), **kw)
    assert 8 in calls
    assert res.lengths.tolist() == ref.lengths.tolist() and (res.lengths > 9).all()
    torch.testing.assert_close(res.positions, ref.positions, rtol=0, atol=1e-12)


def test_can_stop_gates_the_stopping_rule_per_row() -> None:
    """A row may stop only at samples where can_stop(k) is True for it: row 0 is allowed from sample 5 on, row 1
    always. Both start at the goal, so they stop at 5 and 0. Reference: the naive loop with the gate."""
    x0 = np.array([[0.0, 0.0], [0.0, 0.0]])
    gate = lambda k: torch.tensor([k >= 5, True])  # noqa: E731
    res = rollout(lambda x: -x, torch.tensor(x0), 0.1, 20, attractor=torch.zeros(2, dtype=torch.float64),
                  position_tol=0.01, velocity_tol=0.01, hook=lambda k, x, a: None, can_stop=gate)  # fmt: skip
    _, _, L0 = _naive_rollout(lambda x: -x, x0[:1], 0.1, 20, np.zeros(2), 0.01, 0.01, {}, gate=lambda k: k >= 5)
    assert res.lengths.tolist() == [int(L0[0]), 1] == [6, 1]
    assert res.converged.tolist() == [True, True]


# ---------------------------------------------------------------------------------------------- MNIST strokes
def _bar(rows: slice, cols: slice, size: int = 28) -> np.ndarray:
    img = np.zeros((size, size), dtype=np.uint8)
    img[rows, cols] = 255
    return img


def test_stroke_coordinates_are_original_pixels_with_y_up() -> None:
    """A 3 px wide vertical bar centred on column 14 gives a skeleton at x = 14; a horizontal bar centred on row 14
    of a 28-row image gives y = H - 1 - 14 = 13 (the upsampled grid maps back by zoom's corner-aligned scale
    (H - 1) / (H up - 1), not 1 / up). Reference: the bars' known centre lines."""
    v = extract_stroke(_bar(slice(4, 24), slice(13, 16)), smooth=0.0).path
    assert np.abs(v[:, 0] - 14.0).max() < 0.15
    assert v[0, 1] > v[-1, 1] and 3.0 < v[-1, 1] < 6.0 and 21.0 < v[0, 1] < 24.0  # rows 4..23 -> y 23..4
    h = extract_stroke(_bar(slice(13, 16), slice(4, 24)), smooth=0.0).path
    assert np.abs(h[:, 1] - 13.0).max() < 0.15
    assert 3.0 < h[0, 0] < 6.0 and 21.0 < h[-1, 0] < 24.0


def test_a_level_stroke_starts_at_its_left_end() -> None:
    """Ends at the same height (within level_tol): the left-most end starts, whichever way the trail was found
    (the bar written left to right). Reference: the bar's known ends."""
    for cols in (slice(4, 24), slice(2, 26)):
        p = extract_stroke(_bar(slice(12, 15), cols)).path
        assert p[0, 0] < p[-1, 0] - 10


def test_a_pinhole_in_the_ink_is_filled_before_skeletonisation() -> None:
    """A one-pixel hole in a 6 px wide bar (about 12 upsampled px^2, below min_hole = 1.5 original px^2 = 24
    upsampled px^2 at upsample 4) is an ink blot, not a loop: the skeleton is one straight branch without
    junctions (a loop round the hole would add two). Reference: the bar's known skeleton, a vertical segment."""
    img = _bar(slice(4, 24), slice(11, 17))
    img[13, 13] = 0
    st = extract_stroke(img)
    assert st.n_junctions == 0 and st.n_endpoints == 2 and not st.closed
    assert np.ptp(st.path[:, 0]) < 0.6


def test_ink_share_is_the_share_of_the_largest_component() -> None:
    """ink_share is (ink of the kept component) / (all ink): a 3 x 18 px bar and a separate 3 x 3 px dot give
    about 54 / 63 = 0.86 (bilinear upsampling blurs both edges alike); one bar alone gives exactly 1."""
    img = _bar(slice(5, 23), slice(8, 11))
    assert extract_stroke(img).ink_share == 1.0
    img[10:13, 20:23] = 255
    share = extract_stroke(img).ink_share
    assert 0.78 < share < 0.93


def test_the_dense_path_is_sampled_at_most_a_quarter_pixel_apart() -> None:
    """Without smoothing, the path of a bar is resampled at ceil(length / 0.25) + 1 points equally spaced along
    the skeleton polyline: no chord exceeds 0.25 px, and the points are not much denser than that (mean chord
    above 0.9 x 0.25 px). Reference: chord lengths by numpy."""
    for cols in (slice(13, 16), slice(12, 15)):
        st = extract_stroke(_bar(slice(4, 24), cols), smooth=0.0)
        steps = np.linalg.norm(np.diff(st.path, axis=0), axis=1)
        assert steps.max() <= 0.25 + 1e-9
        assert steps.mean() > 0.9 * 0.25


def test_path_smoothing_is_a_gaussian_of_smooth_px_along_the_path() -> None:
    """The Gaussian smoothing along an open path has a standard deviation of ``smooth`` px, i.e. smooth / 0.25
    samples of the dense path (0.25 px apart, up to the rounding of the point count), with 'nearest' ends.
    Reference: scipy.ndimage.gaussian_filter1d applied to the unsmoothed path of the same image (a 7: top bar and
    a diagonal, its corner is where the two differ)."""
    import scipy.ndimage

    img = np.zeros((28, 28), dtype=np.uint8)
    img[5:8, 6:21] = 255
    for r in range(5, 24):
        c = int(round(20 - (r - 5) * 8 / 18))
        img[r, c - 1 : c + 2] = 255
    raw = extract_stroke(img, smooth=0.0)
    sm = extract_stroke(img, smooth=1.5)
    p0 = raw.path
    ref = scipy.ndimage.gaussian_filter1d(p0, 1.5 / 0.25, axis=0, mode="nearest")
    assert sm.path.shape == p0.shape
    np.testing.assert_allclose(sm.path, ref, atol=3e-3)
    assert np.abs(sm.path - p0).max() > 0.1  # the corner is rounded


# ---------------------------------------------------------------------------------------------- stroke timing
def test_repeated_points_of_a_pen_path_do_not_change_its_timing() -> None:
    """Consecutive duplicates are dropped: a path with every point repeated gives the same finite positions,
    times and velocities as the path itself (the velocity is the tangent times the minimum-jerk rate)."""
    s = np.linspace(0.0, 1.0, 40)
    path = np.stack([10 * s, 6 * np.sin(np.pi * s)], 1)
    doubled = np.repeat(path, 2, axis=0)
    a = stroke_trajectory(path, n_points=60)
    b = stroke_trajectory(doubled, n_points=60)
    for u, w in zip(a, b):
        assert np.isfinite(w).all()
        np.testing.assert_allclose(w, u, rtol=0, atol=1e-9)


def test_the_rest_at_a_cusp_is_placed_in_millimetres() -> None:
    """The pen rests where the path reverses at every scale: out 10 px and back 6 px at 2 mm/px and 10 mm/s is
    20 mm then 12 mm; the rest falls at t = 20 / 10 = 2 s (closed form), at the return point, and the two pieces
    are minimum-jerk movements (peak speed 1.875 x mean speed, closed form)."""
    out = np.stack([np.linspace(0, 10, 41), np.zeros(41)], 1)
    back = np.stack([np.linspace(10, 4, 25)[1:], np.zeros(24)], 1)
    path = np.concatenate([out, back])
    pos, t, vel = stroke_trajectory(path, n_points=641, mm_per_pixel=2.0, mean_speed=10.0)
    assert math.isclose(t[-1], 3.2)
    k = int(np.argmin(np.abs(t - 2.0)))
    assert np.linalg.norm(vel[k]) < 1e-6
    np.testing.assert_allclose(pos[k], (path[40] - path[-1]) * 2.0, atol=1e-6)
    speed = np.linalg.norm(vel, axis=1)
    assert math.isclose(speed[t < 2.0].max(), 1.875 * 10.0, rel_tol=2e-3)
    assert math.isclose(speed[t > 2.0].max(), 1.875 * 10.0, rel_tol=2e-3)


def test_a_diagonal_stroke_is_one_branch_without_junctions() -> None:
    """A skeleton staircase along a diagonal links each pixel to its 4-neighbours and drops the diagonal links
    they already bridge (no triangles): a 3 px thick diagonal line is one branch, two endpoints, no junction,
    drawn in full (coverage 1), from its top-left end down to the bottom right. Reference: the line's known
    skeleton."""
    img = np.zeros((28, 28), dtype=np.uint8)
    for r in range(4, 24):
        img[r, r - 1 : r + 2] = 255
    st = extract_stroke(img)
    assert (st.n_endpoints, st.n_junctions, st.closed) == (2, 0, False)
    assert st.coverage == pytest.approx(1.0)
    p = st.path
    assert p[0, 1] > p[-1, 1] + 15 and p[0, 0] < p[-1, 0] - 15
    np.testing.assert_allclose(p[10:-10, 0] + p[10:-10, 1], 27.0, atol=0.5)  # col = row: x + y = H - 1 (ends hook)


def test_disturbances_at_the_same_sample_add_up() -> None:
    """Several disturbances scheduled at one sample add up: two position pushes (one for row 0 only) and two extra
    velocities at sample 3. Reference: a naive Euler loop with the summed push and summed extra velocity during
    the step 3 -> 4 (no attractor: nothing stops)."""
    x0 = np.array([[1.0, 0.0], [0.0, 2.0]])
    A = np.array([[-1.0, 0.5], [-0.5, -1.0]])
    dists = [
        Disturbance(3, [0.5, 0.0]), Disturbance(3, [0.0, -0.25], rows=[0]),
        Disturbance(3, [1.0, 1.0], kind="velocity"), Disturbance(3, [-0.5, 2.0], kind="velocity"),
    ]  # fmt: skip
    res = rollout(lambda x: x @ torch.tensor(A.T), torch.tensor(x0), 0.1, 8, disturbances=dists)
    X = np.zeros((2, 9, 2))
    for b in range(2):
        x = x0[b].copy()
        for k in range(9):
            extra = np.zeros(2)
            if k == 3:
                x = x + np.array([0.5, 0.0]) + (np.array([0.0, -0.25]) if b == 0 else 0.0)
                extra = np.array([0.5, 3.0])
            X[b, k] = x
            x = x + 0.1 * (A @ x + extra)
    np.testing.assert_allclose(res.positions.numpy(), X, rtol=0, atol=1e-12)


def test_a_notch_open_to_the_image_border_is_not_filled_as_a_hole() -> None:
    """Only holes enclosed by ink are filled: a one-pixel notch in ink that runs along the top border is open to
    the outside and stays background, while the same pixel inside the bar is filled. Reference: the image's own
    pixels (the notch's upsampled centre must stay off)."""
    from lfd_torch.data.mnist import _binarise

    img = np.zeros((28, 28), dtype=np.uint8)
    img[0:6, 4:24] = 255
    img[0, 13] = 0  # a notch on the border
    ink, share = _binarise(img, 0.5, 4, 1.5)
    r, c = 0, round(13 * (28 * 4 - 1) / 27)  # the notch pixel on the corner-aligned upsampled grid
    assert not ink[r, c] and share == 1.0
    img[0, 13], img[3, 13] = 255, 0  # the same pixel enclosed: filled
    ink, _ = _binarise(img, 0.5, 4, 1.5)
    assert ink[round(3 * 111 / 27), c]


def test_a_dead_end_branch_is_drawn_out_and_back_only_when_longer_than_its_turning_cost() -> None:
    """turn_weight is in original-image px per radian (the search runs on the upsampled grid, so it is scaled by
    ``upsample`` there). A T whose 7 px stem is a dead end: an excursion down the stem and back turns by about
    2 pi rad (pi / 2 in, pi at the tip, pi / 2 out), so it pays off at turn_weight = 0.5 (cost ~3 px < ~8 px of
    skeleton) and not at turn_weight = 2 (cost ~12.6 px): the bar alone, coverage about 0.7. Closed-form cost vs
    the known branch length."""
    img = np.zeros((28, 28), dtype=np.uint8)
    img[6:9, 4:24] = 255
    img[9:16, 13:16] = 255
    assert extract_stroke(img, turn_weight=0.5).coverage == pytest.approx(1.0)
    st = extract_stroke(img, turn_weight=2.0)
    assert st.coverage < 0.8 and st.n_endpoints == 3
    assert np.ptp(st.path[:, 1]) < 1.0  # the bar only, level


def test_an_mnist_label_above_nine_is_a_store_error(tmp_path: Path) -> None:
    """Labels are digits 0..9: an IDX label file holding a 10 is refused (StoreError naming the label), a 9 is
    accepted. Reference: IDX files written by hand (magic 0x801 / 0x803, big-endian dimensions)."""
    import struct

    from lfd_torch.data.mnist import load_mnist
    from lfd_torch.errors import StoreError

    for last, ok in ((9, True), (10, False)):
        folder = tmp_path / str(last)
        folder.mkdir()
        images = np.zeros((2, 28, 28), dtype=np.uint8)
        (folder / "t10k-images-idx3-ubyte").write_bytes(struct.pack(">IIII", 0x803, 2, 28, 28) + images.tobytes())
        (folder / "t10k-labels-idx1-ubyte").write_bytes(struct.pack(">II", 0x801, 2) + bytes([3, last]))
        if ok:
            assert load_mnist("test", folder)[1].tolist() == [3, 9]
        else:
            with pytest.raises(StoreError, match="label 10"):
                load_mnist("test", folder)


def test_skeleton_adjacency_drops_diagonals_bridged_by_a_4_neighbour() -> None:
    """8-connected neighbours, except a diagonal link whose two pixels are also joined through a lit 4-neighbour
    (no triangles): on a 4-connected staircase every pixel has at most 2 neighbours, and an isolated diagonal
    pair stays linked. Reference: the adjacency of the staircase written out by hand."""
    from lfd_torch.data.mnist import _adjacency

    skel = np.zeros((6, 6), dtype=bool)
    stair = [(0, 0), (0, 1), (1, 1), (1, 2), (2, 2), (2, 3)]
    for p in stair:
        skel[p] = True
    skel[4, 0] = skel[5, 1] = True  # a lone diagonal pair
    adj = {p: sorted(nb) for p, nb in _adjacency(skel).items()}
    expected = {p: sorted(q for q in stair if abs(q[0] - p[0]) + abs(q[1] - p[1]) == 1) for p in stair}
    expected[(4, 0)], expected[(5, 1)] = [(5, 1)], [(4, 0)]
    assert adj == expected


def test_trimming_counts_a_sample_at_exactly_the_velocity_tolerance_as_still() -> None:
    """A sample at rest distance-wise that moves at exactly velocity_tol is still (the bound is inclusive, as the
    docstring says): the tail that creeps at speed 0.5 with velocity_tol = 0.5 is cut after its first sample."""
    move = np.stack([np.linspace(5.0, 0.0, 9), np.zeros(9)], 1)
    x = np.concatenate([move, np.repeat(move[-1:], 6, 0)])
    v = np.zeros_like(x)
    v[:8, 0] = -2.0
    v[8:, 1] = 0.5  # exactly the tolerance
    demos = Demos.from_sequences([x], velocities=[v], attractor=np.zeros(2))
    assert int(trim_still_tail(demos, position_tol=0.1, velocity_tol=0.5).lengths[0]) == 9
    assert int(trim_still_tail(demos, position_tol=0.1, velocity_tol=0.49).lengths[0]) == 15


def test_arc_length_resampling_keeps_the_first_and_last_time_stamps() -> None:
    """A demonstration still for its first 0.2 s and its last 0.5 s, resampled by arc length: the resampled times
    run from its first to its last time stamp (the timing of the demonstration is kept at both ends)."""
    t = np.arange(16) * 0.1
    s = np.concatenate([np.zeros(3), np.linspace(0.0, 1.0, 8)[1:], np.ones(6)])
    x = np.stack([s, 2.0 * s], 1)
    out = resample(Demos.from_sequences([x], times=[t], attractor=x[-1]), 9, "arc_length")
    assert float(out.times[0, 0]) == 0.0 and float(out.times[0, -1]) == pytest.approx(1.5)
    np.testing.assert_allclose(out.positions[0, [0, -1]].numpy(), x[[0, -1]])
