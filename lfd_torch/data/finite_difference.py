"""Finite-difference velocity kernels on padded batches.

Notation: B demonstrations, T padded samples, d state dimensions; ``lengths`` (B,) gives the valid samples
of each row. Padded samples of the output are zero.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lfd_torch.errors import (
    InvalidArgumentError,
    NonFiniteError,
    NonIncreasingTimeError,
    ShapeMismatchError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.utils import check_tensor

__all__ = ["finite_difference", "finite_difference_unchecked", "SCHEMES"]

SCHEMES = ("central", "forward", "backward")


def finite_difference(positions: Tensor, times: Tensor, lengths: Tensor, scheme: str = "central") -> Tensor:
    """Velocities by finite differences on non-uniform time grids.

    Args:
        positions: (B, T, d) padded positions.
        times: (B, T) time stamps, strictly increasing over each row's valid part.
        lengths: (B,) number of valid samples per row (>= 2).
        scheme: ``"central"``: second-order central differences on the non-uniform grid inside, first-order
            one-sided at both ends (what ``numpy.gradient(x, t)`` does); ``"forward"``: (x[t+1]-x[t])/dt, the last
            valid sample gets zero velocity (LPV-DS convention: the demonstration stops at the attractor);
            ``"backward"``: (x[t]-x[t-1])/dt, the first valid sample gets zero velocity.

    Returns:
        (B, T, d) velocities in position units per time unit, zero on padding.

    Raises:
        UnknownNameError: an unknown ``scheme``.
        ShapeMismatchError: ``positions`` not a float (B, T, d) tensor, ``times`` not (B, T), ``lengths`` not (B,) or
            above T, or tensors on different devices.
        InvalidArgumentError: ``lengths`` not an integer tensor.
        TooFewSamplesError: T < 2 or a length < 2.
        NonFiniteError: NaN or Inf in a valid position or time.
        NonIncreasingTimeError: times not strictly increasing over a row's valid part.
    """
    _check_inputs(positions, times, lengths)
    return finite_difference_unchecked(positions, times, lengths, scheme)


def finite_difference_unchecked(positions: Tensor, times: Tensor, lengths: Tensor, scheme: str = "central") -> Tensor:
    """:func:`finite_difference` without its argument checks, for inputs the caller has validated (``Demos``,
    the preprocessing steps): the checks scan every sample once more. ``scheme`` is still checked.

    Raises:
        UnknownNameError: an unknown ``scheme``.
    """
    if scheme not in SCHEMES:
        raise UnknownNameError("finite-difference scheme", str(scheme), SCHEMES)
    B, T, d = positions.shape
    lengths = lengths.to(device=positions.device)
    t = times.to(positions.dtype)
    dx = positions[:, 1:] - positions[:, :-1]  # (B, T-1, d)
    dt = (t[:, 1:] - t[:, :-1]).unsqueeze(-1)  # (B, T-1, 1)
    idx = torch.arange(T, device=positions.device)
    # Steps that lie inside the valid part: step k joins samples k and k+1.
    step_valid = (idx[:-1].unsqueeze(0) < (lengths - 1).unsqueeze(1)).unsqueeze(-1)
    safe_dt = torch.where(step_valid, dt, torch.ones_like(dt))
    slope = torch.where(step_valid, dx / safe_dt, torch.zeros_like(dx))  # (B, T-1, d)
    out = torch.zeros_like(positions)
    if scheme == "forward":
        out[:, :-1] = slope
    elif scheme == "backward":
        out[:, 1:] = slope
    else:
        h1 = safe_dt[:, :-1]  # t_i - t_{i-1}
        h2 = safe_dt[:, 1:]  # t_{i+1} - t_i
        s1 = slope[:, :-1]
        s2 = slope[:, 1:]
        # Weighted mean of the neighbouring slopes: exact for quadratics on a non-uniform grid.
        out[:, 1:-1] = (h2 * s1 + h1 * s2) / (h1 + h2)
        out[:, 0] = slope[:, 0]
        last = (lengths - 1).clamp(min=1)
        rows = torch.arange(B, device=positions.device)
        out[rows, last] = slope[rows, last - 1]
    mask = (idx.unsqueeze(0) < lengths.unsqueeze(1)).unsqueeze(-1)
    return torch.where(mask, out, torch.zeros_like(out))


def _check_inputs(positions: Tensor, times: Tensor, lengths: Tensor) -> None:
    """The argument checks of :func:`finite_difference` (once per call, on the whole batch)."""
    check_tensor(positions, "positions", ndim=3, finite=False, shape_hint="(B, T, d)")
    B, T, _ = positions.shape
    if T < 2:
        raise TooFewSamplesError(f"positions has T = {T} samples; finite differences need at least 2")
    if not isinstance(times, Tensor) or times.is_complex() or times.dtype == torch.bool:
        raise ShapeMismatchError(f"times must be a real (B, T) = {(B, T)} tensor, got "
                                 f"{getattr(times, 'dtype', type(times).__name__)}")  # fmt: skip
    if times.shape != (B, T):
        raise ShapeMismatchError(f"times must have shape (B, T) = {(B, T)}, got {tuple(times.shape)}")
    if not isinstance(lengths, Tensor) or lengths.is_floating_point() or lengths.is_complex() \
            or lengths.dtype == torch.bool:  # fmt: skip
        raise InvalidArgumentError(f"lengths must be a (B,) integer tensor, got "
                                   f"{getattr(lengths, 'dtype', type(lengths).__name__)}")  # fmt: skip
    if lengths.shape != (B,):
        raise ShapeMismatchError(f"lengths must have shape (B,) = ({B},), got {tuple(lengths.shape)}")
    for name, value in (("times", times), ("lengths", lengths)):
        if value.device != positions.device:
            raise ShapeMismatchError(f"{name} is on {value.device}, positions on {positions.device}")
    if (lengths < 2).any():
        i = int(torch.nonzero(lengths < 2)[0])
        raise TooFewSamplesError(f"lengths[{i}] = {int(lengths[i])}; finite differences need at least 2 samples", i)
    if (lengths > T).any():
        i = int(torch.nonzero(lengths > T)[0])
        raise ShapeMismatchError(f"lengths[{i}] = {int(lengths[i])} exceeds the padded length T = {T}", i)
    mask = torch.arange(T, device=positions.device).unsqueeze(0) < lengths.unsqueeze(1)  # (B, T) valid samples
    for name, bad in (("positions", (~torch.isfinite(positions)).any(-1) & mask),
                      ("times", ~torch.isfinite(times) & mask)):  # fmt: skip
        if bad.any():
            i, k = (int(v) for v in torch.nonzero(bad)[0])
            raise NonFiniteError(f"{name} contain NaN or Inf at sample {k}", i)
    bad = (times[:, 1:] <= times[:, :-1]) & mask[:, 1:]
    if bad.any():
        i, k = (int(v) for v in torch.nonzero(bad)[0])
        raise NonIncreasingTimeError(f"times are not strictly increasing at sample {k + 1} "
                                     f"({float(times[i, k])} -> {float(times[i, k + 1])})", i)  # fmt: skip
