"""Arrival in bounded time: the step-completion ball, a convergence-rate floor and a speed cap.

The engine completes step m when ||x - g_m|| < r_a (the arrival ball, ``radius`` x data span). A certified
primitive converges to g_m, but it may crawl: dV/dt < 0 says nothing about how fast. Two ways were measured on
LASA: a field that is slow (||f|| orders of magnitude below the demonstrated speed), and a field that circles g_m
(f nearly orthogonal to grad V: a cosine of -1e-4 between them, V barely decreasing while the robot moves at full
speed). The task then stalls in that step. The engine's commanded velocity is therefore

    u = cap(v + delta),      v = M(x) f(x) (the modulated primitive),

with, V = e^T P e and e = x - g_m (P the primitive's Lyapunov matrix),

* rate floor (a minimum-norm control-Lyapunov correction): delta is the smallest vector such that
  dV/dt = 2 e^T P (v + delta) <= -rho V, i.e.

      delta = -max(0, 2 e^T P v + rho V) / (2 ||P e||^2) P e,

  zero wherever v already decreases V at the rate rho (on the demonstrations, for a good fit). Then
  V(t) <= V(0) exp(-rho t) and the step arrives within t <= ln(V(x0) / (lambda_min(P) r_a^2)) / rho: a bound that
  does not depend on how slowly or how obliquely f moves. rho = ``min_rate`` / T_m with T_m the step's median
  demonstrated duration (V falls by e at least once per demonstrated step time);
* speed cap: cap(w) = w min(1, v_cap(r) / ||w||), v_cap(r) = v_hi min(1, r / r_s), v_hi = ``max_speed`` x the step's
  typical demonstrated speed (``Skill.speed``), r_s = ``slow_radius`` x span. A step whose demonstrations pass
  through g_m at speed (every intermediate step: the robot does not stop at a switch) forces gains ||A_k|| of
  hundreds per second near g_m, which an explicit integrator at a 100 Hz control rate cannot follow; inside r_s the
  cap bounds the effective gain ||u|| / r by v_hi / r_s.

Certificate. The correction only adds a multiple of -P e, and 2 e^T P (-P e) = -2 ||P e||^2 < 0, so dV/dt of
v + delta is <= min(dV/dt of v, -rho V) < 0; the cap multiplies by a positive scalar and keeps the sign. Every
certificate of the modulated field (eqs 19-21, :mod:`lfd_torch.modulation.policy`) therefore holds for u, and the
numerical check of :mod:`~lfd_torch.skills.stability` evaluates u itself. Where the cap is active the rate can fall
below rho, but V still decreases strictly (at a rate bounded below on compact sets away from g_m).
``min_rate = 0`` disables the floor, ``max_speed = inf`` the cap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError

__all__ = ["Arrival", "rate_floor", "shape_single", "speed_cap"]


def _nonneg(value: object, name: str, *, allow_zero: bool, allow_inf: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InvalidArgumentError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if math.isnan(v) or v < 0 or (v == 0 and not allow_zero) or (math.isinf(v) and not allow_inf):
        raise InvalidArgumentError(f"{name} must be a {'non-negative' if allow_zero else 'positive'} "
                                   f"{'number' if allow_inf else 'finite number'}, got {value!r}")  # fmt: skip
    return v


@dataclass(frozen=True)
class Arrival:
    """When a step is complete and how its field is kept from crawling (conf group ``skills``, key ``arrival``).

    Attributes:
        radius: step completion ball r_a, as a fraction of the data span (> 0).
        min_rate: rho T_m, the least decrease rate of V per demonstrated step duration (0 disables the floor).
        max_speed: v_hi as a multiple of the step's typical demonstrated speed (> 0; inf disables the cap).
        slow_radius: r_s, the radius inside which the cap narrows linearly to 0 at g_m, fraction of the span (> 0).
    """

    radius: float = 0.005
    min_rate: float = 1.0
    max_speed: float = 3.0
    slow_radius: float = 0.02

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius", _nonneg(self.radius, "arrival radius", allow_zero=False))
        object.__setattr__(self, "min_rate", _nonneg(self.min_rate, "min_rate", allow_zero=True))
        object.__setattr__(self, "max_speed", _nonneg(self.max_speed, "max_speed", allow_zero=False, allow_inf=True))
        object.__setattr__(self, "slow_radius", _nonneg(self.slow_radius, "slow_radius", allow_zero=False))


def rate_floor(v: Tensor, e: Tensor, P: Tensor | None, rate: Tensor | float, *, dim: int = -1,
               Pe: Tensor | None = None) -> Tensor:  # fmt: skip
    """v + delta with the minimum-norm delta that gives dV/dt <= -rate V (module docstring).

    Args:
        v: (..., d) velocities (units/s).
        e: (..., d) x - g (units).
        P: (..., d, d) or (d, d) Lyapunov matrices (symmetric positive definite); may be None when ``Pe`` is given.
        rate: (...) or scalar rho (1/s); 0 leaves v unchanged.
        dim: the vector axis of ``v``, ``e`` and ``Pe`` (0 for feature-major (d, n) batches).
        Pe: optional precomputed P e, shaped like ``e`` (needed when ``dim`` is not the last axis).

    Returns:
        (..., d) corrected velocities; v itself where it already decreases V fast enough (and at e = 0).
    """
    if Pe is None:
        if P is None or dim not in (-1, e.ndim - 1):
            raise InvalidArgumentError("Pe: pass P e for a vector axis other than the last, or P for the last")
        Pe = (P @ e.unsqueeze(-1)).squeeze(-1)
    V = (e * Pe).sum(dim)
    need = 2 * (Pe * v).sum(dim) + torch.as_tensor(rate, dtype=v.dtype, device=v.device) * V
    norm2 = (Pe * Pe).sum(dim)
    gain = torch.where((need > 0) & (norm2 > 0), need / (2 * norm2.clamp_min(torch.finfo(v.dtype).tiny)), 0.0)
    return v - gain.unsqueeze(dim) * Pe


def speed_cap(u: Tensor, r: Tensor, v_hi: Tensor | float, slow_radius: float, *, dim: int = -1) -> Tensor:
    """u min(1, v_hi min(1, r / r_s) / ||u||) (module docstring).

    Args:
        u: (..., d) velocities (units/s).
        r: (...) distances ||x - g_m|| (units).
        v_hi: (...) or scalar cap speed (units/s); inf: no cap.
        slow_radius: r_s (units, > 0).
        dim: the vector axis of ``u`` (0 for feature-major (d, n) batches).

    Returns:
        (..., d) velocities with ||u|| <= v_hi min(1, r / r_s), same direction.
    """
    speed = torch.linalg.vector_norm(u, dim=dim) if dim in (-1, u.ndim - 1) else (u * u).sum(dim).sqrt()
    cap = torch.as_tensor(v_hi, dtype=u.dtype, device=u.device) * (r / slow_radius).clamp(max=1.0)
    alpha = torch.where(speed > cap, cap / speed.clamp_min(torch.finfo(u.dtype).tiny), 1.0)
    return u * alpha.unsqueeze(dim)


def shape_single(u: list[float], e: list[float], Pe: list[float], rate: float, v_hi: float, slow_radius: float,
                 tiny: float) -> list[float]:  # fmt: skip
    """:func:`rate_floor` then :func:`speed_cap` of one sample in Python floats (u, e = x - g_m and P_m e as lists
    of d floats; ``tiny`` the smallest normal number of the engine's dtype): the same formulas in the same order,
    for the single-state control tick."""
    V = sum(a * b for a, b in zip(e, Pe))
    need = 2 * sum(p * v for p, v in zip(Pe, u)) + rate * V
    norm2 = sum(p * p for p in Pe)
    if need > 0 and norm2 > 0:
        gain = need / (2 * max(norm2, tiny))
        u = [v - gain * p for v, p in zip(u, Pe)]
    speed = math.sqrt(sum(v * v for v in u))
    cap = v_hi * min(math.sqrt(sum(v * v for v in e)) / slow_radius, 1.0)
    if speed > cap:
        alpha = cap / max(speed, tiny)
        u = [v * alpha for v in u]
    return u
