"""The validation layer (lfd_torch.utils checks) and the holes issue 11 named, each pinned by a test.

Every check must raise a typed lfd_torch error whose message names the argument; the holes are the examples of
the issue (fit_seds(n_components=2.5) fitting K=2, fit_seds(max_iter=0) returning the EM start, ...).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from lfd_torch.data import Demos
from lfd_torch.errors import (
    InvalidArgumentError,
    InvalidIndexError,
    LfdError,
    NonFiniteError,
    NonIncreasingTimeError,
    ShapeMismatchError,
    SolverError,
    StoreError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.utils import (
    check_choice,
    check_cost,
    check_float,
    check_generator,
    check_int,
    check_path,
    check_tensor,
    safe_magnitude,
    solver_errors,
)

F64 = torch.float64


# ---------------------------------------------------------------------------------------------- helpers
@pytest.mark.parametrize("value", [2.5, 2.0, "3", None, True, False, [1], math.nan])
def test_check_int_rejects_non_integers(value) -> None:
    with pytest.raises(InvalidArgumentError, match="n_things"):
        check_int(value, "n_things")


def test_check_int_bounds_and_numpy() -> None:
    assert check_int(np.int64(4), "k", low=1, high=4) == 4 and isinstance(check_int(np.int32(2), "k"), int)
    assert check_int(None, "k", allow_none=True) is None
    with pytest.raises(InvalidArgumentError, match=r"k must be an integer in \[1, 4\], got 5"):
        check_int(5, "k", low=1, high=4)
    with pytest.raises(TooFewSamplesError, match="k"):  # a subclass chosen by the caller
        check_int(0, "k", low=1, error=TooFewSamplesError)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, "1", None, True, torch.tensor([1.0, 2.0])])
def test_check_float_rejects(value) -> None:
    with pytest.raises(InvalidArgumentError, match="eps"):
        check_float(value, "eps", low=0.0, low_open=True)


def test_check_float_intervals() -> None:
    assert check_float(0, "t", low=0.0) == 0.0 and check_float(torch.tensor(0.5), "t", high=1.0) == 0.5
    assert check_float(math.inf, "t", allow_inf=True) == math.inf
    for value, kw in ((0.0, dict(low=0.0, low_open=True)), (1.0, dict(high=1.0, high_open=True)),
                      (-1e-9, dict(low=0.0)), (1.5, dict(high=1.0))):  # fmt: skip
        with pytest.raises(InvalidArgumentError, match="t must be"):
            check_float(value, "t", **kw)


def test_check_choice_generator_path_cost() -> None:
    assert check_choice("a", "mode", ("a", "b")) == "a"
    with pytest.raises(UnknownNameError, match="unknown mode 'c'; valid names: a, b"):
        check_choice("c", "mode", ("a", "b"))
    with pytest.raises(UnknownNameError, match="mode"):
        check_choice(3, "mode", ("a", "b"))
    g = torch.Generator()
    assert check_generator(g) is g
    with pytest.raises(InvalidArgumentError, match="generator=torch.Generator"):
        check_generator(0)
    assert check_path("a/b.pt") == Path("a/b.pt")
    for bad in (None, 3, "", b"x"):
        with pytest.raises(StoreError, match="path"):
            check_path(bad, error=StoreError)
    check_cost("n", 10.0, 10.0, "items")
    with pytest.raises(InvalidArgumentError, match="n implies 11 items, above the bound 10"):
        check_cost("n", 11.0, 10.0, "items")


def test_check_tensor() -> None:
    x = torch.zeros(4, 2, dtype=F64)
    assert check_tensor(x, "x", ndim=2, last_dim=2, min_rows=4) is x
    cases = [
        (ShapeMismatchError, [[0.0, 0.0]], {}),
        (ShapeMismatchError, x.long(), {}),
        (ShapeMismatchError, x.half(), {}),
        (ShapeMismatchError, x.to(torch.complex128), {}),
        (ShapeMismatchError, x, {"ndim": 3}),
        (ShapeMismatchError, x, {"last_dim": 3}),
        (ShapeMismatchError, x.float(), {"dtype": F64}),
        (TooFewSamplesError, x, {"min_rows": 5}),
        (NonFiniteError, x.index_put((torch.tensor([0]),), torch.tensor(math.nan, dtype=F64)), {}),
        (NonFiniteError, x + 1e200, {}),
    ]
    for error, value, kw in cases:
        with pytest.raises(error, match="x"):
            check_tensor(value, "x", **kw)
    check_tensor(x + 1e200, "x", bounded=False)  # finite, only the overflow bound is off
    assert safe_magnitude(F64) == pytest.approx(float(torch.finfo(F64).max) ** 0.25)
    assert 1e9 < safe_magnitude(torch.float32) < 1e10


def test_solver_errors_are_typed_with_the_cause_chained() -> None:
    with pytest.raises(SolverError, match="the P step failed: _LinAlgError") as err:
        with solver_errors("the P step"):
            torch.linalg.cholesky(-torch.eye(2, dtype=F64))
    assert isinstance(err.value.__cause__, torch.linalg.LinAlgError)
    with pytest.raises(TooFewSamplesError):  # lfd_torch errors pass through unchanged
        with solver_errors("x"):
            raise TooFewSamplesError("few")


# ---------------------------------------------------------------------------------------------- the holes
@pytest.fixture(scope="module")
def demos() -> Demos:
    t = torch.linspace(0, 3, 40, dtype=F64)
    return Demos.from_sequences([torch.stack([a * 10 * torch.exp(-t) * torch.cos(t), 5 * a * torch.exp(-t)], -1)
                                 for a in (1.0, 0.7)], dt=0.1)  # fmt: skip


@pytest.mark.parametrize("kw", [dict(n_components=2.5), dict(n_components="2"), dict(n_components=True),
                                dict(max_iter=0), dict(max_iter=-1), dict(max_iter=10**12), dict(max_restarts=2.5),
                                dict(em_n_init=0), dict(tolerance_grad=-1.0), dict(eps=math.nan), dict(reg=0.0),
                                dict(gain_prior=0.0)])  # fmt: skip
def test_fit_seds_rejects_bad_hyperparameters(demos, kw) -> None:
    from lfd_torch.ds import fit_seds

    full = {"n_components": 2, "max_iter": 5, **kw}
    with pytest.raises(InvalidArgumentError, match=next(iter(kw))):
        fit_seds(demos, generator=torch.Generator().manual_seed(0), **full)


def test_fit_seds_k_range_and_generator(demos) -> None:
    from lfd_torch.ds import fit_seds

    with pytest.raises(InvalidArgumentError, match="k_range"):
        fit_seds(demos, k_selection="bic", k_range=[2.5], generator=torch.Generator())
    with pytest.raises(InvalidArgumentError, match="k_range has 9999998 candidates"):
        fit_seds(demos, k_selection="bic", k_range=range(2, 10**7), generator=torch.Generator())
    with pytest.raises(InvalidArgumentError, match="generator"):
        fit_seds(demos, n_components=2, generator=0)


def test_em_bounds_and_types() -> None:
    from lfd_torch.gmm import fit_em

    x = torch.randn(30, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    for kw, name in ((dict(n_init=10**9), "n_init"), (dict(max_iter=2.5), "max_iter"), (dict(tol=-1.0), "tol"),
                     (dict(reg_covar=math.inf), "reg_covar")):  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            fit_em(x, 2, generator=torch.Generator(), **kw)
    with pytest.raises(TooFewSamplesError, match="n_components"):
        fit_em(x, 2.5, generator=torch.Generator())
    with pytest.raises(InvalidArgumentError, match="generator"):
        fit_em(x, 2, generator=None)
    with pytest.raises(NonFiniteError, match="x contains NaN, Inf or magnitudes above"):
        fit_em(x * 1e200, 2, generator=torch.Generator())
    gmm = fit_em(x, 2, generator=torch.Generator().manual_seed(0), max_iter=0)  # 0: the k-means start
    assert gmm.n_components == 2


def test_fit_lpvds_typed_errors(demos) -> None:
    from lfd_torch.ds import fit_lpvds
    from lfd_torch.gmm import EMFitter

    fit = EMFitter(n_components=2, max_iter=5)
    cases = [
        (dict(ridge=math.inf), "ridge"),
        (dict(eps="1"), "eps"),
        (dict(p_margin=1.0), "p_margin"),
        (dict(solvers=3), "solvers"),
        (dict(solver_options={"CLARABEL": 3}), "solver_options"),
        (dict(attractor=torch.zeros(1, 1, 2, dtype=F64)), "attractor"),
        (dict(attractor=torch.zeros(2, dtype=torch.complex128)), "attractor"),
        (dict(gmm=3), "gmm"),
    ]
    for kw, name in cases:
        with pytest.raises(LfdError, match=name):
            fit_lpvds(demos, **{"gmm": fit, "generator": torch.Generator(), **kw})


def test_primitive_inputs_name_x(demos) -> None:
    from lfd_torch.ds import fit_lpvds
    from lfd_torch.gmm import EMFitter

    model = fit_lpvds(demos, gmm=EMFitter(n_components=2, max_iter=5), generator=torch.Generator().manual_seed(0))
    x = demos.positions[0]
    for bad, error in ((x * 1e200, NonFiniteError), (x.half(), ShapeMismatchError), (x.numpy(), ShapeMismatchError),
                       (x[:, :1], ShapeMismatchError)):  # fmt: skip
        for fn in (model, model.lyapunov, model.gmm.log_prob):
            with pytest.raises(error, match=r"\bx\b"):
                fn(bad)
    with pytest.raises(ShapeMismatchError, match="dtype must be float32 or float64"):
        model.to(dtype=torch.float16)
    assert model.to(dtype="float32").dtype == torch.float32


def test_demos_constructor_and_index_holes(demos) -> None:
    seq = demos.sequences()[0]
    with pytest.raises(ShapeMismatchError, match="positions must hold real numbers"):
        Demos.from_sequences([seq.to(torch.complex128)])
    with pytest.raises(ShapeMismatchError, match="positions must be a list"):
        Demos.from_sequences("abc")
    with pytest.raises(ShapeMismatchError, match="dtype must be float32 or float64"):
        Demos.from_sequences([seq], dtype=torch.int64)
    with pytest.raises(NonIncreasingTimeError, match="dt"):
        Demos.from_sequences([seq], dt="x")
    with pytest.raises(ShapeMismatchError, match="lengths must be an integer tensor"):
        Demos(demos.positions, demos.velocities, demos.times, demos.lengths.double() + 0.5, demos.attractor)
    with pytest.raises(ShapeMismatchError, match="positions must be a torch.Tensor"):
        Demos(demos.positions.tolist(), demos.velocities, demos.times, demos.lengths, demos.attractor)
    for index in (1.5, "a", 7, [0, 9], slice(None, None, 0), slice(None, None, -1), slice("a", None)):
        with pytest.raises(InvalidIndexError, match="index"):
            demos[index]
    with pytest.raises(ShapeMismatchError, match="times"):  # a (2, 3) array is not 6 time stamps
        Demos.from_sequences([seq[:6]], times=[torch.arange(6, dtype=F64).reshape(2, 3)])
    column = Demos.from_sequences([seq[:6]], times=[torch.arange(6, dtype=F64).reshape(6, 1)])
    assert torch.equal(column.times[0], torch.arange(6, dtype=F64))
    with pytest.raises(ShapeMismatchError, match="float32"):  # the dtypes differ, not the attractors
        Demos.concat([demos, demos.to(dtype=torch.float32)])
    assert issubclass(InvalidIndexError, IndexError) and issubclass(InvalidIndexError, ValueError)


@pytest.mark.parametrize("kw", [dict(window=0), dict(window=-3), dict(window=4), dict(window=10**6),
                                dict(polyorder=-1), dict(subsample_step=0), dict(n_samples=10**9),
                                dict(n_samples=2.5)])  # fmt: skip
def test_preprocess_constructor_rejects(kw) -> None:
    from lfd_torch.preprocess import Preprocess

    with pytest.raises(InvalidArgumentError, match=next(iter(kw))):
        Preprocess(**kw)


def test_preprocess_functions_reject(demos) -> None:
    from lfd_torch import preprocess as pp

    for fn, name in ((lambda: pp.resample(demos, 10**9), "n_samples"), (lambda: pp.subsample(demos, 2.5), "step"),
                     (lambda: pp.moving_average(demos, None), "window"),
                     (lambda: pp.trim_still_tail(demos, math.nan, 0.1), "position_tol"),
                     (lambda: pp.screen_dimensions(demos, None), "threshold"),
                     (lambda: pp.estimate_velocities(demos.positions), "demos")):  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            fn()


def test_rollout_bounds_and_disturbances() -> None:
    from lfd_torch.rollout import Disturbance, rollout

    x0 = torch.ones(2, 2, dtype=F64)
    with pytest.raises(InvalidArgumentError, match="n_steps implies"):
        rollout(lambda x: -x, x0, 0.1, 10**12)
    with pytest.raises(NonIncreasingTimeError, match="dt"):
        rollout(lambda x: -x, x0, "0.1", 5)
    with pytest.raises(InvalidArgumentError, match="disturbances"):
        rollout(lambda x: -x, x0, 0.1, 5, disturbances=3)
    g = torch.zeros(2, dtype=F64)
    for kw, name in ((dict(position_tol="a"), "position_tol"), (dict(velocity_tol=-1.0), "velocity_tol"),
                     (dict(compact_below="a"), "compact_below"), (dict(compact_below=2.0), "compact_below")):
        with pytest.raises(InvalidArgumentError, match=name):
            rollout(lambda x: -x, x0, 0.1, 5, attractor=g, **kw)
    res = rollout(lambda x: -x, x0, 0.1, 5)
    with pytest.raises(ShapeMismatchError, match="times"):
        res.positions_at("a")
    for kw in (dict(steps=-1, value=[1.0, 0.0]), dict(steps=2.5, value=[1.0, 0.0]), dict(steps=1, value="ab")):
        with pytest.raises(InvalidArgumentError, match="disturbance"):
            Disturbance(**kw)


def test_metrics_overflow_and_lengths() -> None:
    from lfd_torch.metrics import aggregate, dtw_distance, velocity_error

    v = torch.ones(2, 5, 2, dtype=F64)
    with pytest.raises(NonFiniteError, match="pred_x_dot contains a magnitude above"):
        velocity_error(v * 1e200, v)
    with pytest.raises(TooFewSamplesError, match="from lengths"):
        velocity_error(v, v, lengths=torch.tensor([0, 5]))
    with pytest.raises(InvalidArgumentError, match="lengths"):
        velocity_error(v, v, lengths="ab")
    with pytest.raises(TooFewSamplesError, match="lengths_a"):
        dtw_distance(v, v, torch.tensor([0, 5]))
    with pytest.raises(ShapeMismatchError, match="values"):
        aggregate([1.0, 2.0])
    with pytest.raises(ShapeMismatchError, match="counts"):
        aggregate(torch.ones(2, dtype=F64), "ab")


def test_store_and_viz_paths(tmp_path) -> None:
    from matplotlib.figure import Figure

    from lfd_torch.ds import load_primitive
    from lfd_torch.errors import PlotError
    from lfd_torch.store import write_table
    from lfd_torch.viz import save_figure

    foreign = tmp_path / "foreign.pt"
    torch.save({"a": torch.zeros(2)}, foreign)
    with pytest.raises(StoreError, match="foreign.pt"):
        load_primitive(foreign)
    with pytest.raises(StoreError, match="path must be a file path"):
        write_table([], None)
    with pytest.raises(StoreError, match="manifest must be a mapping"):
        write_table([{"a": 1}], tmp_path / "t.parquet", manifest=3)
    with pytest.raises(PlotError, match="path"):
        save_figure(Figure(), 3)


def test_mnist_arguments_checked_before_any_io(tmp_path) -> None:
    from lfd_torch.data import mnist_demos, read_idx

    for kw, name in ((dict(digit=10), "digit"), (dict(digit=3, n_demos=10**9), "n_demos"),
                     (dict(digit=3, n_points=2), "n_points"), (dict(digit=3, stroke=3), "stroke")):  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            mnist_demos(directory=tmp_path, **kw)  # an empty folder: the arguments fail first
    with pytest.raises(StoreError, match="path"):
        read_idx(None)
