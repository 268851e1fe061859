"""Independent references for the disturbance modulation, SEDS and the convex-solver helper, each written against a
mutant that the other tests let through: closed forms evaluated by naive loops, scipy densities, numpy quantiles,
the documented branch rules on exact ties, the configs in conf/, and stub cvxpy problems for the solver contract."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from lfd_torch.errors import InvalidArgumentError, SolverError
from lfd_torch.modulation import (
    Branch,
    Modulation,
    goal_direction,
    large_scale_factor,
    large_scale_gain,
    modulate,
    modulated_velocity,
    modulated_velocity_single,
    reference_entropy,
    renyi_entropy,
    velocity_mixture,
)
from test_modulation import pqlf_primitive
from test_primitive_contract import small_lasa

CONF = Path(__file__).resolve().parents[1] / "conf"
F64 = torch.float64


# ---------------------------------------------------------------------------------------------------- matrix
def test_goal_direction_has_a_finite_gradient_at_the_goal() -> None:
    """Property: e_g is 0 at x = g with a finite gradient there (the double-where guard of the division: a NaN
    gradient would poison any differentiable use of the modulated field through the goal), and the closed-form
    gradient (I - e_g e_g^T) w / r of w^T e_g elsewhere."""
    g = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    x = torch.stack([g, g + torch.tensor([3.0, 0.0, 4.0], dtype=F64)]).requires_grad_(True)
    unit, r = goal_direction(x, g)
    assert (unit[0] == 0).all() and float(r[0].detach()) == 0.0
    w = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    (unit * w).sum().backward()
    assert torch.isfinite(x.grad).all()
    # away from the goal: d(w^T e_g)/dx = (I - e_g e_g^T) w / r (closed form)
    e = torch.tensor([0.6, 0.0, 0.8], dtype=F64)
    torch.testing.assert_close(x.grad[1], (w - (e @ w) * e) / 5.0, rtol=1e-12, atol=1e-15)


# ---------------------------------------------------------------------------------------------------- factors
def test_large_scale_factor_is_minus_sign_of_c_times_the_clipped_density_ratio() -> None:
    """Eq. 13 by a naive scalar loop: lambda_ls = -sgn(c) max(min(lambda_limit, p_other / p_own), 1) (0 at c = 0),
    and the modulated velocity diag(lambda_ls, 0) in the W frame, lambda_ls c e_g = -|c| s e_g, points at g."""
    gen = torch.Generator().manual_seed(11)
    n, limit = 64, 2.5
    own = torch.randn(n, dtype=F64, generator=gen)
    other = own + 2.0 * torch.randn(n, dtype=F64, generator=gen)
    c = torch.randn(n, dtype=F64, generator=gen)
    c[:4] = 0.0
    got = large_scale_factor(own, other, c, limit)
    want = []
    for o, p, cc in zip(own.tolist(), other.tolist(), c.tolist()):
        sgn = 0.0 if cc == 0 else math.copysign(1.0, cc)
        want.append(-sgn * max(min(limit, math.exp(p - o)), 1.0))
    torch.testing.assert_close(got, torch.tensor(want, dtype=F64), rtol=1e-12, atol=0.0)
    # through the closed-form W D W^T: the velocity is along -e_g with speed |c| s
    x = torch.randn(n, 3, dtype=F64, generator=gen)
    unit = goal_direction(x, torch.zeros(3, dtype=F64)).unit
    f = torch.randn(n, 3, dtype=F64, generator=gen)
    cf = (f * unit).sum(-1)
    lam = large_scale_factor(own, other, cf, limit)
    v = modulate(f, unit, lam, torch.zeros(n, dtype=F64))
    s = large_scale_gain(own, other, limit)
    torch.testing.assert_close(v, -(cf.abs() * s).unsqueeze(-1) * unit, rtol=1e-12, atol=1e-14)


def test_lambda_limit_one_is_accepted_and_means_no_acceleration() -> None:
    """The documented domain lambda_limit >= 1 includes 1: then s = 1 whatever the densities (closed form)."""
    own = torch.tensor([0.0, -5.0, 3.0, -math.inf], dtype=F64)
    other = torch.tensor([4.0, 0.0, -1.0, 0.0], dtype=F64)
    torch.testing.assert_close(large_scale_gain(own, other, 1.0), torch.ones(4, dtype=F64))
    assert Modulation(lambda_limit=1.0).lambda_limit == 1.0
    with pytest.raises(InvalidArgumentError, match="lambda_limit"):
        large_scale_gain(own, other, 0.999)


def test_radial_floor_one_is_accepted_and_gives_the_full_speed_towards_the_goal() -> None:
    """The documented domain kappa in [0, 1] includes 1: then a = max(|c|, ||f||) = ||f|| and the large-scale
    velocity is -s ||f|| e_g (closed form; the upper end of the speed range [kappa s ||f||, s ||f||])."""
    gen = torch.Generator().manual_seed(13)
    x = torch.randn(8, 3, dtype=F64, generator=gen)
    f = torch.randn(8, 3, dtype=F64, generator=gen)
    g = torch.zeros(3, dtype=F64)
    own = torch.zeros(8, dtype=F64)
    res = modulated_velocity(x, f, g, log_p_own=own, log_p_other=own + math.log(2.0), mode="large", radial_floor=1.0)
    unit = x / x.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(res.velocity, -2.0 * f.norm(dim=-1, keepdim=True) * unit, rtol=1e-12, atol=1e-14)
    assert Modulation(radial_floor=1.0).radial_floor == 1.0


# ---------------------------------------------------------------------------------------------------- entropy
def test_velocity_mixture_and_entropy_match_a_naive_scipy_double_loop() -> None:
    """Eq. 15 with the NOTES 4a/4b corrections by a naive loop with scipy densities: w_k = pi_k N(x; mu_k^x,
    Sigma_k^x), mu_k(x) = A_k (x - g), H2 = -log sum_ij w_i w_j N(mu_i; mu_j, S_i + S_j); the goal is far from the
    origin so that A_k x and A_k (x - g) differ, and the A_k are not symmetric so that A_k and A_k^T differ."""
    gen = torch.Generator().manual_seed(3)
    prim = pqlf_primitive(3, 3, gen)
    assert float((prim.A - prim.A.transpose(-2, -1)).abs().max()) > 0.1 and float(prim.attractor.norm()) > 0.5
    x = prim.gmm.means[[0, 1, 2, 0]] + 0.7 * torch.randn(4, 3, dtype=F64, generator=gen)
    mix = velocity_mixture(prim, x)
    h2 = renyi_entropy(prim, x)
    pi = prim.gmm.weights.numpy()
    mx, Sx = prim.gmm.means.numpy(), prim.gmm.covariances.numpy()
    A, g, Sv = prim.A.numpy(), prim.attractor.numpy(), prim.velocity_covariances.numpy()
    K = A.shape[0]
    for b, xb in enumerate(x.numpy()):
        w = np.array([pi[k] * multivariate_normal(mx[k], Sx[k]).pdf(xb) for k in range(K)])
        mu = np.array([A[k] @ (xb - g) for k in range(K)])
        np.testing.assert_allclose(mix.means[b].numpy(), mu, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(mix.log_weights[b].numpy(), np.log(w), rtol=1e-12)
        total = sum(w[i] * w[j] * multivariate_normal(mu[j], Sv[i] + Sv[j]).pdf(mu[i]) for i in range(K) for j in range(K))
        assert math.isclose(float(h2[b]), -math.log(total), rel_tol=1e-10), (b, float(h2[b]), -math.log(total))


def test_reference_entropy_quantiles_match_numpy() -> None:
    """H2(x_r) as the q-quantile of H2 over the training states, q in the closed interval [0, 1]: numpy.quantile
    (linear interpolation) as the reference, including the end points q = 0 (minimum) and q = 1 (maximum)."""
    gen = torch.Generator().manual_seed(5)
    prim = pqlf_primitive(2, 3, gen)
    x = prim.gmm.means.repeat(7, 1) + torch.randn(21, 2, dtype=F64, generator=gen)
    h2 = renyi_entropy(prim, x).numpy()
    for q in (0.0, 0.25, 0.5, 1.0):
        got = float(reference_entropy(prim, x, q))
        assert math.isclose(got, float(np.quantile(h2, q)), rel_tol=1e-12), q
    assert Modulation(entropy_quantile=0.0).entropy_quantile == 0.0


# ---------------------------------------------------------------------------------------------------- policy
def test_entropy_exactly_at_the_threshold_is_unmodulated() -> None:
    """Branch rule on the tie H2(x) = H2_ref (policy docstring: 'unmodulated, x inside A_m and H2(x) <= H2_ref'):
    D = I, M f = f, in the tensor and the single-sample forms, while H2 just above the threshold is small-scale
    with M f = lambda_ss f - a e_g (closed form)."""
    gen = torch.Generator().manual_seed(17)
    n, d = 12, 3
    g = torch.randn(d, dtype=F64, generator=gen)
    x = g + torch.randn(n, d, dtype=F64, generator=gen)
    f = torch.randn(n, d, dtype=F64, generator=gen)
    own = torch.zeros(n, dtype=F64)
    other = torch.full((n,), -1.0, dtype=F64)  # inside A_m
    ref = torch.randn(n, dtype=F64, generator=gen)
    for mode in ("small", "full"):
        res = modulated_velocity(x, f, g, log_p_own=own, log_p_other=other, h2=ref.clone(), h2_ref=ref, mode=mode)
        assert (res.branch == Branch.UNMODULATED).all(), mode
        assert torch.equal(res.velocity, f)
        above = modulated_velocity(x, f, g, log_p_own=own, log_p_other=other, h2=ref + 0.5, h2_ref=ref, mode=mode)
        assert (above.branch == Branch.SMALL_SCALE).all()
        unit = (x - g) / (x - g).norm(dim=-1, keepdim=True)
        a = torch.maximum((f * unit).sum(-1).abs(), 0.1 * f.norm(dim=-1))
        torch.testing.assert_close(above.velocity, math.exp(-0.5) * f - a.unsqueeze(-1) * unit, rtol=1e-12, atol=1e-14)
        for i in range(n):
            v, branch = modulated_velocity_single((x[i] - g).tolist(), f[i].tolist(), 0.0, -1.0, float(ref[i]),
                                                  float(ref[i]), mode, 3.0, 0.1)  # fmt: skip
            assert branch == Branch.UNMODULATED and v == f[i].tolist(), (mode, i)


def test_dataclass_defaults_match_the_documented_config() -> None:
    """The Python defaults of Modulation (and of the module constants) are the values conf/modulation/full.yaml
    documents: lambda_limit 3, entropy_quantile 1 (the maximum over the training states), radial_floor 0.1."""
    import yaml

    from lfd_torch.modulation import DEFAULT_LAMBDA_LIMIT, DEFAULT_RADIAL_FLOOR

    conf = yaml.safe_load((CONF / "modulation" / "full.yaml").read_text())
    default = Modulation()
    assert default.mode == conf["mode"]
    assert default.lambda_limit == conf["lambda_limit"] == DEFAULT_LAMBDA_LIMIT
    assert default.entropy_quantile == conf["entropy_quantile"]
    assert default.radial_floor == conf["radial_floor"] == DEFAULT_RADIAL_FLOOR


def test_default_modulation_never_stalls_and_accelerates_outside_the_subtask() -> None:
    """Property dV/dt < 0 with V = ||x - g||^2 under the defaults where f is orthogonal to e_g (c = 0, where the
    literal eqs 12/17 stall) in both branches, and the large-scale speed equals max(|c|, kappa ||f||) s with
    s = min(lambda_limit, p_other / p_own) (closed form) where the other subtask is far more likely."""
    gen = torch.Generator().manual_seed(23)
    n, d = 10, 2
    x = torch.randn(n, d, dtype=F64, generator=gen)
    g = torch.zeros(d, dtype=F64)
    e = x / x.norm(dim=-1, keepdim=True)
    f = torch.stack([-e[:, 1], e[:, 0]], -1) * (1.0 + torch.rand(n, 1, dtype=F64, generator=gen))  # c = 0
    own = torch.zeros(n, dtype=F64)
    for other, h2 in ((own + 10.0, own), (own - 1.0, own + 1e4)):  # large scale; small scale with lambda_ss = 0
        v = modulated_velocity(x, f, g, log_p_own=own, log_p_other=other, h2=h2, h2_ref=0.0).velocity  # defaults
        assert (2.0 * (x * v).sum(-1) < 0).all()
    limit = Modulation().lambda_limit
    assert limit > 1.0
    v = modulated_velocity(x, 3.0 * e, g, log_p_own=own, log_p_other=own + 10.0, h2=own, h2_ref=0.0).velocity
    torch.testing.assert_close(v, -3.0 * min(limit, math.exp(10.0)) * e, rtol=1e-12, atol=1e-14)


def test_goal_direction_rejects_an_attractor_of_the_wrong_length() -> None:
    """Contract (matrix docstring): a typed ShapeMismatchError naming the attractor, not a broadcasting error."""
    from lfd_torch.errors import ShapeMismatchError

    x = torch.randn(4, 3, dtype=F64, generator=torch.Generator().manual_seed(31))
    with pytest.raises(ShapeMismatchError, match="attractor"):
        goal_direction(x, torch.zeros(2, dtype=F64))


def test_indefinite_pair_covariance_is_an_error_not_a_nan_entropy() -> None:
    """Contract (entropy docstring): some S_i + S_j not positive definite raises InvalidArgumentError."""
    from lfd_torch.modulation import mixture_renyi_entropy

    bad = torch.stack([torch.eye(2, dtype=F64), -3.0 * torch.eye(2, dtype=F64)])  # S_1 + S_2 = -2 I
    with pytest.raises(InvalidArgumentError, match="positive definite"):
        mixture_renyi_entropy(torch.zeros(2, dtype=F64), torch.zeros(2, 2, dtype=F64), bad)


def test_reference_entropy_of_no_training_states_is_an_error() -> None:
    """Contract (reference_entropy docstring): an empty x is an InvalidArgumentError naming x."""
    prim = pqlf_primitive(2, 2, torch.Generator().manual_seed(37))
    with pytest.raises(InvalidArgumentError, match="x"):
        reference_entropy(prim, torch.empty(0, 2, dtype=F64), 0.5)


def test_mode_none_returns_a_copy_of_f() -> None:
    """Contract (modulated_velocity docstring: 'returns f itself (a clone)'): writing into the result leaves f alone."""
    gen = torch.Generator().manual_seed(41)
    x = torch.randn(4, 3, dtype=F64, generator=gen)
    f = torch.randn(4, 3, dtype=F64, generator=gen)
    keep = f.clone()
    out = modulated_velocity(x, f, torch.zeros(3, dtype=F64), mode="none").velocity
    assert torch.equal(out, f)
    out.add_(1.0)
    assert torch.equal(f, keep)


# ---------------------------------------------------------------------------------------------------- SEDS
def _scaled_joint_objective(model: Any, x: torch.Tensor, v: torch.Tensor, objective: str, gain_prior: float) -> float:
    """The SEDS objective of a returned model, recomputed in the unit-RMS coordinates (x - g) / s, v / u from its
    data-unit GMM, A_k and velocity covariances with scipy: -(1/N) sum_n log p(xs_n, vs_n) (the Jacobian of the
    scaling is d log s + d log u per sample) or the mean squared velocity error / u^2, plus the MAP term
    sum_k ||A_k s / u + I||_F^2 / (2 gain_prior^2 N)."""
    e = (x - model.attractor).numpy()
    vn = v.numpy()
    N, d = e.shape
    s = math.sqrt(float((e**2).sum(-1).mean()))
    u = math.sqrt(float((vn**2).sum(-1).mean()))
    A = model.A.numpy()
    penalty = float(((A * s / u + np.eye(d)) ** 2).sum()) / (2.0 * gain_prior**2 * N)
    if objective == "mse":
        pred = model(x).detach().numpy()
        return float(((vn - pred) ** 2).sum(-1).mean()) / u**2 + penalty
    w, mu, S = model.gmm.weights.numpy(), model.gmm.means.numpy(), model.gmm.covariances.numpy()
    R = model.velocity_covariances.numpy()
    dens = np.zeros(N)
    for k in range(len(w)):
        pos = multivariate_normal(mu[k], S[k]).pdf(x.numpy())
        vel = np.array([multivariate_normal(A[k] @ en, R[k]).pdf(vv) for en, vv in zip(e, vn)])
        dens += w[k] * pos * vel
    return -float(np.mean(np.log(dens) + d * math.log(s) + d * math.log(u))) + penalty


@pytest.mark.parametrize("objective", ["likelihood", "mse"])
def test_seds_reported_objective_is_the_scaled_joint_nll_or_mse_plus_the_per_sample_prior(objective: str) -> None:
    """info['final_objective'] equals the objective recomputed from the returned model by scipy (module docstring:
    unit-RMS scaling, joint density N(x; mu_k, S_k) N(v; A_k (x - g), R_k), MSE = mean over samples of the squared
    velocity norm, MAP term per sample): ties the un-scaling of means, covariances, A_k and R_k, the scale s, and the
    penalty's 1/N to one independent computation."""
    from lfd_torch.ds import fit_seds

    demos = small_lasa("Angle", demos=(0, 1), stride=10)
    x, v, _ = demos.samples()
    model = fit_seds(demos, n_components=2, objective=objective, max_iter=15, generator=torch.Generator().manual_seed(0))
    ref = _scaled_joint_objective(model, x, v, objective, 10.0)
    assert math.isclose(model.info["final_objective"], ref, rel_tol=1e-9), (model.info["final_objective"], ref)
    if objective == "mse":  # S_k: responsibility-weighted residual covariance + one pooled pseudo-sample (naive loop)
        xn, vn, g, A = x.numpy(), v.numpy(), model.attractor.numpy(), model.A.numpy()
        w, mu, S = model.gmm.weights.numpy(), model.gmm.means.numpy(), model.gmm.covariances.numpy()
        N, d = xn.shape
        K = len(w)
        dens = np.stack([w[k] * multivariate_normal(mu[k], S[k]).pdf(xn) for k in range(K)], -1)
        gamma = dens / dens.sum(-1, keepdims=True)
        res = np.stack([vn - (xn - g) @ A[k].T for k in range(K)], 1)  # (N, K, d)
        full = (gamma[..., None] * res).sum(1)
        pooled = full.T @ full / N + 1e-9 * float((vn**2).sum(-1).mean()) / d * np.eye(d)
        for k in range(K):
            cov = sum(gamma[n, k] * np.outer(res[n, k], res[n, k]) for n in range(N)) + pooled
            cov = cov / (gamma[:, k].sum() + 1.0)
            np.testing.assert_allclose(model.velocity_covariances[k].numpy(), cov, rtol=1e-8, atol=1e-12)


