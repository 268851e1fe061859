"""Sugar-scooping task (issue 10, items 3-6): demonstration generator, loader, pipeline, success checks, trials."""

from __future__ import annotations


import math

import numpy as np
import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, StoreError
from lfd_torch.robot import (
    BaxterArm,
    BaxterPlant,
    Scene,
    load_demonstration,
    save_demonstration,
    scooping_demonstration,
)

import mujoco  # noqa: E402  (a declared dependency of the package)


@pytest.fixture(scope="module")
def demo():
    return scooping_demonstration(3)


@pytest.fixture(scope="module")
def plant():
    return BaxterPlant()


@pytest.fixture(scope="module")
def task():
    return learn_scooping(scooping_demonstration(0), generator=torch.Generator().manual_seed(0))


# ---------------------------------------------------------------------------------------------- demonstration
def test_demonstration_shapes_and_rate(demo):
    T = demo.n_samples
    assert demo.q.shape == (T, 7) and demo.tip.shape == (T, 3) and demo.rotation.shape == (T, 3, 3)
    assert demo.stages.dtype == torch.long and demo.stages.shape == (T,)
    torch.testing.assert_close(demo.t[1:] - demo.t[:-1], torch.full((T - 1,), 0.01, dtype=torch.float64))
    # stages appear in order 0, 1, 2 and each is contiguous
    changes = torch.nonzero(demo.stages[1:] != demo.stages[:-1]).flatten()
    assert demo.stages[0] == 0 and demo.stages[-1] == 2 and changes.numel() == 2
    d = demo.demos()
    assert d.n_demos == 1 and d.dim == 3
    torch.testing.assert_close(d.positions[0, :T], demo.tip)


def test_tip_is_the_fk_of_the_joints(demo):
    """Independent reference: the MuJoCo tip site at the recorded joint angles."""
    pl = BaxterPlant()
    idx = torch.linspace(0, demo.n_samples - 1, 25).long()
    mj_tip = np.stack([pl.tip_kinematics(demo.q[i].numpy()) for i in idx.tolist()])
    np.testing.assert_allclose(mj_tip, demo.tip[idx].numpy(), atol=1e-6, rtol=0)


def test_path_dips_into_the_sugar_and_passes_over_the_cup(demo, plant):
    sc = plant.scene
    depth = np.array([plant.sugar_depth(p) for p in demo.tip.numpy()])
    inside = depth > 0
    assert inside.any() and depth.max() > 0.01  # at least 1 cm below the sugar surface, inside the can
    # in the sugar only during the scoop stage
    assert set(demo.stages[torch.from_numpy(inside)].tolist()) == {1}
    cup = torch.tensor(sc.cup.center, dtype=torch.float64)
    cup_rim = sc.table_top + sc.cup.wall + sc.cup.height
    over_cup = ((demo.tip[:, :2] - cup).norm(dim=-1) < sc.cup.radius) & (demo.tip[:, 2] > cup_rim)
    assert bool(over_cup.any()) and set(demo.stages[over_cup].tolist()) == {2}
    # never below the cup rim near the cup (no dipping into the coffee), never below the table
    near_cup = (demo.tip[:, :2] - cup).norm(dim=-1) < sc.cup.radius + 0.02
    assert bool((demo.tip[near_cup, 2] > cup_rim).all())
    assert float(demo.tip[:, 2].min()) > sc.table_top + sc.can.wall


def test_demonstration_is_collision_free(demo, plant):
    d = plant.new_data()
    seen = set()
    for k in range(0, demo.n_samples, 3):
        d.qpos[plant.qpos_adr] = demo.q[k].numpy()
        mujoco.mj_forward(plant.model, d)
        saved, plant.data = plant.data, d
        try:
            seen |= set(plant.contacts())
        finally:
            plant.data = saved
    assert seen == set()


