"""Arrival in bounded time: the step-completion ball and a speed band that keeps the Lyapunov certificate.

The engine completes step m when ||x - g_m|| < r_a (the arrival ball, ``radius`` x data span). A certified
primitive converges to g_m, but it may crawl: its speed ||f(x)|| can be orders of magnitude below the demonstrated
speed far from g_m (a weak component, a nearly singular A_k), and the task then stalls in that step.

Speed band (a time reparametrisation). The commanded velocity is u(x) = alpha(x) M(x) f(x) with the scalar

    alpha(x) = min(max(1, v_floor(r) / ||M f||), v_cap(r) / ||M f||),   r = ||x - g_m||,
    v_floor(r) = v_lo min(1, r / r_s),   v_cap(r) = v_hi min(1, r / r_s),

v_lo = ``min_speed`` and v_hi = ``max_speed`` times the step's typical demonstrated speed
(``Skill.speed``, a high quantile of its speeds), r_s = ``slow_radius``
x span. alpha > 0 only rescales the speed: the streamlines (hence the path metrics E3, DTWD) are those of M f, and
for any SPD P

    dV/dt = 2 (x - g)^T P u = alpha(x) 2 (x - g)^T P M f < 0     wherever 2 (x - g)^T P M f < 0,

so every certificate of the modulated field (eqs 19-21, :mod:`lfd_torch.modulation.policy`) holds unchanged.
Where the field moves at a demonstrated speed nothing changes. Why both ends:

* the floor: a certified primitive may crawl (a weak component far from g_m); without the floor the task stalls;
* the cap: a step whose demonstrations pass through g_m at speed (every intermediate step: the robot does not stop
  at a switch) forces gains ||A_k|| of hundreds per second near g_m, which an explicit integrator at a control
  rate of 100 Hz cannot follow; inside r_s the cap bounds the effective gain ||u|| / r by v_hi / r_s.

Bound. Let S = {x : r >= r_a, V(x) <= V(x0)} (compact, as V is a positive definite quadratic). On S,
-dV/dt >= alpha ||M f|| 2 lambda_min(P) r cos(theta) >= v_floor(r_a) 2 lambda_min(P) r_a cos_min, with cos_min > 0
the smallest cosine between -P e and u over S (positive because dV/dt < 0 on the compact S, the stability check
of :mod:`~lfd_torch.skills.stability` measures it). So the arrival time from x0 is at most
(V(x0) - lambda_min(P) r_a^2) / (2 lambda_min(P) v_floor(r_a) r_a cos_min): finite, independent of how slowly f
itself moves. Without the floor the same bound holds with min ||M f|| over S in place of v_floor(r_a), which is
what makes a crawling primitive slow. ``min_speed = 0`` disables the floor, ``max_speed = inf`` the cap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError

__all__ = ["Arrival", "speed_band"]


def _fraction(value: object, name: str, *, allow_zero: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InvalidArgumentError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InvalidArgumentError(f"{name} must be a finite number {'>=' if allow_zero else '>'} 0, got {value!r}")
    return v


@dataclass(frozen=True)
class Arrival:
    """When a step is complete and how slow or fast its field may be (conf group ``skills``, key ``arrival``).

    Attributes:
        radius: step completion ball r_a, as a fraction of the data span (> 0).
        min_speed: v_lo as a fraction of the step's typical demonstrated speed (0 disables the floor).
        max_speed: v_hi as a fraction of the same speed (>= min_speed; inf disables the cap).
        slow_radius: r_s, the radius inside which the band narrows linearly to 0 at g_m, fraction of the span (> 0).
    """

    radius: float = 0.005
    min_speed: float = 0.1
    max_speed: float = 3.0
    slow_radius: float = 0.02

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius", _fraction(self.radius, "arrival radius", allow_zero=False))
        object.__setattr__(self, "min_speed", _fraction(self.min_speed, "min_speed", allow_zero=True))
        hi = self.max_speed
        if isinstance(hi, bool) or not isinstance(hi, (int, float)) or math.isnan(hi) or hi < self.min_speed or hi <= 0:
            raise InvalidArgumentError(f"max_speed must be a number >= min_speed and > 0 (inf: no cap), got {hi!r}")
        object.__setattr__(self, "max_speed", float(hi))
        object.__setattr__(self, "slow_radius", _fraction(self.slow_radius, "slow_radius", allow_zero=False))


def speed_band(u: Tensor, r: Tensor, v_lo: Tensor | float, v_hi: Tensor | float, slow_radius: float) -> Tensor:
    """alpha(x) u with alpha = min(max(1, v_floor / ||u||), v_cap / ||u||) (module docstring).

    Args:
        u: (..., d) velocities M f (units/s).
        r: (...) distances ||x - g_m|| (units).
        v_lo: (...) or scalar floor speed (units/s); 0: no floor.
        v_hi: (...) or scalar cap speed (units/s), >= v_lo; inf: no cap.
        slow_radius: r_s (units, > 0).

    Returns:
        (..., d) rescaled velocities; u itself where ||u|| = 0 (only at g_m for a certified field).
    """
    speed = torch.linalg.vector_norm(u, dim=-1)
    ramp = (r / slow_radius).clamp(max=1.0)
    lo = torch.as_tensor(v_lo, dtype=u.dtype, device=u.device) * ramp
    hi = torch.as_tensor(v_hi, dtype=u.dtype, device=u.device) * ramp
    inv = 1.0 / speed.clamp_min(torch.finfo(u.dtype).tiny)
    alpha = torch.minimum((lo * inv).clamp(min=1.0), hi * inv)
    alpha = torch.where(speed > 0, alpha, torch.ones_like(alpha))
    return u * alpha.unsqueeze(-1)
