"""The joint-velocity map and the impedance law at their limits: continuity of the speed-limited command in q, and the
torch impedance law against the MuJoCo plant's own clipping of its controls."""

from __future__ import annotations

import torch

from lfd_torch.robot.arm import BaxterArm
from lfd_torch.robot.controller import DLSVelocityMap, ImpedanceController

F64 = torch.float64


def _inner_configurations(arm: BaxterArm, n: int, gen: torch.Generator) -> torch.Tensor:
    lo, hi = arm.lower(F64, torch.device("cpu")), arm.upper(F64, torch.device("cpu"))
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return mid + 0.6 * half * (2 * torch.rand(n, 7, generator=gen, dtype=F64) - 1)


def test_speed_limited_command_is_continuous_in_q() -> None:
    """Property: a rounding-level change of q (1e-12 relative) changes the speed-limited joint velocity by a
    rounding-level amount, with the exact null-space projection (the default). Before the clamp after the uniform
    speed scaling, the joint that set the scale could land one rounding step past its limit, be flagged and fixed,
    and the other six re-solved: jumps of up to 0.66 rad/s on 70 of 2,633 speed-limited 6-D commands."""
    arm = BaxterArm()
    gen = torch.Generator().manual_seed(0)
    dls = DLSVelocityMap(arm, null_space="exact")
    vmax = arm.velocity_limits(F64, torch.device("cpu"))
    worst, limited = 0.0, 0
    for m in (3, 6):
        q = _inner_configurations(arm, 600, gen)
        v = 1.5 * torch.randn(600, m, generator=gen, dtype=F64)
        a = dls(q, v)
        b = dls(q * (1 + 1e-12), v)
        at_limit = ((a.abs() - vmax).abs() < 1e-9).any(-1)
        limited += int(at_limit.sum())
        worst = max(worst, float((a - b).abs().max()))
        assert bool((a.abs() <= vmax).all())
    assert limited > 100  # the case is exercised: many commands are scaled to a speed limit
    assert worst < 1e-6, worst


def test_impedance_torque_clips_its_set_point_as_the_plant_does() -> None:
    """Reference (the plant's actuators, ``ctrlrange`` = the joint range and the velocity limits): a set-point past
    the joint range or a velocity reference past the limit gives the torque of the clipped ones; inside, unchanged."""
    arm = BaxterArm()
    ctrl = ImpedanceController()
    cpu = torch.device("cpu")
    lo, hi, vmax = arm.lower(F64, cpu), arm.upper(F64, cpu), arm.velocity_limits(F64, cpu)
    q = (hi - 0.005).unsqueeze(0)
    qd = torch.zeros(1, 7, dtype=F64)
    beyond = (hi + 0.04).unsqueeze(0)
    fast = (3 * vmax).unsqueeze(0)
    torch.testing.assert_close(ctrl.torque(q, qd, beyond, fast), ctrl.torque(q, qd, hi.unsqueeze(0), vmax.unsqueeze(0)))
    kp = ctrl.stiffness.to(F64)
    tau = ctrl.torque(q, qd, beyond, torch.zeros(1, 7, dtype=F64))
    want = torch.minimum(kp * 0.005, ctrl.effort_limits.to(F64))  # 0.005 rad to the range's end, not 0.045
    torch.testing.assert_close(tau[0], want)
    inside = (0.5 * (lo + hi)).unsqueeze(0)
    q_d = inside + 0.01
    torch.testing.assert_close(ctrl.torque(inside, qd, q_d, qd)[0], torch.minimum(kp * 0.01, ctrl.effort_limits.to(F64)))