def test_joint_position_and_velocity_limits(demo):
    arm = BaxterArm()
    assert bool(arm.within_limits(demo.q).all())
    qdot = (demo.q[1:] - demo.q[:-1]) / (demo.t[1:] - demo.t[:-1])[:, None]
    assert bool((qdot.abs() <= arm.velocity_limits()).all())
    speed = (demo.tip[1:] - demo.tip[:-1]).norm(dim=-1) / 0.01
    assert 0.05 < float(speed.max()) < 0.8  # a person's pace (m/s)


def test_tremor_is_small_and_band_limited(demo):
    """The tremor is the high-pass residual of the tip path: sub-mm to ~1 mm, not zero."""
    x = demo.tip.numpy()
    k = np.ones(15) / 15  # 150 ms moving average keeps the voluntary motion
    smooth = np.stack([np.convolve(x[:, i], k, mode="same") for i in range(3)], 1)
    resid = (x - smooth)[20:-20]
    rms = np.sqrt((resid**2).mean(0))
    assert (rms > 2e-5).all() and (rms < 1.5e-3).all()


def test_same_seed_identical_other_seed_differs(demo, task):
    again = scooping_demonstration(3)
    assert torch.equal(again.q, demo.q) and torch.equal(again.tip, demo.tip) and torch.equal(again.stages, demo.stages)
    other = task.demonstration  # seed 0
    assert other.n_samples != demo.n_samples or not torch.allclose(other.tip, demo.tip)


def test_scene_and_rate_and_dtype_change_the_recording(demo):
    """A moved can moves the dip; float32 at 50 Hz gives the same path, sampled every 20 ms."""
    sc = Scene.from_mapping({"can": {"center": [0.68, 0.52]}})
    moved = scooping_demonstration(3, scene=sc, rate=50.0, dtype=torch.float32)
    assert moved.tip.dtype == torch.float32 and moved.q.dtype == torch.float32
    torch.testing.assert_close(moved.t[1] - moved.t[0], torch.tensor(0.02))
    deepest0, deepest1 = demo.tip[demo.tip[:, 2].argmin()], moved.tip[moved.tip[:, 2].argmin()].double()
    torch.testing.assert_close(deepest1[:2] - deepest0[:2], torch.tensor([-0.02, -0.03], dtype=torch.float64),
                               atol=8e-3, rtol=0)  # fmt: skip
    assert abs(moved.n_samples * 2 - demo.n_samples) < 0.02 * demo.n_samples


@pytest.mark.parametrize("bad", [{"seed": 1.5}, {"seed": 0, "rate": 5.0}, {"seed": 0, "dtype": torch.int64}])
def test_bad_arguments_raise(bad):
    seed = bad.pop("seed")
    with pytest.raises(InvalidArgumentError):
        scooping_demonstration(seed, **bad)


# ---------------------------------------------------------------------------------------------- files
@pytest.mark.parametrize("ext", ["csv", "npz"])
@pytest.mark.parametrize("joints", [True, False])
def test_file_round_trip(demo, tmp_path, ext, joints):
    path = save_demonstration(demo, tmp_path / f"demo.{ext}", joints=joints)
    back = load_demonstration(path)
    torch.testing.assert_close(back.t, demo.t, atol=1e-12, rtol=0)
    torch.testing.assert_close(back.tip, demo.tip, atol=1e-12, rtol=0)
    if joints:
        torch.testing.assert_close(back.q, demo.q, atol=1e-15, rtol=0)
        torch.testing.assert_close(back.rotation, demo.rotation, atol=1e-12, rtol=0)
    else:
        assert back.q is None and back.rotation is None
    assert back.stages is None
    assert back.demos().n_demos == 1


