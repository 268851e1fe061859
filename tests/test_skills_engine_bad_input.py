"""Bad input to the skill engine, its push plans and the stability check: a typed lfd_torch error naming the
argument, never a silent wrong result or a deep crash (each case below returned a value, a NaN or crashed inside
torch before), and a push plan reused in a second rollout reproduces its run."""

from __future__ import annotations

import math

import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, InvalidIndexError, NonFiniteError, ShapeMismatchError
from lfd_torch.skills import SkillEngine, SkillLibrary, check_stability, random_pushes
from test_skills import _l_task

F64 = torch.float64
NAN = math.nan


@pytest.fixture(scope="module")
def task() -> tuple:
    """The two-leg L task (2 demonstrations, steps 0 and 1, one route), its library (stability-checked as learned)
    and a full-mode engine."""
    demos, seg = _l_task()
    lib = SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1))
    return demos, lib, SkillEngine(lib, "full")


# ---------------------------------------------------------------------------------------------------- pushes
def _plan(seed: int = 5):
    return random_pushes(2, generator=torch.Generator().manual_seed(seed), n_pushes=2, window=(10, 60),
                         magnitude=(0.05, 0.1))  # fmt: skip


def test_a_reused_push_plan_reproduces_its_run_and_reports_only_its_own_pushes(task) -> None:
    """Property: a rollout reports the pushes of its own run (2 robots x 2 pushes = 4 entries, not the 8 of both
    runs), and the same plan run again gives the same positions and pushes (the plan's directions restart from
    the plan's creation instead of continuing the used-up generator), equal to a fresh plan of the same seed."""
    demos, _, eng = task
    x0 = demos.start_points
    plan = _plan()
    first = eng.rollout(x0, dt=0.01, n_steps=400, pushes=plan)
    second = eng.rollout(x0, dt=0.01, n_steps=400, pushes=plan)
    assert len(first.pushes) == 4 and len(second.pushes) == 4
    assert second.pushes == first.pushes
    assert torch.equal(second.result.positions, first.result.positions)
    assert torch.equal(second.steps, first.steps) and torch.equal(second.branches, first.branches)
    fresh = eng.rollout(x0, dt=0.01, n_steps=400, pushes=_plan())
    assert torch.equal(fresh.result.positions, first.result.positions) and fresh.pushes == first.pushes


# ---------------------------------------------------------------------------------------------------- stability
def test_check_stability_needs_a_sample_away_from_the_attractors(task) -> None:
    """Property: dV/dt < 0 is checked away from g_m only, so sample sizes that leave no such state are refused,
    naming the counts and the radius (no samples crashed in argmax, near samples of radius 0 crashed in max);
    one box sample is enough."""
    _, lib, _ = task
    with pytest.raises(InvalidArgumentError, match="n_box.*n_near.*near_radius.*n_far"):
        check_stability(lib, n_box=0, n_near=0, n_far=0)
    with pytest.raises(InvalidArgumentError, match="near_radius = 0.0"):
        check_stability(lib, n_box=0, n_near=5, n_far=0, near_radius=0.0)
    assert check_stability(lib, modes=["full"], n_box=1, n_near=0, n_far=0).n_samples == 1


def test_check_stability_bounds_far_scale(task) -> None:
    """Property: far_scale has a finite upper bound, so the check never overflows into a wrong verdict
    (far_scale=1e300 reported passed=False, worst_margin=0.0, max_dvdt=-inf on a library that passes); the
    largest accepted scale still certifies that library with finite numbers."""
    _, lib, _ = task
    kw = {"modes": ["full"], "n_box": 20, "n_near": 5, "n_far": 20}
    for bad in (1e300, 1e7):
        with pytest.raises(InvalidArgumentError, match="far_scale"):
            check_stability(lib, far_scale=bad, **kw)
    rep = check_stability(lib, far_scale=1e6, **kw)
    assert rep.passed and rep.worst_margin < 0 and math.isfinite(rep.max_dvdt) and rep.max_dvdt < 0


