"""The disturbance modulation x_dot = M(x) f(x) of the skill decision engine (paper Sec. IV, eqs 8-21).

Branches, per sample (NOTES sec. 4), with e = x - g, r = ||e||, e_g = e / r, c = e_g^T f:

* large scale, x outside its subtask space (log p(x|A_m) < log p(x|A_m-)): D = diag(lambda_ls, 0, ..., 0) with
  lambda_ls = -sgn(c) s, s in [1, lambda_limit] (eq. 13), so M f = lambda_ls c e_g = -|c| s e_g: it always points at g.
* small scale, x inside A_m and H2(x) > H2_ref: D = D_ls + lambda_ss I with lambda_ls = -sgn(c) and
  lambda_ss = min(1, exp(H2_ref - H2)) (eqs 17-18), i.e. d1 = lambda_ss - sgn(c), d = lambda_ss and
  M f = lambda_ss f - |c| e_g: the components orthogonal to e_g are attenuated and the radial component becomes
  (lambda_ss - 1) c < 0 when f points away from g (c > 0), or (1 + lambda_ss) c when it points towards it.
* unmodulated, x inside A_m and H2(x) <= H2_ref: D = I, M f = f.
* at the goal, x = g: the velocity is 0 (e_g is undefined; f(g) = 0 for every primitive anyway).

The c = 0 rule (no stall). Where f is orthogonal to e_g the literal large-scale velocity -|c| s e_g is zero at a
point x != g, a spurious equilibrium; the small-scale velocity lambda_ss f - |c| e_g has the same defect where
lambda_ss underflows to 0 (H2 - H2_ref > ~745 in float64, ~103 in float32, i.e. far from the data). Both branches
therefore use the floored radial magnitude

    a = max(|c|, radial_floor * ||f||),      large: M f = -a s e_g,     small: M f = lambda_ss f - a e_g,

with ``radial_floor`` = kappa in [0, 1] (default 0.1; 0 gives the paper's literal formulas). Where |c| >= kappa ||f||
this is exactly W D W^T f of eqs 12 and 17; where |c| < kappa ||f|| (only there) it is a stronger pull towards g
than the literal formula. A certified primitive has f(x) != 0 for x != g (2 e^T P f < 0), so a > 0 there and the
modulated field never stalls away from g. The large-scale speed stays within [kappa s ||f||, s ||f||].

Stability (eqs 19-21; checked numerically in the tests). V(x) = e^T P e with P symmetric positive definite and
dV/dt = 2 e^T P x_dot. The unmodulated field satisfies V_f := 2 e^T P f < 0 for x != g. The one fact both branches
need is that the goal direction decreases V for *any* SPD P, not only P = I:

    2 e^T P e_g = 2 e^T P e / r >= 2 lambda_min(P) r > 0      for x != g.

* large scale: dV/dt = -2 a s e^T P e / r < 0 iff a > 0. The paper's eq. 20 therefore needs c != 0 (the floor
  provides it). With P != I the sign of c is not tied to V_f: c > 0 (f moving away from g in the Euclidean sense
  while V decreases) is possible, and eq. 13's -sgn(c) turns that component around; dV/dt < 0 either way.
* small scale: dV/dt = lambda_ss V_f - 2 a e^T P e / r. Both terms are <= 0 and the first is < 0 when
  lambda_ss > 0, so eq. 21 holds for every SPD P as long as lambda_ss > 0 or a > 0 (again provided by the floor
  when lambda_ss underflows and c = 0).
* unmodulated: dV/dt = V_f < 0.

So the paper's claim does not need P = I; its only gaps are the two zero-velocity corners, closed by the floor.
With it, dV/dt <= -2 kappa s lambda_min(P) r ||f|| (large) and dV/dt <= lambda_ss V_f - 2 kappa lambda_min(P) r ||f||
(small). The field is discontinuous where the branch changes (A_m boundary; H2 = H2_ref, where D jumps from I to
diag(1 - sgn c, 1, ..., 1)). Because V is a common Lyapunov function of the three branch fields and dV/dt is linear
in the velocity, every convex combination of them (a Filippov solution on a switching surface) also decreases V:
g stays globally asymptotically stable under arbitrary switching. Explicit-Euler rollouts additionally need a small
enough step, as for the unmodulated field.

Notation (shapes; batch shape (...)):
    x, f, M f            (..., d)  positions (data units), velocities (units/s)
    attractor g          (d,)
    log_p_own            (...)     log p(x|A_m), log density of the primitive's own subtask space
    log_p_other          (...)     log p(x|A_m-), largest log density of the other subtask spaces
    h2, h2_ref           (...)     H2(x) and the threshold H2(x_r) (broadcastable; a float is fine for h2_ref)
    branch               (...)     int8 tensor of :class:`Branch` values
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, UnknownNameError
from lfd_torch.modulation.entropy import reference_entropy, renyi_entropy
from lfd_torch.modulation.factors import (
    check_lambda_limit,
    large_scale_gain_unchecked,
    small_scale_factor_unchecked,
)
from lfd_torch.modulation.matrix import goal_direction_unchecked, radial_component_unchecked

__all__ = [
    "DEFAULT_LAMBDA_LIMIT",
    "DEFAULT_RADIAL_FLOOR",
    "MODULATION_MODES",
    "Branch",
    "Modulation",
    "ModulationResult",
    "modulated_velocity",
    "modulated_velocity_single",
    "modulated_velocity_unchecked",
]

#: Modes of :class:`Modulation`: ``none`` (M = I), ``large`` (large-scale branch only), ``small`` (small-scale
#: branch only, wherever H2 > H2_ref, ignoring the subtask spaces), ``full`` (eq. 9).
MODULATION_MODES = ("none", "large", "small", "full")

#: Default maximum acceleration multiplier of eq. 13 (the paper gives no value).
DEFAULT_LAMBDA_LIMIT = 3.0

#: Default kappa of the c = 0 rule, a = max(|c|, kappa ||f||) (dimensionless).
DEFAULT_RADIAL_FLOOR = 0.1


class Branch(enum.IntEnum):
    """Which branch of the modulation a sample took."""

    UNMODULATED = 0  # M = I (mode none, or inside A_m with H2 <= H2_ref, or mode large inside A_m)
    LARGE_SCALE = 1  # outside A_m: M f = -a s e_g
    SMALL_SCALE = 2  # inside A_m, H2 > H2_ref: M f = lambda_ss f - a e_g
    AT_GOAL = 3  # x = g: zero velocity


class ModulationResult(NamedTuple):
    """Result of :func:`modulated_velocity` and :meth:`Modulation.__call__`.

    Attributes:
        velocity: (..., d) modulated velocity M f (units/s), dtype and device of ``f``.
        branch: (...) int8 tensor of :class:`Branch` values.
    """

    velocity: Tensor
    branch: Tensor


def _check_mode(mode: Any) -> str:
    value = mode.value if isinstance(mode, enum.Enum) else mode
    if value not in MODULATION_MODES:
        raise UnknownNameError("modulation mode", str(value), MODULATION_MODES)
    return str(value)


def _check_radial_floor(radial_floor: Any) -> float:
    if isinstance(radial_floor, bool) or not isinstance(radial_floor, (int, float)):
        raise InvalidArgumentError(f"radial_floor must be a number in [0, 1], got {radial_floor!r}")
    value = float(radial_floor)
    if not 0.0 <= value <= 1.0:
        raise InvalidArgumentError(f"radial_floor must be in [0, 1], got {radial_floor!r}")
    return value


def _check_vectors(x: Any, f: Any, attractor: Any) -> None:
    for name, t in (("x", x), ("f", f), ("attractor", attractor)):
        if not isinstance(t, Tensor):
            raise ShapeMismatchError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if not t.is_floating_point():
            raise ShapeMismatchError(f"{name} must be floating point, got {t.dtype}")
    if x.ndim == 0 or x.shape[-1] == 0:
        raise ShapeMismatchError(f"x must have shape (..., d) with d >= 1, got {tuple(x.shape)}")
    d = x.shape[-1]
    if f.shape != x.shape:
        raise ShapeMismatchError(f"f must have the shape of x {tuple(x.shape)}, got {tuple(f.shape)}")
    if attractor.shape != (d,):
        raise ShapeMismatchError(f"attractor must have shape ({d},), got {tuple(attractor.shape)}")
    for name, t in (("f", f), ("attractor", attractor)):
        if t.dtype != x.dtype or t.device != x.device:
            raise ShapeMismatchError(f"{name} is {t.dtype} on {t.device}, x is {x.dtype} on {x.device}")
    from lfd_torch.utils import safe_magnitude

    for name, t in (("x", x), ("f", f), ("attractor", attractor)):
        if not bool((t.abs() <= safe_magnitude(t.dtype)).all()):
            raise NonFiniteError(f"{name} contains NaN, Inf or a magnitude above {safe_magnitude(t.dtype):.3g}")


def _as_batch(value: Any, name: str, x: Tensor, mode: str) -> Tensor:
    """A (...) tensor in x's dtype/device, broadcast to x.shape[:-1]; NaN is an error (+-inf is allowed)."""
    if value is None:
        raise InvalidArgumentError(f"{name} is required in modulation mode {mode!r}")
    if isinstance(value, Tensor):
        if value.is_complex() or value.dtype == torch.bool:  # .to() would drop an imaginary part with a warning
            raise ShapeMismatchError(f"{name} must be a real tensor or a number, got {value.dtype}")
        if value.device != x.device:
            raise ShapeMismatchError(f"{name} is on {value.device}, x is on {x.device}")
        t = value.to(x.dtype)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        t = torch.tensor(float(value), dtype=x.dtype, device=x.device)
    else:
        raise ShapeMismatchError(f"{name} must be a tensor or a number, got {type(value).__name__}")
    batch = x.shape[:-1]
    try:
        t = torch.broadcast_to(t, batch)
    except RuntimeError:
        raise ShapeMismatchError(
            f"{name} of shape {tuple(t.shape)} does not broadcast to the batch shape {tuple(batch)}"
        ) from None
    if torch.isnan(t).any():
        raise NonFiniteError(f"{name} contains NaN")
    return t


