"""Synthetic multi-step demonstrations with known switch points (for tests and benchmarks of segmentation).

Each demonstration follows a polyline through waypoints w_0 -> w_1 -> ... -> w_M (one leg per step), with
per-demonstration jitter of the waypoints, of each leg's duration (timing variation) and white position noise.
Legs are traversed either at constant speed or with a minimum-jerk profile, which dwells near the corners.

Notation:
    M  number of steps (legs), d state dimension, B demonstrations
    waypoints     (M + 1, d)  nominal corners
    switch_times  (B, M - 1)  sample index at which step m + 1 starts (the corner arrival of leg m)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from lfd_torch.data import Demos

__all__ = ["SyntheticSteps", "random_waypoints", "multi_step_demos"]

PROFILES = ("min_jerk", "constant")


@dataclass(frozen=True, eq=False)
class SyntheticSteps:
    """Demonstrations with their ground truth.

    Attributes:
        demos: the B demonstrations (positions in units of ``scale``, dt = 0.01 s).
        waypoints: (M + 1, d) nominal waypoints.
        switch_times: (B, M - 1) long, first sample of steps 2..M in each demonstration.
        profile: "min_jerk" or "constant".
    """

    demos: Demos
    waypoints: Tensor
    switch_times: Tensor
    profile: str

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
        raise ValueError("need n_steps >= 1 and dim >= 2")
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
    if profile not in PROFILES:
        raise ValueError(f"profile must be one of {PROFILES}, got {profile!r}")
    if waypoints is None:
        waypoints = random_waypoints(n_steps, dim, generator, dtype=dtype)
    device = generator.device  # the data are drawn on the generator's device
    waypoints = waypoints.to(dtype=dtype, device=device)
    M = waypoints.shape[0] - 1
    d = waypoints.shape[1]
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
    return SyntheticSteps(demos, waypoints, torch.stack(switches) if M > 1 else no_switch, profile)
