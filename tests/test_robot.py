"""Baxter left arm (issue 10, items 1-2): pytorch-kinematics FK/Jacobian against independent references, MuJoCo
plant agreement, gravity compensation, impedance law, DLS velocity map with null space and joint limits."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, UnknownNameError
from lfd_torch.robot import (
    ARM_JOINT_NAMES,
    BAXTER_LEFT_TABLE,
    FRAME_NAMES,
    LINK_BODIES,
    BaxterArm,
    BaxterPlant,
    DLSVelocityMap,
    ImpedanceController,
    Scene,
    baxter_left_urdf,
    build_robot,
    orientation_error,
)

from conftest import requires_cuda

P2 = math.pi / 2
# The published parameters exactly as issue 10 lists them (independent of lfd_torch.robot.urdf):
# (xyz, rpy, revolute?, lower, upper)
ISSUE_TABLE = [
    ((0.024645, 0.219645, 0.118588), (0, 0, 0.7854), False, None, None),
    ((0.055695, 0, 0.011038), (0, 0, 0), True, -1.70168, 1.70168),
    ((0.069, 0, 0.27035), (-P2, 0, 0), True, -2.147, 1.047),
    ((0.102, 0, 0), (P2, 0, P2), True, -3.05418, 3.05418),
    ((0.069, 0, 0.26242), (-P2, -P2, 0), True, -0.05, 2.618),
    ((0.10359, 0, 0), (P2, 0, P2), True, -3.059, 3.059),
    ((0.01, 0, 0.2707), (-P2, -P2, 0), True, -P2, 2.094),
    ((0.115975, 0, 0), (P2, 0, P2), True, -3.059, 3.059),
    ((0, 0, 0.11355), (0, 0, 0), False, None, None),
    ((0, 0, 0.05), (0, 0, 0), False, None, None),
]
VEL_LIMITS = [2.5, 2.5, 2.5, 2.5, 5.0, 5.0, 5.0]


def _rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _hom(rot, pos):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot, pos
    return T


def numpy_fk(q, tool_offset=0.12):
    """Independent reference: list of the 12 frame poses, product of origin(xyz, rpy) @ Rz(q_i)."""
    T = np.eye(4)
    out = [T.copy()]
    i = 0
    for xyz, (r, p, y), rev, _, _ in ISSUE_TABLE + [((0, 0, tool_offset), (0, 0, 0), False, None, None)]:
        T = T @ _hom(_rot_z(y) @ _rot_y(p) @ _rot_x(r), xyz)
        if rev:
            T = T @ _hom(_rot_z(q[i]), np.zeros(3))
            i += 1
        out.append(T.copy())
    return out


def _rand_q(n, gen, dtype=torch.float64, shrink=0.9):
    lo = torch.tensor([r[3] for r in ISSUE_TABLE if r[2]], dtype=dtype)
    hi = torch.tensor([r[4] for r in ISSUE_TABLE if r[2]], dtype=dtype)
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * shrink
    return mid + half * (2 * torch.rand(n, 7, generator=gen, dtype=dtype) - 1)


@pytest.fixture(scope="module")
def arm():
    return BaxterArm()


@pytest.fixture(scope="module")
def plant():
    return BaxterPlant()


# ---------------------------------------------------------------------------------------------- item 1: kinematics
def test_table_and_urdf_match_the_issue(arm):
    assert len(BAXTER_LEFT_TABLE) == len(ISSUE_TABLE)
    for row, (xyz, rpy, rev, lo, hi) in zip(BAXTER_LEFT_TABLE, ISSUE_TABLE):
        np.testing.assert_allclose(row.xyz, xyz, atol=0)
        np.testing.assert_allclose(row.rpy, rpy, atol=1e-15)
        assert (row.kind == "revolute") == rev
        if rev:
            assert (row.lower, row.upper) == pytest.approx((lo, hi), abs=1e-15)
    assert ARM_JOINT_NAMES == tuple(f"left_{n}" for n in ("s0", "s1", "e0", "e1", "w0", "w1", "w2"))
    np.testing.assert_allclose(arm.velocity_limits().numpy(), VEL_LIMITS)
    chain = arm.chain(torch.float64)
    lo, hi = chain.get_joint_limits()
    np.testing.assert_allclose(lo, arm.lower().numpy())
    np.testing.assert_allclose(hi, arm.upper().numpy())
    assert "<robot" in baxter_left_urdf() and 'name="spoon_tip"' in baxter_left_urdf(0.2)


@pytest.mark.parametrize("dtype,atol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_fk_matches_numpy_product(arm, generator, dtype, atol):
    q = _rand_q(64, generator, dtype)
    mats = arm.frame_transforms(q)
    assert mats.shape == (64, len(FRAME_NAMES), 4, 4) and mats.dtype == dtype
    ref = np.stack([np.stack(numpy_fk(qi)) for qi in q.double().numpy()])
    np.testing.assert_allclose(mats.double().numpy(), ref, atol=atol)
    tip = arm.tip_position(q)
    np.testing.assert_allclose(tip.double().numpy(), ref[:, -1, :3, 3], atol=atol)


def test_tool_offset_moves_tip_along_gripper_z(generator):
    q = _rand_q(8, generator)
    a, b = BaxterArm(0.12), BaxterArm(0.2)
    grip = a.forward_kinematics(q, "left_gripper")
    expect = grip[:, :3, 3] + 0.2 * grip[:, :3, 2]
    torch.testing.assert_close(b.tip_position(q), expect, atol=1e-12, rtol=0)
    ref = np.stack([numpy_fk(qi, 0.2)[-1] for qi in q.numpy()])
    np.testing.assert_allclose(b.forward_kinematics(q).numpy(), ref, atol=1e-12)


def test_jacobian_matches_autograd_and_finite_differences(arm, generator):
    q = _rand_q(6, generator)
    J = arm.jacobian(q)
    assert J.shape == (6, 6, 7)
    for b in range(q.shape[0]):
        qb = q[b].clone()
        # autograd through the forward ops (not pytorch-kinematics' analytical backward)
        auto = torch.autograd.functional.jacobian(
            lambda x: arm.forward_kinematics(x[None], analytical_grad=False)[0, :3, 3], qb)
        torch.testing.assert_close(J[b, :3], auto, atol=1e-12, rtol=0)
        # central finite differences on the numpy reference: position and rotation
        h = 1e-6
        for i in range(7):
            dq = np.zeros(7)
            dq[i] = h
            Tp, Tm = numpy_fk(qb.numpy() + dq)[-1], numpy_fk(qb.numpy() - dq)[-1]
            lin = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            dR = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h) @ numpy_fk(qb.numpy())[-1][:3, :3].T  # skew(omega)
            ang = np.array([dR[2, 1], dR[0, 2], dR[1, 0]])
            np.testing.assert_allclose(J[b, :3, i].numpy(), lin, atol=1e-8)
            np.testing.assert_allclose(J[b, 3:, i].numpy(), ang, atol=1e-8)
    # the analytical backward of pytorch-kinematics gives the same gradient
    qg = q.clone().requires_grad_(True)
    arm.tip_position(qg)[:, 0].sum().backward()
    torch.testing.assert_close(qg.grad, J[:, 0], atol=1e-12, rtol=0)


def test_batch_equals_loop_and_leading_dims(arm, generator):
    q = _rand_q(10, generator)
    T, J = arm.pose_and_jacobian(q)
    for b in range(10):
        Tb, Jb = arm.pose_and_jacobian(q[b : b + 1])
        torch.testing.assert_close(T[b], Tb[0], atol=1e-14, rtol=0)
        torch.testing.assert_close(J[b], Jb[0], atol=1e-14, rtol=0)
    T2 = arm.forward_kinematics(q.reshape(2, 5, 7))
    assert T2.shape == (2, 5, 4, 4)
    torch.testing.assert_close(T2.reshape(10, 4, 4), T, atol=0, rtol=0)
    assert arm.tip_position(q[0]).shape == (3,)


def test_float32_close_to_float64(arm, generator):
    q = _rand_q(100, generator)
    T64, J64 = arm.pose_and_jacobian(q)
    T32, J32 = arm.pose_and_jacobian(q.float())
    assert T32.dtype == J32.dtype == torch.float32
    np.testing.assert_allclose(T32.double().numpy(), T64.numpy(), atol=2e-6)
    np.testing.assert_allclose(J32.double().numpy(), J64.numpy(), atol=2e-6)


@requires_cuda
def test_cuda_matches_cpu(arm, generator):
    q = _rand_q(32, generator)
    T, J = arm.pose_and_jacobian(q.cuda())
    assert T.device.type == "cuda"
    torch.testing.assert_close(T.cpu(), arm.forward_kinematics(q), atol=1e-10, rtol=0)
    torch.testing.assert_close(J.cpu(), arm.jacobian(q), atol=1e-10, rtol=0)


def test_typed_errors(arm):
    with pytest.raises(ShapeMismatchError, match="q"):
        arm.forward_kinematics(torch.zeros(4, 6, dtype=torch.float64))
    with pytest.raises(InvalidArgumentError, match="float32 or float64"):
        arm.jacobian(torch.zeros(4, 7, dtype=torch.int64))
    with pytest.raises(InvalidArgumentError, match="torch.Tensor"):
        arm.tip_position(np.zeros((1, 7)))
    bad = torch.zeros(2, 7, dtype=torch.float64)
    bad[1, 3] = float("nan")
    with pytest.raises(NonFiniteError, match="q"):
        arm.tip_position(bad)
    q = arm.neutral()[None].clone()
    q[0, 1] = 1.2  # s1 upper limit 1.047
    with pytest.raises(InvalidArgumentError, match="left_s1"):
        arm.check_limits(q, "q0")
    assert not bool(arm.within_limits(q)[0]) and bool(arm.within_limits(arm.neutral())[()])
    with pytest.raises(UnknownNameError):
        arm.forward_kinematics(q, "elbow")
    with pytest.raises(InvalidArgumentError, match="tool_offset"):
        BaxterArm(-0.1)


# ---------------------------------------------------------------------------------------------- item 2: MuJoCo plant
def test_mujoco_site_agrees_with_pytorch_kinematics(arm, plant, generator):
    q = _rand_q(200, generator, shrink=1.0)
    fk = arm.tip_position(q).numpy()
    err = max(np.abs(plant.tip_kinematics(qi) - fi).max() for qi, fi in zip(q.numpy(), fk))
    assert err < 1e-6
    other = BaxterPlant(tool_offset=0.2)
    assert np.abs(other.tip_kinematics(q[0].numpy()) - BaxterArm(0.2).tip_position(q[0]).numpy()).max() < 1e-6
    plant.reset(q[1].numpy())
    np.testing.assert_allclose(plant.tip_pose(), arm.forward_kinematics(q[1]).numpy(), atol=1e-6)


def test_mujoco_model_masses_limits_and_geoms(plant):
    m = plant.model
    for b in LINK_BODIES:
        assert m.body_mass[plant.body_ids[b.link]] == pytest.approx(b.mass)
        assert (m.body_inertia[plant.body_ids[b.link]] > 0).all()
    arm_mass = sum(m.body_mass[plant.body_ids[n]] for n in [b.link for b in LINK_BODIES] + ["spoon"])
    assert 15.0 < arm_mass < 30.0
    np.testing.assert_allclose(plant.lower, BaxterArm().lower().numpy())
    np.testing.assert_allclose(plant.upper, BaxterArm().upper().numpy())
    names = {m.geom(g).name for g in range(m.ngeom)}
    assert {"table", "can/bottom", "cup/bottom", "spoon/bowl"} <= names
    assert m.opt.timestep == 0.001 and plant.n_substeps == 10


def test_gravity_compensation_holds_the_arm(generator):
    plant = BaxterPlant(stiffness=0.0, damping=0.0)  # gravity compensation alone
    q0 = _rand_q(1, generator, shrink=0.6)[0].numpy()
    plant.reset(q0)
    np.testing.assert_allclose(plant.compensation_torque(), plant.gravity_torque(), atol=1e-9)
    assert np.abs(plant.gravity_torque()).max() > 1.0
    for _ in range(100):  # 1 s
        plant.step()
    assert np.abs(plant.q - q0).max() < 1e-6
    assert plant.contacts() == [] or all(p[1] != "table" for p in plant.contacts())


def test_impedance_law_matches_mujoco_actuators(plant, generator):
    ctrl = ImpedanceController(plant.stiffness, plant.damping)
    q0 = BaxterArm().neutral().numpy()
    qd0 = 0.1 * torch.randn(7, generator=generator, dtype=torch.float64).numpy()
    for scale in (0.02, 1.0):  # small error; large error saturates at the effort limits
        plant.reset(q0, qd0)
        q_d = q0 + scale * np.array([1, -1, 1, 1, -1, 1, -1.0])
        qd_d = np.full(7, 0.2)
        plant.set_command(q_d, qd_d)
        plant._mj.mj_forward(plant.model, plant.data)
        t = lambda x: torch.tensor(x)[None]  # noqa: E731
        expect = ctrl.torque(t(q0), t(qd0), t(q_d), t(qd_d))[0].numpy()
        np.testing.assert_allclose(plant.actuator_torque(), expect, atol=1e-9)
        tau = ctrl.torque(t(q0), t(qd0), t(q_d), t(qd_d), gravity=t(plant.gravity_torque()))[0].numpy()
        np.testing.assert_allclose(plant.actuator_torque() + plant.compensation_torque(), tau, atol=1e-9)
    assert np.abs(plant.actuator_torque()).max() == pytest.approx(50.0)


def test_push_displaces_and_impedance_restores():
    plant = BaxterPlant()
    x0 = plant.tip_position()
    plant.apply_force("left_hand", [0.0, 0.0, 20.0])
    for _ in range(30):
        plant.step()
    assert np.linalg.norm(plant.tip_position() - x0) > 0.005
    plant.clear_forces()
    for _ in range(200):
        plant.step()
    assert np.linalg.norm(plant.tip_position() - x0) < 0.002
    with pytest.raises(UnknownNameError):
        plant.apply_force("elbow", [0, 0, 1])


def _scoop_push_contacts(stiffness=None, damping=None, force=20.0, duration=0.4):
    """Forbidden contacts (and the largest tip displacement, m) when a pulse of ``force`` N hits each pushed body of
    the trials horizontally in 8 directions while the arm holds the demonstration's pose closest to the can wall."""
    from lfd_torch.robot import scooping_demonstration
    from lfd_torch.robot.trials import FORCE_BODIES

    demo = scooping_demonstration(0)
    kw = {} if stiffness is None else {"stiffness": stiffness, "damping": damping}
    plant = BaxterPlant(**kw)
    q0 = demo.q[450].double().numpy()  # mid-scoop, in the sugar, bowl about 19 mm from a stave
    hits, worst = set(), 0.0
    for body in FORCE_BODIES:
        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
            plant.reset(q0)
            x0 = plant.tip_position()
            plant.apply_force(body, [force * np.cos(a), force * np.sin(a), 0.0])
            for k in range(int(round((duration + 0.5) / plant.control_period))):
                if k * plant.control_period >= duration:
                    plant.clear_forces()
                plant.step()
                hits |= {c for c in plant.contacts() if c[1] in ("can_wall", "cup_wall", "table")}
                worst = max(worst, float(np.linalg.norm(plant.tip_position() - x0)))
    return hits, worst


