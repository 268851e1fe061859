"""lfd_torch.ds against independent references: closed forms (ridge least squares, the all-hinges-active P step),
naive loops, exact equivariances of the fits under a change of units, documented argument contracts, and the
SEDS fallback / restart rules. All data are float64 and seeded."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lfd_torch.data import Demos
from lfd_torch.ds import (
    StablePrimitive,
    estimate_lyapunov_matrix,
    fit_lpvds,
    fit_seds,
    lyapunov_violation_rate,
    solve_lpv_matrices,
)
from lfd_torch.errors import (
    CertificationError,
    InvalidArgumentError,
    ShapeMismatchError,
    TooFewSamplesError,
)
from lfd_torch.gmm import GMM

F64 = torch.float64
GOAL = torch.tensor([1.0, -2.0], dtype=F64)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _exact_linear_demos(A: torch.Tensor, goal: torch.Tensor, n_starts: int = 6, T: int = 50, dt: float = 0.1,
                        radius: float = 4.0, demo_attractor: torch.Tensor | None = None) -> Demos:
    """Trajectories x(t) = g + expm(A t)(x0 - g) with the exact velocities A (x - g) (scipy-free reference)."""
    t = torch.arange(T, dtype=F64) * dt
    E = torch.linalg.matrix_exp(A * t[:, None, None])
    ang = torch.linspace(0, 2 * math.pi, n_starts + 1, dtype=F64)[:-1] + 0.3
    starts = goal + radius * torch.stack([ang.cos(), ang.sin()], -1)
    seqs = [goal + torch.einsum("tij,j->ti", E, x0 - goal) for x0 in starts]
    vels = [(s - goal) @ A.T for s in seqs]
    att = goal if demo_attractor is None else demo_attractor
    return Demos.from_sequences(seqs, times=[t] * len(seqs), velocities=vels, attractor=att)


def _partition_gmm(x: torch.Tensor, K: int, seed: int) -> GMM:
    labels = torch.randint(0, K, (x.shape[0],), generator=_gen(seed))
    return GMM.from_labels(x, labels)


# ------------------------------------------------------------------------------------------------ P step
def test_quadratic_lyapunov_functions_against_a_loop() -> None:
    """V(x) = (x - g)^T P (x - g) and dV/dt = 2 (x - g)^T P x_dot, batched (..., d), against a loop in numpy with a
    goal away from the origin and a non-diagonal P."""
    from lfd_torch.ds import quadratic_lyapunov, quadratic_lyapunov_derivative

    gen = _gen(1)
    x = torch.randn(3, 4, 2, generator=gen, dtype=F64)
    xd = torch.randn(3, 4, 2, generator=gen, dtype=F64)
    P = torch.tensor([[2.0, 0.3], [0.3, 0.7]], dtype=F64)
    V = quadratic_lyapunov(x, GOAL, P)
    dV = quadratic_lyapunov_derivative(x, xd, GOAL, P)
    assert V.shape == dV.shape == (3, 4)
    for i in range(3):
        for j in range(4):
            e = (x[i, j] - GOAL).numpy()
            assert float(V[i, j]) == pytest.approx(e @ P.numpy() @ e, rel=1e-13)
            assert float(dV[i, j]) == pytest.approx(2 * e @ P.numpy() @ xd[i, j].numpy(), rel=1e-12, abs=1e-14)


def test_p_step_rejects_out_of_range_arguments() -> None:
    """Documented ranges of estimate_lyapunov_matrix: margin in [0, 1) (1.0 is out), min_eigenvalue in (0, 1]
    (0 is out), rel_tol >= 0, and an attractor of another dtype is a ShapeMismatchError."""
    gen = _gen(0)
    x = GOAL + torch.randn(30, 2, generator=gen, dtype=F64)
    v = -(x - GOAL)
    with pytest.raises(InvalidArgumentError, match="margin"):
        estimate_lyapunov_matrix(x, v, GOAL, margin=1.0)
    with pytest.raises(InvalidArgumentError, match="min_eigenvalue"):
        estimate_lyapunov_matrix(x, v, GOAL, min_eigenvalue=0.0)
    with pytest.raises(InvalidArgumentError, match="rel_tol"):
        estimate_lyapunov_matrix(x, v, GOAL, rel_tol=-0.1)
    with pytest.raises(ShapeMismatchError, match="attractor"):
        estimate_lyapunov_matrix(x, v, GOAL.float())


def test_p_step_default_bounds_against_the_all_active_closed_form() -> None:
    """Closed form of the P step when every hinge is active (margin 0.99): P minimises tr(C P) with C the mean of
    sym(e v^T) / (|e| |v|) over informative samples, so P = U diag(1, lambda_min) U^T (U: eigenvectors of C, the
    negative one first). With the *default* min_eigenvalue (1e-3) and rel_tol (1e-3), samples moving at 2 % of the
    top speed are informative and enter C, and the smaller eigenvalue of the normalised P is 1e-3."""
    gen = _gen(11)
    n = 60
    A = torch.tensor([[-1.0, 4.0], [0.0, -1.0]], dtype=F64)
    e = torch.randn(n, 2, generator=gen, dtype=F64) * (0.2 + 3 * torch.rand(n, 1, generator=gen, dtype=F64))
    v = e @ A.T
    # slow samples (2 % of the top speed) whose directions differ from the rest: they shift C
    slow_e = torch.tensor([[2.0, 0.5], [-1.0, 2.0], [0.5, -2.5], [1.5, 1.5]], dtype=F64)
    slow_dir = torch.tensor([[0.6, -0.8], [0.9, 0.1], [-0.2, 0.98], [0.7, 0.7]], dtype=F64)
    vmax = float(v.norm(dim=-1).max())
    slow_v = 0.02 * vmax * slow_dir / slow_dir.norm(dim=-1, keepdim=True)
    E, V = torch.cat([e, slow_e]), torch.cat([v, slow_v])
    # naive loop for C
    C = np.zeros((2, 2))
    for en, vn in zip(E.numpy(), V.numpy()):
        C += np.outer(en, vn) / (np.linalg.norm(en) * np.linalg.norm(vn))
    C = 0.5 * (C + C.T) / len(E)
    w, U = np.linalg.eigh(C)
    assert w[0] < 0 < w[1]
    expected = U @ np.diag([1.0, 1e-3]) @ U.T
    unit_e = E.numpy() / np.linalg.norm(E.numpy(), axis=1, keepdims=True)
    unit_v = V.numpy() / np.linalg.norm(V.numpy(), axis=1, keepdims=True)
    assert np.einsum("ni,ij,nj->n", unit_e, expected, unit_v).min() > -0.99  # all hinges active at the optimum
    P = estimate_lyapunov_matrix(GOAL + E, V, GOAL, margin=0.99)
    np.testing.assert_allclose(P.numpy(), expected, rtol=0, atol=2e-4)
    eig = np.linalg.eigvalsh(P.numpy())
    assert eig[0] == pytest.approx(1e-3, abs=2e-5) and eig[1] == pytest.approx(1.0, abs=1e-12)


def test_p_step_default_margin_zero_leaves_no_violation_when_one_p_explains_all() -> None:
    """Module docstring: with the default margin 0 the objective is zero for any P under which every sample
    decreases V. On a weakly damped elliptical orbit, x_dot = A (x - g) with A = [[-0.02, 2], [-0.5, -0.02]],
    P = I is violated on about half of the samples but P = diag(1/4, 1) gives A^T P + P A = -0.02 diag(1/4, 1) < 0;
    the estimated P must leave no sample with (x - g)^T P x_dot >= 0 (loop), whereas a positive margin trades
    violations for a clearer decrease (contrast)."""
    A = torch.tensor([[-0.02, 2.0], [-0.5, -0.02]], dtype=F64)
    demos = _exact_linear_demos(A, GOAL, n_starts=5, T=80, dt=0.2)
    x, v, _ = demos.samples()
    assert lyapunov_violation_rate(x, v, GOAL, torch.eye(2, dtype=F64)) > 0.3
    e = (x - GOAL).numpy()

    def violations(P: torch.Tensor) -> int:
        return sum(float(en @ P.numpy() @ vn) >= 0 for en, vn in zip(e, v.numpy()))

    assert violations(estimate_lyapunov_matrix(x, v, GOAL)) == 0
    assert violations(estimate_lyapunov_matrix(x, v, GOAL, margin=0.1)) > 0.1 * len(e)


# ------------------------------------------------------------------------------------------------ A step
def test_a_step_is_ridge_least_squares_when_the_constraint_is_inactive() -> None:
    """Without an active LMI the A step is ridge least squares on z_n = [gamma_k e_n]_k: Theta = H (G + r I)^-1
    with G = (1/N) sum z z^T, H = (1/N) sum x_dot z^T and r = ridge tr(G) / (K d) (module docstring; the unit-RMS
    scaling inside cancels). Reference built by a per-sample loop in numpy."""
    gen = _gen(5)
    N, K, d = 120, 3, 2
    x = GOAL + 2.0 * torch.randn(N, d, generator=gen, dtype=F64)
    A_true = torch.tensor([[-3.0, 0.5], [-0.4, -2.5]], dtype=F64)
    v = (x - GOAL) @ A_true.T + 0.3 * torch.randn(N, d, generator=gen, dtype=F64)
    gamma = torch.softmax(torch.randn(N, K, generator=gen, dtype=F64), -1)
    ridge = 0.2
    A, _ = solve_lpv_matrices(x, v, gamma, GOAL, torch.eye(d, dtype=F64), eps=1e-4, ridge=ridge)
    Gm = np.zeros((K * d, K * d))
    Hm = np.zeros((d, K * d))
    for xn, vn, gn in zip(x.numpy(), v.numpy(), gamma.numpy()):
        z = np.concatenate([gn[k] * (xn - GOAL.numpy()) for k in range(K)])
        Gm += np.outer(z, z) / N
        Hm += np.outer(vn, z) / N
    Theta = Hm @ np.linalg.inv(Gm + ridge * np.trace(Gm) / (K * d) * np.eye(K * d))
    ref = np.stack([Theta[:, k * d:(k + 1) * d] for k in range(K)])
    sym_max = np.linalg.eigvalsh(ref + np.swapaxes(ref, 1, 2)).max()
    assert sym_max < -0.5  # the reference itself is well inside the constraint set
    np.testing.assert_allclose(A.numpy(), ref, rtol=0, atol=1e-5 * np.abs(ref).max())


def test_a_step_margin_is_in_data_units_when_it_binds() -> None:
    """A_k^T P + P A_k <= -eps I in the original units (1/s): on a slow system (u / s ~ 0.05) whose own margin is
    weaker than -eps, the returned margins equal -eps to solver tolerance (numpy eigenvalues). A margin converted
    with u / s instead of s / u would be ~400 times off."""
    A_slow = torch.tensor([[-0.01, 0.05], [-0.05, -0.01]], dtype=F64)
    demos = _exact_linear_demos(A_slow, GOAL, n_starts=4, T=40, dt=1.0)
    x, v, _ = demos.samples()
    gamma = torch.ones(x.shape[0], 1, dtype=F64)
    eps = 0.05
    A, _ = solve_lpv_matrices(x, v, gamma, GOAL, torch.eye(2, dtype=F64), eps=eps, ridge=0.0)
    Q = A.numpy() + np.swapaxes(A.numpy(), 1, 2)
    lam = np.linalg.eigvalsh(Q).max(-1)
    assert (lam <= -eps * (1 - 1e-5)).all() and (lam >= -eps * (1 + 1e-3)).all(), lam


def test_a_step_is_equivariant_under_a_change_of_units() -> None:
    """A change of length unit (positions, goal and velocities x c) leaves A (1/s) unchanged; a change of time unit
    (velocities and eps x c) scales A by c. c = 4 is a power of two, so the scaled programs see the same numbers;
    the constraint binds (unstable data), so the margin's unit matters."""
    gen = _gen(8)
    N, K, d = 80, 2, 2
    x = GOAL + torch.randn(N, d, generator=gen, dtype=F64)
    v = (x - GOAL) @ torch.tensor([[0.3, 2.0], [-2.0, 0.2]], dtype=F64).T  # unstable: constraint binds
    v = v + 0.1 * torch.randn(N, d, generator=gen, dtype=F64)
    gamma = torch.softmax(torch.randn(N, K, generator=gen, dtype=F64), -1)
    P = torch.tensor([[1.0, 0.2], [0.2, 0.5]], dtype=F64)
    eps = 0.3
    base, _ = solve_lpv_matrices(x, v, gamma, GOAL, P, eps=eps)
    c = 4.0
    space, _ = solve_lpv_matrices(c * x, c * v, gamma, c * GOAL, P, eps=eps)
    time_, _ = solve_lpv_matrices(x, c * v, gamma, GOAL, P, eps=c * eps)
    torch.testing.assert_close(space, base, rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(time_, c * base, rtol=1e-6, atol=1e-8)


def test_solve_lpv_matrices_argument_checks() -> None:
    """gamma with another N is a ShapeMismatchError; eps <= 0 and ridge < 0 are InvalidArgumentErrors; velocities
    that are all zero leave nothing to fit (TooFewSamplesError)."""
    gen = _gen(2)
    x = torch.randn(20, 2, generator=gen, dtype=F64)
    v = -x
    P = torch.eye(2, dtype=F64)
    g = torch.zeros(2, dtype=F64)
    gamma = torch.full((20, 2), 0.5, dtype=F64)
    with pytest.raises(ShapeMismatchError, match="gamma"):
        solve_lpv_matrices(x, v, torch.full((21, 2), 0.5, dtype=F64), g, P)
    with pytest.raises(InvalidArgumentError, match="eps"):
        solve_lpv_matrices(x, v, gamma, g, P, eps=0.0)
    with pytest.raises(InvalidArgumentError, match="ridge"):
        solve_lpv_matrices(x, v, gamma, g, P, ridge=-1e-3)
    with pytest.raises(TooFewSamplesError):
        solve_lpv_matrices(x, torch.zeros_like(v), gamma, g, P)


# ------------------------------------------------------------------------------------------------ fit_lpvds
def test_default_fit_recovers_a_slowly_contracting_system_exactly() -> None:
    """With the documented defaults eps = 1e-3 1/s and ridge = 1e-6, a linear system with lambda_max(A + A^T) =
    -6e-3 1/s (feasible with margin) is recovered by a QLF fit to 1e-4 relative; a 10x larger default eps would
    bind the constraint and a large default ridge would shrink A."""
    A_true = torch.tensor([[-0.003, 0.6], [-0.6, -0.003]], dtype=F64)
    demos = _exact_linear_demos(A_true, GOAL, n_starts=5, T=60, dt=0.1)
    x, v, _ = demos.samples()
    gmm = _partition_gmm(x, 2, 1)
    model = fit_lpvds(demos, gmm=gmm, lyapunov="qlf")
    np.testing.assert_allclose(model.A.numpy(), A_true.expand(2, 2, 2).numpy(), rtol=0, atol=1e-4 * 0.6)
    # the same defaults of the A step called directly
    A, _ = solve_lpv_matrices(x, v, gmm.posterior(x), GOAL, torch.eye(2, dtype=F64))
    np.testing.assert_allclose(A.numpy(), A_true.expand(2, 2, 2).numpy(), rtol=0, atol=1e-4 * 0.6)


def test_fit_lpvds_attractor_argument_overrides_the_demos() -> None:
    """attractor= overrides demos.attractor: data generated around GOAL but labelled with another goal are
    recovered exactly when GOAL is passed, and the model's attractor is GOAL."""
    A_true = torch.tensor([[-1.0, 1.5], [-0.5, -2.0]], dtype=F64)
    demos = _exact_linear_demos(A_true, GOAL, demo_attractor=GOAL + torch.tensor([3.0, 1.0], dtype=F64))
    x, _, _ = demos.samples()
    model = fit_lpvds(demos, GOAL, gmm=_partition_gmm(x, 2, 3), lyapunov="qlf", ridge=0.0)
    torch.testing.assert_close(model.attractor, GOAL, rtol=0, atol=0)
    np.testing.assert_allclose(model.A.numpy(), A_true.expand(2, 2, 2).numpy(), rtol=0, atol=1e-4)


def test_noise_free_fit_has_negligible_velocity_covariances_and_consistent_info() -> None:
    """On exact linear data around a goal away from the origin the residuals x_dot - A_k (x - g) vanish, so the
    velocity covariances are only the 1e-9 relative diagonal load; info['p_violation_rate'] is the fraction of
    samples with (x - g)^T P x_dot >= 0 counted by a loop with the model's P (0 here, while P = I violates)."""
    A_qlf = torch.tensor([[-1.0, 1.5], [-0.5, -2.0]], dtype=F64)
    demos = _exact_linear_demos(A_qlf, GOAL)
    x, v, _ = demos.samples()
    exact = fit_lpvds(demos, gmm=_partition_gmm(x, 2, 4), lyapunov="qlf", ridge=0.0)
    assert float(exact.velocity_covariances.abs().max()) < 1e-6 * float(v.pow(2).sum(-1).mean())
    A_nonqlf = torch.tensor([[-1.0, 4.0], [0.0, -1.0]], dtype=F64)
    demos = _exact_linear_demos(A_nonqlf, GOAL, n_starts=8)
    x, v, _ = demos.samples()
    model = fit_lpvds(demos, gmm=_partition_gmm(x, 2, 4), ridge=0.0)
    P = model.P.numpy()
    e = (x - GOAL).numpy()
    rate = np.mean([float(en @ P @ vn) >= 0 for en, vn in zip(e, v.numpy())])
    assert model.info["p_violation_rate"] == pytest.approx(rate, abs=0) and rate == 0.0
    assert lyapunov_violation_rate(x, v, GOAL, torch.eye(2, dtype=F64)) > 0.05


def test_given_lyapunov_matrix_must_be_symmetric_positive_definite() -> None:
    """lyapunov=<tensor> must be symmetric positive definite: a singular or a non-symmetric P is a
    CertificationError (before any solve)."""
    A_true = torch.tensor([[-1.0, 1.5], [-0.5, -2.0]], dtype=F64)
    demos = _exact_linear_demos(A_true, GOAL)
    x, _, _ = demos.samples()
    gmm = _partition_gmm(x, 2, 5)
    for bad in (torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=F64), torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=F64)):
        with pytest.raises(CertificationError):
            fit_lpvds(demos, gmm=gmm, lyapunov=bad)