def _write(path, text):
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "text",
    [
        "t,x,y,z\n0,1,2,3\n0.01,1,2\n",  # ragged
        "t,x,y,z\n0,1,2,3\n0.01,1,oops,3\n",  # not a number
        "t,x,y\n0,1,2\n0.01,1,2\n",  # 2 columns of values
        "t,x,y,z\n0,1,2,3\n0,1,2,3\n",  # time not increasing
        "t,x,y,z\n0,1,2,3\n0.01,nan,2,3\n",  # NaN
        "t,x,y,z\n0,1,2,3\n",  # one sample
    ],
)
def test_damaged_csv_raises_store_error_naming_the_file(tmp_path, text):
    path = _write(tmp_path / "bad.csv", text)
    with pytest.raises(StoreError, match="bad.csv"):
        load_demonstration(path)


def test_damaged_npz_raises_store_error(demo, tmp_path):
    good = save_demonstration(demo, tmp_path / "good.npz")
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good.read_bytes()[:200])
    with pytest.raises(StoreError, match="cut.npz"):
        load_demonstration(cut)
    np.savez(tmp_path / "keys.npz", time=np.arange(3.0), joints=np.zeros((3, 7)))
    with pytest.raises(StoreError, match="keys.npz"):
        load_demonstration(tmp_path / "keys.npz")
    np.savez(tmp_path / "len.npz", t=np.arange(3.0), q=np.zeros((4, 7)))
    with pytest.raises(StoreError, match="len.npz"):
        load_demonstration(tmp_path / "len.npz")
    with pytest.raises(StoreError, match="missing.npz"):
        load_demonstration(tmp_path / "missing.npz")
    # the array's name says what it holds: 'q' (T, 7) joint angles, 'tip' (T, 3) positions; real numbers, t (T,)
    bad = {"q3": {"t": np.arange(3.0), "q": np.zeros((3, 3))},
           "complex": {"t": np.arange(3.0), "tip": np.zeros((3, 3)) + 1j},
           "t2d": {"t": np.arange(6.0).reshape(2, 3), "tip": np.zeros((6, 3))},
           "both": {"t": np.arange(3.0), "tip": np.zeros((3, 3)), "q": np.zeros((3, 7))}}
    for name, arrays in bad.items():
        np.savez(tmp_path / f"{name}.npz", **arrays)
        with pytest.raises(StoreError, match=f"{name}.npz"):
            load_demonstration(tmp_path / f"{name}.npz")


def test_load_demonstration_checks_its_dtype(demo, tmp_path):
    good = save_demonstration(demo, tmp_path / "good.npz")
    assert load_demonstration(good, dtype="float32").tip.dtype == torch.float32
    for bad in (torch.int64, torch.float16):
        with pytest.raises(InvalidArgumentError, match="dtype"):
            load_demonstration(good, dtype=bad)
    with pytest.raises(InvalidArgumentError):
        load_demonstration(tmp_path / "demo.txt")


def test_joint_recording_outside_limits_raises(tmp_path):
    q = np.zeros((3, 7))
    q[1, 3] = -1.0  # e1 below its lower limit -0.05
    np.savez(tmp_path / "limits.npz", t=np.arange(3.0) * 0.01, q=q)
    with pytest.raises(InvalidArgumentError, match="left_e1"):
        load_demonstration(tmp_path / "limits.npz")


# ---------------------------------------------------------------------------------------------- pipeline
from lfd_torch.errors import UnknownNameError  # noqa: E402
from lfd_torch.robot import DLSVelocityMap, build_robot  # noqa: E402
from lfd_torch.robot.task import OrientationSchedule, controller_for, learn_scooping  # noqa: E402
from lfd_torch.robot.trials import (  # noqa: E402
    Disturbance,
    SuccessCriteria,
    check_trials,
    plan_disturbances,
    run_trials,
    start_configurations,
    sugar_depth,
    wilson_interval,
)


@pytest.fixture(scope="module")
def robot():
    return build_robot(velocity_map={"null_space": "exact"})


