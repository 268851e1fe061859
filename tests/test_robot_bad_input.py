"""Bad input to the robot task's public pieces: a typed lfd_torch error naming the argument, never a deep crash or a
silent wrong result (each case below returned a value or crashed inside torch/numpy before it was checked)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, LfdError, NonIncreasingTimeError, ShapeMismatchError, UnknownNameError
from lfd_torch.robot.arm import NEUTRAL_POSE, BaxterArm
from lfd_torch.robot.controller import ImpedanceController, orientation_error
from lfd_torch.robot.demonstration import (
    ScoopingDemonstration,
    load_demonstration,
    save_demonstration,
    scooping_via_points,
    solve_ik,
)
from lfd_torch.robot.task import OrientationSchedule
from lfd_torch.robot.trials import Disturbance, plan_disturbances, wilson_interval

F64 = torch.float64


def test_joint_limit_tolerance_must_be_a_finite_number() -> None:
    """A NaN tolerance made every comparison false: a pose 10 rad outside the limits passed the check."""
    arm = BaxterArm()
    far = torch.tensor(NEUTRAL_POSE, dtype=F64) + 10.0
    with pytest.raises(InvalidArgumentError, match="limits"):
        arm.check_limits(far)
    for tol in (math.nan, -0.1, "0.1"):
        with pytest.raises(InvalidArgumentError, match="tol"):
            arm.check_limits(far, tol=tol)
        with pytest.raises(InvalidArgumentError, match="tol"):
            arm.within_limits(far, tol=tol)
    assert not bool(arm.within_limits(far, tol=0.5))


def test_disturbance_fields_are_checked_when_built() -> None:
    ok = Disturbance("force", 1, 0.3, 20.0, body="left_wrist", direction=(0.0, 0.6, 0.8))
    assert ok.body == "left_wrist"
    Disturbance("force", 2, 0.3, 20.0, body="spoon")  # the spoon is a body of the plant too
    for kw, err, name in ((dict(direction=(math.nan, 0.0, 0.0)), InvalidArgumentError, "direction"),
                          (dict(direction=(0.0, 0.0, 0.0)), InvalidArgumentError, "direction"),
                          (dict(direction=(1.0, 0.0)), InvalidArgumentError, "direction"),
                          (dict(direction=(2.0, 0.0, 0.0)), InvalidArgumentError, "unit"),
                          (dict(body="bogus"), UnknownNameError, "body"),
                          (dict(stage=1.0), InvalidArgumentError, "stage"),
                          (dict(stage=True), InvalidArgumentError, "stage"),
                          (dict(magnitude="1"), InvalidArgumentError, "magnitude"),
                          (dict(delay=math.inf), InvalidArgumentError, "delay")):
        args = dict(kind="force", stage=1, delay=0.3, magnitude=20.0) | kw
        with pytest.raises(err, match=name):
            Disturbance(**args)


def test_plan_disturbances_checks_its_generator_and_ranges() -> None:
    g = torch.Generator().manual_seed(0)
    plan = plan_disturbances(4, g)
    assert len(plan) == 4 and all(abs(math.hypot(*d.direction) - 1.0) < 1e-9 for d in plan)
    for args, kw, name in (((2, None), {}, "generator"), ((2, 0), {}, "generator"),
                           ((2, g), dict(force_large=(90.0,)), "force_large"),
                           ((2, g), dict(force_large=(math.nan, 1.0)), "force_large"),
                           ((2, g), dict(jump_small=(0.02, 0.01)), "jump_small"),
                           ((2, g), dict(delay_fraction=(-0.1, 0.5)), "delay_fraction"),
                           ((2, g), dict(stage_durations=(3.0, math.nan, 6.0)), "stage_durations")):
        with pytest.raises(InvalidArgumentError, match=name):
            plan_disturbances(*args, **kw)


def test_orientation_schedule_rejects_steps_it_does_not_hold() -> None:
    """A step outside 0..M-1 left an all-inf row whose argmin was sample 0: a rotation of another step."""
    pos = torch.randn(4, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    rot = torch.eye(3, dtype=F64).expand(4, 3, 3)
    sched = OrientationSchedule(pos, rot, torch.tensor([0, 0, 1, 1]), 2)
    assert int(sched.nearest(pos[2:3], torch.tensor([1]))) == 2
    with pytest.raises(InvalidArgumentError, match="step"):
        sched(torch.zeros(1, 3, dtype=F64), torch.tensor([7]))
    with pytest.raises(ShapeMismatchError, match="x"):
        sched(torch.zeros(1, 2, dtype=F64), torch.tensor([0]))
    for args, err, name in (((pos, rot, torch.tensor([0, 0, 1, 2]), 2), InvalidArgumentError, "outside"),
                            ((pos, rot, torch.tensor([0, 0, 1, 1]), 0), InvalidArgumentError, "n_steps"),
                            ((pos, rot, torch.tensor([0.0, 0.0, 1.0, 1.0]), 2), ShapeMismatchError, "steps"),
                            ((pos * math.nan, rot, torch.tensor([0, 0, 1, 1]), 2), LfdError, "positions")):
        with pytest.raises(err, match=name):
            OrientationSchedule(*args)


def test_scooping_demonstration_is_checked_and_saved_atomically(tmp_path) -> None:
    t = torch.linspace(0.0, 1.0, 5, dtype=F64)
    tip = torch.randn(5, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    demo = ScoopingDemonstration(t=t, q=None, tip=tip)
    path = save_demonstration(demo, tmp_path / "sub" / "d.npz")  # parents are created
    back = load_demonstration(path)
    torch.testing.assert_close(back.tip, tip)
    for kw, err, name in ((dict(tip=tip * math.nan), LfdError, "tip"),
                          (dict(tip=tip[:3]), ShapeMismatchError, "tip"),
                          (dict(t=torch.tensor([0.0, 1.0, 1.0, 2.0, 3.0], dtype=F64)), NonIncreasingTimeError, "t"),
                          (dict(q=torch.zeros(4, 7, dtype=F64)), ShapeMismatchError, "q"),
                          (dict(rotation=torch.eye(3, dtype=F64)), ShapeMismatchError, "rotation")):
        with pytest.raises(err, match=name):
            ScoopingDemonstration(**(dict(t=t, q=None, tip=tip) | kw))
    csv = tmp_path / "d.csv"
    save_demonstration(demo, csv)
    before = csv.read_bytes()
    with pytest.raises(InvalidArgumentError, match="demo"):
        save_demonstration("not a demo", csv)
    with pytest.raises(InvalidArgumentError, match="path"):
        save_demonstration(demo, None)
    with pytest.raises(InvalidArgumentError, match="path"):
        load_demonstration(None)
    assert csv.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.csv", "sub"]  # no temporary file left


def test_controller_and_ik_shapes_and_dtypes() -> None:
    q = torch.tensor(NEUTRAL_POSE, dtype=F64)
    ctl = ImpedanceController()
    tau = ctl.torque(q.expand(2, 7), q.expand(2, 7), q.expand(2, 7) + 0.01, q.expand(2, 7))
    assert tau.shape == (2, 7)
    for bad, name in ((dict(qd=q.expand(3, 7)), "qd"), (dict(q_d=q.expand(1, 7)), "q_d"),
                      (dict(gravity=q.expand(3, 7)), "gravity")):
        args = dict(q=q.expand(2, 7), qd=q.expand(2, 7), q_d=q.expand(2, 7), qd_d=q.expand(2, 7)) | bad
        with pytest.raises(ShapeMismatchError, match=name):
            ctl.torque(**args)
    with pytest.raises(ShapeMismatchError, match="qdot"):
        ctl.reference(q.expand(2, 7), q.expand(3, 7))
    with pytest.raises(ShapeMismatchError, match="q_d_prev"):
        ctl.reference(q.expand(2, 7), q.expand(2, 7), q.expand(3, 7))
    with pytest.raises(ShapeMismatchError, match="rot"):
        orientation_error(torch.eye(2, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(ShapeMismatchError, match="dtype"):
        orientation_error(torch.eye(3, dtype=F64), torch.eye(3, dtype=torch.float32))
    arm = BaxterArm()
    pose = arm.forward_kinematics(q[None])
    tip, rot = pose[:, :3, 3], pose[:, :3, :3]
    torch.testing.assert_close(arm.forward_kinematics(solve_ik(arm, tip, rot, q))[:, :3, 3], tip, atol=1e-6,
                               rtol=0)
    for args, kw, err, name in (((tip.expand(2, 3), rot, q), {}, ShapeMismatchError, "rotation"),
                                ((tip.float(), rot, q), {}, ShapeMismatchError, "dtype"),
                                ((tip, rot, q), dict(iterations=0), InvalidArgumentError, "iterations"),
                                ((tip * math.nan, rot, q), {}, LfdError, "tip")):
        with pytest.raises(err, match=name):
            solve_ik(arm, *args, **kw)


def test_via_points_generator_is_a_generator_or_none() -> None:
    tip, rot, stage = scooping_via_points()
    tip2, _, _ = scooping_via_points(generator=torch.Generator().manual_seed(0))
    assert tip.shape == tip2.shape and not torch.equal(tip, tip2)
    with pytest.raises(InvalidArgumentError, match="generator"):
        scooping_via_points(None, 3)


def test_wilson_interval_is_not_silently_wrong() -> None:
    lo, hi = wilson_interval(3, 10)
    assert 0.0 < lo < 0.3 < hi < 1.0
    np.testing.assert_allclose(wilson_interval(3, 10, 1.96), (lo, hi), atol=1e-4)