def test_default_impedance_keeps_small_pushes_off_the_can_wall():
    """The default joint stiffness is sized so that a push from the small range of the trials (here 20 N for the
    longest 0.4 s, in every horizontal direction, on every pushed body) does not shove the scooping spoon into the
    can wall even with the set-point held still (no reaction of the engine) at the pose closest to the wall (19 mm);
    the former, softer gains (400 / 250 / 60 N m/rad) let the same push move the tip 70 mm, into the wall. (At 30 N
    in the worst direction the bowl reaches the wall here: the trials' measured rates state what remains.)"""
    hits, worst = _scoop_push_contacts()
    assert hits == set() and worst < 0.019, (hits, worst)
    soft_hits, soft_worst = _scoop_push_contacts([400.0, 400.0, 250.0, 250.0, 60.0, 60.0, 30.0],
                                                 [60.0, 60.0, 35.0, 35.0, 4.0, 4.0, 2.0])  # fmt: skip
    assert soft_hits and soft_worst > 3 * worst


def test_contacts_are_read_and_named(arm):
    dls = DLSVelocityMap(arm)
    q = arm.neutral()[None]
    target = torch.tensor([[0.60, 0.45, -0.305]], dtype=torch.float64)  # 5 mm below the table top
    for _ in range(300):  # kinematic integration only
        q = q + 0.01 * dls(q, 2.0 * (target - arm.tip_position(q)), 0.01)
    plant = BaxterPlant()
    plant.reset(q[0].numpy())
    assert ("spoon", "table") in plant.contacts()
    plant.reset()
    assert plant.contacts() == []