def test_wilson_interval_matches_scipy():
    from scipy import stats

    for k, n in [(0, 7), (7, 7), (48, 50), (480, 500), (3, 11)]:
        ci = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        np.testing.assert_allclose(wilson_interval(k, n), (ci.low, ci.high), atol=1e-9)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
    with pytest.raises(InvalidArgumentError):
        wilson_interval(5, 3)


def test_sugar_depth_matches_the_plant(plant, generator):
    c = torch.tensor([*plant.scene.can.center, plant.scene.table_top], dtype=torch.float64)
    x = c + (torch.rand(200, 3, generator=generator, dtype=torch.float64) - 0.5) * torch.tensor([0.2, 0.2, 0.3],
                                                                                               dtype=torch.float64)
    ref = torch.tensor([plant.sugar_depth(p) for p in x.numpy()], dtype=torch.float64)
    torch.testing.assert_close(sugar_depth(plant.scene, x), ref)


def test_task_has_steps_stages_and_orientation(task):
    M = task.n_steps
    assert M >= 2 and task.step_stage.shape == (M,)
    assert task.step_stage[0] == 0 and task.step_stage[-1] == 2
    assert bool((task.step_stage[1:] >= task.step_stage[:-1]).all())  # stages in order along the route
    sched = task.orientation
    n = int(task.demos.lengths[0])
    labels = task.segmentation.labels[0][:n]
    x = task.demos.positions[0, :n]
    # at its own samples the schedule returns the demonstration's rotation; progress rises 0 -> 1 within a step
    idx = torch.arange(0, n, 37)
    torch.testing.assert_close(sched(x[idx], labels[idx]), task.demonstration.rotation[idx])
    for m in range(M):
        p = sched.progress_table[labels == m]
        assert float(p[0]) == pytest.approx(0.0, abs=1e-12) and float(p[-1]) == pytest.approx(1.0)
        assert bool((p[1:] >= p[:-1]).all())


def test_orientation_schedule_rejects_bad_input():
    with pytest.raises(InvalidArgumentError, match="step 1"):
        OrientationSchedule(torch.zeros(4, 3), torch.eye(3).expand(4, 3, 3), torch.zeros(4, dtype=torch.long), 2)