def modulated_velocity(
    x: Tensor,
    f: Tensor,
    attractor: Tensor,
    *,
    log_p_own: Tensor | float | None = None,
    log_p_other: Tensor | float | None = None,
    h2: Tensor | float | None = None,
    h2_ref: Tensor | float | None = None,
    mode: str = "full",
    lambda_limit: float = DEFAULT_LAMBDA_LIMIT,
    radial_floor: float = DEFAULT_RADIAL_FLOOR,
) -> ModulationResult:
    """Modulated velocity M(x) f(x) and the branch taken per sample (module docstring). Pure function.

    Args:
        x: (..., d) positions (data units).
        f: (..., d) unmodulated velocities f(x) (units/s), same dtype/device as ``x``.
        attractor: (d,) goal g.
        log_p_own: (...) log p(x|A_m); needed by modes ``large`` and ``full``.
        log_p_other: (...) log p(x|A_m-); needed by modes ``large`` and ``full`` (-inf: no other subtask).
        h2: (...) H2(x); needed by modes ``small`` and ``full``.
        h2_ref: (...) or scalar H2(x_r); needed by modes ``small`` and ``full``.
        mode: one of :data:`MODULATION_MODES`.
        lambda_limit: maximum acceleration multiplier of eq. 13, >= 1.
        radial_floor: kappa of the c = 0 rule, in [0, 1]; 0 is the paper's literal formula (stalls where c = 0).

    Returns:
        :class:`ModulationResult`; mode ``none`` returns ``f`` itself (a clone) and all-UNMODULATED branches.

    Raises:
        ShapeMismatchError: shapes, dtypes or devices that do not agree (message names the argument).
        NonFiniteError: NaN/Inf in ``x``, ``f`` or ``attractor``; NaN in a density or entropy.
        InvalidArgumentError: a required argument is missing, or ``lambda_limit`` / ``radial_floor`` out of range.
        UnknownNameError: unknown ``mode``.
    """
    mode = _check_mode(mode)
    limit = check_lambda_limit(lambda_limit)
    kappa = _check_radial_floor(radial_floor)
    _check_vectors(x, f, attractor)
    own = other = h = ref = None
    if mode in ("large", "full"):
        own = _as_batch(log_p_own, "log_p_own", x, mode)
        other = _as_batch(log_p_other, "log_p_other", x, mode)
    if mode in ("small", "full"):
        h = _as_batch(h2, "h2", x, mode)
        ref = _as_batch(h2_ref, "h2_ref", x, mode)
    return modulated_velocity_unchecked(x, f, attractor, own, other, h, ref, mode, limit, kappa)


