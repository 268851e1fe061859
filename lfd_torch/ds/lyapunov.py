"""Quadratic Lyapunov functions V(x) = (x - g)^T P (x - g) and the P step of P-QLF LPV-DS.

Notation:
    N  samples, d state dimension
    x        (N, d)  positions (data units, e.g. mm)
    x_dot    (N, d)  demonstrated velocities (units/s)
    g        (d,)    attractor
    P        (d, d)  symmetric positive definite, normalised to largest eigenvalue 1 (dimensionless)

P step (paper Sec. III-C, NOTES.md section 3): P is estimated from the data before the A step so that V decreases
along the demonstrations, i.e. psi_n(P) = (x_n - g)^T P x_dot_n < 0. Figueroa & Billard (CoRL 2018) minimise a
non-convex asymmetric penalty on psi_n; here the same goal is posed as a *convex* program (a linear program over
the PSD cone, solved by cvxpy/Clarabel):

    minimise   (1/N) sum_n max(0, psi~_n(P) + margin)
    subject to min_eigenvalue I <= P <= I,

with the direction-only violation psi~_n(P) = (x_n - g)^T P x_dot_n / (||x_n - g|| ||x_dot_n||), which lies in
[-1, 1] for P <= I. With the default margin 0 the objective is the mean normalised violation of the decrease
condition: zero for any P under which every sample decreases V, and otherwise (curved or looping motions, where no
P explains every sample) the P with the least total violation. A positive margin asks for a clear decrease
(a cosine-like margin) and trades it against the number of violations; on LASA the default 0 gave the best
A-step fits. Samples at the attractor or at rest carry no
direction and are dropped. The solution is normalised to lambda_max(P) = 1. The QLF baseline is P = I.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import cvxpy as cp
import numpy as np
import torch
from torch import Tensor

from lfd_torch.ds.convex import DEFAULT_SOLVERS, solve_problem
from lfd_torch.errors import CertificationError, InvalidArgumentError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.gmm import check_samples
from lfd_torch.utils import check_float, check_tensor, solver_errors

__all__ = [
    "estimate_lyapunov_matrix",
    "lyapunov_violation_rate",
    "quadratic_lyapunov",
    "quadratic_lyapunov_derivative",
]


def _check_attractor(x: Tensor, attractor: Tensor) -> None:
    if not isinstance(attractor, Tensor) or attractor.shape != (x.shape[-1],):
        shape = tuple(attractor.shape) if isinstance(attractor, Tensor) else type(attractor).__name__
        raise ShapeMismatchError(f"attractor must have shape ({x.shape[-1]},), got {shape}")
    if attractor.dtype != x.dtype or attractor.device != x.device:
        raise ShapeMismatchError(f"attractor is {attractor.dtype} on {attractor.device}, x is {x.dtype} on {x.device}")
    check_tensor(attractor, "attractor")


def _check_quadratic_form(x: Tensor, attractor: Tensor, P: Tensor, x_dot: Tensor | None = None) -> None:
    """The checks of the public quadratic-form helpers: x (..., d) finite, x_dot like x, attractor (d,), P (d, d)
    symmetric, all of one dtype and device."""
    check_tensor(x, "x", min_ndim=1, shape_hint="(..., d)")
    d = x.shape[-1]
    if x_dot is not None:
        check_tensor(x_dot, "x_dot", shape_hint="(..., d) like x")
        if x_dot.shape != x.shape or x_dot.dtype != x.dtype or x_dot.device != x.device:
            raise ShapeMismatchError(f"x_dot must match x {tuple(x.shape)} {x.dtype}, got {tuple(x_dot.shape)} "
                                     f"{x_dot.dtype}")  # fmt: skip
    _check_attractor(x, attractor)
    check_tensor(P, "P", ndim=2, last_dim=d, shape_hint=f"({d}, {d})")
    if P.shape[0] != d or P.dtype != x.dtype or P.device != x.device:
        raise ShapeMismatchError(f"P must be ({d}, {d}) {x.dtype} on {x.device} like x, got {tuple(P.shape)} "
                                 f"{P.dtype} on {P.device}")  # fmt: skip
    if not torch.allclose(P, P.T, rtol=1e-6, atol=1e-9 * float(P.abs().max().clamp_min(1e-300))):
        raise InvalidArgumentError("P must be symmetric (a quadratic form's matrix)")


def quadratic_lyapunov(x: Tensor, attractor: Tensor, P: Tensor) -> Tensor:
    """V(x) = (x - g)^T P (x - g).

    Args:
        x: (..., d) positions.
        attractor: (d,) goal g.
        P: (d, d) symmetric matrix.

    Returns:
        (...) values (units^2).

    Raises:
        ShapeMismatchError, NonFiniteError, InvalidArgumentError: see :func:`lyapunov_violation_rate`.
    """
    _check_quadratic_form(x, attractor, P)
    e = x - attractor
    return torch.einsum("...i,ij,...j->...", e, P, e)


def quadratic_lyapunov_derivative(x: Tensor, x_dot: Tensor, attractor: Tensor, P: Tensor) -> Tensor:
    """dV/dt = 2 (x - g)^T P x_dot for symmetric P.

    Args:
        x: (..., d) positions.
        x_dot: (..., d) velocities at ``x``.
        attractor: (d,) goal g.
        P: (d, d) symmetric matrix.

    Returns:
        (...) values (units^2/s).

    Raises:
        ShapeMismatchError, NonFiniteError, InvalidArgumentError: see :func:`lyapunov_violation_rate`.
    """
    _check_quadratic_form(x, attractor, P, x_dot)
    return 2.0 * torch.einsum("...i,ij,...j->...", x - attractor, P, x_dot)


def lyapunov_violation_rate(x: Tensor, x_dot: Tensor, attractor: Tensor, P: Tensor) -> float:
    """Fraction of samples whose demonstrated velocity does not decrease V, i.e. (x - g)^T P x_dot >= 0.

    Args:
        x: (N, d) positions.
        x_dot: (N, d) velocities.
        attractor: (d,) goal.
        P: (d, d) Lyapunov matrix.

    Returns:
        A number in [0, 1].

    Raises:
        ShapeMismatchError: shapes, dtypes or devices that do not match (attractor (d,), P (d, d)).
        NonFiniteError: NaN or Inf in an input. TooFewSamplesError: no sample.
        InvalidArgumentError: P not symmetric.
    """
    check_samples(x, x_dot, min_samples=1)
    return float((quadratic_lyapunov_derivative(x, x_dot, attractor, P) >= 0).to(torch.float64).mean())


def _direction_features(x: Tensor, x_dot: Tensor, attractor: Tensor, rel_tol: float) -> np.ndarray:
    """(M, d*d) rows vec(sym(e v^T)) / (||e|| ||v||) in float64 for samples with informative e and v."""
    e = (x - attractor).to(torch.float64)
    v = x_dot.to(torch.float64)
    ne, nv = e.norm(dim=-1), v.norm(dim=-1)
    keep = (ne > rel_tol * ne.max()) & (nv > rel_tol * nv.max())
    e, v, ne, nv = e[keep], v[keep], ne[keep], nv[keep]
    M = e.unsqueeze(-1) * v.unsqueeze(-2)
    M = 0.5 * (M + M.transpose(-2, -1)) / (ne * nv)[:, None, None]
    return M.reshape(M.shape[0], M.shape[-1] * M.shape[-1]).cpu().numpy()


def estimate_lyapunov_matrix(
    x: Tensor,
    x_dot: Tensor,
    attractor: Tensor,
    *,
    margin: float = 0.0,
    min_eigenvalue: float = 1e-3,
    rel_tol: float = 1e-3,
    solvers: str | Sequence[str] = DEFAULT_SOLVERS,
    solver_options: Mapping[str, Mapping[str, Any]] | None = None,
) -> Tensor:
    """P step of P-QLF: the convex hinge program of the module docstring.

    Args:
        x: (N, d) positions.
        x_dot: (N, d) velocities.
        attractor: (d,) goal g.
        margin: hinge margin on the direction-only decrease psi~ (dimensionless, in [0, 1)).
        min_eigenvalue: lower bound on the eigenvalues of P before normalisation (upper bound is 1); bounds the
            condition number of P by 1 / min_eigenvalue.
        rel_tol: samples with ||x - g|| or ||x_dot|| below ``rel_tol`` times the largest are ignored.
        solvers: cvxpy solver names tried in order.
        solver_options: optional ``{solver: {option: value}}``.

    Returns:
        (d, d) symmetric positive-definite P with largest eigenvalue 1, dtype/device of ``x``.

    Raises:
        ShapeMismatchError, NonFiniteError: malformed input.
        TooFewSamplesError: fewer informative samples than free entries of P.
        InvalidArgumentError: ``margin`` outside [0, 1), ``min_eigenvalue`` outside (0, 1] or ``rel_tol`` < 0.
        SolverError: no solver reached optimality.
        CertificationError: the returned matrix is not positive definite in float64.
    """
    check_samples(x, x_dot, min_samples=1)
    _check_attractor(x, attractor)
    check_float(margin, "margin", low=0.0, high=1.0, high_open=True)
    check_float(min_eigenvalue, "min_eigenvalue", low=0.0, high=1.0, low_open=True)
    check_float(rel_tol, "rel_tol", low=0.0)
    d = x.shape[-1]
    F = _direction_features(x, x_dot, attractor, rel_tol)
    if F.shape[0] < d * (d + 1) // 2:
        raise TooFewSamplesError(
            f"{F.shape[0]} informative samples (away from the attractor and not at rest); "
            f"at least {d * (d + 1) // 2} are needed to estimate P"
        )
    P_var = cp.Variable((d, d), symmetric=True)
    psi = F @ cp.reshape(P_var, (d * d,), order="C")
    eye = np.eye(d)
    problem = cp.Problem(
        cp.Minimize(cp.sum(cp.pos(psi + margin)) / F.shape[0]),
        [P_var >> min_eigenvalue * eye, P_var << eye],
    )
    solve_problem(problem, solvers, solver_options, what="P-QLF P step")
    P = torch.as_tensor(np.asarray(P_var.value), dtype=torch.float64)
    P = 0.5 * (P + P.T)
    with solver_errors("P-QLF P step: eigenvalues of the solution"):
        eig = torch.linalg.eigvalsh(P)
    if not float(eig[0]) > 0:
        raise CertificationError(f"P step returned a matrix that is not positive definite (eigenvalues {eig.tolist()})")
    P = P / eig[-1]
    return P.to(dtype=x.dtype, device=x.device)