def test_controller_caps_the_gain_and_realises_the_task(task, robot):
    ctl = controller_for(task, robot, "full")
    q0 = start_configurations(task, robot.arm, 3)
    pose = robot.arm.forward_kinematics(q0)
    x, R = pose[:, :3, 3], pose[:, :3, :3]
    route, index = torch.full((3,), -1, dtype=torch.long), torch.zeros(3, dtype=torch.long)
    c = ctl.command(q0, x, R, route, index, None)
    assert c.q_d.shape == (3, 7) and c.v.shape == (3, 3) and c.w.shape == (3, 3)
    r = (x - ctl.engine.goals[c.decision.step]).norm(dim=-1)
    assert bool((c.v.norm(dim=-1) <= ctl.max_gain * r + 1e-12).all())
    assert bool((c.w.norm(dim=-1) <= ctl.max_angular_speed + 1e-12).all())
    # v is the engine's velocity, scaled down to max_gain x the distance to the step's goal only where faster
    v_engine = ctl.engine.step_batch(x, route, index)[0]
    cap = (ctl.max_gain * r / v_engine.norm(dim=-1)).clamp(max=1.0)
    torch.testing.assert_close(c.v, v_engine * cap[:, None], rtol=1e-12, atol=1e-12)
    # w turns the spoon towards the demonstrated orientation: R' = exp([w] dt) R is closer to it than R
    r_des = ctl.orientation.rotations[ctl.orientation.nearest(x, c.decision.step)].to(R)

    def angle(a, b):
        return torch.arccos((((a.transpose(1, 2) @ b).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1))

    skew = torch.zeros(3, 3, 3, dtype=R.dtype)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -c.w[:, 2], c.w[:, 1], -c.w[:, 0]
    skew = skew - skew.transpose(1, 2)
    turned = torch.linalg.matrix_exp(1e-3 * skew) @ R
    moving = c.w.norm(dim=-1) > 1e-9
    assert bool(moving.any()) and bool((angle(turned, r_des) < angle(R, r_des))[moving].all())
    # the 6-D DLS task is realised up to the damping: J qdot ~ [v; w]
    J = robot.arm.jacobian(q0)
    got = (J @ c.qdot[..., None]).squeeze(-1)
    torch.testing.assert_close(got[:, :3], c.v, atol=5e-3, rtol=0.05)
    torch.testing.assert_close(c.q_d, q0 + 0.01 * c.qdot)


def test_exact_null_space_does_not_leak(robot, generator):
    arm = robot.arm
    q = arm.neutral() + 0.3 * (torch.rand(16, 7, generator=generator, dtype=torch.float64) - 0.5)
    v = 0.01 * torch.randn(16, 6, generator=generator, dtype=torch.float64)
    base = DLSVelocityMap(arm, null_gain=0.0, null_space="exact")(q, v)
    J = arm.jacobian(q)
    for kind, tol in (("exact", 1e-9), ("damped", None)):
        dq = DLSVelocityMap(arm, posture=arm.neutral() + 0.4, null_space=kind)(q, v) - base
        leak = (J @ dq[..., None]).squeeze(-1).norm(dim=-1).max()
        assert dq.abs().max() > 1e-3
        if tol is not None:
            assert float(leak) < tol
        else:
            assert float(leak) > 1e-6  # the damped projector leaks: the reason for the exact one
    with pytest.raises(UnknownNameError):
        DLSVelocityMap(arm, null_space="approx")


def test_plant_teleport_and_contacts_at(plant, demo):
    p = plant.fork()
    q = np.array([0.1, -0.4, 0.0, 1.1, 0.0, 0.9, 0.0])
    p.teleport(q)
    np.testing.assert_allclose(p.q, q)
    np.testing.assert_allclose(p.qd, 0.0)
    np.testing.assert_allclose(p.tip_position(), p.tip_kinematics(q), atol=1e-12)
    assert p.contacts_at(q) == []
    # a pose that drives the spoon tip 5 mm into the table, beside the can
    from lfd_torch.robot import solve_ik

    target = torch.tensor([[0.80, 0.35, plant.scene.table_top - 0.005]], dtype=torch.float64)
    low = solve_ik(BaxterArm(), target, demo.rotation[:1], demo.q[:1])[0].numpy()
    assert ("spoon", "table") in p.contacts_at(low)
    np.testing.assert_allclose(p.q, q)  # the state is unchanged
    with pytest.raises(InvalidArgumentError):
        p.teleport(np.array([0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0]))


def test_plan_disturbances_cycles_and_repeats():
    a = plan_disturbances(24, torch.Generator().manual_seed(3))
    b = plan_disturbances(24, torch.Generator().manual_seed(3))
    assert a == b
    combos = {(d.stage, d.kind, d.label) for d in a}
    assert len(combos) == 12  # 3 stages x 2 kinds x large/small
    for d in a:
        lo, hi = {("force", "large"): (60, 90), ("force", "small"): (15, 30), ("jump", "large"): (0.05, 0.10),
                  ("jump", "small"): (0.01, 0.025)}[(d.kind, d.label)]  # fmt: skip
        assert lo <= d.magnitude <= hi
        assert math.isclose(float(np.linalg.norm(d.direction)), 1.0)
    with pytest.raises(UnknownNameError):
        Disturbance("kick", 0, 0.1, 1.0)


def test_check_trials_reasons(task, plant, robot):
    """The demonstration itself passes every check; cut or damaged copies fail with the right reason."""
    demo = task.demonstration
    T = demo.n_samples
    tip, q = demo.tip[None].clone(), demo.q[None].clone()
    lengths = torch.tensor([T])
    crit = SuccessCriteria(final_tol=0.02)

    def check(tip, q, lengths, finished, contacts=((),)):
        return check_trials(task, plant.scene, robot.arm, tip, q, lengths, np.array([finished]), contacts, crit)[0]

    ok = check(tip, q, lengths, T - 1)
    assert ok["success"] and ok["reason"] == "" and ok["max_depth_mm"] > 10
    first_scoop = int(torch.nonzero(demo.stages == 1)[0])
    assert check(tip, q, torch.tensor([first_scoop]), -1)["reason"] == "never below the sugar surface"
    last_in = int(torch.nonzero(torch.from_numpy(np.array([plant.sugar_depth(p) for p in demo.tip.numpy()])) > 0)[-1])
    assert check(tip, q, torch.tensor([last_in + 1]), -1)["reason"] == "never left the can after scooping"
    assert check(tip, q, lengths, T - 1, ([("spoon", "can_wall", 3.0)],))["reason"] == "contact spoon-can_wall at 3.00 s"
    assert check(tip, q, lengths, T - 1, ([("spoon", "can_bottom", 3.0)],))["success"]  # not a forbidden contact
    # strict: a contact that a force pulse began fails as well; only the diagnostic lenient verdict excuses it
    wall = ("spoon", "can_wall", 3.0)
    pushed = check_trials(task, plant.scene, robot.arm, tip, q, lengths, np.array([T - 1]), ([wall],), crit,
                          push_contacts=([wall],))[0]  # fmt: skip
    assert not pushed["success"] and not pushed["no_contact"] and pushed["lenient_success"]
    assert pushed["reason"] == "contact spoon-can_wall at 3.00 s (begun by a force pulse)"
    later = ("hand", "can_wall", 4.0)  # a second contact after the pulse fails the lenient verdict too
    both = check_trials(task, plant.scene, robot.arm, tip, q, lengths, np.array([T - 1]), ([wall, later],), crit,
                        push_contacts=([wall],))[0]  # fmt: skip
    assert not both["success"] and not both["lenient_success"]
    assert ok["lenient_success"] and not check(tip, q, lengths, -1)["lenient_success"]
    bad_q = q.clone()
    bad_q[0, 100, 3] = -0.2  # e1 below -0.05 - tol
    assert check(tip, bad_q, lengths, T - 1)["reason"] == "joint limit violated at 1.00 s"
    assert check(tip, q, lengths, -1)["reason"] == "not finished within the budget"


def test_first_second_of_a_trial_heads_for_the_first_attractor(task, robot):
    ctl = controller_for(task, robot, "full")
    q0 = start_configurations(task, robot.arm, 7)[2:3]
    res = run_trials(task, ctl, robot.plant, q0, budget_s=1.0)
    g0 = task.library.attractors[task.library.routes[0][0]]
    d = (res.tip[0] - g0).norm(dim=-1)
    assert float(d[-1]) < 0.8 * float(d[0]) and res.rows[0]["contacts"] == "" and not res.rows[0]["success"]
    assert res.rows[0]["reason"] == "never below the sugar surface"


@pytest.mark.slow
def test_undisturbed_trial_succeeds(task, robot):
    ctl = controller_for(task, robot, "full")
    q0 = start_configurations(task, robot.arm, 7)[2:3]
    res = run_trials(task, ctl, robot.plant, q0, budget_s=30.0)
    row = res.rows[0]
    assert row["success"], row["reason"]
    assert row["disturbance"] == "none" and row["contacts"] == ""
    L = int(res.lengths[0])
    assert res.tip.shape[1] == 3001 and L < 3001
    final = task.library.attractors[task.library.routes[0][-1]]
    assert float((res.tip[0, L - 1] - final).norm()) < 0.01
    # the logged tip is the MuJoCo site at the logged joints
    k = L // 2
    np.testing.assert_allclose(robot.plant.tip_kinematics(res.q[0, k].double().numpy()), res.tip[0, k].numpy(),
                               atol=1e-5)  # fmt: skip


def test_jump_and_force_disturbances(task, robot):
    ctl = controller_for(task, robot, "full")
    q0 = start_configurations(task, robot.arm, 7)[:2]
    dist = [Disturbance("jump", 0, 0.5, 0.06, "large"),
            Disturbance("force", 0, 0.5, 70.0, duration=0.3, body="left_lower_forearm", direction=(0.0, 0.0, 1.0))]
    res = run_trials(task, ctl, robot.plant, q0, disturbances=dist, budget_s=2.0, jump_seed=1)
    jump, force = res.rows
    assert jump["disturbance"] == "jump" and jump["label"] == "large" and jump["fired_s"] == pytest.approx(0.5)
    k = int(res.disturbance_sample[0])
    step = float((res.tip[0, k] - res.tip[0, k - 1]).norm())
    assert step == pytest.approx(0.06, abs=2e-3)  # the tip jumped by the magnitude (plus one tick of motion)
    m = res.steps[0, k - 1]
    own, other = ctl.engine.own_other(res.tip[0, k : k + 1], m[None])
    assert bool(own[0] < other[0])  # it landed outside A_m: a large-scale disturbance
    assert force["disturbance"] == "force" and force["label"] in ("large", "small")
    assert force["displacement_mm"] > 5.0  # 70 N upwards on the forearm moves the tip
    assert force["fired_s"] == pytest.approx(0.5)
    # the same trial and push in the other mode: the same jump at the same time; the same seed repeats exactly
    res_none = run_trials(task, controller_for(task, robot, "none"), robot.plant, q0[:1], disturbances=dist[:1],
                          budget_s=0.6, jump_seed=1)  # fmt: skip
    assert res_none.rows[0]["disturbance"] == "jump" and res_none.rows[0]["fired_s"] == pytest.approx(0.5)
    again = run_trials(task, controller_for(task, robot, "none"), robot.plant, q0[:1], disturbances=dist[:1],
                       budget_s=0.6, jump_seed=1)  # fmt: skip
    assert torch.equal(again.tip, res_none.tip)


def test_contact_caused_by_a_force_pulse_fails_the_trial(task, robot):
    """The success criterion is strict: a pulse (far beyond the trials' 90 N) that shoves the spoon down into the
    scene fails the trial on that contact, although the contact began while the pulse acted."""
    ctl = controller_for(task, robot, "full")
    q0 = start_configurations(task, robot.arm, 7)[:1]
    shove = Disturbance("force", 0, 0.2, 400.0, duration=0.8, body="left_wrist", direction=(0.0, 0.0, -1.0))
    row = run_trials(task, ctl, robot.plant, q0, disturbances=[shove], budget_s=1.5).rows[0]
    assert row["disturbance"] == "force" and row["push_contacts"] != ""
    assert set(row["push_contacts"].split(";")) <= set(row["contacts"].split(";"))
    assert not row["no_contact"] and not row["success"]  # (the stored reason is the first failed check)


def test_summary_rate_is_strict_and_reads_old_tables():
    import sys
    from pathlib import Path

    import pandas as pd

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    import scooping

    rows = [dict(kind="disturbed", method="full", stage="scoop", disturbance="force", label="large", success=s,
                 lenient_success=lenient, reason=r, push_contacts=pc)
            for s, lenient, r, pc in ((True, True, "", ""), (False, True, "contact spoon-can_wall at 1.00 s (begun by a "
                                      "force pulse)", "spoon-can_wall"), (False, False, "never below the sugar surface", ""),
                                      (True, True, "", ""))]  # fmt: skip
    table = pd.DataFrame(rows)
    head = scooping.summary(table).iloc[0]
    assert head.n == 4 and head.successes == 2 and head.rate == 0.5 and head.lenient_rate == 0.75
    assert "contact spoon-can_wall (begun by a force pulse) x1" in head.failures
    # a table written before the strict rule (success excused push contacts, no lenient column) reads the same
    old = table.drop(columns="lenient_success").assign(success=table.lenient_success)
    again = scooping.summary(old).iloc[0]
    assert again.rate == 0.5 and again.lenient_rate == 0.75


@pytest.mark.slow
def test_experiment_run_writes_rows_summary_and_figures(tmp_path):
    import sys
    from pathlib import Path

    import pandas as pd
    from hydra import compose, initialize_config_dir

    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "experiments"))
    import scooping

    with initialize_config_dir(config_dir=str(root / "conf"), version_base="1.3"):
        cfg = compose("scooping", overrides=["n_disturbed=2", "starts.n=2", "budget_s=1.0", "render=false",
                                             "progress=false", f"+out_dir={tmp_path}"])  # fmt: skip
    result = scooping.run(cfg)
    table = pd.read_parquet(tmp_path / "results.parquet")
    assert len(table) == 2 * (2 + 2) and set(table.method) == {"none", "full"}
    assert set(table.kind) == {"start", "disturbed"} and not table.success.any()  # 1 s: not finished
    assert "Wilson" in (tmp_path / "summary.md").read_text() or "wilson_lo" in (tmp_path / "summary.md").read_text()
    figs = {p.name for p in (tmp_path / "figures").iterdir()}
    assert {"scooping_segmentation.png", "scooping_starts.png", "scooping_disturbed.png"} <= figs
    assert len(result["summary"]) > 2