def modulated_velocity_unchecked(
    x: Tensor,
    f: Tensor,
    attractor: Tensor,
    log_p_own: Tensor | None,
    log_p_other: Tensor | None,
    h2: Tensor | None,
    h2_ref: Tensor | None,
    mode: str,
    lambda_limit: float,
    radial_floor: float,
    *,
    dim: int = -1,
) -> ModulationResult:
    """The computation of :func:`modulated_velocity` without its argument checks, for callers that validated the
    inputs once (a control loop's hot path): tensors of the batch shape (or broadcastable), a valid ``mode``,
    ``lambda_limit`` and ``radial_floor``.

    ``dim`` is the vector axis of ``x``, ``f`` and the returned velocity: -1 for (..., d), 0 for feature-major
    (d, n) batches (then ``attractor`` is (d, 1) and the batch shape is (n,)); reductions over a leading axis of a
    feature-major tensor run over contiguous rows, several times faster on CPUs than over a trailing axis of size d.
    """
    dim = dim % x.ndim
    batch = x.shape[:dim] + x.shape[dim + 1 :]
    branch = torch.full(batch, int(Branch.UNMODULATED), dtype=torch.int8, device=x.device)
    if mode == "none":
        return ModulationResult(f.clone(), branch)

    unit, r = goal_direction_unchecked(x, attractor, dim=dim)
    c = radial_component_unchecked(f, unit, dim=dim)
    norm_f = torch.linalg.vector_norm(f, dim=dim) if dim == x.ndim - 1 else (f * f).sum(dim).sqrt()
    a = torch.maximum(c.abs(), radial_floor * norm_f)  # floored radial magnitude
    out = f.clone()

    if mode in ("large", "full"):
        outside = log_p_own < log_p_other
        s = large_scale_gain_unchecked(log_p_own, log_p_other, lambda_limit)
    else:
        outside = torch.zeros(batch, dtype=torch.bool, device=x.device)
    if mode in ("small", "full"):
        uncertain = (h2 > h2_ref) & ~outside
        lam_ss = small_scale_factor_unchecked(h2, h2_ref)
        small = lam_ss.unsqueeze(dim) * f - a.unsqueeze(dim) * unit
        out = torch.where(uncertain.unsqueeze(dim), small, out)
        branch = torch.where(uncertain, torch.full_like(branch, int(Branch.SMALL_SCALE)), branch)
    if mode in ("large", "full"):
        large = -(a * s).unsqueeze(dim) * unit
        out = torch.where(outside.unsqueeze(dim), large, out)
        branch = torch.where(outside, torch.full_like(branch, int(Branch.LARGE_SCALE)), branch)

    at_goal = r == 0
    out = torch.where(at_goal.unsqueeze(dim), torch.zeros_like(out), out)
    branch = torch.where(at_goal, torch.full_like(branch, int(Branch.AT_GOAL)), branch)
    return ModulationResult(out, branch)