# ---------------------------------------------------------------------------------------------- item 2: DLS map
def test_dls_tracks_task_velocity_and_null_space_is_silent(arm, generator):
    dls = DLSVelocityMap(arm, null_gain=0.0)
    q = arm.neutral()[None] + 0.2 * (torch.rand(16, 7, generator=generator, dtype=torch.float64) - 0.5)
    v = 0.05 * torch.randn(16, 3, generator=generator, dtype=torch.float64)
    qdot = dls(q, v, 0.01)
    Jp = arm.jacobian(q)[:, :3]
    got = (Jp @ qdot[..., None]).squeeze(-1)
    assert ((got - v).norm(dim=-1) / v.norm(dim=-1)).max() < 0.02
    with_null = DLSVelocityMap(arm, null_gain=1.0)
    dq = with_null(q, v, 0.01) - qdot
    assert dq.abs().max() > 1e-3  # the posture term acts ...
    assert ((Jp @ dq[..., None]).squeeze(-1).norm(dim=-1) / v.norm(dim=-1)).max() < 0.02  # ... in the null space
    # batch equals loop; float32 works
    loop = torch.cat([dls(q[b : b + 1], v[b : b + 1], 0.01) for b in range(16)])
    torch.testing.assert_close(loop, qdot, atol=1e-12, rtol=0)
    assert dls(q.float(), v.float(), 0.01).dtype == torch.float32


