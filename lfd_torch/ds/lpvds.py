"""LPV-DS with a quadratic (QLF) or parametrised quadratic (P-QLF) Lyapunov function (paper Sec. III-C, eqs 5-7).

Notation:
    N samples, K components, d state dimension
    x (N, d) positions (units), x_dot (N, d) velocities (units/s), g (d,) attractor, e_n = x_n - g
    gamma (N, K) GMM posterior on positions; A (K, d, d) in 1/s; P (d, d), lambda_max(P) = 1

Fitting has three steps: (1) a GMM on positions (PC-GMM, DAMM, EM, ... or a given GMM) gives gamma_k(x);
(2) the P step (:func:`~lfd_torch.ds.lyapunov.estimate_lyapunov_matrix`; QLF: P = I); (3) the A step, the convex
program of eq. (7) with the constraints of eq. (6):

    minimise   (1/N) sum_n || x_dot_n - sum_k gamma_k(x_n) A_k e_n ||^2
    subject to A_k^T P + P A_k <= -eps I,   k = 1..K.

Deviation from the printed eq. (7): the paper sums unsquared norms; the squared error is used here (as in the
LPV-DS reference implementation's MSE option) because it is a function of precomputed moments only, so the
program's size does not grow with N. With z_n = [gamma_1 e_n; ...; gamma_K e_n] (Kd) and Theta = [A_1 ... A_K]
(d x Kd), the prediction is Theta z_n and

    (1/N) sum_n ||x_dot_n - Theta z_n||^2 = ||Theta L - H L^-T||_F^2 + const,
    G = (1/N) sum_n z_n z_n^T = L L^T (Cholesky; blocks M_kl = (1/N) sum_n gamma_k gamma_l e e^T),
    H = (1/N) sum_n x_dot_n z_n^T  (blocks C_k = (1/N) sum_n gamma_k x_dot e^T),

a DCP sum of squares over d x Kd entries. A ridge ``ridge * trace(G) / (Kd)`` is added to G (it keeps the
Cholesky factor defined when a component has no mass). Positions and velocities are scaled to unit RMS inside
the program for conditioning; eps is in 1/s in the original units. The program is built once per (K, d) with
cvxpy Parameters and reused. After solving, the certificate lambda_max(A_k^T P + P A_k) < 0 is verified in
float64 and a :class:`~lfd_torch.errors.CertificationError` is raised if it fails: no uncertified model is
ever returned.
"""

from __future__ import annotations