def modulated_velocity_single(
    e: list[float],
    f: list[float],
    log_p_own: float | None,
    log_p_other: float | None,
    h2: float | None,
    h2_ref: float | None,
    mode: str,
    lambda_limit: float,
    radial_floor: float,
) -> tuple[list[float], Branch]:
    """:func:`modulated_velocity_unchecked` for one sample in Python floats, e = x - g and f as lists of d floats:
    the same formulas in the same order, for the single-state control tick (a few d-vectors, where a tensor
    kernel per operation costs more than the arithmetic). Returns the velocity (list) and the branch.

    Its checks cost a few float comparisons (it runs once per control tick): an unknown ``mode``
    (UnknownNameError), ``e`` and ``f`` of different lengths (ShapeMismatchError), NaN or Inf in ``e`` or ``f``
    or NaN in a density or entropy the mode uses (NonFiniteError), None where the branch taken needs the value
    (InvalidArgumentError), each naming the argument. None stands for a value the branch taken does not need (e.g.
    ``h2`` on the large-scale branch)."""
    if mode not in MODULATION_MODES:
        _check_mode(mode)
    if len(e) != len(f):
        raise ShapeMismatchError(f"f has {len(f)} entries, e = x - g has {len(e)}")
    r = math.sqrt(sum(v * v for v in e))
    norm_f = math.sqrt(sum(v * v for v in f))
    if not (math.isfinite(r) and math.isfinite(norm_f)):  # NaN and Inf propagate into the sums of squares
        name = "e" if not math.isfinite(r) else "f"
        raise NonFiniteError(f"{name} contains NaN, Inf or a magnitude whose square overflows")
    if mode == "none":
        return list(f), Branch.UNMODULATED
    large, small = mode in ("large", "full"), mode in ("small", "full")
    if (large and (log_p_own != log_p_own or log_p_other != log_p_other)
            or small and (h2 != h2 or h2_ref != h2_ref)):  # NaN where the mode uses it (None: not needed here)
        used = ((("log_p_own", log_p_own), ("log_p_other", log_p_other)) if large else ()) + \
            ((("h2", h2), ("h2_ref", h2_ref)) if small else ())  # fmt: skip
        raise NonFiniteError(f"{next(n for n, v in used if v != v)} is NaN")
    if r == 0:
        return [0.0] * len(e), Branch.AT_GOAL
    unit = [v / r for v in e]
    c = sum(a * b for a, b in zip(f, unit))
    a = max(abs(c), radial_floor * norm_f)
    if large and (log_p_own is None or log_p_other is None):
        raise InvalidArgumentError(f"{'log_p_own' if log_p_own is None else 'log_p_other'} is None, but mode {mode!r} "
                                   "compares the subtask densities here")  # fmt: skip
    if large and log_p_own < log_p_other:
        log_ratio = log_p_other - log_p_own
        s = math.exp(min(max(0.0 if math.isnan(log_ratio) else log_ratio, 0.0), math.log(lambda_limit)))
        return [-(a * s) * u for u in unit], Branch.LARGE_SCALE
    if small and (h2 is None or h2_ref is None):
        raise InvalidArgumentError(f"{'h2' if h2 is None else 'h2_ref'} is None, but mode {mode!r} compares the "
                                   "entropy with its threshold here (off the large-scale branch)")  # fmt: skip
    if small and h2 > h2_ref:
        lam_ss = math.exp(h2_ref - h2)
        return [lam_ss * v - a * u for v, u in zip(f, unit)], Branch.SMALL_SCALE
    return list(f), Branch.UNMODULATED