def test_dls_pose_task_and_orientation_error(arm):
    rot = torch.tensor(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]))  # Rx(pi/2)
    np.testing.assert_allclose(orientation_error(torch.eye(3, dtype=torch.float64), rot).numpy(), [P2, 0, 0], atol=1e-12)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # Rx(pi)
    np.testing.assert_allclose(orientation_error(torch.eye(3, dtype=torch.float64), flip).abs().numpy(), [math.pi, 0, 0], atol=1e-6)
    dls = DLSVelocityMap(arm)
    q = arm.neutral()[None]
    T_goal = arm.forward_kinematics(q + 0.15)
    for _ in range(300):
        T = arm.forward_kinematics(q)
        v = torch.cat([2.0 * (T_goal[:, :3, 3] - T[:, :3, 3]), 2.0 * orientation_error(T[:, :3, :3], T_goal[:, :3, :3])], -1)
        q = q + 0.01 * dls(q, v, 0.01)
    T = arm.forward_kinematics(q)
    assert (T[:, :3, 3] - T_goal[:, :3, 3]).norm() < 1e-3
    assert orientation_error(T[:, :3, :3], T_goal[:, :3, :3]).norm() < 1e-2


def test_dls_respects_velocity_and_position_limits(arm):
    dls = DLSVelocityMap(arm)
    vmax = arm.velocity_limits()
    q = arm.neutral()[None]
    fast = torch.tensor([[5.0, 0.0, 0.0]], dtype=torch.float64)
    qdot = dls(q, fast, 0.01)
    assert (qdot.abs() <= vmax + 1e-12).all()
    # the scaled command keeps the Cartesian direction
    d = (arm.jacobian(q)[:, :3] @ qdot[..., None]).squeeze(-1)
    assert torch.nn.functional.cosine_similarity(d, fast).item() > 0.99
    # drive the tip far out of reach: joints must stay within the limits at every step
    lo, hi = arm.lower() + dls.limit_buffer, arm.upper() - dls.limit_buffer
    away = torch.tensor([[0.0, -1.0, 0.0]], dtype=torch.float64)
    q = arm.neutral()[None]
    reached = torch.zeros(7, dtype=torch.bool)
    for _ in range(400):
        qdot = dls(q, 0.5 * away / away.norm(), 0.01)
        q = q + 0.01 * qdot
        assert ((q >= lo - 1e-9) & (q <= hi + 1e-9)).all()
        assert (qdot.abs() <= vmax + 1e-12).all()
        reached |= ((q - lo).abs() < 1e-6).any(0) | ((q - hi).abs() < 1e-6).any(0)
    assert reached[0]  # s0 sat at its lower bound
    # at the bound, the other joints still realise a feasible task velocity (saturation + re-solve)
    q_sat = arm.neutral()[None].clone()
    q_sat[0, 0] = lo[0]
    v = torch.tensor([[0.0, -0.1, 0.0]], dtype=torch.float64)  # the plain DLS solution wants s0 < 0 here
    assert dls(q_sat, v, 0.01)[0, 0] >= 0
    bare = DLSVelocityMap(arm, null_gain=0.0, limit_gain=0.0)
    Jp = arm.jacobian(q_sat)[:, :3]
    plain = (Jp.transpose(1, 2) @ torch.linalg.solve(Jp @ Jp.transpose(1, 2) + 4e-4 * torch.eye(3, dtype=torch.float64), v[..., None]))
    assert plain[0, 0, 0] < -0.01
    clipped = plain.squeeze(-1).clone()
    clipped[0, 0] = 0.0
    qdot = bare(q_sat, v, 0.01)
    assert qdot[0, 0] == pytest.approx(0.0, abs=1e-12)
    err = lambda qd: ((Jp @ qd[..., None]).squeeze(-1) - v).norm() / v.norm()  # noqa: E731
    assert err(clipped) > 0.1 and err(qdot) < 0.01
    # half a millirad inside the bound s0 may still move at (lo - q) / dt < 0: the re-solve subtracts that fixed
    # joint's own share of the task velocity from the others'
    q_near = q_sat.clone()
    q_near[0, 0] = lo[0] + 5e-4
    v_far = torch.tensor([[0.0, -0.3, 0.0]], dtype=torch.float64)
    qdot = bare(q_near, v_far, 0.01)
    J_near = arm.jacobian(q_near)[:, :3]
    assert qdot[0, 0] == pytest.approx(-0.05, abs=1e-9)  # the clamped, non-zero velocity
    assert float(((J_near @ qdot[..., None]).squeeze(-1) - v_far).norm() / v_far.norm()) < 0.01
    # a joint started outside its range is driven back
    q_out = arm.neutral()[None].clone()
    q_out[0, 3] = -0.2  # e1 lower limit -0.05
    assert dls(q_out, torch.zeros(1, 3, dtype=torch.float64), 0.01)[0, 3] > 0


