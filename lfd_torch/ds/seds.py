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

Fitting. An EM fit of the joint data with K components initialises the parameters (A_k from the joint covariance,
projected onto the constraint set); then *all* parameters (priors, means, position covariances, A_k, residual
covariances) are optimised with full-batch L-BFGS (strong Wolfe line search) on either the joint negative
log-likelihood (``objective="likelihood"``, default) or the mean squared velocity error (``objective="mse"``), as in
Khansari-Zadeh's solver. The (S_k, A_k, R_k) parametrisation covers every positive-definite joint covariance whose
GMR slope A_k satisfies the constraint, so this is the constrained problem of the paper, solved without a
constrained solver. Data are scaled to unit RMS around g internally; eps is in 1/s in the original units. The
certificate lambda_max(A_k + A_k^T) < 0 is verified in float64 before a model is returned. If L-BFGS reaches a
non-finite point or fails a factorisation (parameters that left the representable range), it is restarted from the
best point it evaluated with a fresh history (at most ``max_restarts`` times, within ``max_iter`` iterations in
all); if it still ends there or above that best point, the best point (possibly the initialisation) is returned (``info["fallback"]``:
``"best_iterate"`` or ``"initialisation"``; None when the last iterate is kept).

Defaults and why (the one-demonstration regime of the paper: train on one LASA demonstration, ~500 samples,
test on the other six; measured by ``experiments/bench_seds.py``). The former defaults (MSE objective, K by the
plain BIC of the joint EM fit over 2..10, covariance floor 1e-4) predicted up to ~5,000 mm/s at test states where
the demonstrations move at <= 65 mm/s, and some rollouts stalled for 30 s a few mm from the goal. Three causes:

* K. The samples of one demonstration are a smooth curve sampled every 20 ms, strongly autocorrelated
  (integrated autocorrelation time 15-180 samples), so the plain BIC, which assumes N independent samples,
  picks K = 9-10 on every shape. Each component then sees a short, nearly straight stretch of one curve, on which
  A_k is identified only along the stretch; its other directions are free (up to the constraint).
* Collapsed covariances. Across the curve a component's position covariance collapses to the floor (1e-4 of the
  squared RMS radius: ~1 mm on LASA). A few mm off the demonstration the gating h_k(x) is then decided by
  Mahalanobis distances across these collapsed directions, so a distant, broader component can win over the near
  one, and its A_k, fitted to another stretch, is applied far from that stretch: very large velocities, or a
  symmetric part at its bound -eps (a contraction rate of 1e-3 1/s) that stalls rollouts near the goal.
* Unidentified gains near the goal. The last samples of a demonstration sit at the goal with e = x - g ~ 0, where
  A_k e ~ 0 whatever A_k is: the component covering them can take gains of hundreds of 1/s (seen: 490 1/s,
  555 mm/s at a test state 3 mm from the goal) at no cost in either objective.
* The MSE objective fits only the regression: priors, means and covariances are free to shape the gating in any
  way that lowers the training error, which makes the off-demonstration gating even less constrained. The
  likelihood ties the position marginal to the data.

Hence: ``objective="likelihood"``; ``reg=1e-2`` (the covariance floor, in unit-RMS coordinates: every
component extends at least 0.1 x the RMS distance of the data to the attractor in every direction, which sets
the spatial resolution of the gating off the demonstration; chosen from {1e-4, 1e-3, 1e-2} on the development
shapes Snake, Sshape, NShape, JShape, Angle and Trapezoid, and checked on the other LASA shapes);
``gain_prior=10`` (MAP instead of maximum likelihood: a weak Gaussian prior N(-I, 10^2) on the entries of every
A_k in scaled units, i.e. centred on the linear system x_dot = -(u / s)(x - g) that converges at the data's own
time scale, u the RMS speed and s the RMS distance to g, with std 10 u / s; for gains of the data's order it costs
~1e-4 nats per sample and it settles the gains the data do not determine. Chosen after the JShape_2 fit of seed 1
(gain 490 1/s without it); a prior centred at 0 instead shrinks the contraction of unidentified directions towards
-eps and stalled the rollouts of LShape and JShape_2 ~13 mm from the goal); and
``k_selection="pcgmm"``: K is the number of components of the PC-GMM that LPV-DS uses on the same training
positions and velocities (:class:`~lfd_torch.gmm.PCGMMFitter`, the defaults or ``pcgmm``, called exactly as
:func:`~lfd_torch.ds.fit_lpvds` calls it), so that a comparison of SEDS with LPV-DS uses one model-selection rule
and the same K on the training data only, and differs only in how the dynamics are learned. With the same
generator seed, SEDS and LPV-DS get the very same K.

