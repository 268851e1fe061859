"""What the segmentation assumes of the data: the position noise model (AR(1) fit, the velocities' noise under it),
correlated synthetic noise, family overrides, units."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.signal import lfilter

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.segmentation import (
    NOISE_FLOOR,
    position_noise,
    position_noise_model,
    scale_velocities,
    velocity_noise,
)
from lfd_torch.segmentation.synthetic import FAMILIES, multi_step_demos, with_correlated_noise, with_sampling_rate

F64 = torch.float64


def _ar1(shape: tuple[int, ...], rho: float, sigma: float, seed: int) -> torch.Tensor:
    """Stationary AR(1) noise along the second-to-last axis, by scipy's lfilter (an independent reference)."""
    eta = torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=F64).numpy()
    eta[..., 1:, :] *= math.sqrt(1.0 - rho * rho)
    return sigma * torch.as_tensor(lfilter([1.0], [1.0, -rho], eta, axis=-2))


def _min_jerk_path(T: int = 800) -> torch.Tensor:
    """(T, 2) two min-jerk legs with a 90-degree corner, unit legs (the benchmark's scale and rate)."""
    tau = torch.linspace(0.0, 1.0, T // 2, dtype=F64)
    s = (tau**3 * (10 - 15 * tau + 6 * tau**2)).unsqueeze(-1)
    return torch.cat([s * torch.tensor([1.0, 0.0], dtype=F64), torch.tensor([1.0, 0.0], dtype=F64)
                      + s * torch.tensor([0.0, 1.0], dtype=F64)])


@pytest.mark.parametrize("rho", [0.0, 0.3, 0.7])
def test_velocity_noise_matches_monte_carlo_under_ar1_noise(rho):
    """Reference: Monte Carlo. The empirical standard deviation of ``scale_velocities`` on AR(1) noise matches
    ``velocity_noise(..., rho)`` inside the sequence and at its ends (within 10 %); rho = 0 is the white formula."""
    k, T, sigma = 6, 120, 0.01
    noise = _ar1((600, T, 2), rho, sigma, seed=1)
    sd = torch.stack([scale_velocities(e, k, 0.01) for e in noise]).std(dim=(0, 2))
    ref = velocity_noise(sigma, T, k, 0.01, rho=rho)
    assert float((sd[15:-15] / ref[15:-15] - 1).abs().max()) < 0.1
    assert float((sd[:2] / ref[:2] - 1).abs().max()) < 0.1
    if rho == 0.0:
        torch.testing.assert_close(ref, velocity_noise(sigma, T, k, 0.01))
    else:  # correlation makes the slope noisier than white noise of the same level
        assert float(ref[60]) > 1.2 * float(velocity_noise(sigma, T, k, 0.01)[60])


@pytest.mark.parametrize("rho", [0.3, 0.5, 0.7])
def test_position_noise_model_recovers_ar1_noise_on_a_moving_path(rho):
    """Property: on a min-jerk path plus AR(1) noise of 1 % of the leg length the fit recovers rho within 0.1 and
    sigma within 15 % (robust variances of 3200 differences), where the white lag-one estimate sees too little."""
    path = _min_jerk_path()
    seqs = [path + _ar1(path.shape, rho, 0.01, seed=s) for s in range(2)]
    sigma, rho_hat = position_noise_model(seqs)
    assert sigma == pytest.approx(0.01, rel=0.15) and rho_hat == pytest.approx(rho, abs=0.1)
    assert position_noise(seqs) < 0.9 * sigma


def test_position_noise_model_keeps_the_white_estimate_for_white_noise_and_smooth_data():
    """Property: white noise gives (nearly) the white estimate and rho <= 0.1; data whose short-lag differences are
    signal (a smooth curve with 1e-6 noise: second differences growing as L^4) give exactly the white lag-one
    estimate, rho = 0, as before the AR(1) model."""
    path = _min_jerk_path()
    white = [path + 0.01 * torch.randn(path.shape, generator=torch.Generator().manual_seed(s), dtype=F64)
             for s in range(2)]
    sigma, rho = position_noise_model(white)
    assert rho <= 0.1 and sigma == pytest.approx(0.01, rel=0.1)
    t = torch.linspace(0, 2 * math.pi, 1000, dtype=F64)
    smooth = [torch.stack([torch.cos(t), torch.sin(2 * t)], -1)
              + 1e-6 * torch.randn(1000, 2, generator=torch.Generator().manual_seed(3), dtype=F64)]
    assert position_noise_model(smooth) == (position_noise(smooth), 0.0)


def test_with_correlated_noise_has_the_asked_correlation_and_level():
    """Property: the new noise of a family draw has lag-one autocorrelation rho (within 0.05) and the family's
    level (within 10 %), or ``scale`` times it; the noise-free paths and the switches are those of the draw."""
    syn = FAMILIES["straight_dwell_2d"](torch.Generator().manual_seed(0), 4)
    out = with_correlated_noise(syn, 0.6, torch.Generator().manual_seed(1))
    e = torch.cat([out.demos.positions[i, :n] - syn.clean[i, :n] for i, n in enumerate(syn.demos.lengths.tolist())])
    r1 = float((e[1:] * e[:-1]).sum() / (e * e).sum())
    assert r1 == pytest.approx(0.6, abs=0.05) and float(e.std()) == pytest.approx(syn.noise, rel=0.1)
    assert torch.equal(out.switch_times, syn.switch_times) and torch.equal(out.demos.lengths, syn.demos.lengths)
    with pytest.raises(ValueError, match="rho"):
        with_correlated_noise(syn, 1.0, torch.Generator().manual_seed(1))
    quiet = with_correlated_noise(syn, 0.0, torch.Generator().manual_seed(1), scale=0.1)
    e = torch.cat([quiet.demos.positions[i, :n] - syn.clean[i, :n] for i, n in enumerate(syn.demos.lengths.tolist())])
    assert float(e.std()) == pytest.approx(0.1 * syn.noise, rel=0.1) and quiet.noise == pytest.approx(0.1 * syn.noise)
    with pytest.raises(ValueError, match="scale"):
        with_correlated_noise(syn, 0.0, torch.Generator().manual_seed(1), scale=-1.0)


def test_with_sampling_rate_keeps_the_motion_and_maps_the_switches():
    """At 50 Hz the noise-free paths are every second sample of the 100 Hz ones (the interpolation is exact at their
    instants) and a switch c becomes ceil(c / 2); at 500 Hz every fifth sample is an original one and the switch
    sample is the first at or after the corner's instant; the new noise is white with the family's level; the
    correlated-noise variant keeps the new time step."""
    syn = FAMILIES["curved_dwell_2d"](torch.Generator().manual_seed(0), 2)
    slow = with_sampling_rate(syn, 50.0, torch.Generator().manual_seed(1))
    fast = with_sampling_rate(syn, 500.0, torch.Generator().manual_seed(1))
    for i, n in enumerate(syn.demos.lengths.tolist()):
        m = int(slow.demos.lengths[i])
        assert m == (n - 1) // 2 + 1 and int(fast.demos.lengths[i]) == 5 * (n - 1) + 1
        assert torch.allclose(slow.clean[i, :m], syn.clean[i, :n:2], atol=1e-12)
        assert torch.allclose(fast.clean[i, : 5 * (n - 1) + 1 : 5], syn.clean[i, :n], atol=1e-12)
        e = fast.demos.positions[i, : int(fast.demos.lengths[i])] - fast.clean[i, : int(fast.demos.lengths[i])]
        assert float(e.std()) == pytest.approx(syn.noise, rel=0.1)
        assert abs(float((e[1:] * e[:-1]).sum() / (e * e).sum())) < 0.05
    assert torch.equal(slow.switch_times, (syn.switch_times + 1) // 2)
    assert torch.equal(fast.switch_times, 5 * syn.switch_times)
    assert float(fast.demos.times[0, 1] - fast.demos.times[0, 0]) == pytest.approx(0.002)
    ar1 = with_correlated_noise(fast, 0.5, torch.Generator().manual_seed(2))
    assert torch.equal(ar1.demos.times, fast.demos.times)
    with pytest.raises(ValueError, match="rate"):
        with_sampling_rate(syn, 0.1, torch.Generator().manual_seed(1))


def test_segment_rejects_an_unknown_noise_model_and_reports_the_fit():
    syn = FAMILIES["straight_const_2d"](torch.Generator().manual_seed(0), 1)
    with pytest.raises(InvalidArgumentError, match="noise_model"):
        segment(syn.demos, generator=torch.Generator().manual_seed(0), noise_model="pink")
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), n_iterations=4)
    assert seg.info["noise_correlation"] <= 0.1 and seg.info["position_noise"] == pytest.approx(syn.noise, rel=0.15)


