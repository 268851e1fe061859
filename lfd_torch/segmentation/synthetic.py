"""Synthetic multi-step demonstrations with known switch points (for tests and benchmarks of segmentation).

Two kinds of generators live here.

:func:`multi_step_demos` (the original generator, used by the unit tests) follows a polyline through waypoints
w_0 -> w_1 -> ... -> w_M (one leg per step), with per-demonstration jitter of the waypoints, of each leg's duration
(timing variation) and white position noise. Legs are traversed at constant speed or with a minimum-jerk profile.
Its switch is the first sample *after* the sample that sits on the corner.

The benchmark families (:data:`FAMILIES`) are independent generators of harder, more varied cases:

    straight_*      3-5 straight legs, corner angles uniform in [30, 150] degrees, leg lengths log-uniform with a
                    ratio of up to 5 between the longest and the shortest leg.
    curved_*        the same, but every leg is a circular arc that turns its tangent smoothly by 30-90 degrees;
                    the corners (where the tangent *jumps* by 30-150 degrees) are the only true switches.
    out_and_back_*  an approach leg, then a leg out along a line and back along the same line (a 180-degree
                    reversal), optionally a leg away; straight legs.
    revisit_*       a later leg passes through the middle of the first leg in a direction 45-135 degrees away from
                    it (two different steps visit the same region); straight legs.
    scoop_*         3-D "scoop": a straight approach descending onto the surface, a short dip-drag-lift hook (a
                    120-170 degree arc in the vertical plane, below its chord), a long arc over a cup (rising above
                    its chord) ending at the cup; 3 steps.

Each family comes with dwelling (``min_jerk``: every leg is a minimum-jerk profile, so the motion slows to rest at
every corner) and constant-speed (``constant``: uniform speed along each leg, the speed jumps only through the
per-leg timing jitter) timing, in 2-D and/or 3-D (the suffix of the family name). A third timing, ``slowing``, is
kept apart as a held-out set (:data:`SLOWING_FAMILIES`): the motion slows at every corner without stopping, the
leg's progress the blend (1 - lam) tau + lam mj(tau) of constant speed and the minimum-jerk profile mj, lam drawn
per case in [0.3, 0.8], so the speed at a corner is 1 - lam (20-70 %) of the leg's mean speed and 1 + 7 lam / 8 at
its middle; its sample counts follow the constant-speed rule.

Time base and variation: dt = 0.01 s. A leg of arc length L gets n_nom * sqrt(L / L_g) samples (dwelling) or
n_nom * L / L_g samples (constant speed), L_g the geometric mean of the path's leg lengths, n_nom drawn in
[150, 200] (dwelling) or [130, 170] (constant) per case, i.e. about 100-300 samples per leg. Every demonstration of a
case shares the nominal path; each one scales its durations by a factor in [0.85, 1.15] and every leg's by a
further factor in [0.9, 1.1], offsets its corners (not the goal) by Gaussian jitter of 2 % of the shorter adjacent
leg (a few degrees of corner angle; ``corner_angles`` are each demonstration's own), and gets
white position noise whose standard deviation is 0.3-1 % (drawn per case) of the span, the span being the diagonal
of the bounding box of the noise-free demonstrations.

Ground truth: sample c_m of a demonstration is exactly the m-th corner of the noise-free path (for ``min_jerk``
the instant at which the motion is at rest there). Leg m covers samples c_m .. c_{m+1} - 1, the corner sample
c_{m+1} starts step m + 2, so ``switch_times[i, m] = c_{m+1}``: the first sample of steps 2..M, which sits on the
corner.

Notation:
    M  number of steps (legs), d state dimension, B demonstrations, T padded length
    waypoints      (M + 1, d)  nominal corners (including start and goal)
    switch_times   (B, M - 1)  long, first sample of steps 2..M in each demonstration
    clean          (B, T, d)   noise-free positions (edge-padded like ``demos.positions``); families only
    corner_angles  (B, M - 1)  jump of the tangent direction at each corner of each demonstration, degrees;
                               families only
    leg_lengths    (M,)        nominal arc length of each leg; families only
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError
from lfd_torch.utils import check_float, check_generator, check_int, check_tensor

__all__ = [
    "SyntheticSteps",
    "random_waypoints",
    "multi_step_demos",
    "polyline_steps",
    "straight_steps",
    "curved_steps",
    "out_and_back_steps",
    "revisit_steps",
    "scoop_steps",
    "with_correlated_noise",
    "with_sampling_rate",
    "rounded_steps",
    "FAMILIES",
    "HELD_OUT_FAMILIES",
    "SLOWING_FAMILIES",
]

PROFILES = ("min_jerk", "constant", "slowing")
DT = 0.01


@dataclass(frozen=True, eq=False)
class SyntheticSteps:
    """Demonstrations with their ground truth.

    Attributes:
        demos: the B demonstrations (positions in units of ``scale``, dt = 0.01 s).
        waypoints: (M + 1, d) nominal waypoints.
        switch_times: (B, M - 1) long, first sample of steps 2..M in each demonstration.
        profile: "min_jerk", "constant" or "slowing".
        clean: (B, T, d) noise-free positions (edge-padded), or None (:func:`multi_step_demos`).
        corner_angles: (B, M - 1) jump of the tangent direction at each corner of each (noise-free, jittered)
            demonstration in degrees, or None.
        leg_lengths: (M,) nominal arc length of each leg, or None.
        noise: standard deviation of the white position noise (units of the positions).
        span: diagonal of the bounding box of the noise-free demonstrations (0 when unknown).
        family: name of the generator family ("" for :func:`multi_step_demos`).
    """

    demos: Demos
    waypoints: Tensor
    switch_times: Tensor
    profile: str
    clean: Tensor | None = None
    corner_angles: Tensor | None = None
    leg_lengths: Tensor | None = None
    noise: float = 0.0
    span: float = 0.0
    family: str = ""

    @property
    def n_steps(self) -> int:
        return self.waypoints.shape[0] - 1


def random_waypoints(
    n_steps: int, dim: int, generator: torch.Generator, *, min_turn_deg: float = 50.0, max_turn_deg: float = 140.0,
    leg_range: tuple[float, float] = (0.7, 1.3), dtype: torch.dtype = torch.float64,
) -> Tensor:
    """A random polyline of ``n_steps`` legs whose consecutive legs turn by an angle in [min_turn, max_turn] degrees.

    Returns:
        (n_steps + 1, dim) waypoints, first at the origin.
    """
    if n_steps < 1 or dim < 2:
        raise InvalidArgumentError("need n_steps >= 1 and dim >= 2")
    device = generator.device
    pts = [torch.zeros(dim, dtype=dtype, device=device)]
    direction = torch.randn(dim, generator=generator, dtype=dtype, device=device)
    direction = direction / direction.norm()
    for m in range(n_steps):
        if m > 0:
            u = float(torch.rand(1, generator=generator, device=device))
            turn = math.radians(min_turn_deg + (max_turn_deg - min_turn_deg) * u)
            # rotate `direction` by `turn` inside a random plane containing it
            other = torch.randn(dim, generator=generator, dtype=dtype, device=device)
            other = other - (other @ direction) * direction
            other = other / other.norm()
            direction = math.cos(turn) * direction + math.sin(turn) * other
        length = leg_range[0] + (leg_range[1] - leg_range[0]) * float(torch.rand(1, generator=generator, device=device))
        pts.append(pts[-1] + length * direction)
    return torch.stack(pts)


def _profile(tau: Tensor, profile: str) -> Tensor:
    if profile == "min_jerk":
        return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
    return tau


def multi_step_demos(
    generator: torch.Generator,
    *,
    n_demos: int = 5,
    n_steps: int = 3,
    dim: int = 2,
    profile: str = "min_jerk",
    waypoints: Tensor | None = None,
    samples_per_step: int = 100,
    timing_jitter: float = 0.25,
    waypoint_jitter: float = 0.03,
    noise: float = 0.005,
    dtype: torch.dtype = torch.float64,
) -> SyntheticSteps:
    """Draw demonstrations of a piecewise path with known switch points.

    Args:
        generator: source of randomness.
        n_demos: B demonstrations.
        n_steps: M legs (ignored when ``waypoints`` is given).
        dim: d (ignored when ``waypoints`` is given).
        profile: "min_jerk" (dwells near corners) or "constant" (constant speed).
        waypoints: (M + 1, d) fixed corners; None draws them with :func:`random_waypoints`.
        samples_per_step: nominal samples per leg.
        timing_jitter: each leg's sample count is scaled by a factor uniform in [1 - j, 1 + j].
        waypoint_jitter: standard deviation of the per-demonstration corner offsets (same units as the legs, ~1).
        noise: standard deviation of the white position noise.
        dtype: floating dtype.

    Returns:
        SyntheticSteps.
    """
    check_generator(generator, where="multi_step_demos")
    check_int(n_demos, "n_demos", low=1)
    check_int(samples_per_step, "samples_per_step", low=1)
    check_float(timing_jitter, "timing_jitter", low=0.0, high=1.0, high_open=True)  # leg factors must stay > 0
    check_float(waypoint_jitter, "waypoint_jitter", low=0.0)
    check_float(noise, "noise", low=0.0)
    if profile not in ("min_jerk", "constant"):
        raise InvalidArgumentError(f"profile must be 'min_jerk' or 'constant', got {profile!r}")
    if waypoints is None:
        check_int(n_steps, "n_steps", low=1)
        check_int(dim, "dim", low=1)
        waypoints = random_waypoints(n_steps, dim, generator, dtype=dtype)
    else:
        check_tensor(waypoints, "waypoints", ndim=2, min_rows=2, shape_hint="(M + 1, d), M >= 1 legs")
    device = generator.device  # the data are drawn on the generator's device
    waypoints = waypoints.to(dtype=dtype, device=device)
    M = waypoints.shape[0] - 1
    sequences, switches = [], []
    for _ in range(n_demos):
        jitter = torch.randn(waypoints.shape, generator=generator, dtype=dtype, device=device)
        corners = waypoints + waypoint_jitter * jitter
        corners[-1] = waypoints[-1]  # common goal
        pieces, switch = [], []
        total = 0
        for m in range(M):
            factor = 1.0 + timing_jitter * (2.0 * float(torch.rand(1, generator=generator, device=device)) - 1.0)
            n = max(4, int(round(samples_per_step * factor)))
            tau = torch.arange(1 if m > 0 else 0, n + 1, dtype=dtype, device=device) / n
            leg = corners[m] + _profile(tau, profile).unsqueeze(-1) * (corners[m + 1] - corners[m])
            pieces.append(leg)
            total += leg.shape[0]
            if m < M - 1:
                switch.append(total)  # corner arrival is the last sample of this leg; next step starts after it
        path = torch.cat(pieces)
        path = path + noise * torch.randn(path.shape, generator=generator, dtype=dtype, device=device)
        sequences.append(path)
        switches.append(torch.tensor(switch, dtype=torch.long, device=device))
    demos = Demos.from_sequences(sequences, dt=0.01, attractor=waypoints[-1], dtype=dtype)
    no_switch = torch.zeros(n_demos, 0, dtype=torch.long, device=device)
    return SyntheticSteps(demos, waypoints, torch.stack(switches) if M > 1 else no_switch, profile, noise=float(noise))


# ============================================================================================ benchmark families
def _rand(generator: torch.Generator, lo: float, hi: float) -> float:
    """A float uniform in [lo, hi)."""
    return lo + (hi - lo) * float(torch.rand(1, generator=generator, device=generator.device))


def _randint(generator: torch.Generator, lo: int, hi: int) -> int:
    """An int uniform in {lo, ..., hi}."""
    return int(torch.randint(lo, hi + 1, (1,), generator=generator, device=generator.device))


def _sign(generator: torch.Generator) -> float:
    return 1.0 if _rand(generator, 0.0, 1.0) < 0.5 else -1.0


def _unit(v: Tensor) -> Tensor:
    return v / v.norm()


def _random_perp(u: Tensor, generator: torch.Generator) -> Tensor:
    """A random unit vector orthogonal to the unit vector ``u`` (d,) (in 2-D one of the two normals, by a coin)."""
    while True:
        v = torch.randn(u.shape, generator=generator, dtype=u.dtype, device=u.device)
        v = v - (v @ u) * u
        if float(v.norm()) > 1e-6:
            return v / v.norm()


def _arc_frame(a: Tensor, b: Tensor, normal: Tensor, bend: float) -> tuple[Tensor, Tensor, float]:
    """Frame of the circular arc from ``a`` to ``b`` (d,) whose tangent turns by ``bend`` radians.

    The arc lies in the plane of the chord and ``normal`` and bulges to the side opposite to ``normal``; with
    e the chord direction and n ``normal`` made orthogonal to it, the arc is
    p(alpha) = a + R (sin(alpha) t0 + (1 - cos(alpha)) n0), alpha in [0, bend], where
    t0 = cos(bend / 2) e - sin(bend / 2) n is the start tangent and n0 = sin(bend / 2) e + cos(bend / 2) n.

    Returns:
        t0 (d,), n0 (d,), R (inf for a straight leg, bend = 0).
    """
    e = _unit(b - a)
    if bend < 1e-9:
        return e, torch.zeros_like(e), math.inf
    n = _unit(normal - (normal @ e) * e)
    h = 0.5 * bend
    t0 = math.cos(h) * e - math.sin(h) * n
    n0 = math.sin(h) * e + math.cos(h) * n
    return t0, n0, float((b - a).norm()) / (2.0 * math.sin(h))


def _leg_points(a: Tensor, b: Tensor, normal: Tensor, bend: float, s: Tensor) -> Tensor:
    """Points at arc-length fractions ``s`` (K,) in [0, 1] of the leg from a to b: (K, d)."""
    t0, n0, radius = _arc_frame(a, b, normal, bend)
    if math.isinf(radius):
        return a + s.unsqueeze(-1) * (b - a)
    alpha = (bend * s).unsqueeze(-1)
    return a + radius * (torch.sin(alpha) * t0 + (1.0 - torch.cos(alpha)) * n0)


def _leg_tangents(a: Tensor, b: Tensor, normal: Tensor, bend: float) -> tuple[Tensor, Tensor]:
    """Unit tangents (d,) at the start and at the end of the leg."""
    t0, n0, radius = _arc_frame(a, b, normal, bend)
    if math.isinf(radius):
        return t0, t0
    return t0, math.cos(bend) * t0 + math.sin(bend) * n0


def _leg_length(a: Tensor, b: Tensor, bend: float) -> float:
    """Arc length of the leg (the chord for a straight leg)."""
    chord = float((b - a).norm())
    return chord if bend < 1e-9 else chord * 0.5 * bend / math.sin(0.5 * bend)


def _angle_deg(u: Tensor, v: Tensor) -> float:
    """Angle between two vectors in degrees."""
    c = float((u @ v) / (u.norm() * v.norm()))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _corner_angles(corners: Tensor, normals: Tensor, bends: list[float]) -> list[float]:
    """Jump of the tangent direction at each of the M - 1 inner corners, degrees."""
    out = []
    for m in range(len(bends) - 1):
        _, end = _leg_tangents(corners[m], corners[m + 1], normals[m], bends[m])
        start, _ = _leg_tangents(corners[m + 1], corners[m + 2], normals[m + 1], bends[m + 1])
        out.append(_angle_deg(end, start))
    return out


def _heading_path(
    generator: torch.Generator, dim: int, lengths: list[float], turns_deg: list[float], bends_deg: list[float],
    dtype: torch.dtype,
) -> tuple[Tensor, Tensor, list[float]]:
    """A nominal path built from headings: leg m has arc length ``lengths[m]`` and turns its tangent smoothly by
    ``bends_deg[m]`` in a random plane; at corner m the tangent jumps by ``turns_deg[m]`` in a random plane.

    Returns:
        corners (M + 1, d) starting at the origin, normals (M, d) (see :func:`_arc_frame`), bends (M,) radians.
    """
    device = generator.device
    u = _unit(torch.randn(dim, generator=generator, dtype=dtype, device=device))
    corners = [torch.zeros(dim, dtype=dtype, device=device)]
    normals, bends = [], []
    for m, length in enumerate(lengths):
        if m > 0:
            turn = math.radians(turns_deg[m - 1])
            u = _unit(math.cos(turn) * u + math.sin(turn) * _random_perp(u, generator))
        w = _random_perp(u, generator)
        phi = math.radians(bends_deg[m])
        a = corners[-1]
        if phi < 1e-9:
            b, u_end, n = a + length * u, u, w
        else:
            radius = length / phi
            b = a + radius * math.sin(phi) * u + radius * (1.0 - math.cos(phi)) * w
            u_end = math.cos(phi) * u + math.sin(phi) * w
            e = _unit(b - a)
            n = _unit(w - (w @ e) * e)  # arc bends towards w, i.e. bulges away from n (see _arc_frame)
        corners.append(b)
        normals.append(n)
        bends.append(phi)
        u = u_end
    return torch.stack(corners), torch.stack(normals), bends


def _log_uniform_lengths(generator: torch.Generator, n: int, ratio: float) -> list[float]:
    """n lengths log-uniform in [ratio^-1/2, ratio^1/2] (so no two differ by more than ``ratio``)."""
    half = 0.5 * math.log(ratio)
    return [math.exp(_rand(generator, -half, half)) for _ in range(n)]


def _draw_legs(generator: torch.Generator, n_steps: int | None, length_ratio: float, turn_deg: tuple[float, float]
               ) -> tuple[int, list[float], list[float]]:
    """M legs (None: drawn in {3, 4, 5}), their log-uniform arc lengths and the M - 1 corner angles (degrees)."""
    M = _randint(generator, 3, 5) if n_steps is None else n_steps
    if M < 1:
        raise InvalidArgumentError(f"need n_steps >= 1, got {M}")
    lengths = _log_uniform_lengths(generator, M, length_ratio)
    return M, lengths, [_rand(generator, *turn_deg) for _ in range(M - 1)]


def _jitter_scale(lengths: list[float], dtype: torch.dtype, device: torch.device) -> Tensor:
    """(M + 1, 1) the scale of each corner's jitter: the shorter adjacent leg (the start has only the first leg;
    the goal, 0, is not jittered)."""
    M = len(lengths)
    local = [lengths[0]] + [min(lengths[m - 1], lengths[m]) for m in range(1, M)] + [0.0]
    return torch.tensor(local, dtype=dtype, device=device).unsqueeze(-1)


def _render(
    generator: torch.Generator,
    corners: Tensor,
    normals: Tensor,
    bends: list[float],
    *,
    n_demos: int,
    profile: str,
    noise_fraction: float | None,
    waypoint_jitter: float = 0.02,
    duration_jitter: float = 0.15,
    leg_jitter: float = 0.1,
    family: str = "",
) -> SyntheticSteps:
    """Sample B demonstrations of a nominal path of M legs (see the module docstring for the time base).

    Args:
        corners: (M + 1, d) nominal corners.
        normals: (M, d) arc normals (see :func:`_arc_frame`; unused by straight legs).
        bends: M tangent turns along the legs, radians (0: straight).
        noise_fraction: white-noise standard deviation as a fraction of the span; None draws it in [0.003, 0.01].
        waypoint_jitter: standard deviation of each demonstration's corner offsets, as a fraction of the shorter
            adjacent leg (the goal is not jittered).
        duration_jitter: each demonstration scales all durations by a factor uniform in [1 - j, 1 + j].
        leg_jitter: and each leg's duration by a further factor uniform in [1 - j, 1 + j].
    """
    if profile not in PROFILES:
        raise InvalidArgumentError(f"profile must be one of {PROFILES}, got {profile!r}")
    if n_demos < 1:
        raise InvalidArgumentError(f"need n_demos >= 1, got {n_demos}")
    device, dtype = corners.device, corners.dtype
    M = len(bends)
    lengths = [_leg_length(corners[m], corners[m + 1], bends[m]) for m in range(M)]
    geo_mean = math.exp(sum(math.log(v) for v in lengths) / M)
    if profile == "min_jerk":
        n_nom = _rand(generator, 150.0, 200.0)
        nominal = [n_nom * math.sqrt(v / geo_mean) for v in lengths]
    else:
        n_nom = _rand(generator, 130.0, 170.0)
        nominal = [n_nom * v / geo_mean for v in lengths]
    blend = _rand(generator, 0.3, 0.8) if profile == "slowing" else None
    if noise_fraction is None:
        noise_fraction = _rand(generator, 0.003, 0.01)
    local_t = _jitter_scale(lengths, dtype, device)
    cleans, switches, angles = [], [], []
    for _ in range(n_demos):
        jitter = torch.randn(corners.shape, generator=generator, dtype=dtype, device=device)
        c = corners + waypoint_jitter * local_t * jitter
        scale = 1.0 + duration_jitter * (2.0 * _rand(generator, 0.0, 1.0) - 1.0)
        pieces, switch, total = [], [], 0
        for m in range(M):
            factor = scale * (1.0 + leg_jitter * (2.0 * _rand(generator, 0.0, 1.0) - 1.0))
            n = max(20, int(round(nominal[m] * factor)))
            tau = torch.arange(n + 1 if m == M - 1 else n, dtype=dtype, device=device) / n
            progress = (_profile(tau, profile) if blend is None
                        else (1.0 - blend) * tau + blend * _profile(tau, "min_jerk"))
            pieces.append(_leg_points(c[m], c[m + 1], normals[m], bends[m], progress))
            total += n
            if m < M - 1:
                switch.append(total)  # sample `total` is corner m + 1, the first sample of step m + 2
        cleans.append(torch.cat(pieces))
        switches.append(switch)
        angles.append(_corner_angles(c, normals, bends))
    return _noisy_steps(generator, cleans, switches, angles, corners, lengths, profile, noise_fraction, family)


def _noisy_steps(
    generator: torch.Generator, cleans: list[Tensor], switches: list[list[int]], angles: list[list[float]],
    corners: Tensor, lengths: list[float], profile: str, noise_fraction: float, family: str = "",
) -> SyntheticSteps:
    """SyntheticSteps of the noise-free demonstrations ``cleans`` (B tensors (T_i, d)) with white noise of
    ``noise_fraction`` of their span added (drawn in order, after every path), their switches and corner angles."""
    dtype, device = corners.dtype, corners.device
    B, M = len(cleans), len(lengths)
    every = torch.cat(cleans)
    span = float((every.amax(0) - every.amin(0)).norm())
    noise = noise_fraction * span
    noisy = [p + noise * torch.randn(p.shape, generator=generator, dtype=dtype, device=device) for p in cleans]
    demos = Demos.from_sequences(noisy, dt=DT, attractor=corners[-1], dtype=dtype, device=device)
    T = demos.max_length
    clean = torch.stack([torch.cat([p, p[-1:].expand(T - p.shape[0], -1)]) for p in cleans])
    return SyntheticSteps(
        demos=demos,
        waypoints=corners,
        switch_times=torch.tensor(switches, dtype=torch.long, device=device).reshape(B, M - 1),
        profile=profile,
        clean=clean,
        corner_angles=torch.tensor(angles, dtype=dtype, device=device).reshape(B, M - 1),
        leg_lengths=torch.tensor(lengths, dtype=dtype, device=device),
        noise=noise,
        span=span,
        family=family,
    )


def polyline_steps(
    generator: torch.Generator,
    *,
    n_demos: int = 4,
    dim: int = 2,
    n_steps: int | None = None,
    profile: str = "min_jerk",
    turn_deg: tuple[float, float] = (30.0, 150.0),
    bend_deg: tuple[float, float] = (0.0, 0.0),
    length_ratio: float = 5.0,
    noise_fraction: float | None = None,
    dtype: torch.dtype = torch.float64,
) -> SyntheticSteps:
    """A random path of straight or circular legs with tangent jumps at the corners.

    Args:
        generator: the only source of randomness (its device is the data's).
        n_demos: B demonstrations.
        dim: d >= 2.
        n_steps: M legs; None draws it in {3, 4, 5}.
        profile: "min_jerk" (rest at every corner), "constant" (constant speed along each leg) or "slowing" (slower,
            not at rest, at every corner; module docstring).
        turn_deg: range of the corner angles (jump of the tangent direction), degrees.
        bend_deg: range of each leg's smooth tangent turn, degrees (0, 0: straight legs).
        length_ratio: leg arc lengths are log-uniform within a factor ``length_ratio`` of each other.
        noise_fraction: noise standard deviation / span; None draws it in [0.003, 0.01].
        dtype: floating dtype.

    Returns:
        SyntheticSteps with ``clean``, per-demonstration ``corner_angles`` (B, M - 1) and ``leg_lengths`` (M,).
    """
    if dim < 2:
        raise InvalidArgumentError(f"need dim >= 2, got {dim}")
    M, lengths, turns = _draw_legs(generator, n_steps, length_ratio, turn_deg)
    bends = [_rand(generator, *bend_deg) for _ in range(M)]
    corners, normals, phis = _heading_path(generator, dim, lengths, turns, bends, dtype)
    return _render(generator, corners, normals, phis, n_demos=n_demos, profile=profile, noise_fraction=noise_fraction)


def straight_steps(generator: torch.Generator, *, n_demos: int = 4, dim: int = 2, **kw) -> SyntheticSteps:
    """Straight legs, corner angles in [30, 150] degrees (keyword arguments of :func:`polyline_steps`)."""
    return polyline_steps(generator, n_demos=n_demos, dim=dim, bend_deg=(0.0, 0.0), **kw)


def curved_steps(
    generator: torch.Generator, *, n_demos: int = 4, dim: int = 2, bend_deg: tuple[float, float] = (30.0, 90.0), **kw
) -> SyntheticSteps:
    """Circular legs each turning their tangent smoothly by ``bend_deg`` degrees; the corners, where the tangent
    jumps by 30-150 degrees, are the only switches (keyword arguments of :func:`polyline_steps`)."""
    return polyline_steps(generator, n_demos=n_demos, dim=dim, bend_deg=bend_deg, **kw)


def out_and_back_steps(
    generator: torch.Generator,
    *,
    n_demos: int = 4,
    dim: int = 2,
    n_steps: int | None = None,
    profile: str = "min_jerk",
    return_fraction: tuple[float, float] = (0.5, 1.0),
    length_ratio: float = 5.0,
    noise_fraction: float | None = None,
    dtype: torch.dtype = torch.float64,
) -> SyntheticSteps:
    """Approach, out along a line, back along the same line (a 180-degree corner), then (M = 4) a leg away.

    Args:
        n_steps: 3 or 4; None draws one of them.
        return_fraction: the back leg is this fraction (uniform in the range) of the out leg.
        Others: see :func:`polyline_steps`; the other corners turn by 30-150 degrees, legs are straight.

    Returns:
        SyntheticSteps; ``corner_angles[:, 1]`` is (up to the corner jitter) 180 degrees.
    """
    M = _randint(generator, 3, 4) if n_steps is None else n_steps
    if M not in (3, 4):
        raise InvalidArgumentError(f"out_and_back_steps needs n_steps in (3, 4), got {M}")
    while True:
        lengths = _log_uniform_lengths(generator, M, length_ratio)
        lengths[2] = _rand(generator, *return_fraction) * lengths[1]
        if max(lengths) / min(lengths) <= length_ratio:
            break
    turns = [_rand(generator, 30.0, 150.0), 180.0] + ([_rand(generator, 30.0, 150.0)] if M == 4 else [])
    corners, normals, phis = _heading_path(generator, dim, lengths, turns, [0.0] * M, dtype)
    return _render(generator, corners, normals, phis, n_demos=n_demos, profile=profile, noise_fraction=noise_fraction)


def _random_frame(generator: torch.Generator, dim: int, dtype: torch.dtype) -> Tensor:
    """(dim, 2) random orthonormal columns (a random plane of R^dim with a random in-plane orientation)."""
    a = torch.randn(dim, 2, generator=generator, dtype=dtype, device=generator.device)
    q, r = torch.linalg.qr(a)
    return q * torch.sign(torch.diagonal(r)).unsqueeze(0)


def revisit_steps(
    generator: torch.Generator,
    *,
    n_demos: int = 4,
    dim: int = 2,
    n_steps: int | None = None,
    profile: str = "min_jerk",
    crossing_deg: tuple[float, float] = (45.0, 135.0),
    length_ratio: float = 5.0,
    noise_fraction: float | None = None,
    dtype: torch.dtype = torch.float64,
) -> SyntheticSteps:
    """Leg 3 passes through the middle (30-70 %) of leg 1 at 45-135 degrees to it: two steps visit one region.

    Built in a plane (then placed in a random plane of R^d): P0 -> P1 is leg 1, X a point on it, leg 3 runs
    from X - a c to X + b c with c the crossing direction, leg 2 joins P1 to X - a c; with M = 4 a last leg turns
    away by 30-150 degrees. Instances are redrawn until every corner turns by 30-150 degrees and no leg is more
    than ``length_ratio`` times another. Straight legs.

    Args:
        n_steps: 3 or 4; None draws one of them.
        crossing_deg: range of the angle between leg 3 and leg 1.
        Others: see :func:`polyline_steps`.
    """
    M = _randint(generator, 3, 4) if n_steps is None else n_steps
    if M not in (3, 4):
        raise InvalidArgumentError(f"revisit_steps needs n_steps in (3, 4), got {M}")
    if dim < 2:
        raise InvalidArgumentError(f"need dim >= 2, got {dim}")
    device = generator.device

    def rot(v: Tensor, deg: float) -> Tensor:
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        return torch.stack([c * v[0] - s * v[1], s * v[0] + c * v[1]])

    while True:
        L1 = _rand(generator, 1.0, 1.5)
        p0 = torch.zeros(2, dtype=dtype, device=device)
        p1 = torch.tensor([L1, 0.0], dtype=dtype, device=device)
        x = _rand(generator, 0.3, 0.7) * p1
        psi = _sign(generator) * _rand(generator, *crossing_deg)
        c = rot(torch.tensor([1.0, 0.0], dtype=dtype, device=device), psi)
        pts = [p0, p1, x - _rand(generator, 0.5, 1.2) * c, x + _rand(generator, 0.4, 1.0) * c]
        if M == 4:
            away = rot(c, _sign(generator) * _rand(generator, 30.0, 150.0))
            pts.append(pts[-1] + _rand(generator, 0.5, 1.2) * away)
        P = torch.stack(pts)
        legs = P[1:] - P[:-1]
        lengths = legs.norm(dim=1)
        turns = [_angle_deg(legs[m], legs[m + 1]) for m in range(M - 1)]
        if float(lengths.max() / lengths.min()) <= length_ratio and all(30.0 <= t <= 150.0 for t in turns):
            break
    corners = P @ _random_frame(generator, dim, dtype).T
    normals = torch.stack([_random_perp(_unit(corners[m + 1] - corners[m]), generator) for m in range(M)])
    return _render(
        generator, corners, normals, [0.0] * M, n_demos=n_demos, profile=profile, noise_fraction=noise_fraction
    )


def scoop_steps(
    generator: torch.Generator,
    *,
    n_demos: int = 4,
    dim: int = 3,
    profile: str = "min_jerk",
    length_ratio: float = 5.0,
    noise_fraction: float | None = None,
    dtype: torch.dtype = torch.float64,
) -> SyntheticSteps:
    """A 3-D scoop (x forward, y sideways, z up, then a random rotation about z), 3 steps.

    1. approach: straight, length 0.8-1.2, descending at 20-45 degrees onto the scooping point H0;
    2. hook: the dip-drag-lift, a circular arc from H0 to H1 (chord 0.25-0.4 of the approach, forward, H1 up to
       5 % higher) that turns its tangent by 120-170 degrees in the vertical plane below the chord: it starts
       heading steeply down and ends heading steeply up;
    3. transfer: a long arc (chord 1.2-1.8 approaches, towards a random side within +-100 degrees of forward)
       rising over its chord (70-120 degree turn) to the cup.

    Instances are redrawn until both corners turn by 30-150 degrees and no leg is more than ``length_ratio``
    times another.

    Args:
        dim: must be 3.
        Others: see :func:`polyline_steps`.
    """
    if dim != 3:
        raise InvalidArgumentError(f"scoop_steps is 3-D, got dim={dim}")
    device = generator.device

    def vec(*v: float) -> Tensor:
        return torch.tensor(v, dtype=dtype, device=device)

    up = vec(0.0, 0.0, 1.0)
    while True:
        La = _rand(generator, 0.8, 1.2)
        beta = math.radians(_rand(generator, 20.0, 45.0))
        h0 = vec(0.0, 0.0, 0.0)
        start = h0 - La * vec(math.cos(beta), 0.0, -math.sin(beta))
        h1 = vec(_rand(generator, 0.25, 0.4) * La, 0.0, _rand(generator, 0.0, 0.05) * La)
        gamma = math.radians(_rand(generator, -100.0, 100.0))
        r = _rand(generator, 1.2, 1.8) * La
        cup = h1 + vec(r * math.cos(gamma), r * math.sin(gamma), _rand(generator, -0.1, 0.1) * La)
        corners = torch.stack([start, h0, h1, cup])
        normals = torch.stack([_random_perp(_unit(h0 - start), generator), up, -up])
        bends = [0.0, math.radians(_rand(generator, 120.0, 170.0)), math.radians(_rand(generator, 70.0, 120.0))]
        lengths = [_leg_length(corners[m], corners[m + 1], bends[m]) for m in range(3)]
        turns = _corner_angles(corners, normals, bends)
        if max(lengths) / min(lengths) <= length_ratio and all(30.0 <= t <= 150.0 for t in turns):
            break
    yaw = _rand(generator, 0.0, 2.0 * math.pi)
    c, s = math.cos(yaw), math.sin(yaw)
    rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype, device=device)
    return _render(
        generator, corners @ rz.T, normals @ rz.T, bends, n_demos=n_demos, profile=profile,
        noise_fraction=noise_fraction,
    )  # fmt: skip


def with_correlated_noise(syn: SyntheticSteps, rho: float, generator: torch.Generator, scale: float = 1.0
                          ) -> SyntheticSteps:
    """The same noise-free demonstrations with new AR(1) position noise of lag-one correlation ``rho`` and
    marginal standard deviation ``scale * syn.noise``: e_t = rho e_(t-1) + (1 - rho^2)^(1/2) eta_t, eta_t ~ N(0,
    I), e_0 ~ N(0, I) (stationary), times that level. A filtered sensor, a tremor or resampled data are not white
    at the sampling rate; rho = 0 gives new white noise; ``scale`` < 1 a better sensor of the same motions.

    Args:
        syn: a draw with ``clean`` (a benchmark family); rho: in [0, 1); generator: the new noise's randomness;
            scale: > 0, the new level over the draw's (the result's ``noise``).
    """
    from scipy.signal import lfilter

    if syn.clean is None:
        raise InvalidArgumentError("with_correlated_noise needs the noise-free demonstrations (syn.clean)")
    if not 0.0 <= rho < 1.0:
        raise InvalidArgumentError(f"rho must be in [0, 1), got {rho}")
    if not (math.isfinite(scale) and scale > 0.0):
        raise InvalidArgumentError(f"scale must be a positive number, got {scale}")
    level = scale * syn.noise
    sequences = []
    for i, n in enumerate(syn.demos.lengths.tolist()):
        clean = syn.clean[i, : int(n)]
        eta = torch.randn(clean.shape, generator=generator, dtype=clean.dtype, device=clean.device).cpu().numpy()
        eta[1:] *= math.sqrt(1.0 - rho * rho)
        e = torch.as_tensor(lfilter([1.0], [1.0, -rho], eta, axis=0), dtype=clean.dtype, device=clean.device)
        sequences.append(clean + level * e)
    dt = float(syn.demos.times[0, 1] - syn.demos.times[0, 0])
    demos = Demos.from_sequences(sequences, dt=dt, attractor=syn.demos.attractor, dtype=syn.demos.positions.dtype,
                                 device=syn.demos.positions.device)
    return replace(syn, demos=demos, noise=level)


def with_sampling_rate(syn: SyntheticSteps, rate: float, generator: torch.Generator) -> SyntheticSteps:
    """The same motions recorded at another rate: the noise-free demonstrations resampled at ``rate`` Hz (linear
    interpolation between the draw's samples, exact at their instants) over the same durations, with new white
    position noise of the same standard deviation per sample (a slower or faster sensor of the same quality).

    A true switch stays the first sample at or after its corner's instant: ceil(c dt / dt'), c the corner's sample at
    the draw's dt (0.01 s for a family), dt' = 1 / rate. ``corner_angles``, ``waypoints``, ``noise`` and ``span``
    are unchanged.

    Args:
        syn: a draw with ``clean`` (a benchmark family); rate: Hz, > 0, leaving every
            demonstration at least 3 samples; generator: the new noise's randomness.
    """
    if syn.clean is None:
        raise InvalidArgumentError("with_sampling_rate needs the noise-free demonstrations (syn.clean)")
    if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
        raise InvalidArgumentError(f"rate must be a positive number of Hz, got {rate!r}")
    new_dt = 1.0 / float(rate)
    ratio = float(syn.demos.times[0, 1] - syn.demos.times[0, 0]) / new_dt  # new samples per old sample
    clean_out, sequences = [], []
    for i, n in enumerate(syn.demos.lengths.tolist()):
        clean = syn.clean[i, : int(n)]
        m = math.floor((n - 1) * ratio + 1e-9) + 1
        if m < 3:
            raise InvalidArgumentError(f"rate {rate} Hz leaves demonstration {i} with {m} samples (at least 3 needed)")
        where = torch.arange(m, dtype=clean.dtype, device=clean.device) / ratio  # old (fractional) sample index
        j = where.floor().long().clamp(max=int(n) - 2)
        a = (where - j).unsqueeze(-1)
        resampled = clean[j] * (1.0 - a) + clean[j + 1] * a
        clean_out.append(resampled)
        noise = torch.randn(resampled.shape, generator=generator, dtype=clean.dtype, device=generator.device)
        noise = noise.to(clean.device)
        sequences.append(resampled + syn.noise * noise)
    demos = Demos.from_sequences(sequences, dt=new_dt, attractor=syn.demos.attractor,
                                 dtype=syn.demos.positions.dtype, device=syn.demos.positions.device)
    T = max(c.shape[0] for c in clean_out)
    padded = torch.stack([torch.cat([c, c[-1:].expand(T - c.shape[0], -1)]) for c in clean_out])
    switch_times = torch.ceil(syn.switch_times.to(torch.float64) * ratio - 1e-9).long()
    return replace(syn, demos=demos, clean=padded, switch_times=switch_times)


def _speed_to_arc(n: int, total: float, wave: tuple[float, float, float] | None, dtype: torch.dtype,
                  device: torch.device) -> Tensor:
    """(n,) arc length at n equally spaced instants for a speed v(tau) = 1 + a sin(2 pi c tau + phase) over the
    normalised time tau in [0, 1] (``wave`` = (a, c, phase); None: constant speed), scaled to end at ``total``."""
    tau = torch.linspace(0.0, 1.0, n, dtype=dtype, device=device)
    if wave is None:
        return total * tau
    a, c, phase = wave
    # closed-form integral of the speed; a < 1 keeps it increasing
    arc = tau - a / (2.0 * math.pi * c) * (torch.cos(2.0 * math.pi * c * tau + phase) - math.cos(phase))
    return total * arc / arc[-1]


def _filleted_path(corners: Tensor, fractions: list[float]) -> tuple[Tensor, Tensor, Tensor]:
    """Pieces of the polyline through ``corners`` (M + 1, d) with inner corner m + 1 rounded by the circular arc
    tangent to both legs at distance f_m min(L_m, L_m+1) from the corner (``fractions``, M - 1 values < 0.5).

    The arc from A = c - t u (tangent u) turning by theta towards u' is p(phi) = A + R sin(phi) u + R (1 - cos phi) n,
    n the unit normal of u towards u', R = t / tan(theta / 2), phi in [0, theta]; it leaves at c + t u'.

    Returns:
        pieces (P, 3, d): start point, unit tangent u, unit normal n of each piece (n = 0 on a straight piece);
        radii (P,) (0: straight piece); bounds (P + 1,) arc length at the start of each piece, then the total;
        switches (M - 1,) arc length of every inner corner's switch: its arc's midpoint (the corner for f_m = 0).
    """
    M = corners.shape[0] - 1
    d = corners[1:] - corners[:-1]
    lengths = d.norm(dim=-1)
    u = d / lengths.unsqueeze(-1)
    t = [0.0] + [fractions[m] * float(min(lengths[m], lengths[m + 1])) for m in range(M - 1)] + [0.0]
    starts, tangents, normals, radii, sizes, switches = [], [], [], [], [], []
    zero = torch.zeros_like(corners[0])
    for m in range(M):
        starts.append(corners[m] + t[m] * u[m])
        tangents.append(u[m])
        normals.append(zero)
        radii.append(0.0)
        sizes.append(float(lengths[m]) - t[m] - t[m + 1])
        if m < M - 1:
            switches.append(sum(sizes))
        if m < M - 1 and t[m + 1] > 0.0:
            cos_theta = float((u[m] @ u[m + 1]).clamp(-1.0, 1.0))
            theta = math.acos(cos_theta)
            n = u[m + 1] - cos_theta * u[m]
            radius = t[m + 1] / math.tan(0.5 * theta)
            starts.append(corners[m + 1] - t[m + 1] * u[m])
            tangents.append(u[m])
            normals.append(n / n.norm())
            radii.append(radius)
            sizes.append(radius * theta)
            switches[-1] += 0.5 * radius * theta
    bounds = torch.tensor([0.0] + sizes, dtype=corners.dtype, device=corners.device).cumsum(0)
    return (torch.stack([torch.stack(starts), torch.stack(tangents), torch.stack(normals)], 1),
            torch.tensor(radii, dtype=corners.dtype, device=corners.device), bounds,
            torch.tensor(switches, dtype=corners.dtype, device=corners.device))


def _points_on(pieces: Tensor, radii: Tensor, bounds: Tensor, s: Tensor) -> Tensor:
    """(n, d) points at arc lengths ``s`` (n,) of the path of :func:`_filleted_path`."""
    j = (torch.searchsorted(bounds, s, right=True) - 1).clamp(0, radii.shape[0] - 1)
    ds = (s - bounds[j]).unsqueeze(-1)
    r = radii[j].unsqueeze(-1)
    arc = r > 0
    phi = ds / torch.where(arc, r, torch.ones_like(r))
    along = torch.where(arc, r * torch.sin(phi), ds)
    across = torch.where(arc, r * (1.0 - torch.cos(phi)), torch.zeros_like(ds))
    return pieces[j, 0] + along * pieces[j, 1] + across * pieces[j, 2]


def rounded_steps(
    generator: torch.Generator,
    *,
    n_demos: int = 4,
    dim: int = 2,
    n_steps: int | None = None,
    profile: str = "varying",
    turn_deg: tuple[float, float] = (30.0, 150.0),
    fillet: tuple[float, float] = (0.05, 0.25),
    length_ratio: float = 5.0,
    noise_fraction: float | None = None,
    dtype: torch.dtype = torch.float64,
) -> SyntheticSteps:
    """Straight legs whose corners are rounded by circular fillets, traversed at a speed unrelated to the corners.

    A generator of its own (not :func:`_render`): the path is arc-length parametrised and the timing is one speed
    profile over the whole demonstration, so neither the corners' sharpness nor a slow-down marks a switch.
    Corner m is replaced by the arc tangent to both legs at f_m times the shorter adjacent leg from the corner, f_m
    uniform in ``fillet`` per corner (the arc turns the tangent by the whole corner angle over 2 f_m of that leg, up
    to half of it); the true switch is the first sample at or past the arc's midpoint, where the tangent has turned
    by half the angle. Timing: ``"constant"`` speed, or ``"varying"``: v(tau) = 1 + a sin(2 pi c tau + phase) over the
    normalised time, a in [0.3, 0.6] and c in [1, 3] cycles per demonstration drawn per case, the phase per
    demonstration (the slow-downs of different demonstrations fall at different places, at corners or mid-leg).
    Length: n_nom S / L_g samples (S the path length, L_g the legs' geometric mean length, n_nom in [130, 170] per
    case, scaled per demonstration by [0.85, 1.15]); corner jitter and noise as :func:`polyline_steps`.

    Returns:
        SyntheticSteps with ``clean``, ``corner_angles`` (B, M - 1) and ``leg_lengths`` (M,) (the polyline's legs).
    """
    if profile not in ("constant", "varying"):
        raise InvalidArgumentError(f"profile must be 'constant' or 'varying', got {profile!r}")
    if dim < 2 or n_demos < 1:
        raise InvalidArgumentError(f"need dim >= 2 and n_demos >= 1, got {dim}, {n_demos}")
    if not 0.0 <= fillet[0] <= fillet[1] < 0.5:
        raise InvalidArgumentError(f"fillet must be a range within [0, 0.5), got {fillet}")
    device = generator.device
    M, lengths, turns = _draw_legs(generator, n_steps, length_ratio, turn_deg)
    corners, normals, bends = _heading_path(generator, dim, lengths, turns, [0.0] * M, dtype)
    fractions = [_rand(generator, *fillet) for _ in range(M - 1)]
    geo_mean = math.exp(sum(math.log(v) for v in lengths) / M)
    n_nom = _rand(generator, 130.0, 170.0)
    amplitude, cycles = _rand(generator, 0.3, 0.6), _rand(generator, 1.0, 3.0)
    if noise_fraction is None:
        noise_fraction = _rand(generator, 0.003, 0.01)
    local_t = _jitter_scale(lengths, dtype, device)
    cleans, switches, angles = [], [], []
    for _ in range(n_demos):
        c = corners + 0.02 * local_t * torch.randn(corners.shape, generator=generator, dtype=dtype, device=device)
        pieces, radii, bounds, at = _filleted_path(c, fractions)
        n = max(20 * M, int(round(n_nom * sum(lengths) / geo_mean * _rand(generator, 0.85, 1.15))))
        wave = None if profile == "constant" else (amplitude, cycles, _rand(generator, 0.0, 2.0 * math.pi))
        s = _speed_to_arc(n, float(bounds[-1]), wave, dtype, device)
        cleans.append(_points_on(pieces, radii, bounds, s))
        switches.append(torch.searchsorted(s, at).tolist())  # first sample at or past the arc's midpoint
        angles.append(_corner_angles(c, normals, bends))
    return _noisy_steps(generator, cleans, switches, angles, corners, lengths, profile, noise_fraction)


FamilyDraw = Callable[..., SyntheticSteps]  # draw(generator, n_demos, **overrides of the generator's keywords)


def _family(fn: Callable[..., SyntheticSteps], profile: str, dim: int, name: str) -> FamilyDraw:
    def draw(generator: torch.Generator, n_demos: int, **overrides: Any) -> SyntheticSteps:
        return replace(fn(generator, n_demos=n_demos, dim=dim, profile=profile, **overrides), family=name)

    draw.__name__ = name
    draw.__doc__ = f"{fn.__name__}(generator, n_demos=n_demos, dim={dim}, profile={profile!r}), all else drawn."
    return draw


_SHAPES = (
    ("straight", straight_steps, (2, 3)),
    ("curved", curved_steps, (2, 3)),
    ("out_and_back", out_and_back_steps, (2,)),
    ("revisit", revisit_steps, (2,)),
    ("scoop", scoop_steps, (3,)),
)


def _build_families() -> dict[str, FamilyDraw]:
    out = {}
    for shape, fn, dims in _SHAPES:
        for timing, profile in (("dwell", "min_jerk"), ("const", "constant")):
            for dim in dims:
                name = f"{shape}_{timing}_{dim}d"
                out[name] = _family(fn, profile, dim, name)
    return out


def _build_slowing() -> dict[str, FamilyDraw]:
    out = {}
    for shape, fn, dims in _SHAPES:
        for dim in dims:
            name = f"{shape}_slow_{dim}d"
            out[name] = _family(fn, "slowing", dim, name)
    return out


def _build_held_out() -> dict[str, FamilyDraw]:
    out = {}
    for timing, profile in (("const", "constant"), ("vary", "varying")):
        for dim in (2, 3):
            name = f"rounded_{timing}_{dim}d"
            out[name] = _family(rounded_steps, profile, dim, name)
    return out


#: Family name -> ``draw(generator, n_demos, **overrides)`` drawing a random instance (angles, lengths, timing, noise;
#: ``overrides`` fix keywords of the family's generator, e.g. ``n_steps=7`` for the straight and curved ones): the
#: name is ``{shape}_{dwell|const}_{2d|3d}``, "dwell" meaning the min-jerk profile, "const" constant speed.
#: The nominal path is drawn before the demonstrations, so one seed gives the same path for any ``n_demos``.
FAMILIES: dict[str, FamilyDraw] = _build_families()

#: Families drawn by :func:`rounded_steps` (rounded corners, speed unrelated to the corners), added after every
#: default of :func:`lfd_torch.segmentation.segment` was set and used to choose none: a check of the segmentation on
#: paths and timings it was not tuned on, kept apart from :data:`FAMILIES` (whose 280 cases the stored tables count).
#: Names ``rounded_{const|vary}_{2d|3d}``.
HELD_OUT_FAMILIES: dict[str, FamilyDraw] = _build_held_out()

#: The benchmark's shapes with the ``slowing`` timing (module docstring): the motion slows to 20-70 % of the leg's
#: mean speed at every corner without stopping, between the families' rest and constant speed, as a human
#: demonstrator often does. A second held-out set, added after every default of
#: :func:`lfd_torch.segmentation.segment` was set and used to choose none. Names ``{shape}_slow_{2d|3d}``.
SLOWING_FAMILIES: dict[str, FamilyDraw] = _build_slowing()