def test_dls_typed_errors(arm):
    dls = DLSVelocityMap(arm)
    q = arm.neutral()[None]
    with pytest.raises(ShapeMismatchError, match="v"):
        dls(q, torch.zeros(1, 4, dtype=torch.float64))
    with pytest.raises(ShapeMismatchError, match="v"):
        dls(q, torch.zeros(2, 3, dtype=torch.float64))
    with pytest.raises(InvalidArgumentError, match="dtype"):
        dls(q, torch.zeros(1, 3, dtype=torch.float32))
    with pytest.raises(NonFiniteError, match="v"):
        dls(q, torch.full((1, 3), float("nan"), dtype=torch.float64))
    with pytest.raises(InvalidArgumentError, match="dt"):
        dls(q, torch.zeros(1, 3, dtype=torch.float64), dt=0.0)
    with pytest.raises(InvalidArgumentError, match="damping"):
        DLSVelocityMap(arm, damping=-1.0)
    with pytest.raises(InvalidArgumentError, match="posture"):
        DLSVelocityMap(arm, posture=[0, 3.0, 0, 0, 0, 0, 0])
    with pytest.raises(InvalidArgumentError, match="control_period"):
        BaxterPlant(control_period=0.0105)
    with pytest.raises(InvalidArgumentError, match="left_e1"):
        BaxterPlant().reset([0, 0, 0, -0.3, 0, 0, 0])
    with pytest.raises(ShapeMismatchError, match="q_d"):
        BaxterPlant().set_command(np.zeros(6), np.zeros(7))
    with pytest.raises(InvalidArgumentError, match="stiffness"):
        BaxterPlant(stiffness=-1.0)
    with pytest.raises(UnknownNameError):
        Scene.from_mapping({"tabel_top": 0.0})


