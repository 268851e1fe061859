"""Bad input to the stable-primitive helpers and the rollout: a typed lfd_torch error naming the argument, never a
silent wrong result or a deep crash (each case below returned a value or crashed inside torch/cvxpy before)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from lfd_torch.ds import (
    lyapunov_violation_rate,
    quadratic_lyapunov,
    quadratic_lyapunov_derivative,
    residual_velocity_covariances,
    solve_lpv_matrices,
)
from lfd_torch.ds.primitive import StablePrimitive, quadratic_margins
from lfd_torch.errors import (
    InvalidArgumentError,
    LfdError,
    NonFiniteError,
    ShapeMismatchError,
    StoreError,
    TooFewSamplesError,
)
from lfd_torch.rollout import Disturbance, rollout

F64 = torch.float64


@pytest.fixture()
def data():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(50, 2, generator=g, dtype=F64)
    return x, -x, torch.zeros(2, dtype=F64)


def test_a_step_refuses_a_lyapunov_matrix_that_is_not_positive_definite(data) -> None:
    """With P = -I the A step returned A ~ +5e-4 I (a diverging system) under the constraint A^T P + P A < 0."""
    x, v, g = data
    gamma = torch.ones(50, 1, dtype=F64)
    A, _ = solve_lpv_matrices(x, v, gamma, g, torch.eye(2, dtype=F64))
    assert float(torch.linalg.eigvalsh(A[0] + A[0].T)[-1]) < 0  # the valid call: a contracting system
    for P, match in ((-torch.eye(2, dtype=F64), "positive definite"),
                     (torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=F64), "symmetric")):
        with pytest.raises(InvalidArgumentError, match=match):
            solve_lpv_matrices(x, v, gamma, g, P)


def test_lyapunov_helpers_check_their_inputs(data) -> None:
    """NaN positions were reported as 'no violation' (0.0), an empty set as nan, a (1,) goal broadcast silently."""
    x, v, g = data
    P = torch.eye(2, dtype=F64)
    assert lyapunov_violation_rate(x, v, g, P) == 0.0
    torch.testing.assert_close(quadratic_lyapunov(x, g, P), (x * x).sum(-1))
    torch.testing.assert_close(quadratic_lyapunov_derivative(x, v, g, P), -2.0 * (x * x).sum(-1))
    cases = ((lambda: lyapunov_violation_rate(x * math.nan, v, g, P), NonFiniteError, "x"),
             (lambda: lyapunov_violation_rate(x[:0], v[:0], g, P), TooFewSamplesError, "x"),
             (lambda: lyapunov_violation_rate(x, v, g[:1], P), ShapeMismatchError, "attractor"),
             (lambda: quadratic_lyapunov(x * math.nan, g, P), NonFiniteError, "x"),
             (lambda: quadratic_lyapunov(x, g, torch.eye(3, dtype=F64)), ShapeMismatchError, "P"),
             (lambda: quadratic_lyapunov(x, g, torch.tensor([[1.0, 2.0], [0.0, 1.0]], dtype=F64)),
              InvalidArgumentError, "symmetric"),
             (lambda: quadratic_lyapunov_derivative(x, v[:3], g, P), ShapeMismatchError, "x_dot"))
    for call, err, match in cases:
        with pytest.raises(err, match=match):
            call()


def test_residual_velocity_covariances_and_margins_check_shapes_and_weights(data) -> None:
    x, v, g = data
    gamma = torch.full((50, 2), 0.5, dtype=F64)
    A = -torch.eye(2, dtype=F64).expand(2, 2, 2).clone()
    S = residual_velocity_covariances(gamma, x, v, A, g)
    assert S.shape == (2, 2, 2) and bool((torch.linalg.eigvalsh(S) > 0).all())
    cases = ((dict(gamma=gamma[:, :1]), ShapeMismatchError, "A"),  # K = 1 against K = 2 broadcast silently
             (dict(prior_weight=-1.0), InvalidArgumentError, "prior_weight"),
             (dict(prior_weight=math.nan), InvalidArgumentError, "prior_weight"),
             (dict(gamma=-gamma), InvalidArgumentError, "gamma"),
             (dict(x=x * math.nan), NonFiniteError, "x"))
    for kw, err, match in cases:
        args = dict(gamma=gamma, x=x, x_dot=v, A=A, attractor=g) | kw
        with pytest.raises(err, match=match):
            residual_velocity_covariances(**args)
    torch.testing.assert_close(quadratic_margins(A, torch.eye(2, dtype=F64)), torch.full((2,), -2.0, dtype=F64))
    with pytest.raises(ShapeMismatchError, match="A"):
        quadratic_margins(A[0], torch.eye(2, dtype=F64))  # a (d, d) A gave a scalar
    with pytest.raises(ShapeMismatchError, match="P"):
        quadratic_margins(A, torch.eye(3, dtype=F64))


def test_primitive_state_dict_damage_is_a_store_error(tmp_path) -> None:
    from conftest import certified_primitive

    from lfd_torch.ds import LPVDS

    base = certified_primitive(2, 2, 0)
    prim = LPVDS(base.gmm, base.A, base.attractor, base.P, base.velocity_covariances)
    state = prim.state_dict()
    assert torch.equal(StablePrimitive.from_state_dict(state).A, prim.A)
    for bad in (None, [1, 2], {**state, "info": "{"}, {**state, "kind": ["x"]}, {**state, "A": prim.A.tolist()}):
        with pytest.raises(StoreError):
            StablePrimitive.from_state_dict(bad)
    with pytest.raises(LfdError, match="gmm"):
        type(prim)(None, prim.A, prim.attractor, prim.P, prim.velocity_covariances)
    with pytest.raises(InvalidArgumentError, match="info"):
        type(prim)(prim.gmm, prim.A, prim.attractor, prim.P, prim.velocity_covariances, info=3)
    assert json.loads(state["info"]) == dict(prim.info)


def test_solver_options_for_a_solver_not_tried_are_refused(data) -> None:
    """A misspelt solver name in solver_options was dropped without a word."""
    x, v, g = data
    gamma = torch.ones(50, 1, dtype=F64)
    with pytest.raises(InvalidArgumentError, match="CLARBEL"):
        solve_lpv_matrices(x, v, gamma, g, torch.eye(2, dtype=F64), solvers=["CLARABEL"],
                           solver_options={"CLARBEL": {"max_iter": 50}})


def test_rollout_arguments_and_result_queries() -> None:
    x0 = torch.ones(3, 2, dtype=F64)
    res = rollout(lambda x: -x, x0, 0.1, 20)
    far = res.positions_at(torch.tensor([1e300], dtype=F64))  # int64 overflow: an index error before
    torch.testing.assert_close(far[:, 0], res.final_positions)
    with pytest.raises(ShapeMismatchError, match="real"):
        res.positions_at(torch.tensor([0.1 + 5j]))  # the imaginary part was dropped with a warning
    with pytest.raises(InvalidArgumentError, match="names"):
        res.to_demos(names="abc")  # became three names
    with pytest.raises(InvalidArgumentError, match="requires_grad"):
        rollout(lambda x: -x, x0, 0.1, 5, requires_grad="no")  # read as True
    for rows in (["a"], [None], [[0, 1], [2]]):
        with pytest.raises(InvalidArgumentError, match="rows"):
            rollout(lambda x: -x, x0, 0.1, 5, disturbances=[Disturbance(2, [1.0, 0.0], rows=rows)])
