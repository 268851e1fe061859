"""Finite-difference velocity kernels on padded batches.

Notation: B demonstrations, T padded samples, d state dimensions; ``lengths`` (B,) gives the valid samples
of each row. Padded samples of the output are zero.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lfd_torch.errors import TooFewSamplesError, UnknownNameError

__all__ = ["finite_difference", "SCHEMES"]

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
    """
    if scheme not in SCHEMES:
        raise UnknownNameError("finite-difference scheme", scheme, SCHEMES)
    B, T, d = positions.shape
    if T < 2:
        raise TooFewSamplesError("finite differences need at least 2 samples")
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
