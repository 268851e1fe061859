"""Reference checks of the robot code (arm, controller, plant, demonstration, task, system) against independent
closed forms: numpy damped least squares, Rodrigues' formula / scipy rotation vectors, per-joint loops, polynomial
identities. Each test names the property it checks; all are seeded and take well under a second."""

from __future__ import annotations

import math
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.robot import BaxterArm, BaxterPlant, DLSVelocityMap, ImpedanceController, build_robot
from lfd_torch.robot.arm import ARM_JOINT_NAMES
from lfd_torch.robot.controller import orientation_error
from lfd_torch.robot.demonstration import (
    _band_noise,
    _hermite,
    _minimum_jerk,
    _pose_knots,
    _rotation_path,
    load_demonstration,
    solve_ik,
)
from lfd_torch.robot.plant import cylinder_inertia
from lfd_torch.robot.task import OrientationSchedule, ScoopingController, _step_stage
from lfd_torch.robot.urdf import BAXTER_LEFT_TABLE

F64 = torch.float64


@pytest.fixture(scope="module")
def arm() -> BaxterArm:
    return BaxterArm()


def _expm(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: exp([w]) for a rotation vector w (rad)."""
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    a = w / th
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


def _random_rotvec(rng: np.random.Generator, angle: float) -> np.ndarray:
    a = rng.normal(size=3)
    return angle * a / np.linalg.norm(a)


def _np_dls(J: np.ndarray, v: np.ndarray, z: np.ndarray, lam: float) -> np.ndarray:
    """Closed-form damped least squares with the damped null-space projector (numpy, float64)."""
    pinv = J.T @ np.linalg.inv(J @ J.T + lam**2 * np.eye(J.shape[0]))
    return pinv @ v + (np.eye(7) - pinv @ J) @ z


# ---------------------------------------------------------------------------------------------- rotations
def test_orientation_error_is_base_frame_log_of_relative_rotation() -> None:
    """orientation_error(R, R_des) is the rotation vector w with R_des = exp([w]) R (base frame), for any R (not
    only the identity) and any angle below pi, including the near-pi branch; reference: Rodrigues' formula."""
    rng = np.random.default_rng(11)
    for angle in (0.3, 1.2, 2.5, 3.0, 3.12, 3.135):
        for _ in range(4):
            R = _expm(_random_rotvec(rng, rng.uniform(0.2, 3.0)))
            w = _random_rotvec(rng, angle)
            R_des = _expm(w) @ R
            got = orientation_error(torch.tensor(R), torch.tensor(R_des)).numpy()
            np.testing.assert_allclose(got, w, atol=1e-6)
            # and against scipy's rotation vector of R_des R^T
            np.testing.assert_allclose(got, Rotation.from_matrix(R_des @ R.T).as_rotvec(), atol=1e-6)


# ---------------------------------------------------------------------------------------------- DLS velocity map
def _poses(arm: BaxterArm, n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return arm.neutral()[None] + 0.2 * (torch.rand(n, 7, generator=g, dtype=F64) - 0.5)


def test_dls_position_and_pose_task_match_numpy_closed_form(arm: BaxterArm) -> None:
    """Away from every limit, the DLS map is exactly J_w^T (J_w J_w^T + lambda^2 I)^-1 v_w + (I - J_w# J_w) z with
    z = null_gain (posture - q) and, for a pose task, the angular rows of J and v both weighted by
    orientation_weight; reference: the closed form in numpy."""
    q = _poses(arm, 6, 3)
    g = torch.Generator().manual_seed(4)
    J = arm.jacobian(q).numpy()
    dls = DLSVelocityMap(arm, damping=0.02, null_gain=0.7, limit_gain=0.0, orientation_weight=0.1)
    for dim in (3, 6):
        v = 0.05 * torch.randn(6, dim, generator=g, dtype=F64)
        got = dls(q, v, 0.01).numpy()
        for b in range(6):
            z = 0.7 * (arm.neutral().numpy() - q[b].numpy())
            if dim == 3:
                Jb, vb = J[b, :3], v[b].numpy()
            else:
                Jb = np.concatenate([J[b, :3], 0.1 * J[b, 3:]])
                vb = np.concatenate([v[b, :3].numpy(), 0.1 * v[b, 3:].numpy()])
            np.testing.assert_allclose(got[b], _np_dls(Jb, vb, z, 0.02), atol=1e-10)


def test_dls_exact_projector_matches_numpy_pseudo_inverse(arm: BaxterArm) -> None:
    """null_space='exact' uses the orthogonal projector I - pinv(J) J onto the null space of J; reference:
    numpy.linalg.pinv."""
    q = _poses(arm, 4, 5)
    v = 0.02 * torch.randn(4, 3, generator=torch.Generator().manual_seed(6), dtype=F64)
    got = DLSVelocityMap(arm, null_gain=0.5, limit_gain=0.0, null_space="exact")(q, v, 0.01).numpy()
    J = arm.jacobian(q).numpy()[:, :3]
    for b in range(4):
        pinv = J[b].T @ np.linalg.inv(J[b] @ J[b].T + 0.02**2 * np.eye(3))
        z = 0.5 * (arm.neutral().numpy() - q[b].numpy())
        proj = np.eye(7) - np.linalg.pinv(J[b]) @ J[b]
        np.testing.assert_allclose(got[b], pinv @ v[b].numpy() + proj @ z, atol=1e-10)


def test_dls_speed_limit_scales_the_solution_uniformly(arm: BaxterArm) -> None:
    """A command beyond the speed limits returns the unsaturated DLS solution times the single factor
    min_j vmax_j / |qdot_j| (the direction in joint space is kept, one joint at its limit); reference: numpy closed
    form of the unsaturated solution."""
    q = arm.neutral()[None]
    v = torch.tensor([[4.0, -3.0, 2.0]], dtype=F64)
    dls = DLSVelocityMap(arm, null_gain=0.3, limit_gain=0.0)
    got = dls(q, v, 0.01)[0].numpy()
    free = _np_dls(arm.jacobian(q)[0, :3].numpy(), v[0].numpy(), 0.3 * np.zeros(7), 0.02)
    vmax = arm.velocity_limits().numpy()
    s = float(np.min(vmax / np.abs(free)))
    assert s < 1.0
    np.testing.assert_allclose(got, s * free, atol=1e-10)
    assert np.isclose(np.max(np.abs(got) / vmax), 1.0)


def test_dls_saturated_resolve_keeps_the_speed_scaling_of_task_and_posture(arm: BaxterArm) -> None:
    """When the speed scaling s < 1 is active and a joint then hits its position bound, that joint is fixed at the
    bound and the others are the DLS solution of the reduced Jacobian for the *scaled* task s v and the *scaled*
    posture term s z (one consistent, uniformly slowed problem); reference: one saturation pass in numpy."""
    posture = arm.neutral() + torch.tensor([0.0, 0.3, 0.3, -0.3, 0.3, 0.3, 0.3], dtype=F64)
    dls = DLSVelocityMap(arm, null_gain=1.0, limit_gain=0.0, posture=posture.tolist())
    q = arm.neutral()[None].clone()
    q[0, 0] = arm.lower()[0] + dls.limit_buffer  # s0 at its bound: it may not move further down
    v = torch.tensor([[0.0, -3.0, 0.0]], dtype=F64)
    got = dls(q, v, 0.01)[0].numpy()
    J = arm.jacobian(q)[0, :3].numpy()
    z = (posture - q[0]).numpy()
    free = _np_dls(J, v[0].numpy(), z, 0.02)
    vmax = arm.velocity_limits().numpy()
    s = float(np.min(vmax / np.abs(free)))
    assert s < 0.9 and free[0] < 0  # speed-scaled, and the plain solution drives s0 below its bound
    Jf = J.copy()
    Jf[:, 0] = 0.0
    zf = s * z
    zf[0] = 0.0
    ref = _np_dls(Jf, s * v[0].numpy(), zf, 0.02)
    ref[0] = 0.0
    assert (np.abs(ref) <= vmax + 1e-9).all()
    np.testing.assert_allclose(got, ref, atol=1e-9)


def test_null_velocity_matches_per_joint_piecewise_formula(arm: BaxterArm) -> None:
    """z_j = null_gain (posture_j - q_j) + limit_gain * (lo_j + m - q_j if q_j < lo_j + m; -(q_j - (hi_j - m)) if
    q_j > hi_j - m; else 0): the push always points into the range; reference: a per-joint Python loop."""
    dls = DLSVelocityMap(arm, null_gain=0.5, limit_gain=2.0, limit_margin=0.15)
    lo, hi, post = arm.lower().numpy(), arm.upper().numpy(), dls.posture.numpy()
    rng = np.random.default_rng(8)
    rows = [lo + rng.uniform(0.0, 0.1, 7), hi - rng.uniform(0.0, 0.1, 7), (lo + hi) / 2 + rng.uniform(-0.1, 0.1, 7)]
    q = torch.tensor(np.array(rows))
    got = dls.null_velocity(q).numpy()
    for b, row in enumerate(rows):
        for j in range(7):
            push = 0.0
            if row[j] < lo[j] + 0.15:
                push = lo[j] + 0.15 - row[j]
            elif row[j] > hi[j] - 0.15:
                push = -(row[j] - (hi[j] - 0.15))
            assert got[b, j] == pytest.approx(0.5 * (post[j] - row[j]) + 2.0 * push, abs=1e-12)
    # near an upper limit the push points down, near a lower limit up
    assert (got[1] - 0.5 * (post - rows[1]) < 0).all() and (got[0] - 0.5 * (post - rows[0]) > 0).all()


# ---------------------------------------------------------------------------------------------- impedance
def test_impedance_reference_clamps_the_carried_lag() -> None:
    """reference(): q_d = q + clip(q_d_prev - q, +-max_lag) + dt qdot, qd_d = qdot; reference: numpy clip."""
    imp = ImpedanceController(max_lag=0.05)
    q = torch.tensor([[0.1, -0.5, 0.0, 1.2, 0.0, 0.8, 0.0]], dtype=F64)
    lag = torch.tensor([[0.2, -0.2, 0.01, -0.03, 0.0, 0.06, -1.0]], dtype=F64)
    qdot = torch.tensor([[0.3, -0.1, 0.2, 0.0, 1.0, -2.0, 0.5]], dtype=F64)
    q_d, qd_d = imp.reference(q, qdot, q + lag, 0.01)
    expect = q.numpy() + np.clip(lag.numpy(), -0.05, 0.05) + 0.01 * qdot.numpy()
    np.testing.assert_allclose(q_d.numpy(), expect, atol=1e-14)
    torch.testing.assert_close(qd_d, qdot)


def test_impedance_torque_clamps_pd_then_adds_gravity() -> None:
    """torque(): clip(kp (q_d - q) + kv (qd_d - qd), +-effort) + g, the gravity term outside the clamp, q_d and qd_d
    first clipped to the joint range and velocity limits as the plant's actuators clip them; reference: numpy."""
    imp = ImpedanceController()
    kp, kv, tmax = imp.stiffness.numpy(), imp.damping.numpy(), imp.effort_limits.numpy()
    rng = np.random.default_rng(2)
    q, qd = rng.uniform(-0.5, 0.5, (3, 7)), rng.uniform(-1, 1, (3, 7))
    q_d, qd_d = q + rng.uniform(-0.2, 0.2, (3, 7)), rng.uniform(-1, 1, (3, 7))
    g = rng.uniform(-40, 40, (3, 7))
    got = imp.torque(*(torch.tensor(x) for x in (q, qd, q_d, qd_d)), gravity=torch.tensor(g)).numpy()
    joints = [j for j in BAXTER_LEFT_TABLE if j.kind == "revolute"]
    lo, hi, vmax = (np.array([getattr(j, a) for j in joints]) for a in ("lower", "upper", "velocity"))
    q_dc, qd_dc = np.clip(q_d, lo, hi), np.clip(qd_d, -vmax, vmax)
    expect = np.clip(kp * (q_dc - q) + kv * (qd_dc - qd), -tmax, tmax) + g
    np.testing.assert_allclose(got, expect, atol=1e-10)
    assert (np.abs(got) > tmax).any()  # the compensation is not clamped


# ---------------------------------------------------------------------------------------------- limits
def test_limit_checks_accept_the_tolerance_at_both_bounds(arm: BaxterArm) -> None:
    """arm.check_limits and plant.reset accept angles up to LIMIT_TOLERANCE beyond the lower as well as the upper
    limits (float32-rounded limits pass), reject 1e-4 rad beyond; within_limits is False when any one joint is
    out; reference: the limits of BAXTER_LEFT_TABLE."""
    lo32 = arm.lower(torch.float32).double()
    assert bool((lo32 < arm.lower()).any())
    arm.check_limits(lo32)
    arm.check_limits(arm.lower() - 5e-7)
    plant = BaxterPlant()
    plant.reset((arm.lower() - 5e-7).numpy())
    plant.reset(lo32.numpy())
    with pytest.raises(InvalidArgumentError, match="joint limits"):
        arm.check_limits(arm.lower() - 1e-4)
    with pytest.raises(InvalidArgumentError, match="joint limits"):
        plant.reset((arm.lower() - 1e-4).numpy())
    q = arm.neutral().clone()
    q[3] = -0.3
    assert not bool(arm.within_limits(q)) and bool(arm.within_limits(arm.neutral()))
    with pytest.raises(InvalidArgumentError, match="joint limits"):
        plant.teleport(q.numpy())


def test_check_limits_names_the_first_violating_joint(arm: BaxterArm) -> None:
    """The limit error names the first joint (in s0..w2 order) out of its range; reference: the joint order."""
    q = arm.neutral().clone()
    q[1], q[5] = 1.5, 2.5  # s1 and w1 both above their upper limits
    with pytest.raises(InvalidArgumentError, match=ARM_JOINT_NAMES[1]):
        arm.check_limits(q)


# ---------------------------------------------------------------------------------------------- plant model
def test_cylinder_inertia_closed_form_and_model_inertia() -> None:
    """cylinder_inertia is m (3 r^2 + L^2) / 12 across and m r^2 / 2 along the axis, and MuJoCo's principal
    inertia of the upper shoulder equals it for the capsule from s0 to s1; reference: the solid-cylinder formula."""
    assert cylinder_inertia(2.0, 0.1, 0.6) == pytest.approx((0.065, 0.065, 0.01), abs=1e-15)
    plant = BaxterPlant()
    length = float(np.linalg.norm(BAXTER_LEFT_TABLE[2].xyz))
    m, r = 5.70, 0.070
    expect = sorted([m * (3 * r**2 + length**2) / 12] * 2 + [m * r**2 / 2])
    body = plant.body_ids["left_upper_shoulder"]
    np.testing.assert_allclose(sorted(plant.model.body_inertia[body]), expect, rtol=1e-9)


# ---------------------------------------------------------------------------------------------- demonstration
def test_body_quaternions_are_the_joint_rotations_also_for_half_turns() -> None:
    """The MJCF body quaternion of a URDF rpy (plant._quat) against Rodrigues' formula of the rotation it encodes,
    turned back into a matrix by the explicit quaternion formula: random rotations and half turns about random axes
    (w = 0, where signs read off differences of matrix entries were rounding noise: the axis (1, 2, -3) came out as
    a different rotation, 1.7 off in a matrix entry)."""
    from lfd_torch.robot.plant import _quat
    from lfd_torch.robot.urdf import rpy_to_matrix

    rng = np.random.default_rng(7)
    axes = np.vstack([[1.0, 2.0, -3.0], [1.0, 1.0, -1.0], rng.normal(size=(20, 3))])
    angles = np.concatenate([[math.pi, math.pi], np.where(np.arange(20) % 2 == 0, math.pi, rng.uniform(0, math.pi, 20))])
    for axis, angle in zip(axes, angles):
        k = axis / np.linalg.norm(axis)
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        R = np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * K @ K
        rpy = tuple(Rotation.from_matrix(R).as_euler("xyz"))  # URDF rpy: fixed axes x, y, z
        assert np.allclose(np.array(rpy_to_matrix(rpy)), R, atol=1e-12)
        w, x, y, z = _quat(rpy)
        Rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                       [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                       [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])  # fmt: skip
        assert np.allclose(Rq, R, atol=1e-12), (axis, angle)
        assert w >= 0.0 and abs(w * w + x * x + y * y + z * z - 1.0) < 1e-12


def test_solve_ik_one_iteration_is_the_damped_least_squares_step(arm: BaxterArm) -> None:
    """One iteration of solve_ik is q + J_w^T (J_w J_w^T + damping^2 I)^-1 W e with the weighted pose error
    e = [tip - p; log(R_des R^T)] (no posture term in a single pass); reference: numpy and scipy's rotation
    vector."""
    q0 = _poses(arm, 3, 9)
    target = arm.forward_kinematics(q0 + 0.03)
    got = solve_ik(arm, target[:, :3, 3], target[:, :3, :3], q0, iterations=1, strict=False).numpy()
    pose, J = arm.pose_and_jacobian(q0)
    w = np.array([1.0, 1.0, 1.0, 0.1, 0.1, 0.1])
    for b in range(3):
        e = np.concatenate([(target[b, :3, 3] - pose[b, :3, 3]).numpy(),
                            Rotation.from_matrix((target[b, :3, :3] @ pose[b, :3, :3].T).numpy()).as_rotvec()])
        Jw = w[:, None] * J[b].numpy()
        dq = Jw.T @ np.linalg.inv(Jw @ Jw.T + 0.01**2 * np.eye(6)) @ (w * e)
        assert np.abs(dq).max() < 0.2
        np.testing.assert_allclose(got[b], q0[b].numpy() + dq, atol=1e-9)


def test_hermite_tangents_are_exact_for_quadratics() -> None:
    """With the non-uniform Catmull-Rom tangents the cubic Hermite path reproduces a quadratic exactly on every
    interior segment (the tangent at an interior knot is the quadratic's derivative); reference: the polynomial."""
    knots = torch.tensor([0.0, 0.1, 0.4, 0.5, 1.0], dtype=F64)

    def f(t: torch.Tensor) -> torch.Tensor:
        return torch.stack([3 * t**2 - t + 0.5, -2 * t**2 + 0.3 * t], -1)

    u = torch.linspace(0.1, 0.5, 41, dtype=F64)
    torch.testing.assert_close(_hermite(f(knots), u, knots), f(u), atol=1e-12, rtol=0)


def test_rotation_path_passes_through_the_via_rotations() -> None:
    """_rotation_path(rot, knots, knots) returns rot at its knots (rot(u) = exp([w(u)]) rot[0], base frame);
    reference: the via rotations from Rodrigues' formula."""
    rng = np.random.default_rng(5)
    r0 = _expm(_random_rotvec(rng, 1.0))
    rot = np.stack([r0] + [_expm(_random_rotvec(rng, a)) @ r0 for a in (0.4, 0.9, 1.4)])
    knots = torch.tensor([0.0, 0.2, 0.6, 1.0], dtype=F64)
    got = _rotation_path(torch.tensor(rot), knots, knots)
    np.testing.assert_allclose(got.numpy(), rot, atol=1e-10)


def test_minimum_jerk_boundary_conditions() -> None:
    """The minimum-jerk time law s(tau) goes 0 -> 1 with zero velocity and zero acceleration at both ends and
    passes 1/2 at tau = 1/2; reference: finite differences."""
    h = 1e-4
    t = torch.tensor([0.0, h, 2 * h, 1 - 2 * h, 1 - h, 1.0, 0.5], dtype=F64)
    s = _minimum_jerk(t)
    assert float(s[0]) == 0.0 and float(s[5]) == pytest.approx(1.0, abs=1e-15) and float(s[6]) == pytest.approx(0.5)
    for a, b, c in ((0, 1, 2), (3, 4, 5)):
        assert abs(float(s[c] - s[a])) / (2 * h) < 1e-6  # velocity
        assert abs(float(s[a] - 2 * s[b] + s[c])) / h**2 < 1e-2  # acceleration


def test_band_noise_has_no_power_outside_the_band() -> None:
    """_band_noise: unit RMS per axis and no spectral content outside [1, 8] Hz; reference: numpy's rfft."""
    x = _band_noise(1000, 100.0, (1.0, 8.0), torch.Generator().manual_seed(1), F64).numpy()
    np.testing.assert_allclose(np.sqrt((x**2).mean(0)), 1.0, rtol=1e-12)
    spec = np.abs(np.fft.rfft(x, axis=0))
    f = np.fft.rfftfreq(1000, d=0.01)
    out = (f < 1.0) | (f > 8.0)
    assert spec[out].max() < 1e-9 * spec.max()


# ---------------------------------------------------------------------------------------------- task
def test_orientation_schedule_progress_is_per_step_arc_length_fraction() -> None:
    """progress_table is, within each step, the cumulative path length from the step's first sample over the
    step's total (0 at its first sample, 1 at its last; the jump between steps counts for neither); reference:
    a Python loop."""
    g = torch.Generator().manual_seed(3)
    pos = torch.cumsum(torch.rand(12, 3, generator=g, dtype=F64), 0)
    steps = torch.tensor([0] * 5 + [1] * 7)
    sched = OrientationSchedule(pos, torch.eye(3, dtype=F64).expand(12, 3, 3), steps, 2)
    expect = []
    for m in (0, 1):
        p = pos[steps == m].numpy()
        c = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        expect += list(c / c[-1])
    np.testing.assert_allclose(sched.progress_table.numpy(), expect, atol=1e-12)


def test_step_stage_without_ground_truth_splits_the_recording_in_thirds() -> None:
    """Without ground-truth stages a step goes to the third of the recording its mean sample index falls in;
    reference: floor(3 * mean index / (N - 1))."""
    labels = torch.tensor([0] * 10 + [1] * 10 + [2] * 10)
    seg = types.SimpleNamespace(labels=labels[None], n_steps=3)
    demo = types.SimpleNamespace(stages=None)
    assert _step_stage(seg, demo, 30).tolist() == [0, 1, 2]


def test_controller_stops_turning_the_spoon_of_finished_arms(arm: BaxterArm) -> None:
    """ScoopingController.command: w = k_R log(R_des R^T) capped at max_angular_speed for running arms and
    exactly 0 for arms whose route is done; reference: the per-arm formula with scipy's rotation vector (a stub
    engine returns v = 0 and the decision)."""
    q = _poses(arm, 2, 12)
    pose = arm.forward_kinematics(q)
    x, R = pose[:, :3, 3], pose[:, :3, :3]
    r_des = torch.tensor(_expm(np.array([0.0, 0.4, 0.1]))) @ R[0]
    sched = OrientationSchedule(x.clone(), r_des.expand(2, 3, 3).clone(), torch.tensor([0, 0]), 1)
    decision = types.SimpleNamespace(step=torch.tensor([0, 0]), done=torch.tensor([True, False]))
    engine = types.SimpleNamespace(step_batch=lambda x, route, index: (torch.zeros_like(x), decision,
                                                                         torch.zeros(2, dtype=torch.int8)),
                                   goals=x.clone())
    ctl = object.__new__(ScoopingController)
    ctl.__dict__.update(engine=engine, orientation=sched, velocity_map=DLSVelocityMap(arm), impedance=ImpedanceController(),
                        dt=0.01, orientation_gain=2.0, max_angular_speed=1.5, max_gain=None)
    c = ctl.command(q, x, R, torch.zeros(2, dtype=torch.long), torch.zeros(2, dtype=torch.long), None)
    assert bool((c.w[0] == 0).all())
    w1 = 2.0 * Rotation.from_matrix((r_des @ R[1].T).numpy()).as_rotvec()
    w1 = w1 * min(1.0, 1.5 / np.linalg.norm(w1))
    assert np.linalg.norm(w1) > 0.1
    np.testing.assert_allclose(c.w[1].numpy(), w1, atol=1e-9)


def test_controller_caps_v_about_the_active_steps_attractor(arm: BaxterArm) -> None:
    """ScoopingController.command: v = v_engine * min(1, max_gain |x - g_m| / |v_engine|) with g_m the attractor of
    the arm's *active* step m (not step 0); reference: the per-arm formula (a stub engine with two goals)."""
    q = _poses(arm, 2, 13)
    pose = arm.forward_kinematics(q)
    x, R = pose[:, :3, 3], pose[:, :3, :3]
    goals = torch.stack([x[0] + 0.001, x[0] + torch.tensor([0.2, 0.0, 0.0], dtype=F64)])
    v_eng = torch.tensor([[0.3, 0.1, 0.0], [0.0, 0.4, 0.2]], dtype=F64)
    sched = OrientationSchedule(x.clone(), R.clone(), torch.tensor([0, 1]), 2)
    decision = types.SimpleNamespace(step=torch.tensor([1, 1]), done=torch.tensor([False, False]))
    engine = types.SimpleNamespace(step_batch=lambda x, route, index: (v_eng.clone(), decision,
                                                                         torch.zeros(2, dtype=torch.int8)),
                                   goals=goals)
    ctl = object.__new__(ScoopingController)
    ctl.__dict__.update(engine=engine, orientation=sched, velocity_map=DLSVelocityMap(arm), impedance=ImpedanceController(),
                        dt=0.01, orientation_gain=2.0, max_angular_speed=1.5, max_gain=3.0)
    c = ctl.command(q, x, R, torch.zeros(2, dtype=torch.long), torch.zeros(2, dtype=torch.long), None)
    for b in range(2):
        r = float(np.linalg.norm((x[b] - goals[1]).numpy()))
        vb = v_eng[b].numpy()
        expect = vb * min(1.0, 3.0 * r / np.linalg.norm(vb))
        np.testing.assert_allclose(c.v[b].numpy(), expect, atol=1e-12)


def test_contacts_min_depth_filters_by_penetration(arm: BaxterArm) -> None:
    """plant.contacts(min_depth) lists a pair only where MuJoCo's contact distance is below -min_depth (a
    penetration deeper than min_depth); reference: MjData.contact.dist of the same state."""
    dls = DLSVelocityMap(arm)
    q = arm.neutral()[None]
    target = torch.tensor([[0.60, 0.45, -0.305]], dtype=F64)  # 5 mm below the table top
    for _ in range(300):
        q = q + 0.01 * dls(q, 2.0 * (target - arm.tip_position(q)), 0.01)
    plant = BaxterPlant()
    plant.reset(q[0].numpy())
    depth = -float(np.min(plant.data.contact.dist[: plant.data.ncon]))
    assert 1e-3 < depth < 0.02
    assert ("spoon", "table") in plant.contacts(0.5 * depth)
    assert plant.contacts(1.5 * depth) == [] and plant.contacts(0.05) == []


def test_impedance_controller_rejects_negative_gains() -> None:
    """ImpedanceController refuses negative stiffness, damping or effort limits (a negative gain would make the
    PD law push away from the set-point); reference: the documented domain >= 0."""
    for kw in ({"stiffness": -1.0}, {"damping": [1.0] * 6 + [-1.0]}, {"effort_limits": -5.0}):
        with pytest.raises(InvalidArgumentError):
            ImpedanceController(**kw)


def test_pose_knots_are_normalised_cumulative_pose_length() -> None:
    """_pose_knots: k_i = sum_{j<i} (|p_{j+1} - p_j| + angle_length |theta_{j+1,j}|) / total; reference: numpy and
    scipy's rotation angle of R_{j+1} R_j^T."""
    rng = np.random.default_rng(21)
    tip = rng.normal(scale=0.1, size=(5, 3))
    rot = np.stack([_expm(_random_rotvec(rng, rng.uniform(0.1, 2.0))) for _ in range(5)])
    got = _pose_knots(torch.tensor(tip), torch.tensor(rot), 0.4).numpy()
    h = [np.linalg.norm(tip[j + 1] - tip[j]) + 0.4 * np.linalg.norm(Rotation.from_matrix(rot[j + 1] @ rot[j].T).as_rotvec())
         for j in range(4)]
    c = np.concatenate([[0.0], np.cumsum(h)])
    np.testing.assert_allclose(got, c / c[-1], atol=1e-10)


def test_load_demonstration_starts_time_at_zero(tmp_path: Path) -> None:
    """A recording whose clock does not start at 0 is loaded with t - t[0] (same steps); reference: the file's
    column."""
    t = 5.0 + 0.01 * np.arange(6)
    q = np.tile(BaxterArm().neutral().numpy(), (6, 1))
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.concatenate([t[:, None], q], 1), delimiter=",")
    demo = load_demonstration(path)
    np.testing.assert_allclose(demo.t.numpy(), t - t[0], atol=1e-12)


def test_build_robot_forwards_max_lag_and_interpolate() -> None:
    """build_robot passes max_lag to the impedance set-point rule and interpolate to the plant, and both
    controllers share the plant's gains; reference: the arguments given."""
    robot = build_robot(max_lag=0.2, interpolate=False)
    assert robot.impedance.max_lag == 0.2 and robot.plant.interpolate is False
    np.testing.assert_array_equal(robot.impedance.stiffness.numpy(), robot.plant.stiffness)
    np.testing.assert_array_equal(robot.impedance.damping.numpy(), robot.plant.damping)
