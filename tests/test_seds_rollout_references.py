"""SEDS (fit checks, initial projection) and the rollout engine (same-sample disturbances, divergence detection,
to_demos) against independent references: closed forms (the Frobenius projection onto a shifted negative
semidefinite cone by an eigenvalue clamp; x(t) = g + expm(A t)(x0 - g) and its affine variant via scipy), the
documented argument contracts and the engine's documented guarantees. Each test targets a small code change that
the rest of the suite let through (mutation review). All data are float64 and seeded."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch

from lfd_torch.data import Demos
from lfd_torch.ds import fit_seds
from lfd_torch.errors import NonFiniteError, TooFewSamplesError
from lfd_torch.rollout import Disturbance, rollout

F64 = torch.float64
A_SPIRAL = np.array([[-1.0, 2.0], [-2.0, -1.0]])


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _spiral_demos(n_demos: int = 3, T: int = 30) -> Demos:
    """Exact samples of x' = A (x - g), g = (1, -2): x(t) = g + expm(A t)(x0 - g), velocities A (x - g)."""
    g = np.array([1.0, -2.0])
    A = 0.5 * A_SPIRAL
    t = np.linspace(0.0, 4.0, T)
    seqs, vels = [], []
    for i in range(n_demos):
        ang = 0.4 + 2 * math.pi * i / n_demos
        x0 = g + 5.0 * np.array([math.cos(ang), math.sin(ang)])
        x = np.stack([g + scipy.linalg.expm(A * ti) @ (x0 - g) for ti in t])
        seqs.append(x)
        vels.append((x - g) @ A.T)
    return Demos.from_sequences(seqs, times=[t] * n_demos, velocities=vels, attractor=g)


# ------------------------------------------------------------------------------------------------ SEDS
def test_seds_initial_projection_is_the_eigenvalue_clamp_of_the_symmetric_part() -> None:
    """Projection property of the initialisation (module docstring: A_k from the joint covariance, projected onto
    the constraint set, with the margin the code keeps for L: symmetric part <= -2 eps I). Reference: the
    Frobenius-nearest point of {S : S <= -2 eps I} is the eigenvalue clamp min(lambda, -2 eps) in the eigenbasis of
    the symmetric part (numpy eigh); the skew part is kept. A direction that already has the margin (lambda =
    -2.5 eps) must stay where it is; an unstable one (lambda = +0.3) lands on -2 eps."""
    from lfd_torch.ds.seds import _init_parameters
    from lfd_torch.gmm import GMM

    gen = _gen(3)
    K, d, eps, reg = 2, 2, 1e-2, 1e-3
    A0, Sxx = [], []
    for k in range(K):
        Q, _ = np.linalg.qr(torch.randn(d, d, generator=gen, dtype=F64).numpy())
        sym = Q @ np.diag([-2.5 * eps, 0.3 if k == 0 else -1.0]) @ Q.T
        w = float(torch.randn(1, generator=gen, dtype=F64))
        A0.append(sym + w * np.array([[0.0, 1.0], [-1.0, 0.0]]))
        B = torch.randn(d, d, generator=gen, dtype=F64).numpy()
        Sxx.append(B @ B.T + np.eye(d))
    A0, Sxx = np.stack(A0), np.stack(Sxx)
    R = 0.2 * np.eye(d)
    cov = np.concatenate([np.concatenate([Sxx, Sxx @ A0.transpose(0, 2, 1)], -1),
                          np.concatenate([A0 @ Sxx, A0 @ Sxx @ A0.transpose(0, 2, 1) + R], -1)], -2)  # fmt: skip
    means = torch.randn(K, 2 * d, generator=gen, dtype=F64)
    params = _init_parameters(GMM(torch.tensor([0.4, 0.6], dtype=F64), means, torch.from_numpy(cov)), d, eps, reg)
    with torch.no_grad():
        got = params.system_matrices().numpy()
    for k in range(K):
        sym = 0.5 * (A0[k] + A0[k].T)
        lam, V = np.linalg.eigh(sym)
        ref = V @ np.diag(np.minimum(lam, -2.0 * eps)) @ V.T + 0.5 * (A0[k] - A0[k].T)
        np.testing.assert_allclose(got[k], ref, rtol=0, atol=1e-10)
        assert np.linalg.eigvalsh(got[k] + got[k].T).max() <= -2 * eps * (1 - 1e-9)  # the SEDS constraint


def test_seds_refuses_data_without_motion_or_without_extent() -> None:
    """Documented check (fit_seds): samples that all sit at the attractor, or all at rest, leave nothing to fit and
    raise TooFewSamplesError -- each of the two conditions on its own (velocities all zero with positions spread
    out; positions all at the goal with non-zero velocities), not only when both hold."""
    t = np.linspace(0.0, 1.0, 12)
    g = np.zeros(2)
    spread = [np.stack([np.cos(t + i), np.sin(t + i)], 1) * (1 + i) for i in range(2)]
    at_rest = Demos.from_sequences(spread, times=[t, t], velocities=[np.zeros_like(p) for p in spread], attractor=g)
    with pytest.raises(TooFewSamplesError):
        fit_seds(at_rest, n_components=1, generator=_gen(0))
    at_goal = Demos.from_sequences([np.zeros((12, 2))] * 2, times=[t, t], velocities=spread, attractor=g)
    with pytest.raises(TooFewSamplesError):
        fit_seds(at_goal, n_components=1, generator=_gen(0))