# ---------------------------------------------------------------------------------------------- closed loop
def _reach(robot, targets, steps=250, gain=2.0, speed=0.25):
    plant, dls, imp = robot.plant, robot.velocity_map, robot.impedance
    q_d, log = None, []
    for target in targets:
        tgt = torch.tensor(target, dtype=torch.float64)[None]
        for _ in range(steps):
            q = torch.tensor(plant.q)[None]
            v = gain * (tgt - torch.tensor(plant.tip_position())[None])
            v = v * min(1.0, speed / max(float(v.norm()), 1e-12))
            q_d, qd_d = imp.reference(q, dls(q, v, plant.control_period), q_d, plant.control_period)
            plant.set_command(q_d[0].numpy(), qd_d[0].numpy())
            plant.step()
            log.append((plant.tip_position(), plant.sugar_depth(), plant.contacts(), plant.q))
    return log


def test_closed_loop_dip_into_sugar_without_contact():
    robot = build_robot()
    can = robot.plant.scene.can
    rim = robot.plant.scene.table_top + can.wall + can.height
    surface = robot.plant.scene.table_top + can.wall + can.fill
    above = [*can.center, rim + 0.06]
    inside = [*can.center, surface - 0.03]
    log = _reach(robot, [above, inside, above])
    tips = np.array([x for x, *_ in log])
    depth = np.array([d for _, d, *_ in log])
    assert np.linalg.norm(tips[499] - np.array(inside)) < 0.005
    assert depth.max() > 0.02 and depth[-1] < 0  # entered the sugar below its surface and left it
    assert all(c == [] for *_, c, _ in log)
    qs = np.array([q for *_, q in log])
    assert (qs >= robot.plant.lower).all() and (qs <= robot.plant.upper).all()
    # deterministic: a second run gives the same trajectory
    again = np.array([x for x, *_ in _reach(build_robot(), [above])])
    np.testing.assert_array_equal(again, tips[:250])


