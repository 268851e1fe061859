"""Swept-area metric E3 (paper Sec. V-A): the area between a rollout and its reference trajectory.

Notation:
    B          number of trajectories
    T          padded number of samples
    d          state dimension (>= 2)
    rollout    (B, T, d)  x_t, the rollout started at x_ref,0 and sampled with the demonstration's time step
    reference  (B, T, d)  x_ref,t, the demonstration, data units (LASA: mm)
    mask       (B, T)     True on valid samples (or ``lengths`` (B,) for prefix-valid rows)

For each t with samples t and t+1 both valid (t = 0..T_i-2 for a trajectory with T_i valid samples: T_i-1
quadrilaterals) the quadrilateral Q_t = (x_ref,t, x_ref,t+1, x_t+1, x_t) is formed and its area measured: in 2-D the
area of the region it encloses (a rollout crossing the reference within a step forms a bow-tie, whose two lobes add
up), in d >= 3 the two triangles split along the diagonal x_ref,t -> x_t+1 (see :func:`quadrilateral_areas`).
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from lfd_torch.errors import ShapeMismatchError, TooFewSamplesError, UnknownNameError
from lfd_torch.metrics._checks import as_trajectories, check_finite, resolve_mask
from lfd_torch.utils import check_tensor

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

    Raises:
        ShapeMismatchError: not float tensors, d < 2, or shapes that do not agree (broadcast, same d).
        NonFiniteError: NaN or Inf in ``u`` or ``v``.
    """
    _check_vertices(("u", u), ("v", v))
    return _triangle_areas(u, v)


def _check_vertices(*named: tuple[str, Tensor]) -> None:
    """(..., d) float tensors without NaN/Inf, d >= 2 and the same in all, broadcastable batch shapes."""
    for name, x in named:
        check_tensor(x, name, min_ndim=1, bounded=False, shape_hint="(..., d)")
        if x.shape[-1] < 2:
            raise ShapeMismatchError(f"{name} has d = {x.shape[-1]}; areas need d >= 2 (shape {tuple(x.shape)})")
    (first, x0), *rest = named
    for name, x in rest:
        if x.shape[-1] != x0.shape[-1]:
            raise ShapeMismatchError(f"{name} has d = {x.shape[-1]}, {first} has d = {x0.shape[-1]}")
    try:
        torch.broadcast_shapes(*(x.shape for _, x in named))
    except RuntimeError:
        raise ShapeMismatchError(f"shapes of {', '.join(n for n, _ in named)} do not broadcast: "
                                 f"{[tuple(x.shape) for _, x in named]}") from None  # fmt: skip


def _triangle_areas(u: Tensor, v: Tensor) -> Tensor:
    """:func:`triangle_areas` without its argument checks."""
    d = u.shape[-1]
    if d == 2:
        return 0.5 * (u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]).abs()
    i, j = torch.triu_indices(d, d, offset=1, device=u.device)
    minors = u[..., i] * v[..., j] - u[..., j] * v[..., i]
    return 0.5 * torch.linalg.vector_norm(minors, dim=-1)