# ------------------------------------------------------------------------------------------------ primitive
def _toy_primitive() -> StablePrimitive:
    x = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.5], [0.5, -1.0], [2.0, 2.0], [-2.0, 1.0]], dtype=F64)
    gmm = GMM.from_labels(x, torch.tensor([0, 0, 1, 1, 2, 2]))
    A = torch.stack([torch.tensor([[-1.0, 2.0], [-2.0, -0.5]], dtype=F64),
                     torch.tensor([[-2.0, 0.3], [0.1, -1.0]], dtype=F64),
                     torch.tensor([[-0.5, -1.0], [1.5, -0.7]], dtype=F64)])  # fmt: skip
    cov = torch.eye(2, dtype=F64).expand(3, 2, 2).clone()
    return StablePrimitive(gmm, A, torch.tensor([0.4, -0.3], dtype=F64), torch.eye(2, dtype=F64), cov)


def test_component_velocities_and_field_against_a_loop() -> None:
    """component_velocities(x)[..., k, :] = A_k (x - g) and f(x) = sum_k gamma_k(x) of them, with gamma the GMM
    posterior (loop over points and components)."""
    prim = _toy_primitive()
    pts = torch.randn(7, 2, generator=_gen(9), dtype=F64)
    cv = prim.component_velocities(pts)
    gamma = prim.gmm.posterior(pts)
    for n in range(7):
        for k in range(3):
            ref = prim.A[k].numpy() @ (pts[n] - prim.attractor).numpy()
            np.testing.assert_allclose(cv[n, k].numpy(), ref, rtol=1e-13, atol=1e-14)
        f = sum(float(gamma[n, k]) * cv[n, k].numpy() for k in range(3))
        np.testing.assert_allclose(prim(pts[n]).numpy(), f, rtol=1e-12, atol=1e-14)


