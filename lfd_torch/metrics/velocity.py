"""Velocity-reproduction metrics E1 and E2 (paper Sec. V-A).

Notation:
    B       number of reference trajectories
    T       padded number of samples
    d       state dimension
    x_dot_ref  (B, T, d)  demonstrated velocities, data units per second (LASA: mm/s)
    x_dot      (B, T, d)  predicted velocities M f(x_ref) at the demonstrated positions, same units
    mask       (B, T)     True on valid samples (or ``lengths`` (B,) for prefix-valid rows)
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from lfd_torch.errors import UnknownNameError
from lfd_torch.metrics._checks import as_trajectories, check_finite, resolve_mask
from lfd_torch.utils import check_float

__all__ = ["VELOCITY_ERROR_KINDS", "velocity_error", "cosine_dissimilarity"]

VELOCITY_ERROR_KINDS = ("mean_norm", "rms")


def _masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Mean of ``values`` (B, T) over the True entries of ``mask`` (B, T) per row -> (B,)."""
    zero = torch.zeros((), dtype=values.dtype, device=values.device)
    total = torch.where(mask, values, zero).sum(1)
    return total / mask.sum(1).to(values.dtype)


def velocity_error(
    pred_x_dot: Tensor,
    ref_x_dot: Tensor,
    mask: Tensor | None = None,
    *,
    lengths: Tensor | None = None,
    kind: Literal["mean_norm", "rms"] = "mean_norm",
) -> Tensor:
    """Velocity error E1 per trajectory.

    ``"mean_norm"`` is the paper's E1 (which the paper calls RMSE): the mean over valid samples t of
    ||x_dot_ref,t - x_dot_t||. ``"rms"`` is the true root-mean-square error sqrt(mean_t ||x_dot_ref,t - x_dot_t||^2).
    Both are >= 0 and zero only for a perfect prediction; "rms" >= "mean_norm".

    Args:
        pred_x_dot: (B, T, d) predicted velocities, data units per second.
        ref_x_dot: (B, T, d) reference (demonstrated) velocities, same units.
        mask: optional (B, T) bool, True on valid samples; padded samples may hold any value (even NaN).
        lengths: optional (B,) valid-sample counts (prefix rows) instead of ``mask``.
        kind: ``"mean_norm"`` or ``"rms"``.

    Returns:
        (B,) error per trajectory in data units per second, dtype of the (promoted) inputs.

    Raises:
        ShapeMismatchError: inputs not (B, T, d) of equal shape, or a bad mask / lengths shape.
        NonFiniteError: NaN or Inf at a valid sample.
        TooFewSamplesError: a trajectory without a valid sample.
        UnknownNameError: an unknown ``kind``.
    """
    if kind not in VELOCITY_ERROR_KINDS:
        raise UnknownNameError("velocity error kind", kind, VELOCITY_ERROR_KINDS)
    pred, ref = as_trajectories(("pred_x_dot", pred_x_dot), ("ref_x_dot", ref_x_dot))
    B, T, _ = pred.shape
    valid = resolve_mask(mask, lengths, B, T, pred.device, min_samples=1)
    check_finite("pred_x_dot", pred, valid)
    check_finite("ref_x_dot", ref, valid)
    diff = torch.where(valid.unsqueeze(-1), ref - pred, torch.zeros((), dtype=pred.dtype, device=pred.device))
    if kind == "rms":
        return _masked_mean(diff.square().sum(-1), valid).sqrt()
    return _masked_mean(torch.linalg.vector_norm(diff, dim=-1), valid)


def cosine_dissimilarity(
    pred_x_dot: Tensor,
    ref_x_dot: Tensor,
    mask: Tensor | None = None,
    *,
    lengths: Tensor | None = None,
    eps: float = 1e-9,
) -> Tensor:
    """Cosine dissimilarity E2 per trajectory: mean over valid samples t of |1 - cos(x_dot_ref,t, x_dot_t)|.

    Zero-velocity convention (no NaN is ever produced): a velocity whose Euclidean norm is <= ``eps`` counts
    as zero. If both velocities at a sample are zero, the sample contributes 0 (both at rest: full agreement,
    as at the attractor, where f(g) = 0 and the demonstration has stopped). If exactly one is zero, its direction
    is undefined and the pair is treated as orthogonal: cos = 0, the sample contributes 1. Otherwise the
    cosine is computed from the normalised vectors and clipped to [-1, 1], so each term lies in [0, 2].

    Args:
        pred_x_dot: (B, T, d) predicted velocities, data units per second.
        ref_x_dot: (B, T, d) reference velocities, same units.
        mask: optional (B, T) bool, True on valid samples; padded samples may hold any value.
        lengths: optional (B,) valid-sample counts (prefix rows) instead of ``mask``.
        eps: norm threshold (data units per second, >= 0) at or below which a velocity counts as zero.

    Returns:
        (B,) dimensionless dissimilarity in [0, 2] per trajectory.

    Raises:
        ShapeMismatchError, NonFiniteError, TooFewSamplesError: as for :func:`velocity_error`.
        InvalidArgumentError: a negative or non-finite ``eps``.
    """
    eps = check_float(eps, "eps", low=0.0)
    pred, ref = as_trajectories(("pred_x_dot", pred_x_dot), ("ref_x_dot", ref_x_dot))
    B, T, _ = pred.shape
    valid = resolve_mask(mask, lengths, B, T, pred.device, min_samples=1)
    check_finite("pred_x_dot", pred, valid)
    check_finite("ref_x_dot", ref, valid)
    zero = torch.zeros((), dtype=pred.dtype, device=pred.device)
    one = torch.ones((), dtype=pred.dtype, device=pred.device)
    keep = valid.unsqueeze(-1)
    pred = torch.where(keep, pred, zero)
    ref = torch.where(keep, ref, zero)
    n_pred = torch.linalg.vector_norm(pred, dim=-1)
    n_ref = torch.linalg.vector_norm(ref, dim=-1)
    z_pred = n_pred <= eps
    z_ref = n_ref <= eps
    # Normalise first: no overflow in the product of norms, and no division by a zero norm.
    u = pred / torch.where(z_pred, one, n_pred).unsqueeze(-1)
    v = ref / torch.where(z_ref, one, n_ref).unsqueeze(-1)
    cos = (u * v).sum(-1).clamp(-1.0, 1.0)
    cos = torch.where(z_pred & z_ref, one, torch.where(z_pred | z_ref, zero, cos))
    return _masked_mean((1.0 - cos).abs(), valid)
