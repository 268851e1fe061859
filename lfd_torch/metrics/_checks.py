"""Input checks shared by the metrics (private).

Notation: B trajectories, T padded samples, d state dimensions; a valid-sample mask is (B, T) bool.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.utils import check_tensor, safe_magnitude

__all__ = ["as_trajectories", "check_finite", "check_lengths", "resolve_mask"]


def as_trajectories(*named: tuple[str, Tensor], min_dim: int = 1) -> tuple[Tensor, ...]:
    """Check that tensors are (B, T, d) with equal shapes and promote them to a common floating dtype.

    Args:
        named: (name, tensor) pairs, each tensor (B, T, d).
        min_dim: smallest admissible state dimension d.

    Returns:
        The tensors, cast to their promoted floating dtype (float32 with float64 gives float64).

    Raises:
        ShapeMismatchError: not a tensor, not 3-D, a dtype outside :data:`lfd_torch.utils.FLOAT_DTYPES` (float32,
            float64), shapes or devices that differ, or d below ``min_dim``.
    """
    dtype = None
    for name, x in named:
        # a tensor of 3 dimensions in FLOAT_DTYPES (float16 / bfloat16 would overflow the squared distances);
        # finiteness is checked on the valid samples only (check_finite)
        check_tensor(x, name, ndim=3, finite=False, shape_hint="(B, T, d)")
        dtype = x.dtype if dtype is None else torch.promote_types(dtype, x.dtype)
    (first_name, first), *rest = named
    for name, x in rest:
        if x.shape != first.shape:
            raise ShapeMismatchError(f"{name} has shape {tuple(x.shape)}, {first_name} has {tuple(first.shape)}")
        if x.device != first.device:
            raise ShapeMismatchError(f"{name} is on {x.device}, {first_name} on {first.device}")
    if first.shape[-1] < min_dim:
        raise ShapeMismatchError(f"state dimension must be at least {min_dim}, got {first.shape[-1]}")
    return tuple(x.to(dtype) for _, x in named)


def check_lengths(lengths: Tensor | None, B: int, T: int, device: torch.device, *, name: str = "lengths") -> Tensor:
    """Validate valid-sample counts: (B,) integers in [0, T]; None means all T samples are valid.

    Returns:
        (B,) int64 on ``device``.
    """
    if lengths is None:
        return torch.full((B,), T, dtype=torch.long, device=device)
    try:
        lengths = torch.as_tensor(lengths, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InvalidArgumentError(f"{name} must be a (B,) integer tensor, got {lengths!r}") from exc
    if lengths.is_floating_point() or lengths.is_complex() or lengths.dtype == torch.bool:
        raise InvalidArgumentError(f"{name} must be an integer tensor, got {lengths.dtype}")
    if lengths.shape != (B,):
        raise ShapeMismatchError(f"{name} must have shape ({B},), got {tuple(lengths.shape)}")
    lengths = lengths.to(torch.long)
    if (lengths > T).any():
        i = int(torch.nonzero(lengths > T)[0])
        raise ShapeMismatchError(f"{name}: {int(lengths[i])} exceeds the padded length {T}", i)
    if (lengths < 0).any():
        i = int(torch.nonzero(lengths < 0)[0])
        raise TooFewSamplesError(f"{name}: negative length {int(lengths[i])}", i)
    return lengths


def resolve_mask(
    mask: Tensor | None, lengths: Tensor | None, B: int, T: int, device: torch.device, *, min_samples: int
) -> Tensor:
    """The (B, T) bool mask of valid samples, from ``mask``, from ``lengths`` or (neither) all True.

    Raises:
        InvalidArgumentError: both ``mask`` and ``lengths`` given, or a mask that is not bool.
        ShapeMismatchError: a mask that is not (B, T), or a length above T.
        TooFewSamplesError: a trajectory with fewer than ``min_samples`` valid samples.
    """
    if mask is not None and lengths is not None:
        raise InvalidArgumentError("give either mask or lengths, not both")
    mask_given = mask is not None
    if mask is None:
        n = check_lengths(lengths, B, T, device)
        mask = torch.arange(T, device=device).unsqueeze(0) < n.unsqueeze(1)
    else:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
            raise InvalidArgumentError("mask must be a bool tensor of shape (B, T)")
        if mask.shape != (B, T):
            raise ShapeMismatchError(f"mask must have shape ({B}, {T}), got {tuple(mask.shape)}")
        mask = mask.to(device)
    counts = mask.sum(1)
    if (counts < min_samples).any():
        i = int(torch.nonzero(counts < min_samples)[0])
        source = "mask" if mask_given else ("lengths" if lengths is not None else "the padded length T")
        raise TooFewSamplesError(f"has {int(counts[i])} valid samples (from {source}), at least {min_samples} are "
                                 "needed", i)  # fmt: skip
    return mask


def check_finite(name: str, x: Tensor, mask: Tensor) -> None:
    """Raise :class:`NonFiniteError` if ``x`` (B, T, d) holds NaN, Inf or a magnitude above
    :func:`lfd_torch.utils.safe_magnitude` (its squares overflow) at a sample where ``mask`` (B, T) is True."""
    bad = (~(x.abs() <= safe_magnitude(x.dtype))).any(-1) & mask
    if bad.any():
        i, t = (int(v) for v in torch.nonzero(bad)[0])
        what = "NaN" if torch.isnan(x[i, t]).any() else ("Inf" if torch.isinf(x[i, t]).any() else "a magnitude "
                                                          f"above {safe_magnitude(x.dtype):.3g} (it overflows)")
        raise NonFiniteError(f"{name} contains {what} at sample {t}", i)