Other rules (``k_selection``): ``"ess_bic"`` picks K over ``k_range`` by the effective-sample-size BIC
(:func:`lfd_torch.gmm.em.bic` with ``n_effective`` from :func:`lfd_torch.gmm.em.effective_sample_size` per
demonstration on the scaled joint data); it is sane (no blow-ups) but picks K = 2-3 on single LASA
demonstrations, too few for the sharpest shapes; ``"bic"`` is the former plain BIC.
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
from lfd_torch.ds.lpvds import resolve_gmm, training_samples
from lfd_torch.ds.primitive import StablePrimitive, quadratic_margins, residual_velocity_covariances
from lfd_torch.errors import CertificationError, InvalidArgumentError, SolverError, TooFewSamplesError
from lfd_torch.gmm import GMM, PCGMMFitter, fit_em, fit_em_bic
from lfd_torch.gmm.em import MAX_ITER, MAX_RESTARTS, check_k_range, effective_sample_size
from lfd_torch.utils import check_choice, check_float, check_generator, check_int, solver_errors

__all__ = ["SEDS", "SEDS_OBJECTIVES", "SEDS_K_SELECTIONS", "fit_seds", "SEDSParameters"]

#: Accepted values of ``objective``.
SEDS_OBJECTIVES: tuple[str, ...] = ("mse", "likelihood")
#: Accepted values of ``k_selection`` (how K is chosen when ``n_components`` is None).
SEDS_K_SELECTIONS: tuple[str, ...] = ("pcgmm", "ess_bic", "bic")


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


def _gain_penalty(A: Tensor, prior_mean: Tensor, gain_prior: float, n: int = 1) -> Tensor:
    """-log N(A; prior_mean, gain_prior^2 I) summed over the entries of A (K, d, d), up to its constant, per sample
    of ``n``: the MAP term of ``gain_prior`` (prior_mean -I)."""
    penalty = (A - prior_mean).pow(2).sum()
    return penalty / (2.0 * gain_prior**2 * n)


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


def _representable(params: SEDSParameters) -> bool:
    """True when the parameters, the A_k and both covariance families are finite and factorisable."""
    with torch.no_grad():
        try:
            tensors = [*params.parameters(), params.system_matrices(), params.covariances(), params.residual_covariances()]
        except torch.linalg.LinAlgError:
            return False
        return all(bool(torch.isfinite(t).all()) for t in tensors)