@dataclass(frozen=True)
class Modulation:
    """Config-friendly disturbance modulation (conf group ``modulation``; fields = constructor kwargs).

    Attributes:
        mode: one of :data:`MODULATION_MODES` (``full`` = paper eq. 9).
        lambda_limit: maximum acceleration multiplier of eq. 13 (>= 1; the paper gives no value).
        entropy_quantile: how the small-scale threshold H2(x_r) is chosen by :meth:`reference_entropy`: the
            quantile of H2 over the training states (1.0 = their maximum, the NOTES default), or None for the
            paper's literal x_r = g.
        radial_floor: kappa of the c = 0 rule (module docstring), in [0, 1].

    Raises:
        UnknownNameError: unknown ``mode``.
        InvalidArgumentError: a parameter out of range (the message names it).
    """

    mode: str = "full"
    lambda_limit: float = DEFAULT_LAMBDA_LIMIT
    entropy_quantile: float | None = 1.0
    radial_floor: float = DEFAULT_RADIAL_FLOOR

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", _check_mode(self.mode))
        object.__setattr__(self, "lambda_limit", check_lambda_limit(self.lambda_limit))
        object.__setattr__(self, "radial_floor", _check_radial_floor(self.radial_floor))
        q = self.entropy_quantile
        if q is not None:
            if isinstance(q, bool) or not isinstance(q, (int, float)) or not 0.0 <= float(q) <= 1.0:
                raise InvalidArgumentError(f"entropy_quantile must be a number in [0, 1] or None, got {q!r}")
            object.__setattr__(self, "entropy_quantile", float(q))

    @property
    def uses_entropy(self) -> bool:
        """Whether the mode evaluates H2 (``small`` and ``full``)."""
        return self.mode in ("small", "full")

    @property
    def uses_subtask_densities(self) -> bool:
        """Whether the mode needs log p(x|A_m) and log p(x|A_m-) (``large`` and ``full``)."""
        return self.mode in ("large", "full")

    def reference_entropy(self, primitive: Any, x_train: Tensor | None = None) -> Tensor:
        """H2(x_r) for this configuration (see :func:`lfd_torch.modulation.reference_entropy`).

        Args:
            primitive: the primitive.
            x_train: (N, d) training positions; required unless ``entropy_quantile`` is None.

        Returns:
            0-d tensor.
        """
        return reference_entropy(primitive, x_train, self.entropy_quantile)

    def __call__(
        self,
        primitive: Any,
        x: Tensor,
        f: Tensor | None = None,
        log_p_own: Tensor | float | None = None,
        log_p_other: Tensor | float | None = None,
        h2_ref: Tensor | float | None = None,
    ) -> ModulationResult:
        """Modulate the primitive's velocity at ``x``.

        Args:
            primitive: a :class:`~lfd_torch.ds.StablePrimitive` (its ``attractor``; ``gmm``, ``A`` and
                ``velocity_covariances`` for H2).
            x: (..., d) positions, primitive's dtype and device.
            f: (..., d) velocities f(x); None evaluates ``primitive(x)``.
            log_p_own: (...) log p(x|A_m) (modes ``large``, ``full``).
            log_p_other: (...) log p(x|A_m-) (modes ``large``, ``full``).
            h2_ref: threshold H2(x_r) (modes ``small``, ``full``), e.g. from :meth:`reference_entropy`. None is
                accepted only with ``entropy_quantile=None`` and means H2(g).

        Returns:
            :class:`ModulationResult` (velocity (..., d), branch (...)).

        Raises:
            InvalidArgumentError: ``h2_ref`` missing while ``entropy_quantile`` is set, or a density missing.
            ShapeMismatchError, NonFiniteError: see :func:`modulated_velocity`.
        """
        if not callable(primitive) or not isinstance(getattr(primitive, "attractor", None), Tensor):
            raise InvalidArgumentError(f"primitive must be a StablePrimitive, got {type(primitive).__name__}")
        if self.mode == "none" and f is not None:
            return modulated_velocity(x, f, primitive.attractor, mode="none")
        if f is None:
            f = primitive(x)
        h2 = None
        if self.uses_entropy:
            if h2_ref is None:
                if self.entropy_quantile is not None:
                    raise InvalidArgumentError(
                        "h2_ref is required when entropy_quantile is set; compute it once with "
                        "Modulation.reference_entropy(primitive, x_train)"
                    )
                h2_ref = reference_entropy(primitive, None, None)
            h2 = renyi_entropy(primitive, x)
        return modulated_velocity(
            x,
            f,
            primitive.attractor,
            log_p_own=log_p_own,
            log_p_other=log_p_other,
            h2=h2,
            h2_ref=h2_ref,
            mode=self.mode,
            lambda_limit=self.lambda_limit,
            radial_floor=self.radial_floor,
        )

    def field(
        self,
        primitive: Any,
        log_p_own: Callable[[Tensor], Tensor] | None = None,
        log_p_other: Callable[[Tensor], Tensor] | None = None,
        h2_ref: Tensor | float | None = None,
    ) -> Callable[[Tensor], Tensor]:
        """A batched vector field x -> M(x) f(x) for :func:`lfd_torch.rollout.rollout`.

        Args:
            primitive: the primitive.
            log_p_own: callable (N, d) -> (N,) giving log p(x|A_m) (modes ``large``, ``full``).
            log_p_other: callable (N, d) -> (N,) giving log p(x|A_m-); None means no other subtask (-inf).
            h2_ref: threshold H2(x_r) (see :meth:`__call__`).

        Returns:
            Callable (N, d) -> (N, d).
        """
        if self.uses_subtask_densities and log_p_own is None:
            raise InvalidArgumentError(f"log_p_own is required in modulation mode {self.mode!r}")
        for name, fn in (("log_p_own", log_p_own), ("log_p_other", log_p_other)):
            if fn is not None and not callable(fn):
                raise InvalidArgumentError(f"{name} must be a callable (N, d) -> (N,) giving log densities, got "
                                           f"{type(fn).__name__} {fn!r}")  # fmt: skip

        def _field(x: Tensor) -> Tensor:
            own = log_p_own(x) if log_p_own is not None else None
            other = log_p_other(x) if log_p_other is not None else (-math.inf if own is not None else None)
            return self(primitive, x, None, own, other, h2_ref).velocity

        return _field
