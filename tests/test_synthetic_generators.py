"""Benchmark families of synthetic multi-step demonstrations: determinism, shapes, and that the truth is true."""

from __future__ import annotations

import math

import pytest
import torch

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.segmentation.synthetic import (
    FAMILIES,
    HELD_OUT_FAMILIES,
    SLOWING_FAMILIES,
    curved_steps,
    multi_step_demos,
    out_and_back_steps,
    revisit_steps,
    scoop_steps,
    straight_steps,
)

F64 = torch.float64
NAMES = sorted(FAMILIES)


def draw(name: str, seed: int, n_demos: int):
    return FAMILIES[name](torch.Generator().manual_seed(seed), n_demos)


def turn_deg(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Angle between the rows of u and v (..., d), degrees."""
    c = (u * v).sum(-1) / (u.norm(dim=-1) * v.norm(dim=-1))
    return torch.rad2deg(torch.acos(c.clamp(-1.0, 1.0)))


def test_registry_covers_the_issue():
    shapes = {n.rsplit("_", 2)[0] for n in NAMES}
    assert shapes == {"straight", "curved", "out_and_back", "revisit", "scoop"}
    assert {n.rsplit("_", 2)[1] for n in NAMES} == {"dwell", "const"}
    assert {n.rsplit("_", 1)[1] for n in NAMES} == {"2d", "3d"}


@pytest.mark.parametrize("name", NAMES)
def test_family_deterministic_and_well_formed(name):
    a, b, c = draw(name, 5, 4), draw(name, 5, 4), draw(name, 6, 4)
    assert torch.equal(a.demos.positions, b.demos.positions) and torch.equal(a.switch_times, b.switch_times)
    assert not torch.equal(a.demos.positions[:, :50], c.demos.positions[:, :50])
    assert a.family == name
    dim = int(name[-2])
    B, T, d = a.demos.positions.shape
    assert (B, d) == (4, dim) and a.demos.positions.dtype == F64 and a.clean.shape == (B, T, d)
    assert torch.isfinite(a.demos.positions).all() and torch.isfinite(a.demos.velocities).all()
    M = a.n_steps
    assert M >= 2 and a.waypoints.shape == (M + 1, d)
    assert a.switch_times.shape == (B, M - 1) and a.switch_times.dtype == torch.long
    assert a.corner_angles.shape == (B, M - 1) and a.leg_lengths.shape == (M,)
    # switches increasing, inside the sequence, every step at least 20 samples (0.2 s) long
    L = a.demos.lengths.unsqueeze(1)
    bounds = torch.cat([torch.zeros(B, 1, dtype=torch.long), a.switch_times, L], 1)
    assert (bounds.diff(dim=1) >= 20).all()
    # about 100-300 samples per leg on average, dt = 0.01 s
    assert 80 <= float(L.double().mean()) / M <= 320
    assert torch.allclose(a.demos.times[0, 1] - a.demos.times[0, 0], torch.tensor(0.01, dtype=F64))
    # white noise of 0.3-1 % of the span, and the clean path really is the noise-free part
    assert 0.003 <= a.noise / a.span <= 0.01
    resid = torch.cat([(a.demos.positions[i, :n] - a.clean[i, :n]).reshape(-1) for i, n in enumerate(L[:, 0].tolist())])
    assert abs(float(resid.std()) / a.noise - 1.0) < 0.1
    # the goal is shared
    for i in range(B):
        assert torch.allclose(a.clean[i, int(L[i]) - 1], a.waypoints[-1])


@pytest.mark.parametrize("name", NAMES)
def test_same_nominal_path_for_any_number_of_demos(name):
    one, four = draw(name, 3, 1), draw(name, 3, 4)
    assert one.demos.n_demos == 1 and torch.equal(one.waypoints, four.waypoints)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", [0, 1])
def test_switch_is_at_the_corner(name, seed):
    """At every true switch the direction of motion jumps by the corner angle; nowhere else does it jump."""
    syn = draw(name, seed, 4)
    for i in range(syn.demos.n_demos):
        n = int(syn.demos.lengths[i])
        p = syn.clean[i, :n]
        step = p.diff(dim=0)  # step[t] = p[t + 1] - p[t]
        turn = turn_deg(step[:-1], step[1:])  # turn[t - 1]: direction change at sample t
        sw = syn.switch_times[i]
        # the corner sample is the jittered waypoint's position, within the corner jitter of the nominal one
        assert (p[sw] - syn.waypoints[1:-1]).norm(dim=1).max() < 0.15 * float(syn.leg_lengths.min())
        assert torch.allclose(turn[sw - 1], syn.corner_angles[i], atol=2.0), (turn[sw - 1], syn.corner_angles[i])
        inner = torch.ones(n - 2, dtype=torch.bool)
        inner[sw - 1] = False
        assert float(turn[inner].max()) < 5.0
        speed = step.norm(dim=1)
        typical = float(speed.mean())
        if syn.profile == "min_jerk":  # at rest at the corners (and at both ends)
            assert float(speed[sw].max()) < 1e-3 * typical and float(speed[sw - 1].max()) < 1e-2 * typical
        else:  # constant speed: no slowing down at a corner
            assert float(speed[sw].min()) > 0.3 * typical and float(speed[sw - 1].min()) > 0.3 * typical


@pytest.mark.parametrize("seed", range(6))
def test_corner_angles_and_lengths_span_the_stated_ranges(seed):
    for fn in (straight_steps, curved_steps):
        syn = fn(torch.Generator().manual_seed(seed), n_demos=2, dim=3)
        assert syn.corner_angles.min() > 25.0 and syn.corner_angles.max() < 155.0
        assert float(syn.leg_lengths.max() / syn.leg_lengths.min()) <= 5.0
    # across seeds the angles cover the range (nominal 30-150)
    angles = torch.cat([straight_steps(torch.Generator().manual_seed(s), n_demos=1).corner_angles.reshape(-1)
                        for s in range(30)])  # fmt: skip
    assert angles.min() < 45.0 and angles.max() > 135.0


def test_curved_legs_turn_smoothly_by_their_bend():
    syn = curved_steps(torch.Generator().manual_seed(0), n_demos=1, dim=2, n_steps=3, bend_deg=(60.0, 60.0))
    p = syn.clean[0, : int(syn.demos.lengths[0])]
    bounds = [0] + syn.switch_times[0].tolist() + [p.shape[0] - 1]
    for a, b in zip(bounds[:-1], bounds[1:]):
        before, after = p[a + 1] - p[a], p[b] - p[b - 1]
        assert abs(float(turn_deg(before, after)) - 60.0) < 3.0


def test_out_and_back_reverses_along_one_line():
    for seed in range(5):
        syn = out_and_back_steps(torch.Generator().manual_seed(seed), n_demos=2, dim=2)
        assert (syn.corner_angles[:, 1] > 170.0).all()
        W = syn.waypoints
        out, back = W[2] - W[1], W[3] - W[2]
        assert float(turn_deg(out, back)) > 179.0


def test_revisit_crosses_the_first_leg_in_another_direction():
    for seed in range(5):
        for dim in (2, 3):
            syn = revisit_steps(torch.Generator().manual_seed(seed), n_demos=1, dim=dim)
            p = syn.clean[0]
            s1, s2 = syn.switch_times[0, :2].tolist()
            third_end = syn.switch_times[0, 2] if syn.n_steps == 4 else int(syn.demos.lengths[0])
            leg1, leg3 = p[:s1], p[s2:third_end]
            gap = torch.cdist(leg3, leg1).min()
            assert float(gap) < 0.05 * float(syn.leg_lengths.min())
            W = syn.waypoints
            assert 40.0 < float(turn_deg(W[1] - W[0], W[3] - W[2])) < 140.0


def test_scoop_dips_below_its_chord_then_arcs_over():
    for seed in range(5):
        syn = scoop_steps(torch.Generator().manual_seed(seed), n_demos=2)
        assert syn.n_steps == 3 and syn.waypoints.shape == (4, 3)
        for i in range(2):
            s1, s2 = syn.switch_times[i].tolist()
            p = syn.clean[i, : int(syn.demos.lengths[i])]
            hook, transfer = p[s1:s2], p[s2:]
            assert float(hook[:, 2].min()) < float(min(p[s1, 2], p[s2, 2])) - 0.02  # dips
            assert float(transfer[:, 2].max()) > float(max(p[s2, 2], p[-1, 2])) + 0.1  # arcs over
            assert float(syn.leg_lengths[1]) < float(syn.leg_lengths[2])  # short hook, long arc
    with pytest.raises(InvalidArgumentError, match="dim"):
        scoop_steps(torch.Generator().manual_seed(0), dim=2)


def test_generator_device_and_no_global_rng():
    torch.manual_seed(0)
    before = torch.get_rng_state()
    syn = straight_steps(torch.Generator().manual_seed(1), n_demos=1)
    assert torch.equal(before, torch.get_rng_state())
    assert syn.demos.positions.device.type == "cpu"


def test_legacy_generator_unchanged():
    syn = multi_step_demos(torch.Generator().manual_seed(3), n_demos=3, n_steps=3, samples_per_step=30)
    assert syn.clean is None and syn.family == "" and syn.switch_times.shape == (3, 2)


HELD_OUT = sorted(HELD_OUT_FAMILIES)


def test_held_out_registry_is_apart_from_the_families():
    assert HELD_OUT == ["rounded_const_2d", "rounded_const_3d", "rounded_vary_2d", "rounded_vary_3d"]
    assert not set(HELD_OUT) & set(FAMILIES)


@pytest.mark.parametrize("name", HELD_OUT)
def test_rounded_family_deterministic_and_well_formed(name):
    draw_ = HELD_OUT_FAMILIES[name]
    a, b = draw_(torch.Generator().manual_seed(5), 4), draw_(torch.Generator().manual_seed(5), 4)
    assert torch.equal(a.demos.positions, b.demos.positions) and torch.equal(a.switch_times, b.switch_times)
    B, T, d = a.demos.positions.shape
    M = a.n_steps
    assert (B, d) == (4, int(name[-2])) and a.family == name and a.switch_times.shape == (B, M - 1)
    L = a.demos.lengths.unsqueeze(1)
    bounds = torch.cat([torch.zeros(B, 1, dtype=torch.long), a.switch_times, L], 1)
    assert (bounds.diff(dim=1) >= 10).all()
    assert 0.003 <= a.noise / a.span <= 0.01
    for i in range(B):
        assert torch.allclose(a.clean[i, int(L[i]) - 1], a.waypoints[-1])


@pytest.mark.parametrize("name", HELD_OUT)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rounded_switch_is_the_arc_midpoint(name, seed):
    """The path is C1 (no sample carries a corner's turn); at a switch the direction has turned half the corner
    angle: it bisects the directions of the two (straight) leg middles. Constant timing keeps the speed constant;
    varying timing changes it by the drawn factor wherever it falls."""
    syn = HELD_OUT_FAMILIES[name](torch.Generator().manual_seed(seed), 3)
    for i in range(syn.demos.n_demos):
        n = int(syn.demos.lengths[i])
        p = syn.clean[i, :n]
        step = p.diff(dim=0)
        turn = turn_deg(step[:-1], step[1:])
        sw = syn.switch_times[i]
        assert float(turn.max()) < 0.4 * float(syn.corner_angles[i].min())
        bounds = torch.cat([torch.tensor([0]), sw, torch.tensor([n - 1])])
        middle = step[(bounds[:-1] + bounds[1:]) // 2]  # direction in the middle of each leg
        # the midpoint lies on the chord from sample sw - 1 to sw, whose direction is within one sample's turn of it
        chord = step[sw - 1]
        before, after = turn_deg(chord, middle[:-1]), turn_deg(chord, middle[1:])
        assert torch.allclose(before + after, syn.corner_angles[i], atol=1.0)
        assert float((before - after).abs().max()) <= 2.0 * float(turn.max()) + 0.5, (before, after)
        speed = step.norm(dim=1)
        ratio = float(speed.max() / speed.min())
        if syn.profile == "constant":
            assert ratio < 1.01  # chords of the arcs are a little shorter than their arc length
        else:
            assert 1.8 < ratio < 4.1  # (1 + a) / (1 - a), a in [0.3, 0.6] (where the wave peaks inside the demo)


SLOWING = sorted(SLOWING_FAMILIES)


def test_slowing_registry_is_the_shapes_with_the_slowing_timing():
    assert SLOWING == sorted(n.replace("_const_", "_slow_") for n in NAMES if "_const_" in n)
    assert not set(SLOWING) & (set(FAMILIES) | set(HELD_OUT_FAMILIES))
    with pytest.raises(InvalidArgumentError, match="profile"):
        multi_step_demos(torch.Generator().manual_seed(0), profile="slowing")


@pytest.mark.parametrize("name", SLOWING)
@pytest.mark.parametrize("seed", [0, 1])
def test_slowing_family_slows_at_every_corner_without_stopping(name, seed):
    """Every leg's progress is (1 - lam) tau + lam mj(tau): the speed at both ends of a leg is 1 - lam of the leg's
    mean (lam in [0.3, 0.8], one per case) and 1 + 7 lam / 8 of it at the middle; the truth is the corner sample,
    where the direction jumps by the corner angle, as in the families."""
    g = lambda: torch.Generator().manual_seed(seed)  # noqa: E731
    syn, again = SLOWING_FAMILIES[name](g(), 3), SLOWING_FAMILIES[name](g(), 3)
    assert torch.equal(syn.demos.positions, again.demos.positions) and syn.family == name
    assert syn.profile == "slowing" and 0.003 <= syn.noise / syn.span <= 0.01
    ratios = []
    for i in range(syn.demos.n_demos):
        n = int(syn.demos.lengths[i])
        step = syn.clean[i, :n].diff(dim=0)
        sw = syn.switch_times[i]
        turn = turn_deg(step[:-1], step[1:])
        assert torch.allclose(turn[sw - 1], syn.corner_angles[i], atol=2.0)
        speed = step.norm(dim=1)
        bounds = [0] + sw.tolist() + [n - 1]
        for a, b in zip(bounds[:-1], bounds[1:]):
            leg = speed[a:b]
            mean = float(leg.mean())
            ratios.append((float(leg[0]) / mean, float(leg[-1]) / mean, float(leg[(b - a) // 2]) / mean))
    ratios = torch.tensor(ratios, dtype=F64)
    lam = 1.0 - float(ratios[:, :2].mean())
    assert 0.3 - 0.02 <= lam <= 0.8 + 0.02
    assert torch.allclose(ratios[:, :2], torch.full_like(ratios[:, :2], 1.0 - lam), atol=0.02)
    assert torch.allclose(ratios[:, 2], torch.full_like(ratios[:, 2], 1.0 + 7.0 * lam / 8.0), atol=0.03)