# ---------------------------------------------------------------------------------------------------- engine
def test_log_density_checks_its_states(task) -> None:
    """Property: log_density takes a float tensor (..., d) of finite states (a list raised AttributeError, a NaN
    state returned NaN); valid input, also with leading batch axes, is unchanged."""
    _, lib, eng = task
    x = lib.skills[0].train_positions[:6]
    want = lib.segmentation.log_density(x)
    torch.testing.assert_close(eng.log_density(x), want, rtol=1e-12, atol=1e-11)
    torch.testing.assert_close(eng.log_density(x.view(2, 3, 2)), want.view(2, 3, -1), rtol=1e-12, atol=1e-11)
    with pytest.raises(ShapeMismatchError, match="x"):
        eng.log_density([[0.0, 0.0]])
    with pytest.raises(NonFiniteError, match="x"):
        eng.log_density(torch.tensor([[NAN, 0.0]], dtype=F64))
    with pytest.raises(ShapeMismatchError, match="x"):
        eng.log_density(torch.zeros(3, 3, dtype=F64))


def test_step_taking_methods_refuse_a_step_outside_the_library(task) -> None:
    """Property: velocity, own_other and reached take (B,) integer steps in 0..M-1 (a step of 5 in a 2-step
    library crashed with a raw index error inside torch); valid steps give the documented values."""
    _, lib, eng = task
    x = torch.tensor([[-1.0, 0.5]], dtype=F64)
    no = torch.tensor([False])
    calls = {
        "velocity": lambda s: eng.velocity(x, s, no),
        "own_other": lambda s: eng.own_other(x, s),
        "reached": lambda s: eng.reached(x, s),
    }
    for name, call in calls.items():
        call(torch.tensor([1]))  # valid
        for bad, error in ((torch.tensor([5]), InvalidIndexError), (torch.tensor([-1]), InvalidIndexError),
                           (torch.tensor([0.0]), ShapeMismatchError), (torch.tensor([0, 1]), ShapeMismatchError),
                           ([0], ShapeMismatchError)):  # fmt: skip
            with pytest.raises(error, match="step"):
                call(bad)
    assert eng.reached(lib.attractors[1:2], torch.tensor([1])).tolist() == [True]
    with pytest.raises(NonFiniteError, match="x"):
        eng.own_other(torch.tensor([[NAN, 0.0]], dtype=F64), torch.tensor([0]))


def test_velocity_checks_done_inside_and_densities(task) -> None:
    """Property: velocity's flags are (B,) bool tensors and its densities a pair of (B,) tensors without NaN (a float
    done mask, a wrong-length inside mask or NaN densities went into torch.where unchecked); the checked call
    equals the engine's own batched step."""
    _, lib, eng = task
    x = lib.skills[0].train_positions[:4]
    step, no = torch.zeros(4, dtype=torch.long), torch.zeros(4, dtype=torch.bool)
    v, branch = eng.velocity(x, step, no)
    v_ref, dec, branch_ref = eng.step_batch(x, torch.zeros(4, dtype=torch.long), torch.zeros(4, dtype=torch.long))
    assert torch.equal(dec.step, step) and torch.equal(v, v_ref) and torch.equal(branch, branch_ref)
    own, other = eng.own_other(x, step)
    cases = ((lambda: eng.velocity(x, step, no.double()), ShapeMismatchError, "done"),
             (lambda: eng.velocity(x, step, no, no[:3]), ShapeMismatchError, "inside"),
             (lambda: eng.velocity(x, step, no, None, (own, other * NAN)), NonFiniteError, "densities"),
             (lambda: eng.velocity(x, step, no, None, (own, other[:2])), ShapeMismatchError, "densities"),
             (lambda: eng.velocity(x, step, no, None, own), InvalidArgumentError, "densities"))  # fmt: skip
    for call, error, name in cases:
        with pytest.raises(error, match=name) as exc:
            call()
        assert exc.type is error, (name, exc.type)


