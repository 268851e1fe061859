"""The modulation matrix M = W D W^T of eqs 9-12 in closed form (NOTES sec. 4).

W(x) = [e_g, e_1, ..., e_{d-1}] is orthonormal with first column e_g = (x - g)/||x - g|| (eq. 11), so W^-1 = W^T,
and D = diag(d1, d, ..., d). Every later column of W only enters through W_{2:} W_{2:}^T = I - e_g e_g^T, hence

    M = d I + (d1 - d) e_g e_g^T,        M f = d f + (d1 - d) c e_g,   c = e_g^T f = [W^T f]_1.

No SVD or Gram-Schmidt completion is needed per step (the paper builds the other columns by Gram-Schmidt; the
result does not depend on that choice). The explicit W D W^T is kept in the tests as the reference.

At x = g the direction e_g is undefined; :func:`goal_direction` returns e_g = 0 there (so c = 0 and M f = d f).
The modulation policy (:mod:`lfd_torch.modulation.policy`) returns a zero velocity at x = g.

Notation (shapes): x, f, e_g (..., d); c, d1, d, r (...) broadcastable to the batch shape; M (..., d, d).
Units: x, g data units; f, M f units/s; e_g, D, M dimensionless.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

__all__ = ["GoalDirection", "goal_direction", "modulate", "modulation_matrix", "radial_component"]


class GoalDirection(NamedTuple):
    """Result of :func:`goal_direction`.

    Attributes:
        unit: (..., d) e_g = (x - g)/||x - g||, zero where x == g.
        distance: (...) ||x - g|| (data units).
    """

    unit: Tensor
    distance: Tensor


def goal_direction(x: Tensor, attractor: Tensor, *, dim: int = -1) -> GoalDirection:
    """:func:`goal_direction_unchecked` after checking x (..., d) and attractor (d,): real floating tensors of one
    dtype, finite and below the overflow magnitude (a typed error names the argument).

    With the vector axis last (``dim`` -1, the documented layout) the attractor must have shape exactly (d,): a
    (B, d) or (d, 1) attractor would broadcast into a different goal per row. Other ``dim`` values (feature-major
    points, the kernel's layout) keep the broadcasting attractor of :func:`goal_direction_unchecked`.

    Raises:
        ShapeMismatchError: not float tensors, dtypes or devices that differ, or an attractor that is not (d,).
        NonFiniteError: NaN, Inf or an overflowing magnitude in ``x`` or ``attractor``.
    """
    from lfd_torch.errors import ShapeMismatchError
    from lfd_torch.utils import check_tensor

    check_tensor(x, "x", min_ndim=1)
    check_tensor(attractor, "attractor", min_ndim=1, dtype=x.dtype, device=x.device)
    if dim not in (-1, x.ndim - 1):  # feature-major calls are the kernel's, unchecked
        return goal_direction_unchecked(x, attractor, dim=dim)
    if tuple(attractor.shape) != (x.shape[-1],):
        raise ShapeMismatchError(f"attractor must have shape (d,) = ({x.shape[-1]},) for x of shape "
                                 f"{tuple(x.shape)}, got {tuple(attractor.shape)}")  # fmt: skip
    return goal_direction_unchecked(x, attractor, dim=dim)


def goal_direction_unchecked(x: Tensor, attractor: Tensor, *, dim: int = -1) -> GoalDirection:
    """First column of W (eq. 11) and the distance to the goal.

    Args:
        x: (..., d) positions (or the vector axis at ``dim``, e.g. feature-major (d, n) with ``dim=0``).
        attractor: (d,) goal g (broadcast against ``x``; (d, 1) for feature-major points).
        dim: the vector axis of ``x``.

    Returns:
        :class:`GoalDirection` (unit vector zero at x = g, no NaN).
    """
    e = x - attractor
    r = torch.linalg.vector_norm(e, dim=dim) if dim in (-1, e.ndim - 1) else (e * e).sum(dim).sqrt()
    safe = torch.where(r > 0, r, torch.ones_like(r))
    unit = torch.where((r > 0).unsqueeze(dim), e / safe.unsqueeze(dim), torch.zeros_like(e))
    return GoalDirection(unit, r)


def _check_vectors(f: Tensor, unit: Tensor, dim: int = -1) -> None:
    """f and unit: float tensors without NaN/Inf, of one dtype and device (f's: the result's), of one vector length
    along ``dim``, broadcastable."""
    from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
    from lfd_torch.utils import check_int, check_tensor

    check_tensor(f, "f", min_ndim=1, bounded=False, shape_hint="(..., d)")
    check_tensor(unit, "unit", min_ndim=1, dtype=f.dtype, device=f.device, bounded=False, shape_hint="(..., d)")
    check_int(dim, "dim")
    if not (-f.ndim <= dim < f.ndim and -unit.ndim <= dim < unit.ndim):
        raise InvalidArgumentError(f"dim = {dim} is not an axis of f {tuple(f.shape)} and unit {tuple(unit.shape)}")
    if f.shape[dim] != unit.shape[dim]:
        raise ShapeMismatchError(f"unit has d = {unit.shape[dim]}, f has d = {f.shape[dim]} (shapes "
                                 f"{tuple(unit.shape)} and {tuple(f.shape)})")  # fmt: skip
    try:
        torch.broadcast_shapes(f.shape, unit.shape)
    except RuntimeError:
        raise ShapeMismatchError(f"unit of shape {tuple(unit.shape)} does not broadcast with f of shape "
                                 f"{tuple(f.shape)}") from None  # fmt: skip


def _check_eigenvalue(value: Tensor | float, name: str, batch: tuple[int, ...], like: Tensor) -> None:
    """An eigenvalue ``name``: a finite number, or a real tensor without NaN/Inf broadcastable to ``batch``."""
    from lfd_torch.errors import NonFiniteError, ShapeMismatchError
    from lfd_torch.utils import check_float

    if not isinstance(value, Tensor):
        check_float(value, name)
        return
    if value.is_complex() or value.dtype == torch.bool:
        raise ShapeMismatchError(f"{name} must be a real tensor or a number, got {value.dtype}")
    if value.device != like.device:
        raise ShapeMismatchError(f"{name} is on {value.device}, the vectors on {like.device}")
    try:
        torch.broadcast_shapes(value.shape, batch)
    except RuntimeError:
        raise ShapeMismatchError(f"{name} of shape {tuple(value.shape)} does not broadcast to the batch shape "
                                 f"{tuple(batch)}") from None  # fmt: skip
    if not bool(torch.isfinite(value).all()):
        raise NonFiniteError(f"{name} contains NaN or Inf")


def radial_component(f: Tensor, unit: Tensor, *, dim: int = -1) -> Tensor:
    """c = e_g^T f = [W^-1 f]_1, the component of ``f`` along e_g (units/s).

    Args:
        f: (..., d) velocities (vector axis ``dim``).
        unit: (..., d) e_g.
        dim: the vector axis.

    Returns:
        (...) tensor.

    Raises:
        ShapeMismatchError: not float tensors, dtypes or devices that differ, or d (or the batch shapes) that do not
            agree.
        NonFiniteError: NaN or Inf in ``f`` or ``unit``.
    """
    _check_vectors(f, unit, dim)
    return radial_component_unchecked(f, unit, dim=dim)


def radial_component_unchecked(f: Tensor, unit: Tensor, *, dim: int = -1) -> Tensor:
    """:func:`radial_component` without its argument checks (the modulation's hot path)."""
    return (f * unit).sum(dim)


def modulate(f: Tensor, unit: Tensor, d1: Tensor | float, d: Tensor | float) -> Tensor:
    """M f = W diag(d1, d, ..., d) W^T f = d f + (d1 - d) c e_g (closed form of eqs 9-10).

    Args:
        f: (..., d) velocities (units/s).
        unit: (..., d) e_g, unit norm (or zero at the goal).
        d1: (...) eigenvalue along e_g (dimensionless).
        d: (...) eigenvalue of the d - 1 directions orthogonal to e_g (dimensionless).

    Returns:
        (..., d) modulated velocities, dtype and device of ``f`` (``unit`` must share them; tensor eigenvalues are
        cast to that dtype).

    Raises:
        ShapeMismatchError: not float tensors, a ``unit`` of another dtype or device, or d (or the batch shapes)
            that do not agree.
        NonFiniteError, InvalidArgumentError: NaN or Inf in ``f``, ``unit``, ``d1`` or ``d`` (naming it).
    """
    _check_vectors(f, unit)
    batch = torch.broadcast_shapes(f.shape, unit.shape)[:-1]
    _check_eigenvalue(d1, "d1", batch, f)
    _check_eigenvalue(d, "d", batch, f)
    d1 = torch.as_tensor(d1, dtype=f.dtype, device=f.device)
    d = torch.as_tensor(d, dtype=f.dtype, device=f.device)
    c = radial_component_unchecked(f, unit)
    return d.unsqueeze(-1) * f + ((d1 - d) * c).unsqueeze(-1) * unit


def modulation_matrix(unit: Tensor, d1: Tensor | float, d: Tensor | float) -> Tensor:
    """The matrix M = d I + (d1 - d) e_g e_g^T (equal to W D W^T for any orthonormal completion of e_g).

    Args:
        unit: (..., d) e_g.
        d1: (...) eigenvalue along e_g.
        d: (...) eigenvalue orthogonal to e_g.

    Returns:
        (..., d, d) symmetric matrices.

    Raises:
        ShapeMismatchError: ``unit`` not a float (..., d) tensor, or ``d1`` / ``d`` not broadcastable to its batch.
        NonFiniteError, InvalidArgumentError: NaN or Inf in ``unit``, ``d1`` or ``d`` (naming it).
    """
    from lfd_torch.utils import check_tensor

    check_tensor(unit, "unit", min_ndim=1, bounded=False, shape_hint="(..., d)")
    _check_eigenvalue(d1, "d1", unit.shape[:-1], unit)
    _check_eigenvalue(d, "d", unit.shape[:-1], unit)
    d1 = torch.as_tensor(d1, dtype=unit.dtype, device=unit.device)
    d = torch.as_tensor(d, dtype=unit.dtype, device=unit.device)
    n = unit.shape[-1]
    eye = torch.eye(n, dtype=unit.dtype, device=unit.device)
    return d[..., None, None] * eye + (d1 - d)[..., None, None] * (unit.unsqueeze(-1) * unit.unsqueeze(-2))
