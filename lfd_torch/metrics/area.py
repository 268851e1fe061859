"""Swept-area metric E3 (paper Sec. V-A): the area between a rollout and its reference trajectory.

Notation:
    B          number of trajectories
    T          padded number of samples
    d          state dimension (>= 2)
    rollout    (B, T, d)  x_t, the rollout started at x_ref,0 and sampled with the demonstration's time step
    reference  (B, T, d)  x_ref,t, the demonstration, data units (LASA: mm)
    mask       (B, T)     True on valid samples (or ``lengths`` (B,) for prefix-valid rows)

For each t with samples t and t+1 both valid (t = 0..T_i-2 for a trajectory with T_i valid samples: T_i-1
quadrilaterals) the quadrilateral Q_t = (x_ref,t, x_ref,t+1, x_t+1, x_t) is formed and its area measured.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from lfd_torch.errors import TooFewSamplesError, UnknownNameError
from lfd_torch.metrics._checks import as_trajectories, check_finite, resolve_mask

__all__ = ["SWEPT_AREA_REDUCTIONS", "quadrilateral_areas", "swept_area", "triangle_areas"]

SWEPT_AREA_REDUCTIONS = ("mean", "sum")


def triangle_areas(u: Tensor, v: Tensor) -> Tensor:
    """Areas of the triangles spanned by edge vectors ``u`` and ``v`` in any dimension d >= 2.

    The area is 0.5 * sqrt(det G) with the Gram determinant det G = |u|^2 |v|^2 - (u.v)^2. It is evaluated
    through Lagrange's identity, det G = sum_{i<j} (u_i v_j - u_j v_i)^2, which is the same number but free of
    the cancellation that the difference form suffers for thin triangles (a rollout close to its reference),
    and is never negative.

    Args:
        u: (..., d) first edge vector, data units.
        v: (..., d) second edge vector, same shape.

    Returns:
        (...) triangle areas in squared data units.
    """
    d = u.shape[-1]
    if d == 2:
        return 0.5 * (u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]).abs()
    i, j = torch.triu_indices(d, d, offset=1, device=u.device)
    minors = u[..., i] * v[..., j] - u[..., j] * v[..., i]
    return 0.5 * torch.linalg.vector_norm(minors, dim=-1)


def quadrilateral_areas(p0: Tensor, p1: Tensor, p2: Tensor, p3: Tensor) -> Tensor:
    """Areas of the quadrilaterals (p0, p1, p2, p3), vertices in this order.

    d = 2: the shoelace formula, i.e. the absolute value of the signed polygon area,
    0.5 * |(p2 - p0) x (p3 - p1)|. For a self-intersecting ("bow-tie") quadrilateral this is the difference of the
    two lobes' areas, as the shoelace formula gives. d >= 3: the sum of the triangle areas (p0, p1, p2) and
    (p0, p2, p3) (:func:`triangle_areas`); for a planar convex quadrilateral it equals the shoelace area.

    Args:
        p0, p1, p2, p3: (..., d) vertices, data units.

    Returns:
        (...) areas in squared data units.
    """
    if p0.shape[-1] == 2:
        a = p2 - p0
        b = p3 - p1
        return 0.5 * (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]).abs()
    e2 = p2 - p0
    return triangle_areas(p1 - p0, e2) + triangle_areas(e2, p3 - p0)


def swept_area(
    rollout: Tensor,
    reference: Tensor,
    mask: Tensor | None = None,
    *,
    lengths: Tensor | None = None,
    reduction: Literal["mean", "sum"] = "mean",
) -> Tensor:
    """Swept-area error E3 per trajectory: mean (or sum) of the quadrilateral areas between rollout and reference.

    Quadrilateral t is (x_ref,t, x_ref,t+1, x_t+1, x_t); it counts when samples t and t+1 are both valid, so a
    prefix-valid trajectory with T_i samples contributes T_i - 1 quadrilaterals (t = 0..T_i-2) and ``"mean"``
    divides by T_i - 1. Areas follow :func:`quadrilateral_areas` (shoelace in 2-D, two triangles in d >= 3).
    The two inputs are paired sample by sample: a rollout that stopped early must be padded (e.g. with its last
    position) to the reference's time grid by the caller.

    Args:
        rollout: (B, T, d) rollout positions x_t, data units.
        reference: (B, T, d) reference positions x_ref,t, same units.
        mask: optional (B, T) bool, True on valid samples; padded samples may hold any value (even NaN).
        lengths: optional (B,) valid-sample counts (prefix rows) instead of ``mask``.
        reduction: ``"mean"`` (the paper's E3) or ``"sum"`` (total area).

    Returns:
        (B,) area per trajectory in squared data units (LASA: mm^2).

    Raises:
        ShapeMismatchError: inputs not (B, T, d) of equal shape, d < 2, or a bad mask / lengths shape.
        NonFiniteError: NaN or Inf at a valid sample.
        TooFewSamplesError: a trajectory without a pair of consecutive valid samples (fewer than 2 samples).
        UnknownNameError: an unknown ``reduction``.
    """
    if reduction not in SWEPT_AREA_REDUCTIONS:
        raise UnknownNameError("swept-area reduction", reduction, SWEPT_AREA_REDUCTIONS)
    x, x_ref = as_trajectories(("rollout", rollout), ("reference", reference), min_dim=2)
    B, T, _ = x.shape
    valid = resolve_mask(mask, lengths, B, T, x.device, min_samples=2)
    check_finite("rollout", x, valid)
    check_finite("reference", x_ref, valid)
    quad_valid = valid[:, :-1] & valid[:, 1:]  # (B, T-1)
    n_quads = quad_valid.sum(1)
    if (n_quads < 1).any():
        i = int(torch.nonzero(n_quads < 1)[0])
        raise TooFewSamplesError("has no two consecutive valid samples, so no quadrilateral", i)
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    keep = valid.unsqueeze(-1)
    x = torch.where(keep, x, zero)
    x_ref = torch.where(keep, x_ref, zero)
    areas = quadrilateral_areas(x_ref[:, :-1], x_ref[:, 1:], x[:, 1:], x[:, :-1])  # (B, T-1)
    total = torch.where(quad_valid, areas, zero).sum(1)
    if reduction == "sum":
        return total
    return total / n_quads.to(total.dtype)