def test_progress_methods_check_their_states_and_progress(task) -> None:
    """Property: choose_route, advance and active_step check x, route and index as decide does (a list raised
    AttributeError, a NaN state advanced silently, route -1 in active_step silently read the last route)."""
    _, lib, eng = task
    x = lib.skills[0].train_positions[:2]
    zero = torch.zeros(2, dtype=torch.long)
    assert eng.choose_route(x).tolist() == [0, 0]
    assert eng.active_step(zero, zero).tolist() == [0, 0]
    r, j, done = eng.advance(x, zero - 1, zero)
    dec = eng.decide(x)
    assert torch.equal(r, dec.route) and torch.equal(j, dec.index) and torch.equal(done, dec.done)
    cases = ((lambda: eng.choose_route(x.tolist()), ShapeMismatchError, "x"),
             (lambda: eng.choose_route(x, torch.zeros(2, 5, dtype=F64)), ShapeMismatchError, "ld"),
             (lambda: eng.advance(x * NAN, zero, zero), NonFiniteError, "x"),
             (lambda: eng.advance(x, zero + 3, zero), InvalidIndexError, "route"),
             (lambda: eng.advance(x, zero, zero + 9), InvalidIndexError, "index"),
             (lambda: eng.active_step(zero - 1, zero), InvalidIndexError, "route"),
             (lambda: eng.active_step(zero, zero.double()), ShapeMismatchError, "index"))  # fmt: skip
    for call, error, name in cases:
        with pytest.raises(error, match=name):
            call()


def test_assign_steps_checks_states_and_mask(task) -> None:
    """Property: assign_steps takes (B, T, d) states finite on their valid samples, T >= 1, and a prefix-valid bool
    (B, T) mask with a valid sample per row (NaN states were assigned step 0 silently, a wrong-shape mask raised
    IndexError, a float mask RuntimeError, T = 0 a reshape error); padding is not read, so NaN there is fine."""
    demos, _, eng = task
    route, steps = eng.assign_steps(demos.positions, demos.mask)
    padded = demos.positions.clone()
    padded[~demos.mask] = NAN
    route2, steps2 = eng.assign_steps(padded, demos.mask)
    assert torch.equal(route2, route) and torch.equal(steps2, steps)
    x = demos.positions[:1, :5]
    cases = ((lambda: eng.assign_steps(torch.full((1, 5, 2), NAN, dtype=F64)), NonFiniteError, "x"),
             (lambda: eng.assign_steps(x, torch.ones(1, 4, dtype=torch.bool)), ShapeMismatchError, "mask"),
             (lambda: eng.assign_steps(x, torch.ones(1, 5)), InvalidArgumentError, "mask"),
             (lambda: eng.assign_steps(x, torch.zeros(1, 5, dtype=torch.bool)), InvalidArgumentError, "mask"),
             (lambda: eng.assign_steps(x, torch.tensor([[True, False, True, True, True]])), InvalidArgumentError,
              "mask"),
             (lambda: eng.assign_steps(demos.positions[:, :0]), ShapeMismatchError, "x"),
             (lambda: eng.assign_steps(x.tolist()), ShapeMismatchError, "x"))  # fmt: skip
    for call, error, name in cases:
        with pytest.raises(error, match=name):
            call()


def test_the_rollout_loop_does_not_run_the_public_checks(task, monkeypatch) -> None:
    """Property: validation happens at the entry points only: a rollout (with pushes) checks x0 once and its
    per-sample loop calls the unchecked building blocks, never the checked public methods."""
    demos, _, eng = task
    want = eng.rollout(demos.start_points, dt=0.01, n_steps=400, pushes=_plan())

    def refuse(*args, **kwargs):
        raise AssertionError("a checked public method ran inside the rollout loop")

    for name in ("velocity", "own_other", "advance", "active_step", "log_density", "reached", "choose_route"):
        monkeypatch.setattr(eng, name, refuse)
    got = eng.rollout(demos.start_points, dt=0.01, n_steps=400, pushes=_plan())
    assert torch.equal(got.result.positions, want.result.positions) and got.pushes == want.pushes