def test_fork_shares_model_with_independent_state():
    plant = BaxterPlant()
    other = plant.fork()
    assert other.model is plant.model and other.data is not plant.data
    other.apply_force("left_hand", [0.0, 30.0, 0.0])
    for _ in range(20):
        other.step()
    assert np.abs(other.q - plant.q).max() > 1e-3
    np.testing.assert_allclose(plant.q, BaxterArm().neutral().numpy(), atol=1e-12)
    assert not plant.data.xfrc_applied.any()


def test_impedance_step_response_settles_at_random_poses():
    plant = BaxterPlant()
    rng = np.random.default_rng(7)
    mid, half = (plant.lower + plant.upper) / 2, (plant.upper - plant.lower) / 2 * 0.7
    tried = 0
    while tried < 8:
        q0 = mid + half * rng.uniform(-1, 1, 7)
        plant.reset(q0)
        if plant.contacts():
            continue  # a pose inside the table or a vessel
        tried += 1
        target = np.clip(q0 + 0.1 * rng.choice([-1.0, 1.0], 7), plant.lower, plant.upper)
        plant.set_command(target, np.zeros(7))
        for _ in range(100):  # 1 s
            plant.step()
        if plant.contacts():
            continue
        assert np.isfinite(plant.q).all()
        assert np.abs(plant.q - target).max() < 2e-3
        assert np.abs(plant.qd).max() < 0.05


def test_plant_set_point_continues_and_float32_limits_pass():
    """Stepping again without a new command continues the position set-point's ramp at the commanded velocity
    (it jumped back to the start of the ramp before); joint angles at a limit rounded through float32 pass the
    limit checks of the arm and the plant."""
    arm = BaxterArm()
    plant = BaxterPlant()
    plant.reset()
    qd = np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    plant.set_command(plant.q + plant.control_period * qd, qd)
    ends = []
    for _ in range(3):
        plant.step()
        ends.append(plant.data.ctrl[0])
    np.testing.assert_allclose(np.diff(ends), 0.5 * plant.control_period, rtol=1e-9)
    # within one call the set-point ramps at the commanded velocity and reaches q_d at the last substep
    seen, mujoco = [], plant._mj

    def recording(model, data, *args):
        seen.append(float(data.ctrl[0]))
        return mujoco.mj_step(model, data, *args)

    plant._mj = types.SimpleNamespace(mj_step=recording, mj_forward=mujoco.mj_forward)
    q_d = plant.q + plant.control_period * qd
    plant.set_command(q_d, qd)
    plant.step()
    plant._mj = mujoco
    assert len(seen) == plant.n_substeps and seen[-1] == pytest.approx(q_d[0], abs=1e-12)
    np.testing.assert_allclose(np.diff(seen), 0.5 * plant.timestep, rtol=1e-9)
    q32 = arm.upper(torch.float32).double()  # up to 1e-7 rad beyond the float64 limits
    assert bool((q32 > arm.upper()).any())
    arm.check_limits(q32)
    plant.reset(q32.numpy())
    with pytest.raises(InvalidArgumentError, match="joint limits"):
        arm.check_limits(arm.upper() + 1e-4)
