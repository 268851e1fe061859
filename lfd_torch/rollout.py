"""Batched rollout engine: integrate a vector field from many start states at once.

Notation:
    B  number of start states (rows)
    d  state dimension
    T  stored samples per row, ``T = n_steps + 1`` (sample k is at time ``k * dt``)
    x0          (B, d)      start states, in data units (LASA: mm)
    field       (N, d) -> (N, d)   any batched vector field x_dot = f(x), data units per second; it is called
                on the rows that are still integrating, so N varies between calls (N <= B)
    positions   (B, T, d)   x at each sample; after a row stops it repeats the stop state
    velocities  (B, T, d)   x_dot used at each sample (field value plus any extra velocity); zero after a stop
    lengths     (B,)        valid samples per row (int64): stop step + 1, or T when the row never stopped
    converged   (B,)        True when the row met the stopping rule at sample ``lengths - 1`` and stayed there

Stopping rule (only when an ``attractor`` g is given): row b stops at the first sample k with
``||x_k - g|| < position_tol`` AND ``||x_dot_k|| < velocity_tol`` (Euclidean norms, strict inequalities, evaluated
in the working dtype as ``sum_j (x_kj - g_j)^2 < position_tol^2`` and ``sum_j x_dot_kj^2 < velocity_tol^2``).
From then on it is frozen: later samples repeat ``x_k`` with zero velocity and the field is no longer integrated
for it. The rule is evaluated at every sample on the device, so the recorded stop step is exact; the engine only
synchronises with the host every ``check_every`` steps (to drop stopped rows from the working set, finish early
and look for NaN/Inf), and its results do not depend on that period.

Without an attractor nothing stops: every row is integrated for ``n_steps`` steps (``converged`` is all False).

Divergence: a NaN or Inf in a valid sample (position or velocity) raises :class:`~lfd_torch.errors.NonFiniteError`
naming the first such step and start; the rollout never returns NaN silently.

Memory layout (speed): the engine keeps its state feature-major, (d, N), because CPU kernels on (N, d) tensors
with a tiny trailing d are several times slower. Consequences for callers:
  * ``field`` receives an (N, d) tensor that is in general NOT contiguous (the transpose of (d, N) storage): use
    ``reshape`` rather than ``view``, and never modify the input in place. A field that computes in the (d, N)
    layout (``x.T`` is contiguous) and returns the transpose of a (d, N) tensor avoids every copy.
  * ``positions`` / ``velocities`` are (B, T, d) views of (T, d, B) storage; ``.contiguous()`` when needed.

Perturbations (a push of the robot): at sample k, before the field is evaluated,
  1. every :class:`Disturbance` scheduled at k is applied: ``kind="position"`` adds a displacement to x_k (the stored
     sample k is the displaced state), ``kind="velocity"`` adds a constant extra velocity to x_dot during the step
     k -> k+1 (every Runge-Kutta stage sees it; the stored velocity at k includes it);
  2. then ``hook(k, x, active)`` is called and may return a displaced state.
A row touched by either is *reactivated* if it had stopped: its earlier stop is forgotten, the frozen samples before
k stay valid (the robot stood still), and the stopping rule applies again from sample k on. A push that leaves the
row inside both tolerances stops it again at k.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field as dataclass_field
from enum import Enum
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lfd_torch.data.demos import MIN_SAMPLES, Demos
from lfd_torch.utils import check_cost, check_float, real_array
from lfd_torch.errors import (
    InvalidArgumentError,
    NonFiniteError,
    NonIncreasingTimeError,
    ShapeMismatchError,
    TooFewSamplesError,
    UnknownNameError,
)

__all__ = [
    "DEFAULT_POSITION_TOL",
    "DEFAULT_VELOCITY_TOL",
    "Disturbance",
    "DisturbanceKind",
    "IntegrationMethod",
    "RolloutResult",
    "rollout",
]

DEFAULT_POSITION_TOL = 1e-3
"""Default ``position_tol`` in data units (e.g. mm for LASA); pass a value suited to your units."""

DEFAULT_VELOCITY_TOL = 1e-3
"""Default ``velocity_tol`` in data units per second."""

MAX_STORED_VALUES = 5e8
"""Bound on 2 (n_steps + 1) B d, the stored positions and velocities of one rollout (4 GB in float64)."""

Field = Callable[[Tensor], Tensor]
Hook = Callable[[int, Tensor, Tensor], "Tensor | None"]
StopGate = Callable[[int], Tensor]


class IntegrationMethod(str, Enum):
    """Explicit fixed-step integrators."""

    EULER = "euler"  # x_{k+1} = x_k + dt f(x_k); global error O(dt)
    RK4 = "rk4"  # classical 4-stage Runge-Kutta; global error O(dt^4)


class DisturbanceKind(str, Enum):
    """What a :class:`Disturbance` perturbs."""

    POSITION = "position"  # add a displacement (data units) to the state at the given samples
    VELOCITY = "velocity"  # add an extra velocity (data units / s) during the step that starts at the sample


def _parse_enum(enum: type[Enum], value: Any, kind: str) -> Any:
    try:
        return enum(value.value if isinstance(value, Enum) else value)
    except ValueError:
        raise UnknownNameError(kind, str(value), [m.value for m in enum]) from None


@dataclass(frozen=True, eq=False)
class Disturbance:
    """A scheduled perturbation of a rollout (see the module docstring for when it acts).

    Attributes:
        steps: sample indices k (0 <= k <= n_steps) at which it acts; an int or a sequence of ints.
        value: (d,) the same for every affected row, or (B, d) one per row. A displacement in data units
            (``kind="position"``) or an extra velocity in data units per second (``kind="velocity"``).
        kind: ``"position"`` or ``"velocity"`` (:class:`DisturbanceKind`).
        rows: which rows it affects: None for all, a (B,) bool mask, or a sequence/tensor of row indices.

    Several disturbances at the same sample add up. Every affected row is reactivated if it had stopped.
    """

    steps: int | Sequence[int] | Tensor
    value: Any
    kind: DisturbanceKind | str = DisturbanceKind.POSITION
    rows: Any = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", _parse_enum(DisturbanceKind, self.kind, "disturbance kind"))
        raw = self.steps
        if isinstance(raw, Tensor):
            raw = raw.reshape(-1).tolist()
        elif isinstance(raw, (int, np.integer)):
            raw = [raw]
        if isinstance(raw, (str, bytes)) or not isinstance(raw, Iterable):
            raise InvalidArgumentError(f"disturbance steps must be an int or a sequence of ints >= 0, got {raw!r}")
        raw = list(raw)
        if not raw or not all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 0 for s in raw):
            raise InvalidArgumentError(f"disturbance steps must be a non-empty set of integers >= 0, got {self.steps!r}")
        object.__setattr__(self, "steps", tuple(sorted({int(s) for s in raw})))
        value = self.value
        if not isinstance(value, Tensor):
            value = torch.as_tensor(real_array(value, "disturbance value", error=InvalidArgumentError))
        if value.is_complex() or value.dtype == torch.bool or value.ndim not in (1, 2):
            raise InvalidArgumentError(f"disturbance value must be a real (d,) or (B, d) array, got {value.dtype} of "
                                       f"shape {tuple(value.shape)}")  # fmt: skip
        # finiteness and the shape against (B, d) are checked by rollout(), which knows B and d


@dataclass(frozen=True, eq=False)
class RolloutResult:
    """Output of :func:`rollout` (shapes and units in the module docstring).

    ``positions`` and ``velocities`` are (B, T, d) views of time-major (T, d, B) storage (the engine writes one
    contiguous (d, B) slab per step); call ``.contiguous()`` if a later kernel needs contiguous memory.

    Attributes:
        positions: (B, T, d) states, data units.
        velocities: (B, T, d) velocities used at each sample, data units per second; zero after a stop.
        lengths: (B,) int64 valid samples per row.
        converged: (B,) bool, True when the row ended stopped by the stopping rule.
        times: (T,) sample times ``k * dt``, seconds.
        dt: time step, seconds.
        method: integrator used.
        attractor: (d,) the goal used by the stopping rule, or None.
    """

    positions: Tensor
    velocities: Tensor
    lengths: Tensor
    converged: Tensor
    times: Tensor
    dt: float
    method: IntegrationMethod
    attractor: Tensor | None = dataclass_field(default=None)

    @property
    def n_starts(self) -> int:
        return self.positions.shape[0]

    @property
    def n_steps(self) -> int:
        return self.positions.shape[1] - 1

    @property
    def dim(self) -> int:
        return self.positions.shape[2]

    @property
    def mask(self) -> Tensor:
        """(B, T) bool, True on valid samples."""
        T = self.positions.shape[1]
        return torch.arange(T, device=self.lengths.device).unsqueeze(0) < self.lengths.unsqueeze(1)

    @property
    def final_positions(self) -> Tensor:
        """(B, d) last valid state of each row (the stop state for converged rows)."""
        return self.positions[:, -1]

    def positions_at(self, times: Tensor) -> Tensor:
        """Positions at arbitrary times (s from the start), linear between samples; after a row's last valid sample
        it stays at its final state.

        Args:
            times: (B, Q) or (Q,) query times, >= 0.

        Returns:
            (B, Q, d) positions.
        """
        B = self.n_starts
        if times.is_complex() if isinstance(times, Tensor) else np.iscomplexobj(times):  # as_tensor would drop it
            raise ShapeMismatchError("times must be real numbers (s), got complex values")
        try:
            t = torch.as_tensor(times, dtype=self.positions.dtype, device=self.positions.device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ShapeMismatchError(f"times must be a (Q,) or ({B}, Q) array of numbers, got {type(times).__name__}"
                                     ) from exc
        if t.ndim == 1:
            t = t.unsqueeze(0).expand(B, -1)
        if t.ndim != 2 or t.shape[0] != B:
            raise ShapeMismatchError(f"times must have shape (Q,) or ({B}, Q), got {tuple(t.shape)}")
        if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
            raise NonFiniteError("times must be finite and >= 0")
        last = (self.lengths - 1).unsqueeze(1).to(t.device)
        t = t.clamp(max=float(self.positions.shape[1]) * self.dt)  # past the end: the final state (no int overflow)
        k = torch.minimum((t / self.dt).floor().long(), last)
        k1 = torch.minimum(k + 1, last)
        w = (t / self.dt - k).clamp(0, 1).unsqueeze(-1)
        w = torch.where((k1 == k).unsqueeze(-1), torch.zeros_like(w), w)
        d = self.dim
        x0 = self.positions.gather(1, k.unsqueeze(-1).expand(-1, -1, d))
        x1 = self.positions.gather(1, k1.unsqueeze(-1).expand(-1, -1, d))
        return x0 + w * (x1 - x0)

    def to_demos(self, attractor: Tensor | None = None, names: Sequence[str] = ()) -> Demos:
        """Package the rollouts as :class:`~lfd_torch.data.Demos` (times ``k * dt``), e.g. for metrics.

        Rows shorter than ``MIN_SAMPLES`` (a start inside the tolerances) are extended with their frozen samples,
        which are valid (zero velocity), up to ``MIN_SAMPLES``.

        Args:
            attractor: (d,) goal of the set; default the rollout's attractor, else the mean of the final states.
            names: optional B labels.

        Raises:
            TooFewSamplesError: ``n_steps + 1 < MIN_SAMPLES``.
        """
        T = self.positions.shape[1]
        if T < MIN_SAMPLES:
            raise TooFewSamplesError(f"a rollout with {T} samples cannot form demonstrations (need {MIN_SAMPLES})")
        if isinstance(names, (str, bytes)):
            raise InvalidArgumentError(f"names must be a sequence of B labels, got the string {names!r}")
        lengths = self.lengths.clamp(min=MIN_SAMPLES)
        T_keep = int(lengths.max())
        g = attractor if attractor is not None else self.attractor
        if g is None:
            g = self.final_positions.mean(0)
        g = torch.as_tensor(g, dtype=self.positions.dtype, device=self.positions.device).reshape(-1)
        B = self.n_starts
        return Demos(
            self.positions[:, :T_keep],
            self.velocities[:, :T_keep],
            self.times[:T_keep].unsqueeze(0).expand(B, T_keep),
            lengths,
            g,
            tuple(names),
        )


# ---------------------------------------------------------------------------------------------- validation
def _check_tol(value: float | None, default: float, name: str) -> float:
    """``value`` (None: ``default``) as a tolerance >= 0; 0 disables stopping, inf disables this criterion."""
    return default if value is None else check_float(value, name, low=0.0, allow_inf=True)


def _row_mask(rows: Any, B: int, device: torch.device) -> Tensor:
    if rows is None:
        return torch.ones(B, dtype=torch.bool, device=device)
    try:
        r = torch.as_tensor(rows if isinstance(rows, Tensor) else np.asarray(rows), device=device)
    except (TypeError, ValueError, RuntimeError) as exc:  # strings, None, ragged lists
        raise InvalidArgumentError(f"disturbance rows must be a bool mask or integer indices, got {rows!r}") from exc
    if r.dtype == torch.bool:
        if r.shape != (B,):
            raise ShapeMismatchError(f"disturbance row mask has shape {tuple(r.shape)}, expected ({B},)")
        return r
    if r.is_floating_point() or r.is_complex():
        raise InvalidArgumentError("disturbance rows must be a bool mask or integer indices")
    r = r.reshape(-1).long()
    if ((r < -B) | (r >= B)).any():
        raise ShapeMismatchError(f"disturbance row index out of range for {B} starts: {r.tolist()}")
    mask = torch.zeros(B, dtype=torch.bool, device=device)
    mask[r % B] = True
    return mask


@dataclass
class _Kick:
    """Disturbances of one sample, summed over all specs: full-batch tensors."""

    rows: Tensor  # (B,) bool
    displacement: Tensor | None  # (d, B)
    velocity: Tensor | None  # (d, B)


def _schedule(
    disturbances: Iterable[Disturbance] | Disturbance | None, B: int, d: int, n_steps: int, like: Tensor
) -> dict[int, _Kick]:
    """Validate the disturbance specs and sum them per sample into full-batch, feature-major tensors."""
    plan: dict[int, _Kick] = {}
    if disturbances is None:
        return plan
    if isinstance(disturbances, Disturbance):
        disturbances = [disturbances]
    if isinstance(disturbances, (str, bytes)) or not isinstance(disturbances, Iterable):
        raise InvalidArgumentError(f"disturbances must be a Disturbance, an iterable of them or None, got "
                                   f"{type(disturbances).__name__}")  # fmt: skip
    for i, dist in enumerate(disturbances):
        if not isinstance(dist, Disturbance):
            raise InvalidArgumentError(f"disturbances[{i}] is a {type(dist).__name__}, not a Disturbance")
        value = torch.as_tensor(
            dist.value if isinstance(dist.value, Tensor) else np.asarray(dist.value), device=like.device
        ).to(like.dtype)
        if value.shape == (d,):
            value = value.expand(B, d)
        elif value.shape != (B, d):
            raise ShapeMismatchError(
                f"disturbances[{i}].value has shape {tuple(value.shape)}, expected ({d},) or {(B, d)}"
            )
        if not torch.isfinite(value).all():
            raise NonFiniteError(f"disturbances[{i}].value is not finite")
        rows = _row_mask(dist.rows, B, like.device)
        contribution = torch.where(rows.unsqueeze(-1), value, value.new_zeros(())).T.contiguous()  # (d, B)
        for s in dist.steps:
            if not 0 <= s <= n_steps:
                raise InvalidArgumentError(f"disturbances[{i}] acts at step {s}, outside 0..{n_steps}")
            kick = plan.setdefault(s, _Kick(torch.zeros(B, dtype=torch.bool, device=like.device), None, None))
            kick.rows = kick.rows | rows
            if dist.kind is DisturbanceKind.POSITION:
                kick.displacement = contribution if kick.displacement is None else kick.displacement + contribution
            else:
                kick.velocity = contribution if kick.velocity is None else kick.velocity + contribution
    return plan


def _call_field(field: Field, x: Tensor, k: int) -> Tensor:
    out = field(x)
    if not isinstance(out, Tensor):
        raise ShapeMismatchError(f"field returned a {type(out).__name__} at step {k}, expected a tensor")
    if out.shape != x.shape or out.dtype != x.dtype or out.device != x.device:
        raise ShapeMismatchError(
            f"field maps {tuple(x.shape)} {x.dtype} on {x.device} to {tuple(out.shape)} {out.dtype} on {out.device} "
            f"at step {k}; it must return the input's shape, dtype and device"
        )
    return out


# ---------------------------------------------------------------------------------------------- engine
def rollout(
    field: Field,
    x0: Tensor,
    dt: float,
    n_steps: int,
    *,
    method: IntegrationMethod | str = IntegrationMethod.EULER,
    attractor: Tensor | None = None,
    position_tol: float | None = None,
    velocity_tol: float | None = None,
    hook: Hook | None = None,
    can_stop: StopGate | None = None,
    hook_until: int | None = None,
    disturbances: Iterable[Disturbance] | Disturbance | None = None,
    check_every: int = 32,
    compact_below: float = 0.5,
    requires_grad: bool | None = None,
) -> RolloutResult:
    """Integrate ``x_dot = field(x)`` from B start states at once with a fixed step.

    Runs on the dtype and device of ``x0``; keeps no state between calls. Unless ``requires_grad`` (default:
    ``x0.requires_grad``), everything runs under ``torch.no_grad`` (a field that needs autograd internally must
    enable it itself); with it, the result is differentiable with respect to ``x0`` and the field's parameters
    (every row then stays in the working set).

    Args:
        field: batched vector field, (N, d) -> (N, d) with the input's dtype and device; N is the number of rows
            still integrating, which shrinks as rows stop.
        x0: (B, d) start states, floating point.
        dt: time step, seconds (> 0).
        n_steps: number of integration steps (>= 1); T = n_steps + 1 samples are stored, and 2 T B d (positions
            and velocities) must not exceed :data:`MAX_STORED_VALUES` (5e8).
        method: ``"euler"`` or ``"rk4"``.
        attractor: (d,) goal g. Required for the stopping rule; None integrates every row for n_steps steps.
        position_tol: stop when ``||x - g|| < position_tol`` (data units; default :data:`DEFAULT_POSITION_TOL`).
            0 never stops. Only valid with an attractor.
        velocity_tol: ... and ``||x_dot|| < velocity_tol`` (data units / s; default :data:`DEFAULT_VELOCITY_TOL`);
            ``inf`` stops on the position criterion alone. Only valid with an attractor.
        hook: optional ``hook(k, x, active) -> Tensor | None`` called at every sample k (after scheduled
            disturbances) with the full (B, d) state (a copy) and (B,) bool of rows not stopped; it may return a
            (B, d) displaced state. Rows whose state it changes are reactivated. A hook keeps every row in the
            working set (no compaction, no early finish).
        can_stop: optional per-row gate of the stopping rule, ``can_stop(k) -> (B,) bool``, called at every sample
            k after the hook: only rows where it is True may stop at k (e.g. a multi-step task whose rows stop at
            the final attractor only once they are in the last step). Only valid with a ``hook``, which holds the
            per-row state the gate reads (and keeps every row in the working set).
        hook_until: the last sample at which the hook may displace a state. Without it a rollout with a hook runs
            all ``n_steps``; with it, the run ends early once every row has stopped after that sample (the hook is
            then not called for the remaining, frozen samples).
        disturbances: :class:`Disturbance` specs (position pushes or extra velocities at given samples).
        check_every: host synchronisation period in steps: stopped rows are dropped from the working set, the run
            ends once every row has stopped (and no disturbance is pending), and the new samples are checked for
            NaN/Inf. Results do not depend on it.
        compact_below: drop stopped rows when the active fraction of the working set falls below this value
            (0: never; the field is then also evaluated at frozen rows, whose results are discarded).
        requires_grad: build the autograd graph (default ``x0.requires_grad``).

    Returns:
        :class:`RolloutResult`.

    Raises:
        ShapeMismatchError: ``x0`` not (B, d); attractor not (d,); disturbance shapes; a field output whose shape,
            dtype or device differs from its input.
        NonFiniteError: NaN/Inf in ``x0``, the attractor or a disturbance; or the rollout diverged (a NaN/Inf
            position or velocity in a valid sample): the message names the step, ``demo_index`` is the row.
        NonIncreasingTimeError: ``dt`` not a positive finite number.
        TooFewSamplesError: ``n_steps < 1`` or B = 0.
        UnknownNameError: unknown ``method``.
        InvalidArgumentError: other invalid arguments (negative tolerance, tolerance without attractor, ...).
    """
    if not callable(field):
        raise InvalidArgumentError(f"field must be callable, got {type(field).__name__}")
    if not isinstance(x0, Tensor):
        raise InvalidArgumentError(
            f"x0 must be a torch.Tensor (its dtype and device define the rollout's), got {type(x0).__name__}"
        )
    if not x0.is_floating_point():
        raise InvalidArgumentError(f"x0 must be floating point, got {x0.dtype}")
    if x0.ndim != 2:
        raise ShapeMismatchError(f"x0 must have shape (B, d), got {tuple(x0.shape)}")
    B, d = x0.shape
    if B == 0 or d == 0:
        raise TooFewSamplesError(f"x0 must have at least one start and one dimension, got {tuple(x0.shape)}")
    if not bool(torch.isfinite(x0).all()):
        b = int(torch.nonzero(~torch.isfinite(x0).all(-1))[0])
        raise NonFiniteError(f"x0 contains NaN or Inf (start {b})", b)
    dt = check_float(dt, "dt (seconds)", low=0.0, low_open=True, error=NonIncreasingTimeError)
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)):
        raise InvalidArgumentError(f"n_steps must be an int, got {n_steps!r}")
    n_steps = int(n_steps)
    if n_steps < 1:
        raise TooFewSamplesError(f"n_steps must be >= 1, got {n_steps}")
    check_cost("n_steps", 2.0 * (n_steps + 1) * B * d, MAX_STORED_VALUES, "stored positions and velocities")
    method = _parse_enum(IntegrationMethod, method, "integration method")
    if isinstance(check_every, bool) or not isinstance(check_every, (int, np.integer)) or check_every < 1:
        raise InvalidArgumentError(f"check_every must be an int >= 1, got {check_every!r}")
    compact_below = check_float(compact_below, "compact_below", low=0.0, high=1.0)
    if hook is not None and not callable(hook):
        raise InvalidArgumentError(f"hook must be callable, got {type(hook).__name__}")
    if can_stop is not None and (hook is None or not callable(can_stop)):
        raise InvalidArgumentError("can_stop must be a callable and needs a hook (which holds the per-row state)")
    if hook_until is not None and (hook is None or isinstance(hook_until, bool) or not isinstance(hook_until, (int, np.integer))):
        raise InvalidArgumentError(f"hook_until must be an int and needs a hook, got {hook_until!r}")

    g: Tensor | None = None
    if attractor is None:
        if position_tol is not None or velocity_tol is not None:
            raise InvalidArgumentError(
                "position_tol/velocity_tol need an attractor: the stopping rule is convergence to it"
            )
        p_tol = v_tol = 0.0
    else:
        try:
            g = torch.as_tensor(
                attractor.detach() if isinstance(attractor, Tensor) else np.asarray(attractor), device=x0.device
            )
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ShapeMismatchError(f"attractor must be a ({d},) tensor, got {attractor!r}") from exc
        if g.is_complex() or not (g.is_floating_point() or g.dtype in (torch.int32, torch.int64)):
            raise ShapeMismatchError(f"attractor must hold real numbers, got {g.dtype}")
        g = g.to(x0.dtype)
        if g.shape != (d,):
            raise ShapeMismatchError(f"attractor must have shape ({d},), got {tuple(g.shape)}")
        if not bool(torch.isfinite(g).all()):
            raise NonFiniteError("attractor contains NaN or Inf")
        p_tol = _check_tol(position_tol, DEFAULT_POSITION_TOL, "position_tol")
        v_tol = _check_tol(velocity_tol, DEFAULT_VELOCITY_TOL, "velocity_tol")
    plan = _schedule(disturbances, B, d, n_steps, x0)

    if requires_grad is not None and not isinstance(requires_grad, bool):
        raise InvalidArgumentError(f"requires_grad must be True, False or None, got {requires_grad!r}")
    grad = x0.requires_grad if requires_grad is None else requires_grad
    ctx = contextlib.nullcontext() if grad else torch.no_grad()
    with ctx:
        positions, velocities, stop = _integrate(
            field, x0 if grad else x0.detach(), dt, n_steps, method, g, p_tol, v_tol, hook, can_stop, hook_until,
            plan, int(check_every), float(compact_below), grad,
        )
    T = n_steps + 1
    converged = stop < T
    lengths = torch.where(converged, stop + 1, torch.full_like(stop, T))
    times = torch.arange(T, dtype=x0.dtype, device=x0.device) * dt
    return RolloutResult(
        positions.permute(2, 0, 1),
        velocities.permute(2, 0, 1),
        lengths,
        converged,
        times,
        dt,
        method,
        g,
    )


def _integrate(
    field: Field,
    x0: Tensor,
    dt: float,
    n_steps: int,
    method: IntegrationMethod,
    g: Tensor | None,
    p_tol: float,
    v_tol: float,
    hook: Hook | None,
    can_stop: StopGate | None,
    hook_until: int | None,
    plan: dict[int, _Kick],
    check_every: int,
    compact_below: float,
    grad: bool,
) -> tuple[Tensor, Tensor, Tensor]:
    """The time loop. Returns positions and velocities stored (T, d, B) and the stop sample (B,) (T: none).

    Layout: the working state is feature-major, ``xt`` (d, n_w), so that per-row masks broadcast over the
    contiguous row axis (ops on (N, d) tensors with d = 2 innermost are several times slower on CPU). The field
    gets ``xt.T``, an (n_w, d) view. Working set W: the rows still integrated, in ``idx`` order (``idx is None``:
    all rows in order, written with plain slices). Per-row state of W: ``xt``, ``act`` (n_w,) not stopped, ``stop``
    (n_w,) stop sample. Rows outside W are stopped; their frozen state and stop sample live in ``x_all`` (d, B)
    and ``stop_all`` (B,).
    """
    B, d = x0.shape
    T = n_steps + 1
    dtype, device = x0.dtype, x0.device
    stopping = g is not None and p_tol > 0 and v_tol > 0
    rk4 = method is IntegrationMethod.RK4
    pos = torch.empty((T, d, B), dtype=dtype, device=device)
    vel = torch.empty((T, d, B), dtype=dtype, device=device)
    zero = torch.zeros((), dtype=dtype, device=device)
    g_col = None if g is None else g.reshape(d, 1)
    p_tol2, v_tol2 = p_tol * p_tol, v_tol * v_tol
    half_dt, sixth_dt = 0.5 * dt, dt / 6.0

    xt = x0.T.contiguous()
    act = torch.ones(B, dtype=torch.bool, device=device)
    stop = torch.full((B,), T, dtype=torch.long, device=device)
    idx: Tensor | None = None
    x_all = xt.detach().clone()
    stop_all = stop.clone()
    in_w = torch.ones(B, dtype=torch.bool, device=device)
    kick_steps = sorted(plan)
    compactable = hook is None and not grad  # a hook sees every row; autograd keeps every row in one graph
    fast_write = not grad  # out= writes are not differentiable
    last_check = 0
    k = 0

    def evaluate(y: Tensor, extra: Tensor | None) -> Tensor:
        """Field at the (d, n) states y, as a contiguous (d, n) tensor (plus the extra velocity)."""
        out = _call_field(field, y.T, k).T
        if not out.is_contiguous():
            out = out.contiguous()
        return out if extra is None else out + extra

    def check_finite(k_end: int) -> None:
        first: tuple[int, int, str] | None = None
        for name, buf in (("position", pos), ("velocity", vel)):
            block = buf[last_check:k_end].detach()
            if block.numel() == 0:
                continue
            lo, hi = torch.aminmax(block)
            if bool(torch.isfinite(lo) & torch.isfinite(hi)):
                continue
            bad = ~torch.isfinite(block).all(1)  # (K, B)
            j, b = (int(v) for v in torch.nonzero(bad)[0])
            if first is None or last_check + j < first[0]:
                first = (last_check + j, b, name)
        if first is not None:
            step, b, name = first
            raise NonFiniteError(
                f"rollout diverged: non-finite {name} at step {step} (t = {step * dt:g} s) of start {b} (check the "
                "field and dt)", b
            )

    def fill_tail(k_from: int, rows: Tensor | None, states: Tensor) -> None:
        """Freeze ``rows`` (None: all) at ``states`` (d, n) for samples k_from..T-1."""
        if k_from >= T:
            return
        if rows is None:
            pos[k_from:] = states.unsqueeze(0)
            vel[k_from:] = 0
        else:  # scatter_ with broadcast views: several times faster than advanced-index assignment on CPU
            shape = (T - k_from, d, rows.numel())
            where_ = rows.expand(shape)
            pos[k_from:].scatter_(2, where_, states.unsqueeze(0).expand(shape))
            vel[k_from:].scatter_(2, where_, zero.expand(shape))

    while k <= n_steps:
        # ---------------------------------------------------------------- perturbations at sample k
        extra_v: Tensor | None = None
        kick = plan.get(k)
        if kick is not None:
            if idx is not None:
                new = torch.nonzero(kick.rows & ~in_w).reshape(-1)
                if new.numel():
                    idx = torch.cat([idx, new])
                    xt = torch.cat([xt, x_all[:, new]], dim=1)
                    act = torch.cat([act, torch.zeros(new.numel(), dtype=torch.bool, device=device)])
                    stop = torch.cat([stop, stop_all[new]])
                    in_w[new] = True
                hit = kick.rows[idx]
                disp = None if kick.displacement is None else kick.displacement[:, idx]
                extra_v = None if kick.velocity is None else kick.velocity[:, idx]
            else:
                hit = kick.rows
                disp, extra_v = kick.displacement, kick.velocity
            if disp is not None:
                xt = xt + disp
            act = act | hit
            stop = stop.masked_fill(hit, T)
        if hook is not None:
            state = xt.T if grad else xt.T.detach()
            y = hook(k, state.clone(memory_format=torch.contiguous_format), act.clone())
            if y is not None:
                if not isinstance(y, Tensor) or y.shape != (B, d):
                    raise ShapeMismatchError(
                        f"hook returned {type(y).__name__} {tuple(getattr(y, 'shape', ()))} at step {k}, "
                        f"expected a tensor of shape {(B, d)}"
                    )
                yt = y.to(dtype=dtype, device=device).T.contiguous()
                moved = (yt != xt).any(0)
                xt = yt
                act = act | moved
                stop = stop.masked_fill(moved, T)
        if xt.shape[1] == 0:  # every row is frozen until the next scheduled push
            later = [s for s in kick_steps if s > k]
            if not later:
                break
            k = later[0]
            last_check = k
            continue

        # ---------------------------------------------------------------- sample k
        vt = evaluate(xt, extra_v)
        # stored velocity at sample k: zero for frozen rows
        if idx is None and fast_write:
            pos[k].copy_(xt)
            if stopping:
                torch.where(act, vt, zero, out=vel[k])
            else:
                vel[k].copy_(vt)
        else:
            v_rec = torch.where(act, vt, zero) if stopping else vt
            if idx is None:
                pos[k] = xt
                vel[k] = v_rec
            else:
                idx_d = idx.expand(d, idx.numel())
                pos[k].scatter_(1, idx_d, xt)
                vel[k].scatter_(1, idx_d, v_rec)
        if stopping:
            e = xt - g_col
            crit = (e * e).sum(0) < p_tol2
            crit &= (vt * vt).sum(0) < v_tol2
            crit &= act  # rows that stop at this sample
            if can_stop is not None:
                gate = can_stop(k)
                if not isinstance(gate, Tensor) or gate.shape != (B,) or gate.dtype != torch.bool:
                    raise ShapeMismatchError(f"can_stop({k}) must return a ({B},) bool tensor")
                crit &= gate.to(device)
            stop.masked_fill_(crit, k)
            act = act ^ crit
        if k == n_steps:
            break

        # ---------------------------------------------------------------- step k -> k+1
        if rk4:
            k2 = evaluate(torch.add(xt, vt, alpha=half_dt), extra_v)
            k3 = evaluate(torch.add(xt, k2, alpha=half_dt), extra_v)
            k4 = evaluate(torch.add(xt, k3, alpha=dt), extra_v)
            incr = (vt + k4).add_(k2 + k3, alpha=2.0)
            x_next = torch.add(xt, incr, alpha=sixth_dt)
        else:
            x_next = torch.add(xt, vt, alpha=dt)
        xt = torch.where(act, x_next, xt) if stopping else x_next  # stopped rows stay exactly where they stopped
        k += 1

        # ---------------------------------------------------------------- host synchronisation
        if k - last_check >= check_every:
            check_finite(k)
            last_check = k
            if not stopping or grad:
                continue
            n_w = xt.shape[1]
            n_act = int(act.sum())
            hook_done = hook is None or (hook_until is not None and k > hook_until)
            if n_act == 0 and hook_done and not any(s >= k for s in kick_steps):
                fill_tail(k, idx, xt)
                last_check = T
                break
            if not compactable:
                continue
            if n_act < compact_below * n_w:
                gone = torch.nonzero(~act).reshape(-1)
                keep = torch.nonzero(act).reshape(-1)
                rows = gone if idx is None else idx[gone]
                x_gone = xt[:, gone]
                fill_tail(k, rows, x_gone)
                x_all[:, rows] = x_gone
                stop_all[rows] = stop[gone]
                in_w[rows] = False
                idx = keep if idx is None else idx[keep]
                xt, act, stop = xt[:, keep], act[keep], stop[keep]
    check_finite(T)
    if idx is None:
        stop_all = stop
    else:
        stop_all[idx] = stop
    return pos, vel, stop_all