def test_primitive_rejects_velocity_covariances_that_are_not_positive_definite() -> None:
    """velocity_covariances must be symmetric positive definite (class docstring): an indefinite one is refused."""
    prim = _toy_primitive()
    bad = prim.velocity_covariances.clone()
    bad[1] = torch.tensor([[1.0, 0.0], [0.0, -0.5]], dtype=F64)
    with pytest.raises(ShapeMismatchError, match="velocity_covariances"):
        StablePrimitive(prim.gmm, prim.A, prim.attractor, prim.P, bad)


# ------------------------------------------------------------------------------------------------ SEDS
def _seds_demos(pos_scale: float = 1.0, vel_scale: float = 1.0, shift: float = 0.0) -> Demos:
    gen = _gen(21)
    t = torch.linspace(0, 4, 30, dtype=F64)
    seqs, vels = [], []
    for a in (1.0, 0.8, 1.2):
        ph = float(torch.rand(1, generator=gen))
        p = torch.stack([a * 6 * torch.exp(-0.8 * t) * torch.cos(t + ph), a * 4 * torch.exp(-0.8 * t) * torch.sin(t + ph)], -1)
        dp = torch.stack([a * 6 * torch.exp(-0.8 * t) * (-0.8 * torch.cos(t + ph) - torch.sin(t + ph)),
                          a * 4 * torch.exp(-0.8 * t) * (-0.8 * torch.sin(t + ph) + torch.cos(t + ph))], -1)  # fmt: skip
        seqs.append(pos_scale * p + shift)
        vels.append(pos_scale * vel_scale * dp)
    att = torch.full((2,), shift, dtype=F64)
    return Demos.from_sequences(seqs, times=[t / vel_scale] * 3, velocities=vels, attractor=att)


