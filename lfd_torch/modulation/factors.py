"""Modulation factors of the large-scale (eq. 13) and small-scale (eqs 17-18) branches, in log space.

Large scale (x outside its subtask space A_m, i.e. log p(x|A_m) < log p(x|A_m-)):

    lambda_ls = -sgn(c) s,   s = max(min(lambda_limit, p(x|A_m-) / p(x|A_m)), 1) in [1, lambda_limit],

computed as s = exp(clamp(log p(x|A_m-) - log p(x|A_m), 0, log lambda_limit)), so that densities that underflow
(log p = -inf) are fine: own = -inf, other finite gives s = lambda_limit; both -inf gives s = 1 (no information).

Small scale (x inside A_m and H2(x) > H2_ref):

    lambda_ss = min(1, exp(H2_ref - H2(x))) in [0, 1],

which is 1 when H2(x) <= H2_ref (including H2 = H2_ref = +inf) and underflows to 0 far from the data.

Shapes: every argument is (...) and broadcastable; results have the broadcast shape and the dtype/device of the
first tensor argument. All factors are dimensionless.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError

__all__ = ["check_lambda_limit", "large_scale_factor", "large_scale_gain", "small_scale_factor"]


def check_lambda_limit(lambda_limit: float) -> float:
    """Validate lambda_limit (a finite number >= 1) and return it as a float.

    Raises:
        InvalidArgumentError: naming ``lambda_limit``.
    """
    if isinstance(lambda_limit, bool) or not isinstance(lambda_limit, (int, float)):
        raise InvalidArgumentError(f"lambda_limit must be a number >= 1, got {lambda_limit!r}")
    value = float(lambda_limit)
    if not math.isfinite(value) or value < 1.0:
        raise InvalidArgumentError(f"lambda_limit must be a finite number >= 1, got {lambda_limit!r}")
    return value


def large_scale_gain(log_p_own: Tensor, log_p_other: Tensor, lambda_limit: float) -> Tensor:
    """s = max(min(lambda_limit, p(x|A_m-)/p(x|A_m)), 1), the magnitude of eq. 13.

    Args:
        log_p_own: (...) log p(x|A_m).
        log_p_other: (...) log p(x|A_m-) (largest log density among the other subtask spaces).
        lambda_limit: maximum acceleration multiplier, >= 1.

    Returns:
        (...) gains in [1, lambda_limit].

    Raises:
        InvalidArgumentError: ``lambda_limit`` < 1, or a density that is not a real floating tensor.
        ShapeMismatchError: shapes that do not broadcast, or tensors on different devices.
        NonFiniteError: NaN in a log density (-inf and +inf are allowed).
    """
    limit = check_lambda_limit(lambda_limit)
    _check_log_densities(log_p_own=log_p_own, log_p_other=log_p_other)
    return large_scale_gain_unchecked(log_p_own, log_p_other.to(log_p_own.dtype), limit)


def _check_log_densities(**named: object) -> None:
    """Each argument a real floating tensor without NaN (+-inf allowed), all broadcastable, on one device."""
    shapes: list[torch.Size] = []
    first: tuple[str, Tensor] | None = None
    for name, t in named.items():
        if not isinstance(t, Tensor) or t.is_complex() or not t.is_floating_point():
            raise InvalidArgumentError(f"{name} must be a real floating tensor, got "
                                       f"{getattr(t, 'dtype', type(t).__name__)}")  # fmt: skip
        if first is not None and t.device != first[1].device:
            raise ShapeMismatchError(f"{name} is on {t.device}, {first[0]} on {first[1].device}")
        try:
            torch.broadcast_shapes(*shapes, t.shape)
        except RuntimeError:
            before = list(named)[: len(shapes)]
            raise ShapeMismatchError(f"{name} of shape {tuple(t.shape)} does not broadcast with {', '.join(before)} "
                                     f"of shape {tuple(torch.broadcast_shapes(*shapes))}") from None  # fmt: skip
        if bool(torch.isnan(t).any()):
            raise NonFiniteError(f"{name} contains NaN")
        shapes.append(t.shape)
        first = first or (name, t)


def large_scale_gain_unchecked(log_p_own: Tensor, log_p_other: Tensor, limit: float) -> Tensor:
    """:func:`large_scale_gain` without its argument checks (a checked ``limit`` as a float), for the hot path."""
    log_ratio = log_p_other - log_p_own
    log_ratio = torch.where(torch.isnan(log_ratio), torch.zeros_like(log_ratio), log_ratio)  # -inf - -inf
    return torch.exp(log_ratio.clamp(min=0.0, max=math.log(limit)))


def large_scale_factor(log_p_own: Tensor, log_p_other: Tensor, c: Tensor, lambda_limit: float) -> Tensor:
    """lambda_ls = -sgn(c) s of eq. 13 (literal: 0 where c = 0).

    Args:
        log_p_own: (...) log p(x|A_m).
        log_p_other: (...) log p(x|A_m-).
        c: (...) radial component e_g^T f (units/s).
        lambda_limit: maximum acceleration multiplier, >= 1.

    Returns:
        (...) signed factor; |lambda_ls| in [1, lambda_limit] where c != 0.

    Raises:
        InvalidArgumentError, ShapeMismatchError, NonFiniteError: as for :func:`large_scale_gain` (NaN in ``c`` too).
    """
    limit = check_lambda_limit(lambda_limit)
    _check_log_densities(log_p_own=log_p_own, log_p_other=log_p_other, c=c)
    dtype = log_p_own.dtype  # the first argument's (module docstring)
    return -torch.sign(c.to(dtype)) * large_scale_gain_unchecked(log_p_own, log_p_other.to(dtype), limit)


def small_scale_factor(h2: Tensor, h2_ref: Tensor | float) -> Tensor:
    """lambda_ss = min(1, exp(H2_ref - H2(x))) of eq. 18.

    Args:
        h2: (...) entropy H2(x).
        h2_ref: (...) or scalar threshold H2(x_r), a tensor broadcastable with ``h2`` (cast to its dtype) or a
            number; +-inf is allowed, NaN is not.

    Returns:
        (...) factors in [0, 1]; exactly 1 where h2 <= h2_ref.

    Raises:
        InvalidArgumentError: ``h2`` or ``h2_ref`` not a real floating tensor (or, for ``h2_ref``, a number), or a
            NaN number ``h2_ref``.
        ShapeMismatchError: shapes that do not broadcast, or tensors on different devices.
        NonFiniteError: NaN in ``h2`` or in a tensor ``h2_ref``.
    """
    if isinstance(h2_ref, Tensor):
        _check_log_densities(h2=h2, h2_ref=h2_ref)
    else:
        from lfd_torch.utils import check_float

        _check_log_densities(h2=h2)
        check_float(h2_ref, "h2_ref", allow_inf=True)
    return small_scale_factor_unchecked(h2, h2_ref)


def small_scale_factor_unchecked(h2: Tensor, h2_ref: Tensor | float) -> Tensor:
    """:func:`small_scale_factor` without its argument checks (no device sync), for the modulation's hot path."""
    ref = torch.as_tensor(h2_ref, dtype=h2.dtype, device=h2.device)
    inside = h2 <= ref
    gap = torch.where(inside, torch.zeros_like(h2), ref - h2)  # <= 0, never inf - inf
    return torch.where(inside, torch.ones_like(gap), torch.exp(gap))
