"""Batched rollout engine: closed-form accuracy, stopping rule and disturbances against a naive per-row loop."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import scipy.linalg
import torch

from conftest import requires_cuda
from lfd_torch.data import Demos
from lfd_torch.errors import (
    InvalidArgumentError,
    LfdError,
    NonFiniteError,
    NonIncreasingTimeError,
    ShapeMismatchError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.rollout import Disturbance, DisturbanceKind, IntegrationMethod, RolloutResult, rollout


# ---------------------------------------------------------------------------------------------- fields
def linear_mixture_field(A, g, mu, sigma, prior):
    """f(x) = sum_k gamma_k(x) A_k (x - g), gamma = softmax_k(log prior_k + log N(x; mu_k, sigma_k)).

    The benchmark field of the rollout engine (an LPV-DS without fitting). Shapes: A (K, d, d), g (d,), mu (K, d),
    sigma (K, d, d), prior (K,). Computed feature-major, (K*d, N), because reductions over a tiny trailing axis are
    slow on CPU; returns an (N, d) view of (d, N) storage. Works for any (N, d) input layout.
    """
    K, d, _ = A.shape
    chol = torch.linalg.cholesky(torch.linalg.inv(sigma))  # precision_k = chol_k chol_k^T
    LT = chol.transpose(1, 2).reshape(K * d, d)  # z_k = chol_k^T (x - mu_k)
    shift = torch.einsum("kij,kj->ki", chol.transpose(1, 2), mu).reshape(K * d, 1)
    log_w = (torch.log(prior) - 0.5 * torch.logdet(sigma)).reshape(K, 1)
    A_cat = A.reshape(K * d, d)
    shift_A = (A_cat @ g).reshape(K * d, 1)

    def field(x: torch.Tensor) -> torch.Tensor:
        n = x.shape[0]
        xt = x.T  # (d, N); contiguous when the engine calls
        z = torch.mm(LT, xt).sub_(shift).view(K, d, n)  # chol_k^T (x - mu_k)
        q = z[:, 0].square()
        for j in range(1, d):  # loops over the few state dimensions, not over samples
            q.addcmul_(z[:, j], z[:, j])
        gamma = torch.softmax(q.mul_(-0.5).add_(log_w), 0)  # (K, N) responsibilities
        y = torch.mm(A_cat, xt).sub_(shift_A).view(K, d, n)  # A_k (x - g)
        out = torch.empty(d, n, dtype=x.dtype, device=x.device)
        for j in range(d):
            torch.sum(y[:, j].mul_(gamma), 0, out=out[j])
        return out.T
    return field


def stable_mixture(generator, K=4, d=2, dtype=torch.float64, spread=3.0):
    """Parameters of a mixture whose A_k all satisfy A_k + A_k^T < 0 (V = ||x - g||^2 decreases: globally stable)."""
    M = torch.randn(K, d, d, generator=generator, dtype=torch.float64)
    S = torch.randn(K, d, d, generator=generator, dtype=torch.float64)
    A = -(M @ M.transpose(1, 2)) - 0.5 * torch.eye(d, dtype=torch.float64) + 0.8 * (S - S.transpose(1, 2))
    g = torch.randn(d, generator=generator, dtype=torch.float64)
    mu = g + spread * torch.randn(K, d, generator=generator, dtype=torch.float64)
    R = torch.randn(K, d, d, generator=generator, dtype=torch.float64)
    sigma = R @ R.transpose(1, 2) + torch.eye(d, dtype=torch.float64)
    prior = torch.rand(K, generator=generator, dtype=torch.float64) + 0.5
    prior = prior / prior.sum()
    return [t.to(dtype) for t in (A, g, mu, sigma, prior)]


def linear_field(A, g):
    return lambda x: (x - g) @ A.T


A_SPIRAL = torch.tensor([[-1.0, 2.0], [-2.0, -1.0]], dtype=torch.float64)


# ---------------------------------------------------------------------------------------------- naive reference
def naive_rollout(field, x0, dt, n_steps, method="euler", g=None, p_tol=None, v_tol=None, disturbances=()):
    """One start at a time, one step at a time: the stopping rule and disturbances as the docs state them."""
    B, d = x0.shape
    T = n_steps + 1
    P = torch.zeros(B, T, d, dtype=x0.dtype)
    V = torch.zeros(B, T, d, dtype=x0.dtype)
    lengths = torch.full((B,), T, dtype=torch.long)
    converged = torch.zeros(B, dtype=torch.bool)
    for b in range(B):
        x = x0[b].clone()
        stopped = False
        stop_k = None
        for k in range(T):
            u = torch.zeros(d, dtype=x0.dtype)
            for dist in disturbances:
                if k not in dist.steps:
                    continue
                rows = dist.rows
                hit = rows is None or (bool(rows[b]) if torch.as_tensor(rows).dtype == torch.bool else b in list(rows))
                if not hit:
                    continue
                val = torch.as_tensor(dist.value, dtype=x0.dtype)
                val = val if val.ndim == 1 else val[b]
                if dist.kind is DisturbanceKind.POSITION:
                    x = x + val
                else:
                    u = u + val
                stopped, stop_k = False, None
            P[b, k] = x
            if stopped:
                continue  # frozen: zero velocity
            f = lambda y: field(y.unsqueeze(0))[0] + u  # noqa: E731
            v = f(x)
            V[b, k] = v
            if g is not None and ((x - g) ** 2).sum() < p_tol**2 and (v**2).sum() < v_tol**2:
                stopped, stop_k = True, k
            if k == n_steps or stopped:
                continue
            if method == "euler":
                x = x + dt * v
            else:
                k2 = f(x + 0.5 * dt * v)
                k3 = f(x + 0.5 * dt * k2)
                k4 = f(x + dt * k3)
                x = x + dt / 6.0 * (v + 2.0 * k2 + 2.0 * k3 + k4)
        if stop_k is not None:
            lengths[b] = stop_k + 1
            converged[b] = True
    return P, V, lengths, converged


def assert_same(result: RolloutResult, ref, rtol=1e-12, atol=1e-12):
    P, V, L, C = ref
    assert torch.equal(result.lengths, L), (result.lengths, L)
    assert torch.equal(result.converged, C)
    torch.testing.assert_close(result.positions, P, rtol=rtol, atol=atol)
    torch.testing.assert_close(result.velocities, V, rtol=rtol, atol=atol)


# ---------------------------------------------------------------------------------------------- accuracy
def closed_form(A, g, x0, t):
    """x(t) = g + expm(A t) (x0 - g) for all t: (B, len(t), d), via scipy."""
    E = np.stack([scipy.linalg.expm(A.numpy() * ti) for ti in t.numpy()])  # (T, d, d)
    return g + torch.einsum("tij,bj->bti", torch.from_numpy(E), x0 - g)


def final_error(method, dt, x0, g, horizon=2.0):
    n = round(horizon / dt)
    res = rollout(linear_field(A_SPIRAL, g), x0, dt, n, method=method)
    exact = closed_form(A_SPIRAL, g, x0, res.times)
    return (res.positions - exact).norm(dim=-1).max().item()


@pytest.mark.parametrize("method, order", [("euler", 1), ("rk4", 4)])
def test_convergence_order_against_closed_form(generator, method, order):
    x0 = torch.randn(5, 2, generator=generator, dtype=torch.float64) * 3
    g = torch.tensor([0.5, -1.0], dtype=torch.float64)
    dts = [0.04, 0.02, 0.01] if order == 4 else [0.01, 0.005, 0.0025]
    errors = [final_error(method, dt, x0, g) for dt in dts]
    ratios = [errors[i] / errors[i + 1] for i in range(2)]
    for r in ratios:  # halving dt divides the global error by 2^order
        assert 0.85 * 2**order < r < 1.15 * 2**order, (errors, ratios)


def test_rk4_matches_closed_form_trajectory(generator):
    x0 = torch.randn(4, 2, generator=generator, dtype=torch.float64)
    g = torch.tensor([1.0, 2.0], dtype=torch.float64)
    res = rollout(linear_field(A_SPIRAL, g), x0, 0.01, 300, method=IntegrationMethod.RK4)
    exact = closed_form(A_SPIRAL, g, x0, res.times)
    torch.testing.assert_close(res.positions, exact, rtol=0, atol=2e-8)  # O(dt^4): measured 6.5e-9
    # the stored velocity is the field at the stored state
    torch.testing.assert_close(res.velocities, (exact - g) @ A_SPIRAL.T, rtol=0, atol=1e-7)
    torch.testing.assert_close(res.times, torch.arange(301, dtype=torch.float64) * 0.01)
    assert res.lengths.tolist() == [301] * 4 and not res.converged.any()


# ---------------------------------------------------------------------------------------------- stopping rule
@pytest.mark.parametrize("method", ["euler", "rk4"])
@pytest.mark.parametrize("check_every, compact_below", [(1, 0.9), (7, 0.9), (32, 0.0), (32, 1.0), (1000, 0.5)])
def test_stopping_matches_naive_loop(generator, method, check_every, compact_below):
    A, g, mu, sigma, prior = stable_mixture(generator)
    field = linear_mixture_field(A, g, mu, sigma, prior)
    x0 = g + torch.randn(24, 2, generator=generator, dtype=torch.float64) * torch.linspace(0.05, 6, 24).unsqueeze(1)
    x0[3] = g  # starts converged: stops at sample 0
    sizes = []

    def counting(x):
        sizes.append(x.shape[0])
        return field(x)

    kw = dict(method=method, attractor=g, position_tol=0.05, velocity_tol=0.1)
    res = rollout(counting, x0, 0.02, 60, check_every=check_every, compact_below=compact_below, **kw)
    ref = naive_rollout(field, x0, 0.02, 60, method, g, 0.05, 0.1)
    assert_same(res, ref)
    # the test must exercise stops at many different steps and rows that never stop
    assert res.converged.sum() >= 10 and (~res.converged).sum() >= 2
    assert len(set(res.lengths[res.converged].tolist())) >= 8 and res.lengths[3] == 1
    # stopped rows leave the working set (except when compaction is off or too rare to happen)
    compacts = compact_below > 0 and check_every < 60
    assert (min(sizes) < 24) == compacts


def test_stopped_rows_are_frozen(generator):
    A, g, mu, sigma, prior = stable_mixture(generator)
    x0 = g + torch.randn(50, 2, generator=generator, dtype=torch.float64) * 3
    res = rollout(linear_mixture_field(A, g, mu, sigma, prior), x0, 0.05, 400, attractor=g, position_tol=0.1,
                  velocity_tol=0.2)
    assert res.converged.all()
    for b in range(50):
        n = int(res.lengths[b])
        assert torch.equal(res.positions[b, n:], res.positions[b, n - 1].expand(401 - n, 2))
        assert torch.all(res.velocities[b, n:] == 0)
        assert ((res.positions[b, n - 1] - g).norm() < 0.1) and (res.velocities[b, n - 1].norm() < 0.2)
        # and not one sample earlier: the stop is the first sample meeting the rule
        before = (res.positions[b, : n - 1] - g).norm(dim=-1).lt(0.1) & res.velocities[b, : n - 1].norm(dim=-1).lt(0.2)
        assert not before.any()
    assert torch.equal(res.mask, torch.arange(401).unsqueeze(0) < res.lengths.unsqueeze(1))
    torch.testing.assert_close(res.final_positions, res.positions[torch.arange(50), res.lengths - 1])


def test_velocity_tol_inf_uses_position_only_and_zero_tol_never_stops():
    g = torch.zeros(2, dtype=torch.float64)
    x0 = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    field = linear_field(-torch.eye(2, dtype=torch.float64), g)  # x(t) = exp(-t) x0
    res = rollout(field, x0, 0.01, 500, method="rk4", attractor=g, position_tol=0.5, velocity_tol=math.inf)
    assert int(res.lengths[0]) - 1 == math.ceil(math.log(2) / 0.01)  # first k with exp(-0.01 k) < 0.5
    n = int(res.lengths[0])  # finished early: the tail is frozen
    assert torch.equal(res.positions[0, n:], res.positions[0, n - 1].expand(501 - n, 2))
    assert torch.all(res.velocities[0, n:] == 0) and torch.all(res.velocities[0, :n].norm(dim=-1) > 0)
    res0 = rollout(field, x0, 0.01, 500, attractor=g, position_tol=0.0)
    assert not res0.converged.any() and res0.lengths.tolist() == [501]
    none = rollout(field, x0, 0.01, 50)
    assert none.attractor is None and none.lengths.tolist() == [51]


def test_batched_equals_per_row(generator):
    A, g, mu, sigma, prior = stable_mixture(generator, K=3)
    field = linear_mixture_field(A, g, mu, sigma, prior)
    x0 = g + torch.randn(9, 2, generator=generator, dtype=torch.float64) * 4
    for method in ("euler", "rk4"):
        kw = dict(method=method, attractor=g, position_tol=0.1, velocity_tol=0.2)
        batch = rollout(field, x0, 0.05, 150, **kw)
        for b in range(9):
            one = rollout(field, x0[b : b + 1], 0.05, 150, **kw)
            assert torch.equal(one.lengths, batch.lengths[b : b + 1])
            torch.testing.assert_close(one.positions[0], batch.positions[b], rtol=1e-13, atol=1e-13)
            torch.testing.assert_close(one.velocities[0], batch.velocities[b], rtol=1e-13, atol=1e-13)


# ---------------------------------------------------------------------------------------------- disturbances
def test_disturbances_match_naive_loop(generator):
    A, g, mu, sigma, prior = stable_mixture(generator)
    field = linear_mixture_field(A, g, mu, sigma, prior)
    B = 16
    x0 = g + torch.randn(B, 2, generator=generator, dtype=torch.float64) * 3
    mask = torch.arange(B) % 3 == 0
    per_row = torch.randn(B, 2, generator=generator, dtype=torch.float64)
    disturbances = [
        Disturbance(steps=0, value=[0.5, 0.0]),  # a push of the start itself
        Disturbance(steps=[60, 150], value=[2.0, -1.5], rows=mask),  # pushes after most rows converged
        Disturbance(steps=150, value=per_row, kind="velocity", rows=[1, 2, 5]),  # kick, same step as a push
        Disturbance(steps=(200,), value=torch.tensor([0.0, 30.0]), kind=DisturbanceKind.VELOCITY),
        Disturbance(steps=250, value=[0.3, 0.3], rows=[0]),  # the last sample
    ]
    kw = dict(attractor=g, position_tol=0.05, velocity_tol=0.1)
    for method in ("euler", "rk4"):
        ref = naive_rollout(field, x0, 0.05, 250, method, g, 0.05, 0.1, disturbances)
        for check_every in (1, 16):
            sizes = []

            def counting(x):
                sizes.append(x.shape[0])
                return field(x)

            res = rollout(
                counting, x0, 0.05, 250, method=method, disturbances=disturbances, check_every=check_every, **kw
            )
            assert_same(res, ref)
            # stopped rows left the working set and pushes brought them back
            assert min(sizes) < B and any(b > a for a, b in zip(sizes, sizes[1:]))
        P, V, L, C = ref
        assert (V[mask][:, 150].norm(dim=-1) > 0).all()  # pushed rows move again
        assert (L[1:] > 200).all() and C[1:].all()  # the kick at 200 reactivated every row; they stopped again
        assert L[0] == 251 and not C[0]  # pushed at the last sample: not converged


def test_kick_of_stopped_row_reactivates_it():
    g = torch.zeros(2, dtype=torch.float64)
    field = linear_field(-2.0 * torch.eye(2, dtype=torch.float64), g)
    x0 = torch.tensor([[1.0, 1.0], [0.5, 0.0]], dtype=torch.float64)
    push = Disturbance(steps=300, value=[3.0, 0.0], rows=torch.tensor([True, False]))
    res = rollout(field, x0, 0.01, 600, attractor=g, position_tol=0.01, velocity_tol=0.05, disturbances=[push])
    first_stop = rollout(field, x0, 0.01, 600, attractor=g, position_tol=0.01, velocity_tol=0.05).lengths
    assert (first_stop < 300).all() and res.converged.all()
    assert res.lengths[1] == first_stop[1]  # untouched row keeps its stop
    assert res.lengths[0] > 300  # pushed row moved again and stopped later
    push_vector = torch.tensor([3.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(res.positions[0, 300], res.positions[0, 299] + push_vector)
    assert torch.all(res.velocities[0, first_stop[0] : 300] == 0)  # it stood still until the push


def test_hook_equals_disturbance_and_sees_active_rows(generator):
    A, g, mu, sigma, prior = stable_mixture(generator)
    field = linear_mixture_field(A, g, mu, sigma, prior)
    x0 = g + torch.randn(10, 2, generator=generator, dtype=torch.float64) * 3
    delta = torch.tensor([1.5, -2.0], dtype=torch.float64)
    rows = torch.arange(10) < 5
    kw = dict(attractor=g, position_tol=0.05, velocity_tol=0.1)
    seen: dict[int, torch.Tensor] = {}

    def hook(step, x, active):
        seen[step] = active
        assert x.shape == (10, 2) and x.is_contiguous()
        if step == 120:
            return torch.where(rows.unsqueeze(-1), x + delta, x)
        return None

    res = rollout(field, x0, 0.05, 200, hook=hook, **kw)
    ref = rollout(field, x0, 0.05, 200, disturbances=[Disturbance(120, delta, rows=rows)], **kw)
    assert torch.equal(res.lengths, ref.lengths)
    # the two paths add the push in a different order of operations: equal up to rounding (1e-16 here)
    torch.testing.assert_close(res.positions, ref.positions, rtol=0, atol=1e-12)
    assert sorted(seen) == list(range(201))
    first = rollout(field, x0, 0.05, 200, **kw)  # without the push
    assert (first.lengths - 1 < 120).sum() >= 3  # some rows had stopped before the push
    for k, active in seen.items():  # active at k iff not stopped before k (the push at 120 acts after the call)
        expected = (first.lengths - 1 >= k) if k <= 120 else (ref.lengths - 1 >= k)
        assert torch.equal(active, expected), k


# ---------------------------------------------------------------------------------------------- dtypes, devices
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtype_is_preserved(generator, dtype):
    A, g, mu, sigma, prior = stable_mixture(generator, dtype=dtype)
    x0 = (g + torch.randn(6, 2, generator=generator, dtype=torch.float64).to(dtype) * 2)
    res = rollout(linear_mixture_field(A, g, mu, sigma, prior), x0, 0.05, 50, method="rk4", attractor=g,
                  position_tol=0.1, velocity_tol=0.1)
    for t in (res.positions, res.velocities, res.times, res.attractor):
        assert t.dtype == dtype
    assert res.lengths.dtype == torch.long and res.converged.dtype == torch.bool
    assert res.positions.shape == (6, 51, 2) and res.velocities.shape == (6, 51, 2) and res.times.shape == (51,)
    assert torch.equal(res.positions[:, 0], x0)


def test_to_demos(generator):
    g = torch.zeros(2, dtype=torch.float64)
    field = linear_field(A_SPIRAL, g)
    x0 = torch.randn(4, 2, generator=generator, dtype=torch.float64)
    x0[3] = 0.0
    res = rollout(field, x0, 0.02, 400, method="rk4", attractor=g, position_tol=0.01, velocity_tol=0.05)
    demos = res.to_demos(names=["a", "b", "c", "d"])
    assert isinstance(demos, Demos) and demos.names == ("a", "b", "c", "d")
    assert res.lengths[3] == 1 and demos.lengths[3] == 3  # a start at the goal is extended with frozen samples
    assert torch.equal(demos.lengths[:3], res.lengths[:3])
    assert demos.max_length == int(res.lengths.max())
    n0 = int(demos.lengths[0])
    torch.testing.assert_close(demos.times[0, :n0], torch.arange(n0, dtype=torch.float64) * 0.02)
    torch.testing.assert_close(demos.positions, res.positions[:, : demos.max_length])
    assert torch.all(demos.times[0, n0:] == demos.times[0, n0 - 1])  # Demos edge-pads times
    assert torch.equal(demos.attractor, g)
    with pytest.raises(TooFewSamplesError):
        rollout(field, x0, 0.02, 1).to_demos()


def test_gradient_flows_to_start_when_requested():
    A = torch.tensor([[-1.0, 0.5], [-0.5, -2.0]], dtype=torch.float64)
    x0 = torch.tensor([[1.0, 2.0]], dtype=torch.float64, requires_grad=True)
    res = rollout(linear_field(A, torch.zeros(2, dtype=torch.float64)), x0, 0.1, 10)
    J = torch.stack([torch.autograd.grad(res.positions[0, -1, i], x0, retain_graph=True)[0][0] for i in range(2)])
    torch.testing.assert_close(J, torch.linalg.matrix_power(torch.eye(2, dtype=torch.float64) + 0.1 * A, 10))
    no_grad = rollout(linear_field(A, torch.zeros(2, dtype=torch.float64)), x0.detach(), 0.1, 3)
    assert not no_grad.positions.requires_grad
    # gradient with respect to a field parameter: x_n = (1 - c dt)^n x0, d x_n / dc = -n dt (1 - c dt)^(n - 1) x0
    c = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
    start = torch.tensor([[2.0, -1.0]], dtype=torch.float64)
    res = rollout(lambda x: -c * x, start, 0.1, 10, requires_grad=True)
    (dc,) = torch.autograd.grad(res.positions[0, -1].sum(), c)
    torch.testing.assert_close(dc, -10 * 0.1 * (1 - 0.07) ** 9 * start.sum())


@requires_cuda
def test_cuda_matches_cpu(generator):
    A, g, mu, sigma, prior = stable_mixture(generator)
    x0 = g + torch.randn(64, 2, generator=generator, dtype=torch.float64) * 3
    kw = dict(method="rk4", position_tol=0.05, velocity_tol=0.1,
              disturbances=[Disturbance(100, [1.0, 1.0], rows=torch.arange(64) % 2 == 0)])
    cpu = rollout(linear_mixture_field(A, g, mu, sigma, prior), x0, 0.05, 200, attractor=g, **kw)
    dev = [t.cuda() for t in (A, g, mu, sigma, prior)]
    kw["disturbances"] = [Disturbance(100, [1.0, 1.0], rows=(torch.arange(64) % 2 == 0).cuda())]
    gpu = rollout(linear_mixture_field(*dev), x0.cuda(), 0.05, 200, attractor=dev[1], **kw)
    assert gpu.positions.device.type == "cuda" and gpu.lengths.device.type == "cuda"
    assert torch.equal(gpu.lengths.cpu(), cpu.lengths)
    torch.testing.assert_close(gpu.positions.cpu(), cpu.positions, rtol=1e-10, atol=1e-10)


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_inputs_raise_typed_errors():
    g = torch.zeros(2, dtype=torch.float64)
    field = linear_field(A_SPIRAL, g)
    x0 = torch.ones(3, 2, dtype=torch.float64)
    cases = [
        (ShapeMismatchError, dict(x0=torch.ones(2, dtype=torch.float64))),
        (ShapeMismatchError, dict(x0=torch.ones(1, 3, 2, dtype=torch.float64))),
        (TooFewSamplesError, dict(x0=torch.ones(0, 2, dtype=torch.float64))),
        (InvalidArgumentError, dict(x0=torch.ones(3, 2, dtype=torch.long))),
        (InvalidArgumentError, dict(x0=[[1.0, 2.0]])),
        (NonFiniteError, dict(x0=torch.tensor([[1.0, 2.0], [float("nan"), 0.0]], dtype=torch.float64))),
        (NonFiniteError, dict(x0=torch.tensor([[1.0, float("inf")]], dtype=torch.float64))),
        (TooFewSamplesError, dict(n_steps=0)),
        (TooFewSamplesError, dict(n_steps=-3)),
        (InvalidArgumentError, dict(n_steps=2.5)),
        (NonIncreasingTimeError, dict(dt=0.0)),
        (NonIncreasingTimeError, dict(dt=-0.1)),
        (NonIncreasingTimeError, dict(dt=float("nan"))),
        (NonIncreasingTimeError, dict(dt=float("inf"))),
        (UnknownNameError, dict(method="midpoint")),
        (ShapeMismatchError, dict(attractor=torch.zeros(3))),
        (NonFiniteError, dict(attractor=torch.tensor([0.0, float("nan")]))),
        (InvalidArgumentError, dict(position_tol=0.1)),  # tolerance without attractor
        (InvalidArgumentError, dict(attractor=g, velocity_tol=-1.0)),
        (InvalidArgumentError, dict(check_every=0)),
        (InvalidArgumentError, dict(field="not callable")),
        (ShapeMismatchError, dict(field=lambda x: x[:, :1])),
        (ShapeMismatchError, dict(field=lambda x: x.float())),
        (ShapeMismatchError, dict(field=lambda x: x.numpy())),
        (InvalidArgumentError, dict(disturbances=[Disturbance(11, [1.0, 0.0])])),
        (ShapeMismatchError, dict(disturbances=[Disturbance(1, [1.0, 0.0, 0.0])])),
        (ShapeMismatchError, dict(disturbances=[Disturbance(1, [1.0, 0.0], rows=torch.ones(4, dtype=torch.bool))])),
        (ShapeMismatchError, dict(disturbances=[Disturbance(1, [1.0, 0.0], rows=[3])])),
        (NonFiniteError, dict(disturbances=[Disturbance(1, [1.0, float("nan")])])),
        (InvalidArgumentError, dict(disturbances=["push"])),
        (ShapeMismatchError, dict(hook=lambda k, x, a: x[:1])),
    ]
    for error, override in cases:
        args = dict(field=field, x0=x0, dt=0.1, n_steps=10)
        args.update(override)
        with pytest.raises(error):
            rollout(args.pop("field"), args.pop("x0"), args.pop("dt"), args.pop("n_steps"), **args)
    with pytest.raises(UnknownNameError):
        Disturbance(1, [1.0, 0.0], kind="torque")
    with pytest.raises(InvalidArgumentError):
        Disturbance([], [1.0, 0.0])
    with pytest.raises(InvalidArgumentError):
        Disturbance([1.5], [1.0, 0.0])


def test_divergence_raises_naming_the_step():
    x0 = torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=torch.float32)
    with pytest.raises(NonFiniteError, match=r"step \d+") as err:  # x(t) = x0 exp(200 t) overflows float32
        rollout(lambda x: 200.0 * x, x0, 0.05, 100)
    assert err.value.demo_index == 0 and isinstance(err.value, LfdError)

    def nan_at_step(x, calls=[0]):  # noqa: B006 - counts calls
        calls[0] += 1
        return torch.full_like(x, float("nan")) if calls[0] == 8 else -x

    with pytest.raises(NonFiniteError, match="step 7"):
        rollout(nan_at_step, x0.double(), 0.1, 20, check_every=5)

    def finite_then_nan(x, calls=[0]):  # noqa: B006 - huge but finite velocities, NaN from the 6th call (step 5)
        calls[0] += 1
        return torch.full_like(x, float("nan") if calls[0] >= 6 else 1e308)

    # the position overflows at step 2 (0 -> 1e308 -> inf), the velocity turns NaN at step 5: the earlier is named
    with pytest.raises(NonFiniteError, match="non-finite position at step 2"):
        rollout(finite_then_nan, torch.zeros(1, 2, dtype=torch.float64), 1.0, 20, check_every=10)


# ---------------------------------------------------------------------------------------------- performance
def eager_rollout(field, x0, dt, n_steps, g, p_tol, v_tol):
    """The plain baseline: one start at a time, a Python loop over steps (Euler, same stopping rule)."""
    out = []
    for b in range(x0.shape[0]):
        x = x0[b : b + 1]
        traj = [x]
        for _ in range(n_steps):
            v = field(x)
            if ((x - g) ** 2).sum() < p_tol**2 and (v**2).sum() < v_tol**2:
                break
            x = x + dt * v
            traj.append(x)
        out.append(torch.cat(traj))
    return out


@pytest.mark.slow
def test_batched_engine_is_much_faster_than_eager_loop(generator):
    A, g, mu, sigma, prior = stable_mixture(generator, K=8, dtype=torch.float32)
    field = linear_mixture_field(A, g, mu, sigma, prior)
    x0 = g + torch.randn(2000, 2, generator=generator).float() * 5
    t = time.perf_counter()
    res = rollout(field, x0, 0.01, 500, attractor=g, position_tol=1e-2, velocity_tol=1e-2)
    batched = time.perf_counter() - t
    n_eager = 4
    t = time.perf_counter()
    eager = eager_rollout(field, x0[:n_eager], 0.01, 500, g, 1e-2, 1e-2)
    per_start = (time.perf_counter() - t) / n_eager
    for b in range(n_eager):  # same trajectories
        torch.testing.assert_close(eager[b], res.positions[b, : len(eager[b])], rtol=1e-5, atol=1e-5)
    assert per_start * 2000 / batched > 50  # measured ~400 on the 2-core CI box


def test_positions_at_interpolates_and_holds_the_end() -> None:
    x0 = torch.tensor([[1.0, 0.0], [2.0, 0.0]], dtype=torch.float64)
    res = rollout(lambda x: -x, x0, 0.1, 50, attractor=torch.zeros(2, dtype=torch.float64), position_tol=0.5,
                  velocity_tol=float("inf"))  # fmt: skip
    t = torch.tensor([0.0, 0.05, 0.1, 0.25, 100.0], dtype=torch.float64)
    got = res.positions_at(t)
    naive = torch.empty(2, 5, 2, dtype=torch.float64)
    for b in range(2):
        n = int(res.lengths[b])
        for q, tq in enumerate(t.tolist()):
            k = min(int(tq // 0.1), n - 1)
            k1 = min(k + 1, n - 1)
            w = 0.0 if k1 == k else (tq - k * 0.1) / 0.1
            naive[b, q] = res.positions[b, k] + w * (res.positions[b, k1] - res.positions[b, k])
    assert torch.allclose(got, naive, atol=1e-12)
    assert torch.equal(got[:, -1], res.positions[torch.arange(2), res.lengths - 1])


def test_stopping_rule_is_strict_at_the_tolerances():
    """A row stops only *inside* the tolerances (strict inequalities, module docstring): on a still field, a start
    exactly position_tol from g never stops, one just inside stops at once; likewise for a speed exactly at
    velocity_tol."""
    g = torch.zeros(2, dtype=torch.float64)
    x0 = torch.tensor([[0.5, 0.0], [0.25, 0.0]], dtype=torch.float64)  # |x0 - g| = 0.5 (on the tolerance), 0.25
    still = rollout(lambda x: 0.0 * x, x0, 0.1, 10, attractor=g, position_tol=0.5, velocity_tol=1.0)
    assert still.lengths.tolist() == [11, 1] and still.converged.tolist() == [False, True]
    x_in = torch.tensor([[0.25, 0.0]], dtype=torch.float64)
    for speed, length in ((0.5, 11), (0.25, 1)):  # a constant velocity exactly at velocity_tol, then inside it
        v = torch.tensor([speed, 0.0], dtype=torch.float64)
        moving = rollout(lambda x, v=v: v.expand(x.shape[0], 2), x_in, 1e-12, 10, attractor=g, position_tol=0.5,
                         velocity_tol=0.5)  # fmt: skip
        assert moving.lengths.tolist() == [length], speed