def test_white_noise_data_segment_exactly_as_under_the_white_model():
    """Property: where the test keeps white noise (a benchmark family's white noise) ``noise_model="ar1"`` is the
    earlier white estimate bit for bit: the same labels as ``noise_model="white"`` for the same seed."""
    syn = FAMILIES["curved_dwell_2d"](torch.Generator().manual_seed(3), 2)
    a = segment(syn.demos, generator=torch.Generator().manual_seed(0), n_iterations=10)
    b = segment(syn.demos, generator=torch.Generator().manual_seed(0), n_iterations=10, noise_model="white")
    assert a.info["noise_correlation"] == 0.0 and a.info["position_noise"] == b.info["position_noise"]
    assert all(torch.equal(x, y) for x, y in zip(a.labels, b.labels))


def test_family_draws_take_overrides_of_their_generator():
    """``FAMILIES[name](generator, n_demos, n_steps=M)``: M legs (M - 1 switches in every demonstration); without
    overrides the draw is unchanged."""
    syn = FAMILIES["curved_const_2d"](torch.Generator().manual_seed(4), 2, n_steps=7)
    assert syn.n_steps == 7 and syn.switch_times.shape == (2, 6) and syn.family == "curved_const_2d"
    a = FAMILIES["straight_dwell_3d"](torch.Generator().manual_seed(4), 1)
    b = FAMILIES["straight_dwell_3d"](torch.Generator().manual_seed(4), 1, **{})
    assert torch.equal(a.demos.positions, b.demos.positions)


