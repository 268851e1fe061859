"""SEDS baseline: Stable Estimator of Dynamical Systems (Khansari-Zadeh & Billard, IEEE T-RO 2011), in PyTorch.

Notation:
    N samples, K components, d state dimension
    x (N, d) positions (units), x_dot (N, d) velocities (units/s), g (d,) attractor
    joint GMM on (x, x_dot) with priors pi_k, position means mu_k, position covariances S_k (d, d),
    system matrices A_k (d, d) and velocity residual covariances R_k (d, d)

Model. SEDS is a GMM on (x, x_dot) whose regression E[x_dot | x] is the mixture of linear systems
f(x) = sum_k h_k(x) A_k (x - g) with h_k the posterior of the position marginal (the same form as LPV-DS,
:class:`~lfd_torch.ds.primitive.StablePrimitive`) and stability from A_k + A_k^T < 0, i.e. the quadratic Lyapunov
function with P = I. The constraints hold *by construction* of the parametrisation (no constrained solver):

    A_k = -(L_k L_k^T + eps I) + (W_k - W_k^T)                      (A_k + A_k^T = -2 (L_k L_k^T + eps I) <= -2 eps I)
    pi = softmax(logits);  S_k = C_k C_k^T + reg I  (C_k lower triangular, log-diagonal);  R_k likewise
    joint mean (mu_k, A_k (mu_k - g)),  joint covariance [[S_k, S_k A_k^T], [A_k S_k, A_k S_k A_k^T + R_k]],

so that the GMR slope of every component is exactly A_k and its offset is -A_k g (the SEDS equality constraints).

Fitting. An EM fit of the joint data (K given, or chosen by BIC over ``k_range``) initialises the parameters
(A_k from the joint covariance, projected onto the constraint set); then all parameters are optimised with
full-batch L-BFGS (strong Wolfe line search) on either the mean squared velocity error (``objective="mse"``,
default; SEDS's MSE criterion) or the joint negative log-likelihood (``objective="likelihood"``). Data are scaled
to unit RMS around g internally; eps is in 1/s in the original units. The certificate
lambda_max(A_k + A_k^T) < 0 is verified in float64 before a model is returned.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.ds.lpvds import training_samples
from lfd_torch.ds.primitive import StablePrimitive, quadratic_margins, residual_velocity_covariances
from lfd_torch.errors import CertificationError, SolverError, TooFewSamplesError, UnknownNameError
from lfd_torch.gmm import GMM, fit_em, fit_em_bic

__all__ = ["SEDS", "SEDS_OBJECTIVES", "fit_seds", "SEDSParameters"]

#: Accepted values of ``objective``.
SEDS_OBJECTIVES: tuple[str, ...] = ("mse", "likelihood")


@dataclass(frozen=True, eq=False)
class SEDS(StablePrimitive):
    """A certified SEDS model (P = I); see :class:`~lfd_torch.ds.primitive.StablePrimitive`."""

    kind: ClassVar[str] = "SEDS"

    @classmethod
    def fit(cls, demos: Demos, attractor: Tensor | None = None, **kwargs: Any) -> SEDS:
        """Fit to demonstrations; the keyword arguments are those of :func:`fit_seds`."""
        return fit_seds(demos, attractor, **kwargs)


def _tril_with_log_diag(raw: Tensor) -> Tensor:
    """(K, d, d) unconstrained -> lower-triangular with positive diagonal exp(raw_ii)."""
    lower = torch.tril(raw, diagonal=-1)
    return lower + torch.diag_embed(torch.exp(torch.diagonal(raw, dim1=-2, dim2=-1)))


def _inverse_tril_with_log_diag(L: Tensor) -> Tensor:
    return torch.tril(L, diagonal=-1) + torch.diag_embed(torch.log(torch.diagonal(L, dim1=-2, dim2=-1)))


class SEDSParameters(torch.nn.Module):
    """Unconstrained parameters of SEDS in scaled coordinates (x - g) / s, x_dot / u (module docstring).

    Args:
        logits: (K,) prior logits.
        means: (K, d) position means.
        cov_factors: (K, d, d) unconstrained factors of the position covariances (log-diagonal).
        stable_factors: (K, d, d) unconstrained L_k (log-diagonal) of the symmetric part of A_k.
        skew_factors: (K, d, d) W_k of the skew part of A_k.
        residual_factors: (K, d, d) unconstrained factors of the velocity residual covariances.
        eps: margin (scaled units), A_k + A_k^T <= -2 eps I.
        reg: diagonal added to every covariance (scaled units squared).
    """

    def __init__(
        self,
        logits: Tensor,
        means: Tensor,
        cov_factors: Tensor,
        stable_factors: Tensor,
        skew_factors: Tensor,
        residual_factors: Tensor,
        eps: float,
        reg: float,
    ):
        super().__init__()
        self.logits = torch.nn.Parameter(logits)
        self.means = torch.nn.Parameter(means)
        self.cov_factors = torch.nn.Parameter(cov_factors)
        self.stable_factors = torch.nn.Parameter(stable_factors)
        self.skew_factors = torch.nn.Parameter(skew_factors)
        self.residual_factors = torch.nn.Parameter(residual_factors)
        self.eps = float(eps)
        self.reg = float(reg)

    @property
    def dim(self) -> int:
        return self.means.shape[-1]

    def system_matrices(self) -> Tensor:
        """(K, d, d) A_k = -(L L^T + eps I) + (W - W^T)."""
        L = _tril_with_log_diag(self.stable_factors)
        eye = torch.eye(self.dim, dtype=L.dtype, device=L.device)
        return -(L @ L.transpose(-2, -1) + self.eps * eye) + (self.skew_factors - self.skew_factors.transpose(-2, -1))

    def _cov_cholesky(self, raw: Tensor) -> Tensor:
        """Cholesky factor of C C^T + reg I (exact, via torch.linalg.cholesky)."""
        C = _tril_with_log_diag(raw)
        eye = torch.eye(self.dim, dtype=C.dtype, device=C.device)
        return torch.linalg.cholesky(C @ C.transpose(-2, -1) + self.reg * eye)

    def covariances(self) -> Tensor:
        """(K, d, d) position covariances S_k."""
        L = self._cov_cholesky(self.cov_factors)
        return L @ L.transpose(-2, -1)

    def residual_covariances(self) -> Tensor:
        """(K, d, d) velocity residual covariances R_k."""
        L = self._cov_cholesky(self.residual_factors)
        return L @ L.transpose(-2, -1)

    @staticmethod
    def _log_normal(y: Tensor, mean: Tensor, chol: Tensor) -> Tensor:
        """log N(y_n; m, L_k L_k^T) for m = mean (K, d) or (N, K, d); y (N, 1, d), chol (K, d, d) -> (N, K)."""
        diff = (y - mean).permute(1, 2, 0)  # (K, d, N)
        z = torch.linalg.solve_triangular(chol, diff, upper=False)
        half_log_det = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
        d = y.shape[-1]
        return (-0.5 * (z * z).sum(-2) - half_log_det[:, None] - 0.5 * d * math.log(2 * math.pi)).T

    def log_joint_position(self, xs: Tensor) -> Tensor:
        """(N, K) log pi_k + log N(xs; mu_k, S_k)."""
        chol = self._cov_cholesky(self.cov_factors)
        return torch.log_softmax(self.logits, -1) + self._log_normal(xs.unsqueeze(1), self.means, chol)

    def regression(self, xs: Tensor) -> Tensor:
        """(N, d) f(xs) = sum_k h_k(xs) A_k xs in scaled coordinates."""
        h = torch.softmax(self.log_joint_position(xs), -1)
        return torch.einsum("nk,kij,nj->ni", h, self.system_matrices(), xs)

    def mse(self, xs: Tensor, vs: Tensor) -> Tensor:
        """Mean squared velocity error (scaled units)."""
        return (vs - self.regression(xs)).pow(2).sum(-1).mean()

    def negative_log_likelihood(self, xs: Tensor, vs: Tensor) -> Tensor:
        """-(1/N) sum_n log p(xs_n, vs_n): p_k(x, v) = N(x; mu_k, S_k) N(v; A_k x, R_k) (x centred at g)."""
        A = self.system_matrices()
        pred = torch.einsum("kij,nj->nki", A, xs)  # (N, K, d)
        chol_r = self._cov_cholesky(self.residual_factors)
        log_v = self._log_normal(vs.unsqueeze(1), pred, chol_r)
        return -torch.logsumexp(self.log_joint_position(xs) + log_v, -1).mean()


def _init_parameters(joint: GMM, d: int, eps: float, reg: float) -> SEDSParameters:
    """SEDS parameters from an EM fit of the scaled joint data, projected onto the constraint set."""
    w, mu, S = joint.weights, joint.means, joint.covariances
    Sxx, Svx, Svv = S[:, :d, :d], S[:, d:, :d], S[:, d:, d:]
    A0 = torch.linalg.solve(Sxx, Svx.transpose(-2, -1)).transpose(-2, -1)  # Svx Sxx^-1
    sym = 0.5 * (A0 + A0.transpose(-2, -1))
    skew = 0.5 * (A0 - A0.transpose(-2, -1))
    evals, evecs = torch.linalg.eigh(sym)
    evals = torch.clamp(evals, max=-2.0 * eps)  # the symmetric part must be <= -eps I; keep a margin for L
    eye = torch.eye(d, dtype=S.dtype, device=S.device)
    LLt = -(evecs @ torch.diag_embed(evals) @ evecs.transpose(-2, -1)) - eps * eye
    L = torch.linalg.cholesky(0.5 * (LLt + LLt.transpose(-2, -1)))
    R0 = Svv - A0 @ Sxx @ A0.transpose(-2, -1)
    R0 = 0.5 * (R0 + R0.transpose(-2, -1))
    r_evals, r_evecs = torch.linalg.eigh(R0)
    floor = 1e-3 * float(torch.diagonal(Svv, dim1=-2, dim2=-1).mean())
    R0 = r_evecs @ torch.diag_embed(torch.clamp(r_evals, min=floor)) @ r_evecs.transpose(-2, -1)

    def factor(C: Tensor) -> Tensor:
        C = C - reg * eye
        vals, vecs = torch.linalg.eigh(0.5 * (C + C.transpose(-2, -1)))
        C = vecs @ torch.diag_embed(torch.clamp(vals, min=reg)) @ vecs.transpose(-2, -1)
        return _inverse_tril_with_log_diag(torch.linalg.cholesky(0.5 * (C + C.transpose(-2, -1))))

    return SEDSParameters(
        logits=torch.log(w.clamp_min(1e-12)),
        means=mu[:, :d].clone(),
        cov_factors=factor(Sxx),
        stable_factors=_inverse_tril_with_log_diag(L),
        skew_factors=0.5 * skew,
        residual_factors=factor(R0),
        eps=eps,
        reg=reg,
    )


def fit_seds(
    demos: Demos,
    attractor: Tensor | None = None,
    *,
    n_components: int | None = None,
    k_range: Iterable[int] = range(2, 11),
    objective: str = "mse",
    eps: float = 1e-3,
    reg: float = 1e-4,
    max_iter: int = 300,
    tolerance_grad: float = 1e-7,
    tolerance_change: float = 1e-10,
    em_n_init: int = 1,
    generator: torch.Generator,
) -> SEDS:
    """Fit SEDS to demonstrations (module docstring).

    Args:
        demos: training demonstrations (all valid samples are used).
        attractor: optional (d,) goal; default ``demos.attractor``.
        n_components: K; None chooses K by BIC of an EM fit of the joint data over ``k_range``.
        k_range: candidate K when ``n_components`` is None.
        objective: ``"mse"`` (velocity mean squared error) or ``"likelihood"`` (joint negative log-likelihood).
        eps: stability margin (1/s): A_k + A_k^T <= -2 eps I.
        reg: diagonal added to the covariances in scaled (unit-RMS) coordinates.
        max_iter: L-BFGS iterations.
        tolerance_grad: L-BFGS first-order optimality tolerance.
        tolerance_change: L-BFGS tolerance on changes of the objective and parameters.
        em_n_init: k-means++ restarts of the EM initialisation.
        generator: torch generator for the EM initialisation (the only randomness).

    Returns:
        A certified :class:`SEDS` (P = I). ``info`` holds K, the objective, the training MSE (units^2/s^2), the
        number of L-BFGS iterations, and the time of the initialisation and of the optimisation (s).

    Raises:
        UnknownNameError: unknown ``objective``.
        TooFewSamplesError, ShapeMismatchError, NonFiniteError: malformed input.
        SolverError: the optimisation produced a non-finite objective.
        CertificationError: the result fails lambda_max(A_k + A_k^T) < 0 in float64.
    """
    if objective not in SEDS_OBJECTIVES:
        raise UnknownNameError("SEDS objective", str(objective), SEDS_OBJECTIVES)
    if not eps > 0:
        raise ValueError(f"eps must be positive, got {eps}")
    if not reg > 0:
        raise ValueError(f"reg must be positive, got {reg}")
    t0 = time.perf_counter()
    x, x_dot, g = training_samples(demos, attractor)
    N, d = x.shape
    f64 = dict(dtype=torch.float64, device=x.device)
    e = (x - g).to(**f64)
    v = x_dot.to(**f64)
    s = float(e.pow(2).sum(-1).mean().sqrt())
    u = float(v.pow(2).sum(-1).mean().sqrt())
    if not (s > 0 and u > 0):
        raise TooFewSamplesError("all samples sit at the attractor or at rest; nothing to fit")
    xs, vs = e / s, v / u
    joint_data = torch.cat([xs, vs], dim=-1)
    if n_components is None:
        joint = fit_em_bic(joint_data, k_range=k_range, generator=generator, n_init=em_n_init)
    else:
        if int(n_components) < 1 or int(n_components) > N:
            raise TooFewSamplesError(f"n_components={n_components} needs 1 <= K <= N = {N}")
        joint = fit_em(joint_data, int(n_components), generator=generator, n_init=em_n_init)
    eps_s = eps * s / u
    params = _init_parameters(joint, d, eps_s, reg)
    t_init = time.perf_counter()

    loss_fn = params.mse if objective == "mse" else params.negative_log_likelihood
    optimizer = torch.optim.LBFGS(
        params.parameters(),
        lr=1.0,
        max_iter=int(max_iter),
        tolerance_grad=tolerance_grad,
        tolerance_change=tolerance_change,
        history_size=20,
        line_search_fn="strong_wolfe",
    )
    initial = {k: p.detach().clone() for k, p in params.named_parameters()}
    with torch.no_grad():
        initial_loss = float(loss_fn(xs, vs))

    def closure() -> Tensor:
        optimizer.zero_grad()
        loss = loss_fn(xs, vs)
        loss.backward()
        return loss

    try:
        optimizer.step(closure)
    except torch.linalg.LinAlgError:
        pass  # handled below: fall back to the initialisation
    with torch.no_grad():
        try:  # parameters that left the representable range make a covariance factorisation fail: fall back
            final_loss = float(loss_fn(xs, vs)) if all(torch.isfinite(p).all() for p in params.parameters()) else math.nan
        except torch.linalg.LinAlgError:
            final_loss = math.nan
        if not math.isfinite(final_loss) or final_loss > initial_loss:
            for k, p in params.named_parameters():
                p.copy_(initial[k])
            final_loss = initial_loss
        if not math.isfinite(final_loss):
            raise SolverError(f"SEDS {objective} objective is not finite at the initialisation")
        first = optimizer.param_groups[0]["params"][0]
        n_iter = int(optimizer.state[first].get("n_iter", 0))
        A_s = params.system_matrices()
        gmm = GMM(
            torch.softmax(params.logits, -1),
            g.to(**f64) + s * params.means,
            s * s * params.covariances(),
        )
        A = A_s * (u / s)
        margins = quadratic_margins(A, torch.eye(d, **f64))
        if not bool((margins < 0).all()):
            raise CertificationError(f"SEDS produced lambda_max(A_k + A_k^T) = {margins.tolist()}; all must be < 0")
        gamma = gmm.posterior(x.to(**f64))
        pred = torch.einsum("nk,kij,nj->ni", gamma, A, e)
        if objective == "likelihood":
            Sv = u * u * params.residual_covariances()
        else:
            Sv = residual_velocity_covariances(gamma, x.to(**f64), v, A, g.to(**f64))
    t_opt = time.perf_counter()
    info = {
        "method": "seds",
        "objective": objective,
        "eps": float(eps),
        "reg": float(reg),
        "n_components": gmm.n_components,
        "n_samples": int(N),
        "n_iter": n_iter,
        "initial_objective": initial_loss,
        "final_objective": final_loss,
        "train_mse": float((v - pred).pow(2).sum(-1).mean()),
        "max_margin": float(margins.max()),
        "time_init_s": t_init - t0,
        "time_opt_s": t_opt - t_init,
        "time_total_s": t_opt - t0,
    }
    f = dict(dtype=x.dtype, device=x.device)
    return SEDS(
        gmm=gmm.to(**f), A=A.to(**f), attractor=g, P=torch.eye(d, **f), velocity_covariances=Sv.to(**f), info=info
    )
