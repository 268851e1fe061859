"""Quadratic Renyi entropy of a primitive's velocity mixture (paper Sec. IV-B, eqs 14-16; NOTES sec. 4).

At a position x, component k of a GMM-scheduled primitive predicts the velocity

    u | x, k ~ N(mu_k(x), S_k),   mu_k(x) = A_k x + b_k = A_k (x - g),

and is weighted by w_k(x) = pi_k N(x; mu_k^x, Sigma_k^x) (the joint density of the position GMM, NOT the
posterior gamma_k(x): NOTES 4b). The quadratic Renyi entropy of the unnormalised mixture sum_k w_k N(u; mu_k, S_k)
is (eq. 15, with the product of Gaussians written in closed form)

    H2(x) = -log sum_ij w_i(x) w_j(x) N(mu_i(x); mu_j(x), S_i + S_j).

Two corrections to the printed eq. 16 (NOTES sec. 4, followed here where it disagrees with the paper):
  (a) the determinant term is log(|S_i^-1 + S_j^-1| / (|S_i^-1| |S_j^-1|)) = log|S_i + S_j|, a *product* in the
      denominator (the paper prints a sum). The form above is exactly eq. 16 with that fix, because
      mu_i^T S_i^-1 mu_i + mu_j^T S_j^-1 mu_j - mu_ij^T S_ij^-1 mu_ij = (mu_i - mu_j)^T (S_i + S_j)^-1 (mu_i - mu_j).
  (b) the weights are not normalised over k. With Z(x) = sum_k w_k(x) = p(x) and q the normalised mixture,
      H2(x) = -log(Z^2 E_{u~q}[q(u)]) = H2[q] - 2 log p(x): low on the data and growing without bound away from it
      (quadratically in the distance), as Fig. 5 of the paper shows; the normalised H2[q] alone stays bounded.

Choice of S_k: the primitive's ``velocity_covariances`` (the responsibility-weighted covariance of the velocity
residual x_dot - A_k (x - g) of component k on the training data, shrunk towards the pooled residual covariance;
see :func:`lfd_torch.ds.residual_velocity_covariances`). The paper does not say which velocity covariance it uses;
this is the covariance a GMR over (x, x_dot) would give for the conditional velocity of component k around its
linear mean. Pass ``velocity_covariances=`` to override it (e.g. to use an isotropic S_k = s^2 I); a primitive
without the attribute needs the override.

Numerics: everything is in log space (``torch.logsumexp`` over the K^2 pairs), in the dtype and on the device of
``x``. Far from the data every exponent is a large negative number, so H2 is finite and large (about 1e10..1e13 at
1e6 data units from LASA-sized data, in float32 and float64), never NaN or Inf. It reaches +inf only once the
squared Mahalanobis distances themselves overflow the dtype (beyond ~1e19 units from the data in float32).

Notation (shapes):
    K components, d state dimension, batch shape (...)
    x                       (..., d)        positions (data units, e.g. mm)
    log_weights             (..., K)        log w_k(x) = log pi_k + log N(x; mu_k^x, Sigma_k^x) (log 1/units^d)
    means                   (..., K, d)     mu_k(x) = A_k (x - g) (units/s)
    covariances             (K, d, d)       S_k (units/s)^2, or broadcastable (..., K, d, d)
    H2                      (...)           dimensionless (log of a density in velocity and position space)
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch
from torch import Tensor

from lfd_torch.ds.primitive import check_velocity_covariances
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.utils import check_tensor

__all__ = [
    "VelocityMixture",
    "mixture_renyi_entropy",
    "pair_factors",
    "pairwise_log_overlap",
    "reference_entropy",
    "renyi_entropy",
    "velocity_mixture",
]


class VelocityMixture(NamedTuple):
    """The unnormalised Gaussian mixture over velocities that a primitive predicts at x.

    Attributes:
        log_weights: (..., K) log w_k(x) (not normalised over k).
        means: (..., K, d) mu_k(x) = A_k (x - g), units/s.
        covariances: (K, d, d) S_k, (units/s)^2.
    """

    log_weights: Tensor
    means: Tensor
    covariances: Tensor


def _check_positions(primitive: Any, x: Tensor, name: str = "x") -> None:
    d = primitive.attractor.shape[-1]
    if not isinstance(x, Tensor) or x.ndim == 0 or x.shape[-1] != d:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ShapeMismatchError(f"{name} must have shape (..., {d}), got {shape}")
    if x.dtype != primitive.attractor.dtype or x.device != primitive.attractor.device:
        raise ShapeMismatchError(
            f"{name} is {x.dtype} on {x.device}, the primitive is {primitive.attractor.dtype} on "
            f"{primitive.attractor.device}; convert one with .to(dtype=..., device=...)"
        )
    if not torch.isfinite(x).all():
        raise NonFiniteError(f"{name} contains NaN or Inf")


def _check_velocity_covariances(S: Tensor, x: Tensor) -> None:
    """An override S_k of shape (K, d, d) (checked by the caller) validated as the
    :class:`~lfd_torch.ds.StablePrimitive` constructor validates its ``velocity_covariances``: the dtype and
    device of ``x`` (the primitive's), finite, symmetric (``allclose`` to its transpose, rtol 1e-6) and positive
    definite (smallest eigenvalue of the symmetric part > 0, in float64).

    Raises:
        ShapeMismatchError: another dtype or device; not symmetric, or not positive definite (naming
            ``velocity_covariances``). NonFiniteError: NaN or Inf.
    """
    check_tensor(S, "velocity_covariances", dtype=x.dtype, device=x.device, bounded=False, shape_hint="(K, d, d)")
    check_velocity_covariances(S)


def velocity_mixture(primitive: Any, x: Tensor, *, velocity_covariances: Tensor | None = None) -> VelocityMixture:
    """The velocity mixture of ``primitive`` at ``x`` (module docstring).

    Args:
        primitive: a :class:`~lfd_torch.ds.StablePrimitive` (or any object with ``gmm``, ``A``, ``attractor`` and,
            unless overridden, ``velocity_covariances``).
        x: (..., d) positions, same dtype and device as the primitive.
        velocity_covariances: optional (K, d, d) S_k replacing ``primitive.velocity_covariances``: symmetric
            positive definite, finite, in the dtype and on the device of ``x`` (checked as the primitive's
            constructor checks its own).

    Returns:
        :class:`VelocityMixture` with (..., K) log weights, (..., K, d) means and (K, d, d) covariances.

    Raises:
        ShapeMismatchError: ``x`` or ``velocity_covariances`` of the wrong shape, dtype or device, or
            ``velocity_covariances`` that is not symmetric positive definite.
        NonFiniteError: NaN or Inf in ``x`` or ``velocity_covariances``.
        InvalidArgumentError: ``primitive`` is not a primitive, or it has no velocity covariances and none are given.
    """
    if not all(isinstance(getattr(primitive, a, None), Tensor) for a in ("attractor", "A")) \
            or not hasattr(primitive, "gmm"):  # fmt: skip
        raise InvalidArgumentError(f"primitive must be a StablePrimitive (with gmm, A and attractor), got "
                                   f"{type(primitive).__name__}")  # fmt: skip
    _check_positions(primitive, x)
    K, d = primitive.A.shape[0], primitive.A.shape[-1]
    S = velocity_covariances
    if S is None:
        S = getattr(primitive, "velocity_covariances", None)
        if S is None:
            raise InvalidArgumentError(
                "velocity_covariances: the primitive has no per-component velocity covariances; pass them explicitly"
            )
    if not isinstance(S, Tensor) or tuple(S.shape) != (K, d, d):
        shape = tuple(S.shape) if isinstance(S, Tensor) else type(S).__name__
        raise ShapeMismatchError(f"velocity_covariances must have shape {(K, d, d)}, got {shape}")
    if velocity_covariances is not None:  # the primitive's own S_k were validated by its constructor
        _check_velocity_covariances(S, x)
    S = S.to(dtype=x.dtype, device=x.device)
    log_w = primitive.gmm.log_prob_components(x)  # (..., K): log pi_k + log N(x; mu_k^x, Sigma_k^x)
    means = torch.einsum("kij,...j->...ki", primitive.A, x - primitive.attractor)
    return VelocityMixture(log_w, means, S)


def pair_factors(covariances: Tensor) -> tuple[Tensor, Tensor]:
    """Factors of the pairwise overlaps that do not depend on the means: L_ij^-1 and 0.5 log|S_i + S_j|.

    Args:
        covariances: (K, d, d) or broadcastable (..., K, d, d) symmetric positive-definite covariances S_k.

    Returns:
        (..., K, K, d, d) inverse lower Cholesky factors of S_i + S_j and (..., K, K) half log-determinants.

    Raises:
        ShapeMismatchError: ``covariances`` not a float (..., K, d, d) tensor.
        NonFiniteError: NaN or Inf in ``covariances``.
        InvalidArgumentError: some S_i + S_j is not positive definite.
    """
    check_tensor(covariances, "covariances", min_ndim=3, bounded=False, shape_hint="(..., K, d, d)")
    if covariances.shape[-1] != covariances.shape[-2]:
        raise ShapeMismatchError(f"covariances must be square (..., K, d, d), got shape {tuple(covariances.shape)}")
    return _pair_factors(covariances)


def _pair_factors(covariances: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`pair_factors` without its argument checks."""
    d = covariances.shape[-1]
    S_pair = covariances.unsqueeze(-3) + covariances.unsqueeze(-4)  # (..., K, K, d, d)
    S_pair = 0.5 * (S_pair + S_pair.transpose(-2, -1))
    L, info = torch.linalg.cholesky_ex(S_pair)
    if bool((info != 0).any()):
        raise InvalidArgumentError("covariances: some S_i + S_j is not positive definite")
    eye = torch.eye(d, dtype=L.dtype, device=L.device)
    L_inv = torch.linalg.solve_triangular(L, eye.expand_as(L), upper=False)
    return L_inv, torch.diagonal(L, dim1=-2, dim2=-1).log().sum(-1)


def _check_batch(name: str, batch: tuple[int, ...], means: Tensor) -> None:
    """``batch`` (the leading shape of ``name``) broadcasts with the batch shape of ``means`` (..., K, d)."""
    try:
        torch.broadcast_shapes(torch.Size(batch), means.shape[:-2])
    except RuntimeError:
        raise ShapeMismatchError(f"{name} has the batch shape {tuple(batch)}, which does not broadcast with the "
                                 f"batch shape {tuple(means.shape[:-2])} of means") from None  # fmt: skip


def _check_covariances(covariances: Any, means: Tensor) -> None:
    """(..., K, d, d) covariances without NaN/Inf in the dtype and on the device of ``means`` (..., K, d), with K
    and d those of ``means`` and a batch shape that broadcasts with theirs."""
    check_tensor(covariances, "covariances", min_ndim=3, dtype=means.dtype, device=means.device, bounded=False,
                 shape_hint="(..., K, d, d)")  # fmt: skip
    K, d = means.shape[-2:]
    if tuple(covariances.shape[-3:]) != (K, d, d):
        raise ShapeMismatchError(f"covariances must have shape (..., {K}, {d}, {d}) (K and d of means "
                                 f"{tuple(means.shape)}), got {tuple(covariances.shape)}")  # fmt: skip
    _check_batch("covariances", tuple(covariances.shape[:-3]), means)


def _check_factors(factors: Any, means: Tensor) -> None:
    """``factors`` the (L_inv (..., K, K, d, d), half_log_det (..., K, K)) of :func:`pair_factors`, without
    NaN/Inf, in the dtype and on the device of ``means``, for the K and d of ``means`` and a broadcasting batch."""
    if not (isinstance(factors, tuple) and len(factors) == 2 and all(isinstance(t, Tensor) for t in factors)):
        got = (f"a tuple of ({', '.join(type(t).__name__ for t in factors)})" if isinstance(factors, tuple)
               else type(factors).__name__)  # fmt: skip
        raise ShapeMismatchError(f"factors must be the (L_inv, half_log_det) tensors of pair_factors, got {got}")
    L_inv, half = factors
    K, d = means.shape[-2:]
    check_tensor(L_inv, "factors[0] (L_inv)", min_ndim=4, dtype=means.dtype, device=means.device, bounded=False,
                 shape_hint="(..., K, K, d, d)")  # fmt: skip
    check_tensor(half, "factors[1] (half_log_det)", min_ndim=2, dtype=means.dtype, device=means.device,
                 bounded=False, shape_hint="(..., K, K)")  # fmt: skip
    if tuple(L_inv.shape[-4:]) != (K, K, d, d) or tuple(half.shape[-2:]) != (K, K):
        raise ShapeMismatchError(
            f"factors must be pair_factors of covariances with the K = {K} and d = {d} of means: shapes "
            f"(..., {K}, {K}, {d}, {d}) and (..., {K}, {K}), got {tuple(L_inv.shape)} and {tuple(half.shape)}"
        )
    _check_batch("factors", tuple(L_inv.shape[:-4]), means)
    _check_batch("factors", tuple(half.shape[:-2]), means)


def pairwise_log_overlap(
    means: Tensor, covariances: Tensor | None = None, *, factors: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """log N(mu_i; mu_j, S_i + S_j) = log of the integral of N(u; mu_i, S_i) N(u; mu_j, S_j) over u.

    Args:
        means: (..., K, d) component means.
        covariances: (K, d, d) or broadcastable (..., K, d, d) symmetric positive-definite covariances, in the dtype
            and on the device of ``means``.
        factors: precomputed :func:`pair_factors` of the covariances (then ``covariances`` is not used).

    Returns:
        (..., K, K) symmetric tensor.

    Raises:
        ShapeMismatchError: ``means`` not a float (..., K, d) tensor; covariances (or factors) whose K, d or batch
            shape do not agree with the means', of another dtype or device, or factors that are not a
            (L_inv, half_log_det) pair.
        NonFiniteError: NaN or Inf in ``means``, ``covariances`` or ``factors``.
        InvalidArgumentError: some S_i + S_j is not positive definite.
    """
    check_tensor(means, "means", min_ndim=2, bounded=False, shape_hint="(..., K, d)")
    if factors is None:
        _check_covariances(covariances, means)
    else:
        _check_factors(factors, means)
    return _pairwise_log_overlap(means, covariances, factors=factors)


def _pairwise_log_overlap(
    means: Tensor, covariances: Tensor | None = None, *, factors: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """:func:`pairwise_log_overlap` without its argument checks."""
    d = means.shape[-1]
    L_inv, half_log_det = _pair_factors(covariances) if factors is None else factors
    diff = means.unsqueeze(-2) - means.unsqueeze(-3)  # (..., K, K, d): mu_i - mu_j
    z = (L_inv @ diff.unsqueeze(-1)).squeeze(-1)
    return -0.5 * (z * z).sum(-1) - half_log_det - 0.5 * d * math.log(2.0 * math.pi)


def mixture_renyi_entropy(
    log_weights: Tensor, means: Tensor, covariances: Tensor, *, factors: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """Quadratic Renyi entropy -log sum_ij w_i w_j N(mu_i; mu_j, S_i + S_j) of an unnormalised Gaussian mixture.

    Args:
        log_weights: (..., K) log w_k; need not be normalised (``-inf`` allowed for a zero weight).
        means: (..., K, d) component means.
        covariances: (K, d, d) or broadcastable (..., K, d, d) covariances.
        factors: optional precomputed :func:`pair_factors` of ``covariances`` (e.g. gathered per row).

    ``log_weights``, ``covariances`` and ``factors`` share the dtype and device of ``means`` (the result's); a
    mixed call is a ShapeMismatchError naming the argument (convert it with ``.to(means.dtype)``).

    Returns:
        (...) H2, computed with one ``logsumexp`` over the K^2 pairs (+inf only if every weight is zero).

    Raises:
        ShapeMismatchError: inconsistent shapes (also batch shapes that do not broadcast), dtypes or devices, or
            ``factors`` that are not the (L_inv, half_log_det) of :func:`pair_factors` for these K and d.
        TooFewSamplesError: no component (K = 0).
        NonFiniteError: NaN or +inf in ``log_weights``, NaN or Inf in ``means``, ``covariances`` or ``factors``.
        InvalidArgumentError: some S_i + S_j is not positive definite.
    """
    for name, t in (("log_weights", log_weights), ("means", means), ("covariances", covariances)):
        if not isinstance(t, Tensor):
            raise ShapeMismatchError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if means.ndim < 2 or log_weights.shape != means.shape[:-1]:
        raise ShapeMismatchError(
            f"log_weights must have shape means.shape[:-1]; got {tuple(log_weights.shape)} and {tuple(means.shape)}"
        )
    K, d = means.shape[-2:]
    if covariances.ndim < 3 or tuple(covariances.shape[-3:]) != (K, d, d):
        raise ShapeMismatchError(f"covariances must have shape (..., {K}, {d}, {d}), got {tuple(covariances.shape)}")
    if K == 0:
        raise TooFewSamplesError("means has K = 0 components; a mixture needs at least one")
    check_tensor(means, "means", bounded=False)
    check_tensor(log_weights, "log_weights", finite=False, dtype=means.dtype, device=means.device)
    if bool((torch.isnan(log_weights) | (log_weights == math.inf)).any()):
        raise NonFiniteError("log_weights contains NaN or +inf (-inf, a zero weight, is allowed)")
    if factors is None:
        _check_covariances(covariances, means)
    else:
        _check_factors(factors, means)
    return _mixture_renyi_entropy(log_weights, means, covariances, factors=factors)


def _mixture_renyi_entropy(
    log_weights: Tensor, means: Tensor, covariances: Tensor, *, factors: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """:func:`mixture_renyi_entropy` without its argument checks (inputs from a checked :func:`velocity_mixture`)."""
    log_overlap = _pairwise_log_overlap(means, covariances, factors=factors)  # (..., K, K)
    terms = log_weights.unsqueeze(-1) + log_weights.unsqueeze(-2) + log_overlap
    return -torch.logsumexp(terms.flatten(-2), dim=-1)


def renyi_entropy(primitive: Any, x: Tensor, *, velocity_covariances: Tensor | None = None) -> Tensor:
    """H2(x) of the primitive's velocity mixture (module docstring: unnormalised weights, S_k choice).

    Args:
        primitive: a :class:`~lfd_torch.ds.StablePrimitive` (see :func:`velocity_mixture`).
        x: (..., d) positions (data units), same dtype and device as the primitive.
        velocity_covariances: optional (K, d, d) override of the primitive's S_k, (units/s)^2.

    Returns:
        (...) entropy values in the dtype and on the device of ``x``; finite for every finite ``x`` that does not
        overflow the squared Mahalanobis distances.

    Raises:
        ShapeMismatchError, NonFiniteError, InvalidArgumentError: see :func:`velocity_mixture`.
    """
    mix = velocity_mixture(primitive, x, velocity_covariances=velocity_covariances)  # checks x and the primitive
    return _mixture_renyi_entropy(mix.log_weights, mix.means, mix.covariances)


def reference_entropy(
    primitive: Any,
    x: Tensor | None = None,
    quantile: float | None = 1.0,
    *,
    velocity_covariances: Tensor | None = None,
) -> Tensor:
    """Threshold H2(x_r) of the small-scale modulation (eqs 17-18; NOTES sec. 4).

    NOTES default: the ``quantile`` of H2 over the primitive's training states ``x`` (1.0 = the largest), so that a
    rollout inside the demonstrated range is not modulated. ``quantile=None`` is the paper's literal choice
    x_r = g (H2 at the attractor; ``x`` is then ignored), which modulates almost every demonstrated state.

    Args:
        primitive: the primitive.
        x: (N, d) training positions; required unless ``quantile`` is None.
        quantile: in [0, 1], or None for x_r = g.
        velocity_covariances: optional override of S_k (see :func:`renyi_entropy`).

    Returns:
        0-d tensor in the primitive's dtype and device.

    Raises:
        InvalidArgumentError: ``quantile`` outside [0, 1], or ``x`` missing / empty when it is needed.
    """
    if quantile is None:
        return renyi_entropy(primitive, primitive.attractor, velocity_covariances=velocity_covariances)
    if isinstance(quantile, bool) or not isinstance(quantile, (int, float)) or not 0.0 <= float(quantile) <= 1.0:
        raise InvalidArgumentError(f"quantile must be a number in [0, 1] or None, got {quantile!r}")
    if x is None:
        raise InvalidArgumentError("x: training positions are required when quantile is not None")
    h2 = renyi_entropy(primitive, x, velocity_covariances=velocity_covariances).reshape(-1)
    if h2.numel() == 0:
        raise InvalidArgumentError("x: no training positions given")
    return torch.quantile(h2, float(quantile))
