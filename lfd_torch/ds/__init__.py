"""Globally stable motion primitives: LPV-DS (QLF / P-QLF) and the SEDS baseline.

Notation:
    K components, d state dimension, x (..., d) positions (data units), f(x) (..., d) velocities (units/s)
    f(x) = sum_k gamma_k(x) A_k (x - g);  A (K, d, d), g (d,), P (d, d) with A_k^T P + P A_k < 0
    V(x) = (x - g)^T P (x - g), dV/dt = 2 (x - g)^T P f(x) < 0 for x != g

Modules: :mod:`~lfd_torch.ds.primitive` (common interface, certificate, save/load),
:mod:`~lfd_torch.ds.lyapunov` (P step), :mod:`~lfd_torch.ds.lpvds`, :mod:`~lfd_torch.ds.seds`,
:mod:`~lfd_torch.ds.convex` (solver fallback and status check).
"""

from lfd_torch.ds.convex import DEFAULT_SOLVERS, solve_problem
from lfd_torch.ds.lpvds import LPVDS, LYAPUNOV_KINDS, fit_lpvds, resolve_gmm, solve_lpv_matrices
from lfd_torch.ds.lyapunov import (
    estimate_lyapunov_matrix,
    lyapunov_violation_rate,
    quadratic_lyapunov,
    quadratic_lyapunov_derivative,
)
from lfd_torch.ds.seds import SEDS, SEDS_OBJECTIVES, SEDSParameters, fit_seds
from lfd_torch.ds.primitive import (
    SCHEMA_VERSION,
    StabilityCertificate,
    StablePrimitive,
    load_primitive,
    quadratic_margins,
    residual_velocity_covariances,
)

__all__ = [
    "DEFAULT_SOLVERS",
    "LPVDS",
    "LYAPUNOV_KINDS",
    "SCHEMA_VERSION",
    "SEDS",
    "SEDS_OBJECTIVES",
    "SEDSParameters",
    "fit_seds",
    "StabilityCertificate",
    "StablePrimitive",
    "estimate_lyapunov_matrix",
    "fit_lpvds",
    "load_primitive",
    "lyapunov_violation_rate",
    "quadratic_lyapunov",
    "quadratic_lyapunov_derivative",
    "quadratic_margins",
    "residual_velocity_covariances",
    "resolve_gmm",
    "solve_lpv_matrices",
    "solve_problem",
]