def test_seds_initialisation_reproduces_a_joint_gmm_that_already_satisfies_the_constraints() -> None:
    """Projection property of the EM initialisation: for a joint GMM whose slopes A_k = Svx Sxx^-1 already satisfy
    A_k + A_k^T <= -4 eps I and whose covariances are above the floors, the initial SEDS parameters reproduce it
    exactly: priors, position means, Sxx, A_k (symmetric and skew parts) and the conditional covariance
    R_k = Svv - A_k Sxx A_k^T (closed form of the Gaussian conditional)."""
    from lfd_torch.ds.seds import _init_parameters
    from lfd_torch.gmm import GMM

    gen = torch.Generator().manual_seed(29)
    K, d, eps, reg = 3, 2, 1e-2, 1e-2

    def spd(scale: float) -> torch.Tensor:
        B = torch.randn(K, d, d, dtype=F64, generator=gen)
        return scale * (B @ B.transpose(-2, -1) + torch.eye(d, dtype=F64))

    Q = spd(1.0)
    W = torch.randn(K, d, d, dtype=F64, generator=gen)
    A0 = -Q + (W - W.transpose(-2, -1))  # sym part -Q <= -I: feasible
    Sxx, R = spd(0.5), spd(0.3)
    joint_cov = torch.cat([torch.cat([Sxx, Sxx @ A0.transpose(-2, -1)], -1),
                           torch.cat([A0 @ Sxx, A0 @ Sxx @ A0.transpose(-2, -1) + R], -1)], -2)  # fmt: skip
    w = torch.tensor([0.2, 0.3, 0.5], dtype=F64)
    means = torch.randn(K, 2 * d, dtype=F64, generator=gen)
    params = _init_parameters(GMM(w, means, joint_cov), d, eps, reg)
    with torch.no_grad():
        torch.testing.assert_close(torch.softmax(params.logits, -1), w, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(params.means, means[:, :d], rtol=0, atol=0)
        torch.testing.assert_close(params.system_matrices(), A0, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(params.covariances(), Sxx, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(params.residual_covariances(), R, rtol=1e-9, atol=1e-9)


def test_seds_margin_eps_is_in_data_units_when_it_binds() -> None:
    """eps is in 1/s of the original units (module docstring): every returned A_k has lambda_max(A_k + A_k^T)
    <= -2 eps in data units, checked by numpy eigenvalues on a slow linear system (u / s ~ 0.1, so that a margin
    converted with the wrong factor, eps u / s instead of eps s / u, is 100 times too weak) whose own contraction
    (lambda_max(A + A^T) ~ -0.16 1/s) is weaker than the requested -2 eps = -0.4 1/s, so the constraint binds."""
    from lfd_torch.ds import fit_seds
    from test_lpvds import A_QLF, G, linear_demos, starts_on_circle

    A_true = 0.1 * A_QLF
    demos = linear_demos(A_true, G, starts_on_circle(4), T=40, dt=0.5)
    eps = 0.2
    assert float(np.linalg.eigvalsh((A_true + A_true.T).numpy()).max()) > -2 * eps
    model = fit_seds(demos, n_components=1, eps=eps, max_iter=10, generator=torch.Generator().manual_seed(0))
    A = model.A.numpy()
    margins = np.linalg.eigvalsh(A + np.swapaxes(A, -1, -2)).max(-1)
    assert (margins <= -2 * eps * (1 - 1e-9)).all(), margins


def test_seds_falls_back_to_the_best_point_it_evaluated(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fallback rule (module docstring): when L-BFGS ends at a non-finite objective, the returned parameters are
    those of the lowest finite objective evaluated (a naive minimum over every evaluation, recorded by a wrapper
    that makes the objective NaN from its 8th evaluation on), and info['fallback'] says 'best_iterate'."""
    from lfd_torch.ds import SEDSParameters, fit_seds

    original = SEDSParameters.negative_log_likelihood
    seen: list[float] = []

    def poisoned(self: SEDSParameters, xs: torch.Tensor, vs: torch.Tensor) -> torch.Tensor:
        loss = original(self, xs, vs)
        if len(seen) >= 8:
            loss = loss * math.nan
        seen.append(float(loss.detach()))
        return loss

    monkeypatch.setattr(SEDSParameters, "negative_log_likelihood", poisoned)
    demos = small_lasa("Angle", demos=(0, 1), stride=10)
    model = fit_seds(demos, n_components=2, gain_prior=None, max_iter=20, max_restarts=0,
                     generator=torch.Generator().manual_seed(0))  # fmt: skip
    finite = [v for v in seen if math.isfinite(v)]
    assert min(finite) < finite[0]  # some iterate improved on the initialisation
    assert model.info["fallback"] == "best_iterate" and model.info["n_restarts"] == 0  # max_restarts=0 is honoured
    assert model.info["final_objective"] == min(finite)


# ---------------------------------------------------------------------------------------------------- convex
def _small_qp() -> Any:
    import cvxpy as cp

    z = cp.Variable(3)
    return cp.Problem(cp.Minimize(cp.sum_squares(z - np.array([1.0, 2.0, 3.0])) + cp.norm1(z)), [z >= 0.5])


class _StubProblem:
    """Duck-typed cvxpy problem: records the keyword arguments of every solve and ends with a given status."""

    def __init__(self, status: str) -> None:
        self.status = "unsolved"
        self._final = status
        self.calls: list[dict[str, Any]] = []

    def solve(self, **kwargs: Any) -> None:
        self.calls.append(kwargs)
        self.status = self._final


def test_solve_problem_default_order_case_and_options() -> None:
    """solve_problem's contract (convex module docstring): Clarabel first by default; solver names and option keys
    are case-insensitive (upper-cased), so an option given for 'clarabel' reaches a solve named 'CLARABEL' and
    vice versa (max_iter=1 then stops Clarabel short of 'optimal': SolverError); an empty solver list is an
    InvalidArgumentError."""
    from lfd_torch.ds.convex import normalize_solvers, solve_problem

    assert solve_problem(_small_qp()) == "CLARABEL"
    assert solve_problem(_small_qp(), "clarabel") == "CLARABEL"
    with pytest.raises(SolverError, match="CLARABEL"):
        solve_problem(_small_qp(), ["CLARABEL"], {"clarabel": {"max_iter": 1}})
    with pytest.raises(SolverError, match="CLARABEL"):
        solve_problem(_small_qp(), ["clarabel"], {"CLARABEL": {"max_iter": 1}})
    with pytest.raises(InvalidArgumentError, match="solvers"):
        normalize_solvers([])


def test_solve_problem_accepts_only_optimal_and_never_warm_starts() -> None:
    """Status rule (convex module docstring): only 'optimal' is accepted, 'optimal_inaccurate' is a SolverError that
    lists every attempt; each solve is called with warm_start=False unless the caller's options say otherwise."""
    from lfd_torch.ds.convex import solve_problem

    stub = _StubProblem("optimal_inaccurate")
    with pytest.raises(SolverError, match="optimal_inaccurate"):
        solve_problem(stub, ["CLARABEL", "SCS"])  # type: ignore[arg-type]
    assert [c["solver"] for c in stub.calls] == ["CLARABEL", "SCS"]
    assert all(c["warm_start"] is False for c in stub.calls)
    ok = _StubProblem("optimal")
    assert solve_problem(ok, "scs", {"SCS": {"eps": 1e-9}}) == "SCS"  # type: ignore[arg-type]
    assert ok.calls == [{"solver": "SCS", "warm_start": False, "eps": 1e-9}]