def test_forked_workers_equal_one_process(task, robot):
    ctl = controller_for(task, robot, "full")
    q0 = start_configurations(task, robot.arm, 7)[:3]
    dist = [None, Disturbance("jump", 0, 0.2, 0.03, "small"), Disturbance("force", 0, 0.2, 40.0, duration=0.2)]
    one = run_trials(task, ctl, robot.plant, q0, disturbances=dist, budget_s=0.5, jump_seed=4)
    two = run_trials(task, ctl, robot.plant, q0, disturbances=dist, budget_s=0.5, jump_seed=4, workers=2)
    # the same trials, seeds and pushes: the same decisions and paths; the batched engine's arithmetic depends on
    # the batch size in the last bit (its grouped and per-row paths agree to rounding), so the paths agree to 1e-12
    torch.testing.assert_close(two.tip, one.tip, atol=1e-12, rtol=0)
    assert torch.equal(one.steps, two.steps) and torch.equal(one.branches, two.branches)
    assert [(r["success"], r["reason"]) for r in two.rows] == [(r["success"], r["reason"]) for r in one.rows]
    assert [r["trial"] for r in two.rows] == [0, 1, 2]
    assert [r["disturbance"] for r in two.rows] == [r["disturbance"] for r in one.rows]


def test_the_stored_scooping_steps_are_what_the_code_finds():
    """The published scooping run's segmentation (``results/libraries/scooping/segmentation.pt``, written with the
    table by ``+experiment=scooping_publish``) is what the present code finds from the same demonstration and seed:
    the trial outcomes move with switches a few samples away (mode none 95.5 % -> 91.7 % when two switches moved by
    1-3 of 1,300 samples), so a change that moves them fails here until the published table is remade."""
    import sys
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from lfd_torch.segmentation import Segmentation

    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "experiments"))
    import scooping

    with initialize_config_dir(config_dir=str(root / "conf"), version_base="1.3"):
        cfg = compose("scooping", overrides=["+experiment=scooping_publish"])
    task = scooping.learn(cfg, instantiate(cfg.robot, _convert_="all"))
    stored = Segmentation.load(root / "results" / "libraries" / "scooping" / "segmentation.pt")
    assert [p.tolist() for p in task.segmentation.pieces] == [p.tolist() for p in stored.pieces]
    torch.testing.assert_close(task.segmentation.attractors, stored.attractors, rtol=1e-9, atol=1e-12)
