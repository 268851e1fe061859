"""Aggregation of per-trajectory metric values over a set of trajectories.

Notation:
    B        number of trajectories
    values   (B,)  per-trajectory values of a metric that is a mean over terms (samples or quadrilaterals)
    counts   (B,)  number of terms behind each value (T_i valid samples for E1/E2, T_i - 1 for E3)
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from lfd_torch.utils import check_tensor
from lfd_torch.errors import InvalidDemoError, NonFiniteError, ShapeMismatchError, TooFewSamplesError, UnknownNameError

__all__ = ["AGGREGATE_KINDS", "aggregate"]

AGGREGATE_KINDS = ("mean", "rms")


def aggregate(
    values: Tensor, counts: Tensor | None = None, *, kind: Literal["mean", "rms"] = "mean"
) -> Tensor:
    """Combine per-trajectory metric values into one value for the set.

    With ``counts`` None every trajectory weighs the same (mean over i of the per-trajectory means). With
    ``counts`` the result is the pooled mean over all terms of all trajectories, sum_i n_i v_i / sum_i n_i: this is
    the paper's "mean over i and t" for E1/E2 (n_i = T_i) and E3 (n_i = T_i - 1). ``kind="rms"`` pools values
    that are themselves root-mean-squares (``velocity_error(..., kind="rms")``): sqrt(sum_i n_i v_i^2 / sum_i n_i),
    the RMS over all terms of the set.

    Args:
        values: (B,) per-trajectory values.
        counts: optional (B,) non-negative term counts (integer or floating), not all zero.
        kind: ``"mean"`` or ``"rms"``.

    Returns:
        () scalar tensor, dtype of ``values``.

    Raises:
        ShapeMismatchError: ``values`` not 1-D or ``counts`` of another shape.
        TooFewSamplesError: no value, or counts summing to zero.
        NonFiniteError: a non-finite value with a positive weight.
        InvalidArgumentError: negative counts, or (``kind="rms"``) a negative value with a positive weight.
        UnknownNameError: an unknown ``kind``.
    """
    if kind not in AGGREGATE_KINDS:
        raise UnknownNameError("aggregate kind", kind, AGGREGATE_KINDS)
    check_tensor(values, "values", ndim=1, finite=False, shape_hint="(B,)")
    if values.numel() == 0:
        raise TooFewSamplesError("values is empty: nothing to aggregate")
    if counts is None:
        w = torch.ones_like(values)
    else:
        try:
            counts = torch.as_tensor(counts, device=values.device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ShapeMismatchError(f"counts must be a (B,) tensor, got {counts!r}") from exc
        if counts.is_complex() or counts.dtype == torch.bool:
            raise ShapeMismatchError(f"counts must be a real (B,) tensor, got {counts.dtype}")
        if counts.shape != values.shape:
            raise ShapeMismatchError(f"counts have shape {tuple(counts.shape)}, values {tuple(values.shape)}")
        w = counts.to(values.dtype)
        if (w < 0).any():
            raise InvalidDemoError("counts must be non-negative", int(torch.nonzero(w < 0)[0]))
        if not bool(torch.isfinite(w).all()):
            raise NonFiniteError("counts contain NaN or Inf")
        if not w.sum() > 0:
            raise TooFewSamplesError("counts sum to zero")
    bad = ~torch.isfinite(values) & (w > 0)
    if bad.any():
        raise NonFiniteError("values: a value with a positive weight is not finite", int(torch.nonzero(bad)[0]))
    if kind == "rms" and ((values < 0) & (w > 0)).any():  # an RMS is >= 0: a negative one is not an RMS value
        i = int(torch.nonzero((values < 0) & (w > 0))[0])
        raise InvalidDemoError(f"values: kind='rms' pools root-mean-squares, which are >= 0; got "
                               f"{float(values[i])}", i)  # fmt: skip
    x = values.square() if kind == "rms" else values
    zero = torch.zeros((), dtype=values.dtype, device=values.device)
    pooled = torch.where(w > 0, w * x, zero).sum() / w.sum()
    return pooled.sqrt() if kind == "rms" else pooled