def test_seds_accepts_k_equal_to_n_and_refuses_k_above_n() -> None:
    """The documented range of n_components is 1 <= K <= N: K = N (one component per sample) gives a certified
    model (lambda_max(A_k + A_k^T) <= -2 eps by numpy), K = N + 1 raises TooFewSamplesError."""
    demos = _spiral_demos(n_demos=2, T=5)
    N = int(demos.lengths.sum())
    model = fit_seds(demos, n_components=N, max_iter=5, generator=_gen(0))
    assert model.n_components == N
    A = model.A.numpy()
    assert (np.linalg.eigvalsh(A + A.transpose(0, 2, 1)).max(-1) <= -2 * 1e-3 * (1 - 1e-9)).all()
    with pytest.raises(TooFewSamplesError):
        fit_seds(demos, n_components=N + 1, max_iter=5, generator=_gen(0))


# ------------------------------------------------------------------------------------------------ rollout
def _affine_step(A: np.ndarray, g: np.ndarray, u: np.ndarray, x: np.ndarray, t: float) -> np.ndarray:
    """Exact flow of x' = A (x - g) + u for time t: x(t) = c + expm(A t)(x - c), c = g - A^-1 u."""
    c = g - np.linalg.solve(A, u)
    return c + scipy.linalg.expm(A * t) @ (x - c)


def test_disturbances_at_the_same_sample_add_up_against_the_closed_form() -> None:
    """Disturbance docstring: several disturbances at the same sample add up -- two position pushes and two extra
    velocities, each pair at one sample and on overlapping row sets. Reference: the exact flow of the linear DS
    x' = A (x - g) (+ the summed constant velocity during its one step), expm via scipy; RK4 with dt = 0.01 agrees
    to ~1e-8 here (tolerance 1e-7; a lost push moves the state by >= 0.25, a lost kick the stored velocity by >= 5).
    The stored velocity at the kicked sample includes both extra velocities."""
    A = A_SPIRAL
    g = np.array([0.5, -1.0])
    dt, n = 0.01, 120
    rng = np.random.default_rng(11)
    x0 = rng.normal(size=(4, 2)) * 2
    d1, d2 = np.array([1.0, -0.5]), np.array([0.25, 2.0])
    u1, u2 = np.array([30.0, 0.0]), np.array([-5.0, 12.0])
    rows_a, rows_b = [0, 1, 2], [1, 3]
    dists = [Disturbance(40, d1, rows=rows_a), Disturbance(40, d2, rows=rows_b),
             Disturbance(80, u1, kind="velocity", rows=rows_a), Disturbance(80, u2, kind="velocity", rows=rows_b)]
    At = torch.from_numpy(A)
    gt = torch.from_numpy(g)
    res = rollout(lambda x: (x - gt) @ At.T, torch.from_numpy(x0), dt, n, method="rk4", disturbances=dists)
    ref = np.empty((4, n + 1, 2))
    for b in range(4):
        x = x0[b].copy()
        for k in range(n + 1):
            if k == 40:
                x = x + (d1 if b in rows_a else 0) + (d2 if b in rows_b else 0)
            ref[b, k] = x
            u = (u1 if (k == 80 and b in rows_a) else 0) + (u2 if (k == 80 and b in rows_b) else 0) + np.zeros(2)
            if k == 80:
                np.testing.assert_allclose(res.velocities[b, k].numpy(), A @ (x - g) + u, rtol=0, atol=1e-7)
            x = _affine_step(A, g, u, x, dt)
    np.testing.assert_allclose(res.positions.numpy(), ref, rtol=0, atol=1e-7)


def test_a_divergence_after_the_last_synchronisation_still_raises() -> None:
    """Module docstring: a NaN or Inf in a valid sample raises NonFiniteError naming the first such step; the
    rollout never returns NaN silently -- also when it appears after the last host synchronisation (no
    synchronisation at all with check_every > n_steps; the last one at step 8 with check_every = 4). Reference: the
    step at which the field is made to return NaN."""
    x0 = torch.tensor([[1.0, -1.0], [0.5, 0.0]], dtype=F64)
    for check_every, bad_step in ((32, 5), (4, 9)):
        calls = [0]

        def field(x: torch.Tensor) -> torch.Tensor:
            calls[0] += 1
            return torch.full_like(x, float("nan")) if calls[0] == bad_step + 1 else -x

        with pytest.raises(NonFiniteError, match=f"velocity at step {bad_step} "):
            rollout(field, x0, 0.1, 10, check_every=check_every)


def test_to_demos_uses_the_attractor_it_is_given() -> None:
    """RolloutResult.to_demos: the attractor argument is the goal of the set and the rollout's own attractor only
    its default. Reference: the given vector (and the rollout's attractor when none is given)."""
    g = torch.zeros(2, dtype=F64)
    x0 = torch.tensor([[1.0, 0.0], [0.0, 2.0]], dtype=F64)
    res = rollout(lambda x: -x, x0, 0.05, 20, attractor=g, position_tol=1e-6, velocity_tol=1e-6)
    other = torch.tensor([0.3, -0.7], dtype=F64)
    assert torch.equal(res.to_demos(attractor=other).attractor, other)
    assert torch.equal(res.to_demos().attractor, g)