def _cross2(u: Tensor, v: Tensor) -> Tensor:
    """z-component of the 2-D cross product u x v, shapes (..., 2) -> (...)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _region_areas_2d(p0: Tensor, p1: Tensor, p2: Tensor, p3: Tensor) -> Tensor:
    """Area of the plane region enclosed by the closed polygon p0 -> p1 -> p2 -> p3 -> p0 (see quadrilateral_areas)."""
    e0, e1, e2, e3 = p1 - p0, p2 - p1, p3 - p2, p0 - p3
    # twice the signed corner triangles, c_k = 2 T(p_{k-1}, p_k, p_{k+1}) = e_{k-1} x e_k
    c0, c1, c2, c3 = _cross2(e3, e0), _cross2(e0, e1), _cross2(e1, e2), _cross2(e2, e3)
    # opposite strict signs from comparisons, not products: a product of two tiny corners can underflow to 0
    pos0, pos1, pos2, pos3 = c0 > 0, c1 > 0, c2 > 0, c3 > 0
    neg0, neg1, neg2, neg3 = c0 < 0, c1 < 0, c2 < 0, c3 < 0
    cross_01_23 = ((pos0 & neg1) | (neg0 & pos1)) & ((pos2 & neg3) | (neg2 & pos3))  # edge p0p1 crosses p2p3
    cross_12_30 = ((pos0 & neg3) | (neg0 & pos3)) & ((pos1 & neg2) | (neg1 & pos2))  # edge p1p2 crosses p3p0
    crossing = cross_01_23 | cross_12_30
    # Lobe sums (see quadrilateral_areas) as 2 A = |c0| w + |r| (1 - w) with w = q / (q - c2):
    #   p0p1 crosses p2p3: (q, r) = (c3, c1), w = mu = |c3| / (|c2| + |c3|);
    #   p1p2 crosses p3p0: (q, r) = (c1, c3), w = |c1| / (|c1| + |c2|) = |c1| / (|c0| + |c3|) as c0 - c3 = c1 - c2,
    #   so that |c0| w + |c3| (1 - w) = lam |c1| + (1 - lam) |c2|.
    # q and c2 have opposite signs there: w lies in [0, 1] without cancellation, and no product of two corners is
    # formed (it could underflow for tiny quadrilaterals).
    q = torch.where(cross_01_23, c3, c1)
    r = torch.where(cross_01_23, c1, c3)
    w = q / torch.where(crossing, q - c2, torch.ones((), dtype=c0.dtype, device=c0.device))  # q - c2 != 0 there
    lobes = c0.abs() * w + r.abs() * (1.0 - w)
    shoelace = (c1 + c3).abs()  # = |c0 + c2|, twice the area of a simple quadrilateral
    return 0.5 * torch.where(crossing, lobes, shoelace)


def quadrilateral_areas(p0: Tensor, p1: Tensor, p2: Tensor, p3: Tensor) -> Tensor:
    """Areas of the quadrilaterals (p0, p1, p2, p3), vertices in this order (edges p0p1, p1p2, p2p3, p3p0).

    d = 2: the area of the plane region enclosed by the closed polygon, i.e. the integral of |winding number|:

    * simple quadrilateral (convex or concave): |shoelace| = 0.5 |c1 + c3| (= 0.5 |(p2 - p0) x (p3 - p1)|);
    * self-intersecting ("bow-tie") quadrilateral, where edge p0p1 crosses edge p2p3 or edge p1p2 crosses edge
      p3p0 at a point X: the sum of the two triangular lobes' areas, split at X. (The shoelace would give the
      difference of the lobes, so that a rollout crossing its reference within a step would score 0.)

      With twice the signed corner triangles c_k = (p_k - p_{k-1}) x (p_{k+1} - p_k) (indices mod 4; the
      shoelace is c0 + c2 = c1 + c3): p0p1 and p2p3 cross iff c0, c1 have opposite signs and c2, c3 have
      opposite signs; they meet at X = p0 + mu (p1 - p0), mu = |c3| / (|c2| + |c3|), and the area is
      0.5 (mu |c0| + (1 - mu) |c1|). p1p2 and p3p0 cross iff c0, c3 and c1, c2 have opposite signs; they meet at
      X = p1 + lam (p2 - p1), lam = |c0| / (|c0| + |c3|), and the area is 0.5 (lam |c1| + (1 - lam) |c2|). At
      most one pair of opposite edges can cross. Both lobe formulas reduce to |shoelace| when a corner triangle
      vanishes, so the area is continuous across touching and collinear configurations, and their denominators
      are never 0 where they are used: degenerate quadrilaterals (collinear vertices, touching at a
      vertex, zero-length edges) give finite values.

    d >= 3: the sum of the triangle areas (p0, p1, p2) and (p0, p2, p3) (:func:`triangle_areas`), i.e. the
    quadrilateral split along the diagonal p0p2 (NOTES.md: "use the two triangles"); it is defined for non-planar
    quadrilaterals, where there is no enclosed plane region. For a *planar* quadrilateral it equals
    |T(p0,p1,p2)| + |T(p0,p2,p3)|, which is never below the 2-D area above and equals it exactly when the diagonal
    p0p2 lies inside the quadrilateral: for every convex quadrilateral and for a concave one whose reflex vertex is
    p0 or p2. A concave quadrilateral with its reflex vertex at p1 (or p3) gives the 2-D area plus twice the notch
    triangle |T(p0,p1,p2)| (or |T(p0,p2,p3)|); a bow-tie gives at least the lobe sum, in general more (each
    triangle contains one lobe and some outside area; the unit-square bow-tie gives 1 against 0.5).

    Args:
        p0, p1, p2, p3: (..., d) vertices, data units.

    Returns:
        (...) areas in squared data units.

    Raises:
        ShapeMismatchError: not float tensors, d < 2, or shapes that do not agree (broadcast, same d).
        NonFiniteError: NaN or Inf in a vertex.
    """
    _check_vertices(("p0", p0), ("p1", p1), ("p2", p2), ("p3", p3))
    return _quadrilateral_areas(p0, p1, p2, p3)


def _quadrilateral_areas(p0: Tensor, p1: Tensor, p2: Tensor, p3: Tensor) -> Tensor:
    """:func:`quadrilateral_areas` without its argument checks."""
    if p0.shape[-1] == 2:
        return _region_areas_2d(p0, p1, p2, p3)
    e2 = p2 - p0
    return _triangle_areas(p1 - p0, e2) + _triangle_areas(e2, p3 - p0)


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
    divides by T_i - 1. Areas follow :func:`quadrilateral_areas` (enclosed region in 2-D, bow-tie lobes added, not
    cancelled; two triangles in d >= 3).
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
    areas = _quadrilateral_areas(x_ref[:, :-1], x_ref[:, 1:], x[:, 1:], x[:, :-1])  # (B, T-1), checked above
    total = torch.where(quad_valid, areas, zero).sum(1)
    if reduction == "sum":
        return total
    return total / n_quads.to(total.dtype)