def test_steps_do_not_depend_on_the_units_or_the_origin():
    """Property: the model sees standardised positions, unit directions and log time ratios, so positions in
    millimetres about another origin (x 1000 + offset) give the same step labels and the same switches."""
    from lfd_torch.data import Demos

    syn = FAMILIES["straight_const_3d"](torch.Generator().manual_seed(2), 2)
    offset = torch.tensor([5000.0, -3000.0, 200.0], dtype=F64)
    mm = Demos.from_sequences([1000.0 * s + offset for s in syn.demos.sequences()], dt=0.01)
    a = segment(syn.demos, generator=torch.Generator().manual_seed(1), n_iterations=10)
    b = segment(mm, generator=torch.Generator().manual_seed(1), n_iterations=10)
    assert a.n_steps >= 3 and a.n_steps == b.n_steps and all(torch.equal(x, y) for x, y in zip(a.labels, b.labels))
    torch.testing.assert_close(1000.0 * a.attractors[:-1] + offset, b.attractors[:-1])


def test_every_stored_data_set_keeps_the_white_estimate():
    """Regression for the README's claim that the AR(1) model left every stored result unchanged: the test keeps
    white noise (rho = 0, the lag-one estimate) on all 30 LASA shapes, on the 280 white-noise benchmark cases
    (14 families x 10 data seeds x 1 and 4 demonstrations), on preprocessed scooping demonstrations and on the
    3-D set."""
    import sys
    from pathlib import Path

    from omegaconf import OmegaConf

    from lfd_torch.data import load_lasa
    from lfd_torch.data.lasa import LASA_NAMES
    from lfd_torch.preprocess import Preprocess
    from lfd_torch.robot.demonstration import scooping_demonstration

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    from bench_segmentation import data_seed

    sets = [[s.to(F64) for s in load_lasa(name).sequences()] for name in LASA_NAMES]
    sets += [FAMILIES[f](torch.Generator().manual_seed(data_seed(f, seed)), n).demos.sequences()
             for f in FAMILIES for n in (1, 4) for seed in range(10)]
    sets += [[s.to(F64) for s in Preprocess()(scooping_demonstration(seed).demos()).sequences()] for seed in (0, 5)]
    kw = OmegaConf.to_container(OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "segment_lasa.yaml")
                                .synthetic_3d)  # the 3-D set of experiments/segment_lasa.py
    sets.append(multi_step_demos(torch.Generator().manual_seed(int(kw.pop("data_seed", 0))), dim=3, **kw)
                .demos.sequences())
    kept = [position_noise_model(seqs) == (position_noise(seqs), 0.0) for seqs in sets]
    assert len(kept) == 313 and all(kept), [i for i, k in enumerate(kept) if not k]
    # and segment's noise floor (for noise-free data) binds on none of them: their results do not depend on it
    spans = [float((torch.cat(s).amax(0) - torch.cat(s).amin(0)).norm()) for s in sets]
    above = [position_noise(s) > NOISE_FLOOR * span for s, span in zip(sets, spans)]
    assert all(above), [i for i, a in enumerate(above) if not a]