import functools
import inspect
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import cvxpy as cp
import numpy as np
import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.ds.convex import DEFAULT_SOLVERS, normalize_solver_options, normalize_solvers, solve_problem
from lfd_torch.ds.lyapunov import estimate_lyapunov_matrix, lyapunov_violation_rate
from lfd_torch.ds.primitive import StablePrimitive, quadratic_margins, residual_velocity_covariances
from lfd_torch.errors import (
    CertificationError,
    InvalidArgumentError,
    ShapeMismatchError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.gmm import GMM, PCGMMFitter, check_samples
from lfd_torch.utils import check_float, check_generator, check_tensor, solver_errors

__all__ = ["LPVDS", "LYAPUNOV_KINDS", "fit_lpvds", "resolve_gmm", "solve_lpv_matrices", "training_samples"]

#: Accepted values of the ``lyapunov`` argument (besides an explicit (d, d) tensor).
LYAPUNOV_KINDS: tuple[str, ...] = ("pqlf", "qlf")

GMMSource = GMM | Callable[..., GMM]


@dataclass(frozen=True, eq=False)
class LPVDS(StablePrimitive):
    """A certified LPV-DS (see :class:`~lfd_torch.ds.primitive.StablePrimitive` for fields and methods)."""

    kind: ClassVar[str] = "LPVDS"

    @classmethod
    def fit(cls, demos: Demos, attractor: Tensor | None = None, **kwargs: Any) -> LPVDS:
        """Fit to demonstrations; the keyword arguments are those of :func:`fit_lpvds`."""
        return fit_lpvds(demos, attractor, **kwargs)


def training_samples(demos: Demos, attractor: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Valid samples of ``demos`` and the attractor to fit to.

    Args:
        demos: demonstrations.
        attractor: optional (d,) goal overriding ``demos.attractor``.

    Returns:
        x (N, d), x_dot (N, d), g (d,), all in the dtype/device of ``demos``.
    """
    if not isinstance(demos, Demos):
        raise ShapeMismatchError(f"demos must be a lfd_torch.data.Demos, got {type(demos).__name__}")
    x, x_dot, _ = demos.samples()
    check_tensor(x, "demos positions")
    check_tensor(x_dot, "demos velocities")
    if attractor is None:
        g = demos.attractor
    else:
        check_tensor(attractor, "attractor", ndim=1, last_dim=demos.dim, shape_hint=f"({demos.dim},)")
        g = attractor.to(dtype=demos.dtype, device=demos.device)
    return x, x_dot, g


def resolve_gmm(gmm: GMMSource, x: Tensor, x_dot: Tensor, generator: torch.Generator | None) -> GMM:
    """A GMM on positions from a fitted :class:`GMM` or a fitter.

    A fitter is any callable returning a GMM, e.g. ``functools.partial(fit_em, n_components=5)``,
    ``fit_pcgmm`` or ``fit_damm``. It is called as ``gmm(x, x_dot=x_dot, generator=generator)`` when its signature
    has an ``x_dot`` parameter, and as ``gmm(x, generator=generator)`` otherwise.

    Args:
        gmm: a GMM (cast to the dtype/device of ``x``) or a fitter.
        x: (N, d) positions.
        x_dot: (N, d) velocities.
        generator: torch generator; required for a fitter.

    Returns:
        A GMM of dimension d in the dtype/device of ``x``.
    """
    if isinstance(gmm, GMM):
        out = gmm.to(dtype=x.dtype, device=x.device)
    elif callable(gmm):
        if generator is None:
            raise InvalidArgumentError("a GMM fitter needs generator=torch.Generator(), got None")
        try:
            params = inspect.signature(gmm).parameters
        except (TypeError, ValueError):
            params = {}
        out = gmm(x, x_dot=x_dot, generator=generator) if "x_dot" in params else gmm(x, generator=generator)
        if not isinstance(out, GMM):
            raise InvalidArgumentError(f"the gmm fitter returned {type(out).__name__}, not a lfd_torch.gmm.GMM")
    else:
        raise InvalidArgumentError(f"gmm must be a lfd_torch.gmm.GMM or a fitter callable, got {type(gmm).__name__}")
    if out.dim != x.shape[-1]:
        raise ShapeMismatchError(f"the gmm has dimension {out.dim}, the data {x.shape[-1]}")
    return out


@functools.lru_cache(maxsize=32)
def _a_step_problem(K: int, d: int) -> tuple[cp.Problem, list[cp.Variable], dict[str, cp.Parameter]]:
    """The parametrised A-step program for K components in d dimensions (built once, reused)."""
    A = [cp.Variable((d, d), name=f"A_{k}") for k in range(K)]
    params = {
        "L": cp.Parameter((K * d, K * d), name="L"),
        "Y": cp.Parameter((d, K * d), name="Y"),
        "P": cp.Parameter((d, d), symmetric=True, name="P"),
        "eps": cp.Parameter(nonneg=True, name="eps"),
    }
    theta = cp.hstack(A) if K > 1 else A[0]
    eye = np.eye(d)
    constraints = [A_k.T @ params["P"] + params["P"] @ A_k << -params["eps"] * eye for A_k in A]
    problem = cp.Problem(cp.Minimize(cp.sum_squares(theta @ params["L"] - params["Y"])), constraints)
    return problem, A, params


def solve_lpv_matrices(
    x: Tensor,
    x_dot: Tensor,
    gamma: Tensor,
    attractor: Tensor,
    P: Tensor,
    *,
    eps: float = 1e-3,
    ridge: float = 1e-6,
    solvers: str | Sequence[str] = DEFAULT_SOLVERS,
    solver_options: Mapping[str, Mapping[str, Any]] | None = None,
) -> tuple[Tensor, str]:
    """A step: the moment-based convex program of the module docstring.

    Args:
        x: (N, d) positions.
        x_dot: (N, d) velocities.
        gamma: (N, K) responsibilities (rows sum to 1).
        attractor: (d,) goal g.
        P: (d, d) symmetric positive-definite Lyapunov matrix.
        eps: stability margin, A_k^T P + P A_k <= -eps I (1/s, > 0).
        ridge: relative ridge on the moment matrix G (>= 0).
        solvers: cvxpy solver names tried in order.
        solver_options: optional ``{solver: {option: value}}``.

    Returns:
        A (K, d, d) in the dtype/device of ``x`` (not yet verified: see :func:`fit_lpvds`), and the solver used.

    Raises:
        SolverError: no solver reached optimality.
        InvalidArgumentError: ``P`` not symmetric positive definite, bad ``gamma``, ``eps`` or ``ridge``.
        ShapeMismatchError / NonFiniteError / TooFewSamplesError: inputs of the wrong shape, not finite, or empty.
    """
    check_samples(x, x_dot, min_samples=1)
    N, d = x.shape
    if gamma.ndim != 2 or gamma.shape[0] != N:
        raise ShapeMismatchError(f"gamma must have shape ({N}, K), got {tuple(gamma.shape)}")
    check_tensor(gamma, "gamma")
    rows = gamma.to(torch.float64).sum(-1)
    if bool((gamma < 0).any()) or not torch.allclose(rows, torch.ones_like(rows), atol=1e-6):
        raise InvalidArgumentError("gamma: responsibilities must be >= 0 with rows summing to 1")
    check_tensor(attractor, "attractor", ndim=1, last_dim=d, shape_hint=f"({d},)")
    check_tensor(P, "P", ndim=2, last_dim=d, shape_hint=f"({d}, {d})")
    if P.shape[0] != d:
        raise ShapeMismatchError(f"P must have shape ({d}, {d}), got {tuple(P.shape)}")
    P64 = P.to(dtype=torch.float64, device=x.device)
    scale = float(P64.abs().max().clamp_min(1e-300))
    if not torch.allclose(P64, P64.T, rtol=1e-6, atol=1e-9 * scale):
        raise InvalidArgumentError("P must be symmetric: the A step constrains A^T P + P A with the Lyapunov "
                                   "matrix P of V(x) = (x - g)^T P (x - g)")  # fmt: skip
    if float(torch.linalg.eigvalsh(0.5 * (P64 + P64.T))[0]) <= 0:
        raise InvalidArgumentError("P must be positive definite: with an indefinite P the constraint "
                                   "A^T P + P A < 0 does not make the system stable")  # fmt: skip
    check_float(eps, "eps", low=0.0, low_open=True)
    check_float(ridge, "ridge", low=0.0)
    K = gamma.shape[1]
    f64 = dict(dtype=torch.float64, device=x.device)
    e = (x - attractor).to(**f64)
    v = x_dot.to(**f64)
    s = float(e.pow(2).sum(-1).mean().sqrt())
    u = float(v.pow(2).sum(-1).mean().sqrt())
    if not (s > 0 and u > 0):
        raise TooFewSamplesError("all samples sit at the attractor or at rest; nothing to fit")
    z = (gamma.to(**f64).unsqueeze(-1) * (e / s).unsqueeze(-2)).reshape(N, K * d)
    G = z.T @ z / N
    G = G + (ridge * float(torch.trace(G)) / (K * d) + 1e-14) * torch.eye(K * d, **f64)
    H = (v / u).T @ z / N
    with solver_errors("LPV-DS A step: Cholesky factor of the moment matrix"):
        L = torch.linalg.cholesky(G)
        Y = torch.linalg.solve_triangular(L, H.T, upper=False).T  # H L^-T
    problem, A_vars, params = _a_step_problem(K, d)
    params["L"].value = L.cpu().numpy()
    params["Y"].value = Y.cpu().numpy()
    params["P"].value = (0.5 * (P64 + P64.T)).cpu().numpy()
    params["eps"].value = eps * s / u
    solver = solve_problem(problem, solvers, solver_options, what="LPV-DS A step")
    A = torch.stack([torch.as_tensor(np.asarray(a.value), dtype=torch.float64) for a in A_vars]) * (u / s)
    return A.to(dtype=x.dtype, device=x.device), solver


def fit_lpvds(
    demos: Demos,
    attractor: Tensor | None = None,
    *,
    gmm: GMMSource | None = None,
    lyapunov: str | Tensor = "pqlf",
    eps: float = 1e-3,
    ridge: float = 1e-6,
    p_margin: float = 0.0,
    p_min_eigenvalue: float = 1e-3,
    solvers: str | Sequence[str] = DEFAULT_SOLVERS,
    solver_options: Mapping[str, Mapping[str, Any]] | None = None,
    generator: torch.Generator | None = None,
) -> LPVDS:
    """Fit a globally stable LPV-DS: GMM, then P step, then A step (module docstring).

    Cost: the GMM fit (its own bounds), an O(N K^2 d^2) moment matrix, and two convex programs: the P step with
    d (d + 1) / 2 variables and N hinge terms, the A step with K d^2 variables and K LMI constraints of size d.

    Args:
        demos: training demonstrations (all valid samples are used).
        attractor: optional (d,) goal; default ``demos.attractor``.
        gmm: a fitted GMM on positions, or a fitter (see :func:`resolve_gmm`); None: PC-GMM with its defaults
            (:class:`~lfd_torch.gmm.PCGMMFitter`), as ``conf/ds/lpvds.yaml``.
        lyapunov: ``"pqlf"`` (P estimated from data), ``"qlf"`` (P = I) or an explicit (d, d) SPD tensor.
        eps: stability margin of the A step, A_k^T P + P A_k <= -eps I (1/s).
        ridge: relative ridge on the A-step moment matrix.
        p_margin: hinge margin of the P step (``lyapunov="pqlf"`` only).
        p_min_eigenvalue: lower eigenvalue bound of the P step (``lyapunov="pqlf"`` only).
        solvers: cvxpy solver names tried in order (Clarabel, then SCS by default).
        solver_options: optional ``{solver: {option: value}}`` for both programs.
        generator: torch generator for a stochastic GMM fitter.

    Returns:
        A certified :class:`LPVDS`; ``info`` holds the hyperparameters, K, the solver, the training MSE, the
        fraction of samples violating the P decrease, and the time of each step (s).

    Raises:
        UnknownNameError: unknown ``lyapunov`` string.
        ShapeMismatchError, NonFiniteError, TooFewSamplesError: malformed input.
        InvalidArgumentError: a hyperparameter of the wrong type or out of range, a fitter without a generator.
        SolverError: a convex program was not solved to optimality by any solver.
        CertificationError: the solution does not satisfy lambda_max(A_k^T P + P A_k) < 0 in float64.
    """
    t_start = time.perf_counter()
    if gmm is None:
        gmm = PCGMMFitter()
    x, x_dot, g = training_samples(demos, attractor)
    check_float(eps, "eps", low=0.0, low_open=True)
    check_float(ridge, "ridge", low=0.0)
    check_float(p_margin, "p_margin", low=0.0, high=1.0, high_open=True)
    check_float(p_min_eigenvalue, "p_min_eigenvalue", low=0.0, high=1.0, low_open=True)
    normalize_solvers(solvers)
    normalize_solver_options(solver_options)
    if generator is not None:
        check_generator(generator)
    mixture = resolve_gmm(gmm, x, x_dot, generator)
    K, d = mixture.n_components, mixture.dim
    if x.shape[0] < 2:
        raise TooFewSamplesError(f"{x.shape[0]} samples; at least 2 are needed")
    t_gmm = time.perf_counter()
    if isinstance(lyapunov, Tensor):
        check_tensor(lyapunov, "lyapunov", ndim=2, shape_hint=f"({d}, {d})")
        P = lyapunov.to(dtype=x.dtype, device=x.device)
        if P.shape != (d, d):
            raise ShapeMismatchError(f"lyapunov (P) must have shape ({d}, {d}), got {tuple(P.shape)}")
        P64 = P.to(torch.float64)
        if not torch.allclose(P64, P64.T) or float(torch.linalg.eigvalsh(P64)[0]) <= 0:
            raise CertificationError("the given lyapunov matrix P is not symmetric positive definite")
        P = 0.5 * (P + P.T) / float(torch.linalg.eigvalsh(P64)[-1])
        lyapunov_name = "given"
    elif lyapunov == "qlf":
        P = torch.eye(d, dtype=x.dtype, device=x.device)
        lyapunov_name = "qlf"
    elif lyapunov == "pqlf":
        with solver_errors("LPV-DS P step"):
            P = estimate_lyapunov_matrix(
                x,
                x_dot,
                g,
                margin=p_margin,
                min_eigenvalue=p_min_eigenvalue,
                solvers=solvers,
                solver_options=solver_options,
            )
        lyapunov_name = "pqlf"
    else:
        raise UnknownNameError("lyapunov", repr(lyapunov), LYAPUNOV_KINDS)
    t_p = time.perf_counter()
    gamma = mixture.posterior(x)
    with solver_errors("LPV-DS A step"):
        A, solver = solve_lpv_matrices(
            x, x_dot, gamma, g, P, eps=eps, ridge=ridge, solvers=solvers, solver_options=solver_options
        )
    margins = quadratic_margins(A, P)
    if not bool((margins < 0).all()):
        raise CertificationError(
            f"LPV-DS A step ({solver}) returned matrices with lambda_max(A_k^T P + P A_k) = {margins.tolist()}; "
            "all must be < 0"
        )
    t_a = time.perf_counter()
    pred = torch.einsum("nk,kij,nj->ni", gamma, A, x - g)
    info = {
        "method": "lpvds",
        "lyapunov": lyapunov_name,
        "eps": float(eps),
        "ridge": float(ridge),
        "p_margin": float(p_margin),
        "p_min_eigenvalue": float(p_min_eigenvalue),
        "n_components": K,
        "n_samples": int(x.shape[0]),
        "solver": solver,
        "train_mse": float((x_dot - pred).pow(2).sum(-1).mean()),
        "p_violation_rate": lyapunov_violation_rate(x, x_dot, g, P),
        "max_margin": float(margins.max()),
        "time_gmm_s": t_gmm - t_start,
        "time_p_s": t_p - t_gmm,
        "time_a_s": t_a - t_p,
        "time_total_s": t_a - t_start,
    }
    Sv = residual_velocity_covariances(gamma, x, x_dot, A, g)
    return LPVDS(gmm=mixture, A=A, attractor=g, P=P, velocity_covariances=Sv, info=info)
