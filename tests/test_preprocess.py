"""Preprocessing against per-demonstration numpy/scipy references and properties."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal
import torch

from lfd_torch.data import Demos, load_lasa
from lfd_torch.errors import InvalidArgumentError, TooFewSamplesError, UnknownNameError
from lfd_torch.preprocess import (
    Preprocess,
    dimension_shares,
    estimate_velocities,
    moving_average,
    resample,
    savitzky_golay,
    screen_dimensions,
    subsample,
    trim_still_tail,
)


@pytest.fixture
def demos(generator) -> Demos:
    seqs = [torch.randn(n, 2, generator=generator, dtype=torch.float64).cumsum(0).numpy() for n in (40, 25, 33)]
    times = [np.cumsum(0.05 + 0.1 * torch.rand(len(s), generator=generator, dtype=torch.float64).numpy()) for s in seqs]
    return Demos.from_sequences(seqs, times=times)


def odd_extend(x: np.ndarray, h: int) -> np.ndarray:
    """Reference point reflection: x[-k] = 2 x[0] - x[k], x[L-1+k] = 2 x[L-1] - x[L-1-k]."""
    head = 2 * x[0] - x[1 : h + 1][::-1]
    tail = 2 * x[-1] - x[-h - 1 : -1][::-1]
    return np.concatenate([head, x, tail])


def naive_moving_average(x: np.ndarray, window: int) -> np.ndarray:
    h = window // 2
    ext = odd_extend(x, h)
    return np.stack([ext[t : t + window].mean(0) for t in range(len(x))])


@pytest.mark.parametrize("window", [1, 3, 7])
def test_moving_average_matches_loop(demos, window):
    before = demos.positions.clone()
    out = moving_average(demos, window)
    for i, seq in enumerate(demos.sequences()):
        ref = naive_moving_average(seq.numpy(), window) if window > 1 else seq.numpy()
        np.testing.assert_allclose(out.sequences()[i].numpy(), ref, rtol=1e-12, atol=1e-12)
    assert out.positions.shape == demos.positions.shape
    assert torch.equal(demos.positions, before)  # input untouched
    torch.testing.assert_close(out.start_points, demos.start_points, rtol=0, atol=1e-12)


def test_savgol_matches_scipy_inside_and_keeps_end_points(demos):
    window, order = 9, 3
    h = window // 2
    out = savitzky_golay(demos, window, order)
    for i, seq in enumerate(demos.sequences()):
        x = seq.numpy()
        ref = scipy.signal.savgol_filter(x, window, order, axis=0)
        got = out.sequences()[i].numpy()
        np.testing.assert_allclose(got[h:-h], ref[h:-h], rtol=1e-10, atol=1e-10)
        # ends: the same filter applied to the point-reflected extension (numpy reference)
        ext = odd_extend(x, h)
        coeffs = scipy.signal.savgol_coeffs(window, order)
        full = np.stack([np.convolve(ext[:, k], coeffs, mode="valid") for k in range(x.shape[1])], 1)
        np.testing.assert_allclose(got, full, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(got[[0, -1]], x[[0, -1]], atol=1e-12)


def test_savgol_smooths_noise_and_keeps_lines(generator):
    t = np.linspace(0, 1, 60)
    line = np.stack([3 * t - 1, 2 * t + 1], 1)
    out = savitzky_golay(Demos.from_sequences([line], times=[t]), 11, 3)
    np.testing.assert_allclose(out.sequences()[0].numpy(), line, atol=1e-12)
    curve = np.stack([np.sin(3 * t), t**2], 1)
    noisy = curve + 0.01 * torch.randn(60, 2, generator=generator, dtype=torch.float64).numpy()
    out = savitzky_golay(Demos.from_sequences([noisy], times=[t]), 11, 3)
    assert np.abs(out.sequences()[0].numpy() - curve).mean() < 0.6 * np.abs(noisy - curve).mean()


def test_smoothing_rejects_bad_windows(demos):
    with pytest.raises(InvalidArgumentError):
        moving_average(demos, 4)
    with pytest.raises(TooFewSamplesError):
        moving_average(demos, 31)  # shortest demonstration has 25 samples
    with pytest.raises(InvalidArgumentError):
        savitzky_golay(demos, 5, polyorder=5)


def test_resample_time_matches_numpy_interp(demos):
    out = resample(demos, 50)
    assert out.lengths.tolist() == [50, 50, 50]
    for i, seq in enumerate(demos.sequences()):
        t = demos.times[i, : int(demos.lengths[i])].numpy()
        tq = np.linspace(t[0], t[-1], 50)
        np.testing.assert_allclose(out.times[i].numpy(), tq, rtol=1e-12)
        for k in range(2):
            np.testing.assert_allclose(out.positions[i, :, k].numpy(), np.interp(tq, t, seq[:, k].numpy()), atol=1e-12)


def test_resample_arc_length_is_uniform_in_path_length():
    # a quarter circle traversed at very uneven speed
    s = np.linspace(0, 1, 200) ** 3
    arc = np.stack([np.cos(s * np.pi / 2), np.sin(s * np.pi / 2)], 1)
    out = resample(Demos.from_sequences([arc]), 40, mode="arc_length")
    steps = np.linalg.norm(np.diff(out.positions[0].numpy(), axis=0), axis=1)
    assert steps.std() / steps.mean() < 1e-3
    np.testing.assert_allclose(out.positions[0, -1].numpy(), arc[-1], atol=1e-12)


def test_subsample_matches_slicing(demos):
    out = subsample(demos, 4)
    for i, seq in enumerate(demos.sequences()):
        n = len(seq)
        idx = list(range(0, n - 1, 4)) + [n - 1]
        np.testing.assert_array_equal(out.sequences()[i].numpy(), seq.numpy()[idx])
        np.testing.assert_array_equal(out.times[i, : len(idx)].numpy(), demos.times[i, idx].numpy())
    plain = subsample(demos, 4, keep_last=False)  # x[::4], the LASA protocol of the LPV-DS literature
    for i, seq in enumerate(demos.sequences()):
        np.testing.assert_array_equal(plain.sequences()[i].numpy(), seq.numpy()[::4])
        np.testing.assert_array_equal(plain.velocities[i, : int(plain.lengths[i])].numpy(),
                                      demos.velocities[i, : len(seq)].numpy()[::4])  # fmt: skip


def test_screen_dimensions_drops_quiet_dimension(generator):
    seqs = [np.concatenate([torch.randn(30, 2, generator=generator, dtype=torch.float64).cumsum(0).numpy(),
                            1e-4 * np.ones((30, 1))], 1) for _ in range(2)]  # fmt: skip
    demos = Demos.from_sequences(seqs)
    shares = dimension_shares(demos)
    x = np.concatenate(seqs)
    np.testing.assert_allclose(shares.numpy(), x.var(0) / x.var(0).sum(), rtol=1e-12, atol=1e-15)
    out, kept = screen_dimensions(demos, 0.01, return_kept=True)
    assert kept.tolist() == [0, 1] and out.dim == 2 and out.attractor.shape == (2,)


def test_screen_dimensions_keeps_a_share_at_the_threshold():
    """Only shares *below* the threshold are dropped: variances 4, 1, 1 give shares 2/3, 1/6, 1/6 exactly, and a
    threshold of 1/6 keeps all three (one just above drops the two quiet ones)."""
    s = np.tile([1.0, -1.0], 20)
    demos = Demos.from_sequences([np.stack([2.0 * s, s, -s], 1)])
    assert dimension_shares(demos).tolist() == [4.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0]
    assert screen_dimensions(demos, 1.0 / 6.0, return_kept=True)[1].tolist() == [0, 1, 2]
    assert screen_dimensions(demos, np.nextafter(1.0 / 6.0, 1.0), return_kept=True)[1].tolist() == [0]


def test_trim_still_tail_matches_loop():
    path = np.concatenate([np.linspace([10.0, 5.0], [0.0, 0.0], 30), np.zeros((20, 2))])
    demos = estimate_velocities(Demos.from_sequences([path, path[:35]], attractor=np.zeros(2)))
    out = trim_still_tail(demos, position_tol=0.1, velocity_tol=0.1)
    for i, seq in enumerate(demos.sequences()):
        v = demos.velocities[i, : len(seq)].norm(dim=-1).numpy()
        still = (np.linalg.norm(seq.numpy(), axis=1) <= 0.1) & (v <= 0.1)
        last_moving = max(t for t in range(len(seq)) if not still[t])
        assert int(out.lengths[i]) == last_moving + 2
    assert out.end_points.abs().max() == 0


def test_pipeline_runs_on_lasa_and_is_pure():
    demos = load_lasa("Sshape")
    before = demos.positions.clone()
    out = Preprocess(window=15, n_samples=300, subsample_step=2)(demos)
    assert torch.equal(before, demos.positions)
    assert out.lengths.tolist() == [151] * 7
    assert (out.end_points - demos.end_points).abs().max() < 1e-9
    with pytest.raises(UnknownNameError):
        Preprocess(smoothing="gaussian")


@pytest.mark.parametrize(
    "kwargs",
    [
        {"window": 5, "polyorder": -1}, {"window": 0}, {"window": -3}, {"window": 4}, {"window": 2.5},
        {"subsample_step": 0}, {"subsample_step": -2}, {"n_samples": 2}, {"resample_mode": "fast"},
        {"window": 5, "polyorder": 5}, {"screen_threshold": 1.5}, {"trim_position_tol": -1.0, "trim_velocity_tol": 1.0},
        {"screen_threshold": "x"}, {"screen_threshold": True}, {"screen_threshold": float("nan")},
        {"trim_position_tol": "x"},
    ],
)
def test_preprocess_checks_its_arguments_at_construction(kwargs) -> None:
    from lfd_torch.errors import LfdError

    with pytest.raises(LfdError) as info:
        Preprocess(**kwargs)
    assert any(k in str(info.value) for k in kwargs)