def fit_seds(
    demos: Demos,
    attractor: Tensor | None = None,
    *,
    n_components: int | None = None,
    k_selection: str = "pcgmm",
    pcgmm: PCGMMFitter | None = None,
    k_range: Iterable[int] = range(2, 11),
    objective: str = "likelihood",
    eps: float = 1e-3,
    reg: float = 1e-2,
    gain_prior: float | None = 10.0,
    max_iter: int = 300,
    max_restarts: int = 3,
    tolerance_grad: float = 1e-7,
    tolerance_change: float = 1e-10,
    em_n_init: int = 1,
    generator: torch.Generator,
) -> SEDS:
    """Fit SEDS to demonstrations (module docstring).

    Args:
        demos: training demonstrations (all valid samples are used).
        attractor: optional (d,) goal; default ``demos.attractor``.
        n_components: K; None chooses K by ``k_selection``.
        k_selection: how K is chosen when ``n_components`` is None (module docstring): ``"pcgmm"`` (default; K of
            the PC-GMM LPV-DS fits to the same positions and velocities), ``"ess_bic"`` (effective-sample-size BIC
            of EM fits of the joint data over ``k_range``) or ``"bic"`` (plain BIC over ``k_range``).
        pcgmm: the PC-GMM fitter for ``k_selection="pcgmm"``; None: ``PCGMMFitter()`` (LPV-DS's default).
        k_range: candidate K for the BIC rules.
        objective: ``"likelihood"`` (joint negative log-likelihood, default) or ``"mse"`` (velocity mean squared
            error).
        eps: stability margin (1/s): A_k + A_k^T <= -2 eps I.
        reg: diagonal added to the position and residual covariances in scaled (unit-RMS) coordinates (the
            covariance floor; module docstring).
        gain_prior: standard deviation of a Gaussian prior N(-I, gain_prior^2) on the entries of every A_k, in
            units of u / s (the RMS speed over the RMS distance to g of the training data), added to either
            objective as ||A_k + I||^2 / (2 gain_prior^2 N) summed over k; None: no prior (maximum likelihood /
            least squares).
        max_iter: L-BFGS iterations (in total, over restarts), in [1, 100000]; each costs O(N K d^2).
        max_restarts: restarts of L-BFGS from the best point evaluated when it leaves the representable range,
            in [0, 1000].
        tolerance_grad: L-BFGS first-order optimality tolerance.
        tolerance_change: L-BFGS tolerance on changes of the objective and parameters.
        em_n_init: k-means++ restarts of the EM initialisation, in [1, 1000].
        generator: torch generator for PC-GMM (``k_selection="pcgmm"``) and the EM initialisation (the only
            randomness).

    Returns:
        A certified :class:`SEDS` (P = I). ``info`` holds K, how it was chosen (``k_selection``; ``"given"`` for an
        explicit ``n_components``), N_eff for ``"ess_bic"``, the objective, the training MSE (units^2/s^2), the
        number of L-BFGS iterations, the fallback taken (module docstring), and the time of the
        initialisation and of the optimisation (s).

    Raises:
        UnknownNameError: unknown ``objective`` or ``k_selection``.
        TooFewSamplesError, ShapeMismatchError, NonFiniteError: malformed input.
        InvalidArgumentError: a hyperparameter of the wrong type or out of range (e.g. ``n_components=2.5``,
            ``max_iter=0``), or no generator.
        SolverError: the optimisation produced a non-finite objective.
        CertificationError: the result fails lambda_max(A_k + A_k^T) < 0 in float64.
    """
    check_choice(objective, "objective", SEDS_OBJECTIVES)
    check_choice(k_selection, "k_selection", SEDS_K_SELECTIONS)
    check_int(n_components, "n_components", low=1, allow_none=True)
    check_float(eps, "eps", low=0.0, low_open=True)
    check_float(reg, "reg", low=0.0, low_open=True)
    check_float(gain_prior, "gain_prior", low=0.0, low_open=True, allow_none=True)
    check_int(max_iter, "max_iter", low=1, high=MAX_ITER)
    check_int(max_restarts, "max_restarts", low=0, high=MAX_RESTARTS)
    check_int(em_n_init, "em_n_init", low=1, high=MAX_RESTARTS)
    check_float(tolerance_grad, "tolerance_grad", low=0.0)
    check_float(tolerance_change, "tolerance_change", low=0.0)
    check_generator(generator, where="fit_seds")
    if pcgmm is not None and not callable(pcgmm):
        raise InvalidArgumentError(f"pcgmm must be a PC-GMM fitter (e.g. PCGMMFitter()) or None, got {pcgmm!r}")
    t0 = time.perf_counter()
    x, x_dot, g = training_samples(demos, attractor)
    N, d = x.shape
    if n_components is None and k_selection != "pcgmm":
        check_k_range(k_range, N)
    f64 = dict(dtype=torch.float64, device=x.device)
    e = (x - g).to(**f64)
    v = x_dot.to(**f64)
    s = float(e.pow(2).sum(-1).mean().sqrt())
    u = float(v.pow(2).sum(-1).mean().sqrt())
    if not (s > 0 and u > 0):
        raise TooFewSamplesError("all samples sit at the attractor or at rest; nothing to fit")
    xs, vs = e / s, v / u
    joint_data = torch.cat([xs, vs], dim=-1)
    n_eff = None
    if n_components is None and k_selection == "pcgmm":
        # the position GMM LPV-DS would get (same fitter, same call, same generator state)
        position_gmm = resolve_gmm(pcgmm if pcgmm is not None else PCGMMFitter(), x, x_dot, generator)
        joint = fit_em(joint_data, position_gmm.n_components, generator=generator, n_init=em_n_init)
    elif n_components is None:
        if k_selection == "ess_bic":
            _, _, demo_index = demos.samples()
            n_eff = effective_sample_size(joint_data, demo_index.to(x.device))
        joint = fit_em_bic(joint_data, k_range=k_range, generator=generator, n_init=em_n_init, n_effective=n_eff)
    else:
        if n_components > N:
            raise TooFewSamplesError(f"n_components={n_components} needs 1 <= K <= N = {N}")
        joint = fit_em(joint_data, n_components, generator=generator, n_init=em_n_init)
    eps_s = eps * s / u
    with solver_errors("SEDS initialisation"):
        params = _init_parameters(joint, d, eps_s, reg)
    t_init = time.perf_counter()

    data_loss = params.mse if objective == "mse" else params.negative_log_likelihood
    if gain_prior is None:
        loss_fn = data_loss
    else:  # MAP: Gaussian prior N(-I, gain_prior^2) on the entries of A_k (scaled units), per sample
        prior_mean = -torch.eye(d, **f64)

        def loss_fn(xs: Tensor, vs: Tensor) -> Tensor:
            # the penalty's graph first: it fixes the order of the gradient sums, and L-BFGS amplifies a change
            # of their last bits into another fit
            penalty = _gain_penalty(params.system_matrices(), prior_mean, gain_prior, N)
            return data_loss(xs, vs) + penalty
    def make_optimizer(budget: int) -> torch.optim.LBFGS:
        return torch.optim.LBFGS(
            params.parameters(),
            lr=1.0,
            max_iter=budget,
            tolerance_grad=tolerance_grad,
            tolerance_change=tolerance_change,
            history_size=20,
            line_search_fn="strong_wolfe",
        )

    initial = {k: p.detach().clone() for k, p in params.named_parameters()}
    with torch.no_grad():
        initial_loss = float(loss_fn(xs, vs))
    best: dict[str, Any] = {"loss": initial_loss, "params": initial, "initial": True}
    optimizer = make_optimizer(int(max_iter))

    def closure() -> Tensor:
        optimizer.zero_grad()
        loss = loss_fn(xs, vs)
        value = float(loss.detach())
        if math.isfinite(value) and value < best["loss"] and _representable(params):  # kept for a fallback
            best.update(loss=value, params={k: p.detach().clone() for k, p in params.named_parameters()}, initial=False)
        loss.backward()
        return loss

    # L-BFGS; when it leaves the representable range (overflowing factors, failing factorisations), restart it
    # from the best point evaluated with a fresh history, within the same total iteration budget
    n_iter, restarts, remaining = 0, 0, int(max_iter)
    while True:
        try:
            optimizer.step(closure)
        except torch.linalg.LinAlgError:
            pass
        first = optimizer.param_groups[0]["params"][0]
        used = max(1, int(optimizer.state[first].get("n_iter", 0)))
        n_iter += used
        remaining -= used
        with torch.no_grad():
            ok = _representable(params) and math.isfinite(float(loss_fn(xs, vs)))
            if ok or remaining <= 0 or restarts >= max_restarts:
                break
            for k, p in params.named_parameters():
                p.copy_(best["params"][k])
        restarts += 1
        optimizer = make_optimizer(remaining)
    with torch.no_grad():
        final_loss = float(loss_fn(xs, vs)) if _representable(params) else math.nan
        fallback = None
        if not math.isfinite(final_loss) or final_loss > best["loss"]:
            for k, p in params.named_parameters():
                p.copy_(best["params"][k])
            final_loss = best["loss"]
            fallback = "initialisation" if best["initial"] else "best_iterate"
        if not math.isfinite(final_loss):
            raise SolverError(f"SEDS {objective} objective is not finite at the initialisation")
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
        "k_selection": "given" if n_components is not None else k_selection,
        "n_effective": n_eff,
        "eps": float(eps),
        "reg": float(reg),
        "gain_prior": None if gain_prior is None else float(gain_prior),
        "n_components": gmm.n_components,
        "n_samples": int(N),
        "n_iter": n_iter,
        "n_restarts": restarts,
        "fallback": fallback,
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