def test_noise_free_demonstrations_segment():
    """Generated paths without noise estimate a position noise of 0 (or of rounding size); ``segment`` then assumes
    the floor NOISE_FLOOR x span instead of failing in the block evidence's Cholesky factors (a SolverError before the
    floor), and a noise-free single path of three straight legs at constant speed gets its three steps."""
    syn = multi_step_demos(torch.Generator().manual_seed(0), n_demos=1, n_steps=3, profile="constant", noise=0.0)
    assert position_noise(syn.demos.sequences()) < 1e-9
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0))
    assert seg.n_steps == 3
    t = torch.linspace(0.0, 1.0, 200, dtype=F64)[:, None]
    corner = torch.cat([t * torch.tensor([1.0, 0.0], dtype=F64), torch.tensor([1.0, 0.0], dtype=F64)
                        + t[1:] * torch.tensor([0.0, 1.0], dtype=F64)])  # an exact L, second differences all 0
    assert position_noise([corner]) == 0.0
    assert segment([corner], generator=torch.Generator().manual_seed(0)).n_steps >= 2


def test_speed_estimates_remove_the_noise_of_every_axis():
    """||v||^2 of a noisy velocity is s^2 + d sigma_v^2 on average: the path length's speeds and the direction
    emission's reliability weights subtract d sigma_v^2, so their squared-speed estimates average s^2 (Monte Carlo,
    3-D, s = 1, sigma_v = 0.2: 1 within 0.01, where subtracting one sigma_v^2 leaves 1.08)."""
    from lfd_torch.segmentation.field import field_observations
    from lfd_torch.segmentation.segmentation import path_length

    g = torch.Generator().manual_seed(0)
    T, d, sigma = 100_000, 3, 0.2
    u = torch.randn(T, d, generator=g, dtype=F64)
    v = u / u.norm(dim=-1, keepdim=True) + sigma * torch.randn(T, d, generator=g, dtype=F64)
    s = torch.diff(path_length(v, torch.full((T,), sigma, dtype=F64), 1.0), prepend=torch.zeros(1, dtype=F64))
    assert abs(float(s.square().mean()) - 1.0) < 0.01
    x = torch.randn(1, T, d, generator=g, dtype=F64)
    direction_noise = 0.2
    obs = field_observations(x, v[None], torch.ones(1, T, dtype=torch.bool), velocity_noise=sigma,
                             direction_noise=direction_noise)  # fmt: skip
    s0 = sigma / direction_noise
    signal = obs.w[0] * s0**2 / (1.0 - obs.w[0])  # w = signal / (signal + s0^2)
    assert abs(float(signal.mean()) - 1.0) < 0.01