@pytest.mark.parametrize("objective", ["likelihood", "mse"])
def test_seds_is_equivariant_under_a_change_of_units(objective: str) -> None:
    """Positions x c (goal too): A unchanged, means and covariances scaled by c and c^2, velocity covariances by c^2.
    Velocities x c with eps x c: A and velocity covariances scaled by c and c^2, the GMM unchanged. A shift of
    positions and goal shifts the means only. c = 4: the unit-RMS programs see the same numbers."""
    kw = dict(n_components=2, objective=objective, max_iter=25, eps=0.05)
    base = fit_seds(_seds_demos(), generator=_gen(0), **kw)
    c = 4.0
    space = fit_seds(_seds_demos(pos_scale=c), generator=_gen(0), **kw)
    tol = dict(rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(space.A, base.A, **tol)
    torch.testing.assert_close(space.gmm.means, c * base.gmm.means, **tol)
    torch.testing.assert_close(space.gmm.covariances, c * c * base.gmm.covariances, **tol)
    torch.testing.assert_close(space.velocity_covariances, c * c * base.velocity_covariances, **tol)
    kw_t = {**kw, "eps": c * kw["eps"]}
    fast = fit_seds(_seds_demos(vel_scale=c), generator=_gen(0), **kw_t)
    torch.testing.assert_close(fast.A, c * base.A, **tol)
    torch.testing.assert_close(fast.gmm.means, base.gmm.means, **tol)
    torch.testing.assert_close(fast.gmm.covariances, base.gmm.covariances, **tol)
    torch.testing.assert_close(fast.velocity_covariances, c * c * base.velocity_covariances, **tol)
    shifted = fit_seds(_seds_demos(shift=8.0), generator=_gen(0), **kw)
    torch.testing.assert_close(shifted.gmm.means, base.gmm.means + 8.0, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(shifted.A, base.A, rtol=1e-5, atol=1e-6)


def test_seds_falls_back_when_the_last_iterate_is_finite_but_worse(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fallback rule (module docstring): if L-BFGS ends above the best point it evaluated, that best point is
    returned (info['fallback'] == 'best_iterate', final_objective = the minimum over every evaluation, recorded by a
    wrapper that adds 1e3 to the objective from its 8th evaluation on, finite)."""
    from lfd_torch.ds import SEDSParameters

    original = SEDSParameters.negative_log_likelihood
    seen: list[float] = []

    def worse(self: SEDSParameters, xs: torch.Tensor, vs: torch.Tensor) -> torch.Tensor:
        loss = original(self, xs, vs)
        if len(seen) >= 8:
            loss = loss + 1e3
        seen.append(float(loss.detach()))
        return loss

    monkeypatch.setattr(SEDSParameters, "negative_log_likelihood", worse)
    model = fit_seds(_seds_demos(), n_components=2, gain_prior=None, max_iter=20, generator=_gen(0))
    assert min(seen[:8]) < seen[0]
    assert model.info["fallback"] == "best_iterate"
    assert model.info["final_objective"] == min(seen)


def test_seds_restarts_from_the_best_point_up_to_max_restarts(monkeypatch: pytest.MonkeyPatch) -> None:
    """Restart rule (module docstring): while L-BFGS ends at a non-finite objective it is restarted, at most
    max_restarts times (here the objective stays NaN from its 8th evaluation on, so every restart is used)."""
    from lfd_torch.ds import SEDSParameters

    original = SEDSParameters.negative_log_likelihood
    calls = [0]

    def poisoned(self: SEDSParameters, xs: torch.Tensor, vs: torch.Tensor) -> torch.Tensor:
        loss = original(self, xs, vs)
        calls[0] += 1
        return loss * math.nan if calls[0] > 8 else loss

    monkeypatch.setattr(SEDSParameters, "negative_log_likelihood", poisoned)
    model = fit_seds(_seds_demos(), n_components=2, gain_prior=None, max_iter=50, max_restarts=2, generator=_gen(0))
    assert model.info["n_restarts"] == 2
    assert model.info["fallback"] == "best_iterate"


def test_solve_lpv_matrices_rejects_an_attractor_p_or_gamma_of_the_wrong_shape() -> None:
    """attractor is documented as (d,) and P as (d, d): a (1,) goal must be a ShapeMismatchError as in the P step,
    not a goal broadcast to (0.5, 0.5), and a (3, 3) P one too, not a deep cvxpy ValueError; responsibilities
    whose rows do not sum to 1 (0.7 / 0.7) or are negative are an InvalidArgumentError."""
    gen = _gen(4)
    x = torch.randn(30, 2, generator=gen, dtype=F64)
    gamma = torch.full((30, 2), 0.5, dtype=F64)
    with pytest.raises(ShapeMismatchError, match="P"):
        solve_lpv_matrices(x, -x, gamma, torch.zeros(2, dtype=F64), torch.eye(3, dtype=F64))
    with pytest.raises(InvalidArgumentError, match="gamma"):
        solve_lpv_matrices(x, -x, torch.full((30, 2), 0.7, dtype=F64), torch.zeros(2, dtype=F64),
                           torch.eye(2, dtype=F64))
    with pytest.raises(InvalidArgumentError, match="gamma"):
        solve_lpv_matrices(x, -x, torch.tensor([[1.5, -0.5]], dtype=F64).expand(30, 2), torch.zeros(2, dtype=F64),
                           torch.eye(2, dtype=F64))
    with pytest.raises(ShapeMismatchError, match="attractor"):
        solve_lpv_matrices(x, -x, gamma, torch.tensor([0.5], dtype=F64), torch.eye(2, dtype=F64))
