"""Scooping trials (plan, start ring, wall crossing, jump targets, success checks, forked bookkeeping), stored figure
state and violin data against independent references: naive Python loops, closed forms, scipy, pandas, properties.

The success checks run on synthetic tip paths in the default :class:`~lfd_torch.robot.Scene` with a stand-in task
(only its final attractor is read); the jump target runs with a stand-in engine and plant; the forked runner runs a
stand-in of :func:`run_trials` in its forked workers. Nothing here runs a MuJoCo rollout.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, PlotError, ShapeMismatchError, StoreError, UnknownNameError
from lfd_torch.robot import BaxterArm, Scene
from lfd_torch.robot import trials as trials_module
from lfd_torch.robot.trials import (
    FORCE_BODIES,
    Disturbance,
    SuccessCriteria,
    TrialBatch,
    check_trials,
    plan_disturbances,
    run_trials,
    start_configurations,
    wilson_interval,
)
from lfd_torch.store.checksum import DIGEST_KEY, payload_digest
from lfd_torch.viz import metric_columns, save_figure, violin, violin_grid
from lfd_torch.viz.stored import load_config, load_demos, load_state, save_config, save_demos, save_state

F64 = torch.float64


@pytest.fixture(scope="module")
def arm() -> BaxterArm:
    return BaxterArm()


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene()


# ---------------------------------------------------------------------------------------------- plan_disturbances
def _reference_plan(n, seed, kinds=("force", "jump"), stages=(0, 1, 2), stage_durations=(3.0, 4.0, 6.0)):
    """The documented plan, drawn in a plain loop: combos cycle (stage, kind, large/small); per trial the
    magnitude, a Gaussian direction, the body, the delay fraction and the duration, in that order."""
    g = torch.Generator().manual_seed(seed)
    ranges = {("force", "large"): (60.0, 90.0), ("force", "small"): (15.0, 30.0), ("jump", "large"): (0.05, 0.10),
              ("jump", "small"): (0.01, 0.025)}  # fmt: skip
    combos = []
    for s in stages:
        for k in kinds:
            for lab in ("large", "small"):
                combos.append((s, k, lab))
    out = []
    for i in range(n):
        s, k, lab = combos[i % len(combos)]
        lo, hi = ranges[(k, lab)]
        mag = lo + (hi - lo) * torch.rand((), generator=g, dtype=F64).item()
        d = torch.randn(3, generator=g, dtype=F64).numpy()
        body = FORCE_BODIES[torch.randint(4, (), generator=g).item()]
        frac = 0.15 + 0.45 * torch.rand((), generator=g, dtype=F64).item()
        dur = 0.2 + 0.2 * torch.rand((), generator=g, dtype=F64).item()
        out.append((s, k, lab, mag, d / math.sqrt(float(d @ d)), body, frac * stage_durations[s], dur))
    return out


@pytest.mark.parametrize("kinds,stages,durations", [(("force", "jump"), (0, 1, 2), (3.0, 4.0, 6.0)),
                                                     (("jump",), (2, 0), (1.0, 2.0, 5.0))])  # fmt: skip
def test_plan_disturbances_equals_a_plain_loop(kinds, stages, durations):
    """Each planned disturbance equals the one a plain loop draws from the same seed: the combination cycles
    in (stage, kind, large/small) order starting at the first, the delay is a fraction of the stage's duration."""
    got = plan_disturbances(30, torch.Generator().manual_seed(11), kinds=kinds, stages=stages,
                            stage_durations=durations)  # fmt: skip
    ref = _reference_plan(30, 11, kinds, stages, durations)
    assert len(got) == 30
    for d, (s, k, lab, mag, direction, body, delay, dur) in zip(got, ref):
        assert (d.stage, d.kind, d.label, d.body) == (s, k, lab, body)
        assert d.magnitude == pytest.approx(mag, rel=1e-12)
        assert d.delay == pytest.approx(delay, rel=1e-12)
        assert d.duration == pytest.approx(dur, rel=1e-12)
        np.testing.assert_allclose(d.direction, direction, rtol=1e-12, atol=1e-15)


def test_plan_disturbances_covers_every_body_and_the_delay_range():
    """Over many trials every force body is drawn, and delay / stage duration spans the documented fraction range."""
    plan = plan_disturbances(240, torch.Generator().manual_seed(5))
    assert {d.body for d in plan} == set(FORCE_BODIES)
    frac = np.array([d.delay / (3.0, 4.0, 6.0)[d.stage] for d in plan])
    assert frac.min() >= 0.15 and frac.max() <= 0.6 and frac.max() - frac.min() > 0.4
    assert plan_disturbances(0, torch.Generator().manual_seed(5)) == []
    for bad in (-1, 2.0, True):
        with pytest.raises(InvalidArgumentError):
            plan_disturbances(bad, torch.Generator().manual_seed(5))
    # no kind or stage to cycle through, an unknown kind, a stage without a duration: typed errors naming them
    for kwargs, name in ((dict(kinds=()), "kinds"), (dict(stages=()), "stages"), (dict(kinds=("shove",)), "kinds"),
                         (dict(stages=(3,)), "stages"), (dict(stages=(True,)), "stages")):  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            plan_disturbances(2, torch.Generator().manual_seed(5), **kwargs)


def test_disturbance_argument_bounds():
    """Stage 0..2 and zero delays/magnitudes are valid; stage 3, negative or non-finite numbers, unknown labels not."""
    Disturbance("force", 2, 0.0, 0.0, duration=0.0)
    Disturbance("jump", 0, 0, 1, "small")
    for kwargs in (dict(stage=3), dict(stage=-1), dict(delay=-1e-9), dict(magnitude=math.inf),
                   dict(duration=math.nan), dict(delay="1")):  # fmt: skip
        args = dict(kind="force", stage=0, delay=0.1, magnitude=1.0) | kwargs
        with pytest.raises(InvalidArgumentError):
            Disturbance(**args)
    with pytest.raises(UnknownNameError):
        Disturbance("jump", 0, 0.1, 1.0, "medium")


# ---------------------------------------------------------------------------------------------- wilson, batch
def test_wilson_interval_with_another_z_matches_scipy():
    """With z = 1 (68.27 %) the interval equals scipy's Wilson interval at that level, and it stays in [0, 1]."""
    from scipy import stats

    level = math.erf(1 / math.sqrt(2))
    for k, n in [(0, 5), (1, 1), (2, 9), (9, 9), (33, 40)]:
        ci = stats.binomtest(k, n).proportion_ci(confidence_level=level, method="wilson")
        lo, hi = wilson_interval(k, n, z=1.0)
        np.testing.assert_allclose((lo, hi), (ci.low, ci.high), atol=1e-12)
        assert 0.0 <= lo <= k / n <= hi <= 1.0
    for bad in ((-1, 4), (5, 4)):
        with pytest.raises(InvalidArgumentError):
            wilson_interval(*bad)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))  # no trials: no interval
    for bad, name in (((0, -3), "n"), ((3, 10.5), "n"), ((2.0, 4), "successes"), ((3, 10, math.nan), "z"),
                      ((3, 10, -1.96), "z"), ((3, "10"), "n")):
        with pytest.raises(InvalidArgumentError, match=name):
            wilson_interval(*bad)


def test_trial_batch_success_reads_the_strict_verdict():
    """``TrialBatch.success`` is the rows' ``success``, not their lenient verdict."""
    rows = [dict(success=True, lenient_success=True), dict(success=False, lenient_success=True),
            dict(success=np.bool_(False), lenient_success=False)]  # fmt: skip
    b = TrialBatch(rows, torch.zeros(3, 2, 3), torch.zeros(3, 2, 7), torch.tensor([2, 2, 2]),
                   torch.zeros(3, 2, dtype=torch.long), torch.zeros(3, 2, dtype=torch.int8), torch.full((3,), -1), 0.01)
    assert b.success.dtype == torch.bool and b.success.tolist() == [True, False, False]


def test_run_trials_rejects_bad_arguments_before_simulating():
    """Shape, count and type errors come before any use of the task, controller or plant."""
    q0 = torch.zeros(2, 7, dtype=F64)
    with pytest.raises(ShapeMismatchError):
        run_trials(None, None, None, torch.zeros(2, 6))
    with pytest.raises(ShapeMismatchError):
        run_trials(None, None, None, torch.zeros(7))
    with pytest.raises(ShapeMismatchError):
        run_trials(None, None, None, q0, disturbances=[None])
    with pytest.raises(InvalidArgumentError):
        run_trials(None, None, None, q0, jump_seed=True)
    with pytest.raises(InvalidArgumentError):
        run_trials(None, None, None, q0, jump_seed=1.0)
    for bad in (0, True, 1.5):
        with pytest.raises(InvalidArgumentError):
            run_trials(None, None, None, q0, workers=bad)


# ---------------------------------------------------------------------------------------------- start ring
def test_start_configurations_lie_on_the_documented_ring(arm):
    """The FK tips of the starts lie on the ring x0 + (r cos t, r sin t, h sin 2t), t = 2 pi k / n, with the
    demonstration's first spoon orientation; a demonstration without joints is refused."""
    q0 = arm.neutral()
    pose = arm.forward_kinematics(q0[None])[0]
    demo = SimpleNamespace(tip=pose[None, :3, 3], rotation=pose[None, :3, :3], q=q0[None])
    n, radius, height = 5, 0.06, 0.03
    qs = start_configurations(SimpleNamespace(demonstration=demo), arm, n, radius=radius, height=height)
    got = arm.forward_kinematics(qs)
    assert qs.shape == (n, 7)
    for k in range(n):
        t = 2 * math.pi * k / n
        want = [float(pose[0, 3]) + radius * math.cos(t), float(pose[1, 3]) + radius * math.sin(t),
                float(pose[2, 3]) + height * math.sin(2 * t)]  # fmt: skip
        np.testing.assert_allclose(got[k, :3, 3].numpy(), want, atol=1e-5)
        np.testing.assert_allclose(got[k, :3, :3].numpy(), pose[:3, :3].numpy(), atol=1e-4)
    with pytest.raises(InvalidArgumentError):
        start_configurations(SimpleNamespace(demonstration=SimpleNamespace(tip=demo.tip, rotation=None, q=demo.q)),
                             arm)  # fmt: skip


# ---------------------------------------------------------------------------------------------- wall crossing
def _naive_crosses(scene, x, land, margin=0.02, n=32):
    """Per candidate: does one of n evenly spaced points of the segment x -> land lie within ``margin`` of the
    middle of a vessel wall (radially) and below the vessel's rim + margin?"""
    out = []
    for e in land.tolist():
        hit = False
        for j in range(n):
            s = j / (n - 1)
            p = [x[i] + s * (e[i] - x[i]) for i in range(3)]
            for v in (scene.can, scene.cup):
                r = math.hypot(p[0] - v.center[0], p[1] - v.center[1])
                rim = scene.table_top + v.wall + v.height
                if abs(r - (v.radius + v.wall / 2)) < margin and p[2] < rim + margin:
                    hit = True
        out.append(hit)
    return out


def test_crosses_walls_equals_a_point_loop(scene, generator):
    """Random segments around both vessels: the batched test equals the plain loop over the path points; a
    segment through the can's wall below the rim crosses, the same one 3 cm above the rim does not."""
    can, cup = scene.can, scene.cup
    for v in (can, cup):
        c = torch.tensor([*v.center, scene.table_top + v.height * 0.8], dtype=F64)
        x = c + (torch.rand(3, generator=generator, dtype=F64) - 0.5) * torch.tensor([0.3, 0.3, 0.2], dtype=F64)
        land = c + (torch.rand(200, 3, generator=generator, dtype=F64) - 0.5) * torch.tensor([0.3, 0.3, 0.25],
                                                                                           dtype=F64)
        got = trials_module._crosses_walls(scene, x, land)
        ref = _naive_crosses(scene, x.tolist(), land)
        assert got.dtype == torch.bool and got.tolist() == ref
        assert 10 < sum(ref) < 190  # both outcomes present
        got = trials_module._crosses_walls(scene, x, land, margin=0.005, n=7)
        assert got.tolist() == _naive_crosses(scene, x.tolist(), land, margin=0.005, n=7)
    rim = scene.table_top + can.wall + can.height
    inside = torch.tensor([can.center[0], can.center[1], rim - 0.03], dtype=F64)
    out = torch.tensor([[can.center[0] + 0.15, can.center[1], rim - 0.03],
                        [can.center[0] + 0.15, can.center[1], rim + 0.03]], dtype=F64)  # fmt: skip
    assert trials_module._crosses_walls(scene, inside, out[:1]).tolist() == [True]
    above = torch.tensor([can.center[0], can.center[1], rim + 0.03], dtype=F64)
    assert trials_module._crosses_walls(scene, above, out[1:]).tolist() == [False]


# ---------------------------------------------------------------------------------------------- jump target
class _Engine:
    """Stand-in engine: a landing point is outside A_m ("large") when it lies at smaller x than the tip."""

    def __init__(self, x, train):
        self.x = x
        self.library = SimpleNamespace(skills=[None, SimpleNamespace(train_positions=train)])

    def own_other(self, land, st):
        assert bool((st == 1).all())
        return (land - self.x)[:, 0], torch.zeros(land.shape[0], dtype=land.dtype)


def _reference_landing(scene, x, magnitude, label, seed, n, train, away, refused=()):
    """The index of the first random direction whose landing point is 3 cm above the table, crosses no wall, has
    the requested label (and a small one lies ``away`` from the training data), not counting ``refused``."""
    dirs = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=F64)
    for j in range(n):
        d = dirs[j].tolist()
        norm = math.sqrt(sum(c * c for c in d))
        land = [x[i] + magnitude * d[i] / norm for i in range(3)]
        if land[2] <= scene.table_top + 0.03 or _naive_crosses(scene, x, torch.tensor([land], dtype=F64))[0]:
            continue
        near = min(math.dist(land, t) for t in train.tolist())
        if label == "large" and not land[0] < x[0]:
            continue
        if label == "small" and not (land[0] >= x[0] and near >= away):
            continue
        if j in refused:
            continue
        return j, land
    return None, None


def test_jump_target_takes_the_first_valid_direction(arm, scene):
    """The jump lands (FK of the returned joints) on the first candidate that passes the documented filters,
    both labels; a landing state in contact is skipped for the next one; no valid one gives None and a reason."""
    q0 = torch.tensor([0.1, -0.45, 0.0, 1.35, 0.0, 0.75, 0.0], dtype=F64)
    pose = arm.forward_kinematics(q0[None])[0]
    x, R = pose[:3, 3], pose[:3, :3]
    # a tip low over the table, close to the cup: some directions hit the table band or the cup wall
    assert float(x[2]) - scene.table_top < 0.2
    train = x[None] + torch.tensor([[0.02, 0.0, 0.0], [0.0, 0.02, 0.0], [0.015, 0.0, 0.015]], dtype=F64)
    engine = _Engine(x, train.float())
    free = SimpleNamespace(scene=scene, contacts_at=lambda q: [])
    for label, mag, seed in (("large", 0.06, 0), ("small", 0.02, 1), ("large", 0.06, 2), ("small", 0.02, 3)):
        d = Disturbance("jump", 1, 0.1, mag, label)
        q, why = trials_module._jump_target(free, arm, engine, None, q0, x, R, 1, d,
                                            torch.Generator().manual_seed(seed), 0.012, 24)  # fmt: skip
        j, land = _reference_landing(scene, x.tolist(), mag, label, seed, 24, train.float().double(), 0.012)
        assert j is not None and q is not None and why == ""
        tip = arm.forward_kinematics(q[None])[0, :3, 3]
        np.testing.assert_allclose(tip.numpy(), land, atol=2e-3)
        assert bool(arm.within_limits(q))
        # the same landing refused by a contact: the next valid candidate
        def contact_at_first(qq, land=land):
            tip = arm.forward_kinematics(torch.as_tensor(qq)[None])[0, :3, 3].tolist()
            return [("spoon", "cup_wall")] if math.dist(tip, land) < 3e-3 else []

        blocked = SimpleNamespace(scene=scene, contacts_at=contact_at_first)
        q2, _ = trials_module._jump_target(blocked, arm, engine, None, q0, x, R, 1, d,
                                           torch.Generator().manual_seed(seed), 0.012, 24)  # fmt: skip
        j2, land2 = _reference_landing(scene, x.tolist(), mag, label, seed, 24, train.float().double(), 0.012, {j})
        assert j2 is not None and j2 > j
        np.testing.assert_allclose(arm.forward_kinematics(q2[None])[0, :3, 3].numpy(), land2, atol=2e-3)
    none_ok = _Engine(x, train.float())
    none_ok.own_other = lambda land, st: (torch.ones(len(land), dtype=F64), torch.zeros(len(land), dtype=F64))
    q, why = trials_module._jump_target(free, arm, none_ok, None, q0, x, R, 1, Disturbance("jump", 1, 0.1, 0.05),
                                        torch.Generator().manual_seed(0), 0.005, 9)  # fmt: skip
    assert q is None and why == "no large landing point among 9 directions"


# ---------------------------------------------------------------------------------------------- success checks
def _stand_in_task(goal):
    attractors = torch.stack([goal + 0.3, goal - 0.3, goal, goal + 0.1])
    return SimpleNamespace(library=SimpleNamespace(segmentation=SimpleNamespace(attractors=attractors),
                                                   routes=[[0, 1, 2], [3]]))  # fmt: skip


def _regions(scene, crit):
    can, cup = scene.can, scene.cup
    bottom = scene.table_top + can.wall
    can_rim = bottom + can.height
    cup_rim = scene.table_top + cup.wall + cup.height
    goal = [cup.center[0], cup.center[1], cup_rim + 0.5 * crit.cup_height]

    def polar(c, r, z):
        def f(g):
            a = 2 * math.pi * float(torch.rand((), generator=g, dtype=F64))
            rr = r[0] + (r[1] - r[0]) * float(torch.rand((), generator=g, dtype=F64))
            zz = z[0] + (z[1] - z[0]) * float(torch.rand((), generator=g, dtype=F64))
            return [c[0] + rr * math.cos(a), c[1] + rr * math.sin(a), zz]

        return f

    return goal, {
        "air": polar(can.center, (0.1, 0.3), (can_rim + 0.02, can_rim + 0.2)),
        "sugar": polar(can.center, (0.0, can.radius - 0.004), (bottom + 0.002, bottom + can.fill - 0.001)),
        "can": polar(can.center, (0.0, can.radius), (bottom + can.fill, can_rim + 0.01)),
        "wall": polar(can.center, (can.radius - 0.01, can.radius + can.wall + 0.01), (bottom, can_rim)),
        "cup": polar(cup.center, (0.0, cup.radius), (cup_rim - 0.01, cup_rim + crit.cup_height + 0.01)),
        "goal": lambda g: list(goal),
    }


def _synthetic_paths(scene, crit, generator, B, T):
    """B piecewise straight tip paths (T samples) through random regions: air, sugar, can, wall, cup, goal."""
    goal, regions = _regions(scene, crit)
    names = list(regions)
    tips = torch.zeros(B, T, 3, dtype=F64)
    for b in range(B):
        k = 3 + int(torch.randint(5, (), generator=generator))
        seq = [names[int(torch.randint(len(names), (), generator=generator))] for _ in range(k)]
        if b % 3 == 0:
            seq = ["air", "sugar", "can", "air", "cup", "goal"]
        pts = torch.tensor([regions[s](generator) for s in seq], dtype=F64)
        s = torch.linspace(0, len(pts) - 1, T, dtype=F64)
        i = s.floor().long().clamp(max=len(pts) - 2)
        w = (s - i)[:, None]
        tips[b] = pts[i] * (1 - w) + pts[i + 1] * w
    return torch.tensor(goal, dtype=F64), tips


def _reference_check(scene, arm, tip, q, L, finished_at, contacts, push, crit, goal):
    """The module docstring's checks, one trial, a plain loop over its valid samples."""
    can, cup = scene.can, scene.cup
    bottom = scene.table_top + can.wall
    can_rim = bottom + can.height
    cup_rim = scene.table_top + cup.wall + cup.height
    lo, hi = arm.lower(q.dtype).tolist(), arm.upper(q.dtype).tolist()
    depth, in_sugar, out_can, over_cup, viol = [], [], [], [], []
    for t in range(L):
        x, y, z = tip[t].tolist()
        r = math.hypot(x - can.center[0], y - can.center[1])
        d = min(bottom + can.fill - z, can.radius - r, z - bottom)
        depth.append(d)
        in_sugar.append(d > crit.sugar_depth)
        out_can.append(z > can_rim or r > can.radius + can.wall)
        rc = math.hypot(x - cup.center[0], y - cup.center[1])
        over_cup.append(rc < cup.radius - crit.cup_margin and cup_rim < z < cup_rim + crit.cup_height)
        viol.append(any(v < lo[j] - crit.limit_tol or v > hi[j] + crit.limit_tol for j, v in enumerate(q[t].tolist())))
    entered = any(in_sugar)
    last = max((t for t in range(L) if in_sugar[t]), default=-1)
    err = math.dist(tip[L - 1].tolist(), goal.tolist())
    bad = [c for c in contacts if c[1] in crit.forbidden]
    checks = {
        "entered_sugar": entered,
        "left_sugar": entered and any(out_can[t] for t in range(last + 1, L)),
        "reached_cup": entered and any(over_cup[t] for t in range(last + 1, L)),
        "no_contact": not bad,
        "joint_limits": not any(viol),
        "finished": finished_at >= 0 and err < crit.final_tol,
    }
    reasons = {"entered_sugar": "never below the sugar surface", "left_sugar": "never left the can after scooping",
               "reached_cup": "never above the cup after scooping"}  # fmt: skip
    reason = ""
    for name, ok in checks.items():
        if ok:
            continue
        if name == "no_contact":
            reason = f"contact {bad[0][0]}-{bad[0][1]} at {bad[0][2]:.2f} s" + (
                " (begun by a force pulse)" if bad[0] in push else "")
        elif name == "joint_limits":
            reason = f"joint limit violated at {viol.index(True) * 0.01:.2f} s"
        elif name == "finished":
            reason = f"final error {err * 1e3:.1f} mm" if finished_at >= 0 else "not finished within the budget"
        else:
            reason = reasons[name]
        break
    others = all(ok for name, ok in checks.items() if name != "no_contact")
    return dict(success=all(checks.values()), reason=reason, **checks,
                lenient_success=others and all(c in push for c in bad), max_depth_mm=max(depth) * 1e3,
                final_error_mm=err * 1e3, contacts=";".join(sorted({f"{p}-{o}" for p, o, _ in contacts})))


@pytest.mark.parametrize("crit", [SuccessCriteria(), SuccessCriteria(sugar_depth=0.02, cup_height=0.05, cup_margin=0.015,
                                                                     limit_tol=0.05, final_tol=0.03,
                                                                     forbidden=("table", "cup_wall"))])  # fmt: skip
def test_check_trials_equals_a_plain_loop_on_synthetic_paths(crit, scene, arm, generator):
    """Random tip paths, lengths (samples past the length hold garbage), joint paths near the limits, contact
    lists and finish ticks: every check, the reason, the lenient verdict, the depth and the final error equal a
    per-sample loop over the documented rules."""
    B, T = 48, 60
    goal, tip = _synthetic_paths(scene, crit, generator, B, T)
    lengths = torch.randint(T // 2, T + 1, (B,), generator=generator)
    lengths[:6] = T
    lo, hi = arm.lower(), arm.upper()
    q = lo + (hi - lo) * torch.rand(B, T, 7, generator=generator, dtype=F64)
    for b in range(B):
        L = int(lengths[b])
        if b % 4 == 1:  # a violation inside the valid part, beyond the tolerance
            t, j = int(torch.randint(L, (), generator=generator)), b % 7
            q[b, t, j] = hi[j] + 2 * crit.limit_tol if b % 8 == 1 else lo[j] - 2 * crit.limit_tol
        if b % 4 == 2:  # within the tolerance: still held
            q[b, L // 2, 3] = lo[3] - 0.5 * crit.limit_tol
        if L < T:  # garbage after the end: deep in the sugar, out of limits, over the cup
            tip[b, L:] = torch.tensor([scene.can.center[0], scene.can.center[1], scene.table_top + 0.03], dtype=F64)
            tip[b, -1] = torch.tensor([scene.cup.center[0], scene.cup.center[1], goal[2]], dtype=F64)
            q[b, L:, 0] = hi[0] + 1.0
        if b % 5 == 0:  # ends at the goal, within the tolerance
            tip[b, L - 1] = goal + torch.tensor([0.5, -0.3, 0.2], dtype=F64) * crit.final_tol * 0.9 / math.sqrt(0.38)
    finished = np.where(np.arange(B) % 6 == 5, -1, lengths.numpy() - 1)
    finished[7] = 0
    parts, objects = ("spoon", "hand", "left_wrist"), ("can_wall", "cup_wall", "table", "can_bottom", "sugar")
    contacts, push = [], []
    for b in range(B):
        n = [0, 0, 1, 2, 3][b % 5]
        c = [(parts[int(torch.randint(3, (), generator=generator))], objects[int(torch.randint(5, (), generator=generator))],
              round(float(torch.rand((), generator=generator)) * 5, 2)) for _ in range(n)]  # fmt: skip
        contacts.append(c)
        push.append(c[:1] if b % 2 else c[1:])
    task = _stand_in_task(goal)
    got = check_trials(task, scene, arm, tip, q, lengths, finished, contacts, crit, push_contacts=push)
    for b in range(B):
        ref = _reference_check(scene, arm, tip[b], q[b], int(lengths[b]), int(finished[b]), contacts[b], push[b],
                               crit, goal)  # fmt: skip
        for key, value in ref.items():
            if isinstance(value, float):
                assert got[b][key] == pytest.approx(value, rel=1e-12, abs=1e-12), (b, key)
            else:
                assert got[b][key] == value, (b, key)
    # the paths exercise every outcome
    for key in ("entered_sugar", "left_sugar", "reached_cup", "no_contact", "joint_limits", "finished", "success"):
        assert {bool(r[key]) for r in got} == {True, False}, key


def test_check_trials_boundaries(scene, arm):
    """Joint angles (float32, as logged) exactly at limit -/+ tol hold; the first forbidden contact names the
    reason; without push contacts the lenient verdict excuses nothing; the depth ignores samples past the end."""
    goal, regions = _regions(scene, SuccessCriteria())
    g = torch.Generator().manual_seed(2)
    pts = torch.tensor([regions[s](g) for s in ("air", "sugar", "air", "cup", "goal")], dtype=F64)
    T = 41
    s = torch.linspace(0, 4, T, dtype=F64)
    i = s.floor().long().clamp(max=3)
    tip = (pts[i] * (1 - (s - i)[:, None]) + pts[i + 1] * (s - i)[:, None])[None].repeat(2, 1, 1)
    tip[:, -1] = torch.tensor(goal, dtype=F64)
    crit = SuccessCriteria()
    q = arm.neutral(torch.float32).expand(2, T, 7).clone()
    q[0, 5] = arm.lower(torch.float32) - crit.limit_tol
    q[0, 6] = arm.upper(torch.float32) + crit.limit_tol
    q[1, 9, 2] = torch.nextafter(arm.upper(torch.float32)[2] + crit.limit_tol, torch.tensor(10.0))
    task = _stand_in_task(torch.tensor(goal, dtype=F64))
    contacts = [[("hand", "can_bottom", 0.5), ("hand", "table", 1.25), ("spoon", "cup_wall", 2.0)], []]
    rows = check_trials(task, scene, arm, tip, q, torch.tensor([T, T]), np.array([T - 1, T - 1]), contacts, crit)
    assert rows[0]["joint_limits"] and not rows[0]["no_contact"]
    assert rows[0]["reason"] == "contact hand-table at 1.25 s" and not rows[0]["lenient_success"]
    assert rows[0]["contacts"] == "hand-can_bottom;hand-table;spoon-cup_wall"
    assert rows[1]["reason"] == "joint limit violated at 0.09 s"
    slow = check_trials(task, scene, arm, tip, q, torch.tensor([T, T]), np.array([T - 1, T - 1]), contacts, crit,
                        dt=0.02)  # logs of a 50 Hz loop: the time of sample 9 is 0.18 s
    assert slow[1]["reason"] == "joint limit violated at 0.18 s"
    assert rows[1]["entered_sugar"] and rows[1]["left_sugar"] and rows[1]["reached_cup"]
    # back in the sugar at the end (after the cup): never left the can after the last time in the sugar
    back = torch.cat([tip[:1, :35], tip[:1, 10:11].expand(1, 6, 3)], 1)
    short = check_trials(task, scene, arm, back, q[:1], torch.tensor([T]), np.array([-1]), [[]], crit)[0]
    assert short["reason"] == "never left the can after scooping"
    no_cup = tip[:1].clone()
    no_cup[0, 21:, :2] += 0.3  # the same heights, far beside the cup
    row = check_trials(task, scene, arm, no_cup, q[:1], torch.tensor([T]), np.array([T - 1]), [[]], crit)[0]
    assert row["left_sugar"] and row["reason"] == "never above the cup after scooping"
    depth_all = check_trials(task, scene, arm, tip[:1], q[:1], torch.tensor([T]), np.array([-1]), [[]], crit)[0]
    depth_cut = check_trials(task, scene, arm, tip[:1], q[:1], torch.tensor([5]), np.array([-1]), [[]], crit)[0]
    assert depth_cut["max_depth_mm"] < 0 < depth_all["max_depth_mm"]


# ---------------------------------------------------------------------------------------------- forked bookkeeping
def _fake_run_trials(task, controller, plant, q0, *, disturbances=None, trial_offset=0, **kw):
    """Stand-in of run_trials for the forked workers: records what each part received."""
    B = q0.shape[0]
    rows = [dict(trial=i, offset=trial_offset, q0=q0[i, 0].item(), dist=disturbances[i], kw=sorted(kw.items()))
            for i in range(B)]  # fmt: skip
    tip = q0[:, None, :3].expand(B, 4, 3).clone()
    return TrialBatch(rows, tip, q0[:, None, :].expand(B, 4, 7).float(), torch.full((B,), 4), torch.zeros(B, 4,
                      dtype=torch.long), torch.zeros(B, 4, dtype=torch.int8), torch.arange(B) + trial_offset, 0.01)


@pytest.mark.parametrize("B,workers,offset", [(5, 2, 0), (7, 3, 10), (4, 9, 3)])
def test_forked_runner_splits_and_merges_in_trial_order(monkeypatch, B, workers, offset):
    """The forked runner gives each trial to exactly one worker with its own q0, disturbance and jump-seed index
    ``trial_offset + i``, and merges rows and logs back in trial order."""
    monkeypatch.setattr(trials_module, "run_trials", _fake_run_trials)
    q0 = torch.arange(B, dtype=F64)[:, None] + torch.zeros(B, 7, dtype=F64)
    dist = [f"d{i}" for i in range(B)]
    kw = dict(budget_s=1.0, jump_seed=3, criteria=None, away=0.005, n_candidates=8)
    ticks = []
    progress = SimpleNamespace(update=ticks.append)
    res = trials_module._run_forked(None, None, None, q0, dist, kw, min(workers, B), offset, progress)
    assert [r["trial"] for r in res.rows] == list(range(B))
    assert [r["q0"] for r in res.rows] == [float(i) for i in range(B)]
    assert [r["dist"] for r in res.rows] == dist
    assert res.disturbance_sample.tolist() == [offset + i for i in range(B)]
    assert all(r["kw"] == sorted(kw.items()) for r in res.rows)
    torch.testing.assert_close(res.tip[:, 0, 0], q0[:, 0])
    assert res.lengths.tolist() == [4] * B and ticks == [4]
    sizes = np.bincount([r["offset"] for r in res.rows])
    sizes = sizes[sizes > 0]
    assert len(sizes) == min(workers, B) and sizes.max() - sizes.min() <= 1


# ---------------------------------------------------------------------------------------------- stored state
class _Foreign:
    """An object that a weights-only load must refuse."""

    def __init__(self):
        self.value = 1


def test_state_round_trip_returns_exactly_what_was_stored(tmp_path):
    """load_state(save_state(s)) == s: the same keys (no schema or checksum entries), bit-equal tensors; a digest
    entry in the input is replaced, not kept."""
    state = {"x": torch.linspace(0, 1, 7, dtype=F64), "n": 3, "s": "text", "l": [1, 2.5, None], "d": {"k": True},
             DIGEST_KEY: "stale"}  # fmt: skip
    back = load_state(save_state(state, tmp_path / "deep" / "er" / "s.pt"))
    assert set(back) == {"x", "n", "s", "l", "d"}
    assert torch.equal(back["x"], state["x"]) and back["x"].dtype == F64
    assert (back["n"], back["s"], back["l"], back["d"]) == (3, "text", [1, 2.5, None], {"k": True})


def test_damaged_or_foreign_state_files_raise_store_error(tmp_path):
    """Truncated, digestless, other-schema and foreign-object files all raise StoreError naming the file."""
    path = save_state({"x": torch.arange(100.0)}, tmp_path / "s.pt")
    raw = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(StoreError, match=r"cannot read stored file .*cut\.pt"):
        load_state(tmp_path / "cut.pt")
    torch.save({"x": torch.ones(2), "schema_version": 1}, tmp_path / "plain.pt")
    with pytest.raises(StoreError, match=r"plain\.pt is not a checksummed state"):
        load_state(tmp_path / "plain.pt")
    other = {"x": torch.ones(2), "schema_version": 2}
    other[DIGEST_KEY] = payload_digest(other)
    torch.save(other, tmp_path / "other.pt")
    with pytest.raises(StoreError, match=r"other\.pt: schema 2, expected 1"):
        load_state(tmp_path / "other.pt")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(StoreError, match="not a checksummed state"):
        load_state(tmp_path / "list.pt")
    torch.save({"x": _Foreign(), DIGEST_KEY: "0" * 64, "schema_version": 1}, tmp_path / "foreign.pt")
    with pytest.raises(StoreError, match=r"cannot read stored file .*foreign\.pt"):
        load_state(tmp_path / "foreign.pt")


def test_demos_files_check_their_keys(tmp_path, generator):
    """A state without demos or with demos lacking an entry raises StoreError; the extras come back without the
    demonstrations; lean files keep times, lengths and names."""
    x = torch.randn(2, 9, 2, generator=generator, dtype=F64).cumsum(1)
    demos = Demos.from_sequences([x[0], x[1, :6]], dt=0.05, names=["p", "q"])
    back, extra = load_demos(save_demos(demos, tmp_path / "d.pt", velocities=False, tag=[1, 2]))
    assert extra == {"tag": [1, 2]}
    torch.testing.assert_close(back.times, demos.times, rtol=0, atol=0)
    assert back.lengths.tolist() == [9, 6] and back.names == ("p", "q")
    save_state({"other": 1}, tmp_path / "none.pt")
    with pytest.raises(StoreError, match="holds no demonstrations"):
        load_demos(tmp_path / "none.pt")
    save_state({"demos": {"positions": demos.positions, "lengths": demos.lengths, "attractor": demos.attractor,
                          "names": ["p", "q"]}}, tmp_path / "lack.pt")  # fmt: skip
    with pytest.raises(StoreError, match=r"lack 'times'"):
        load_demos(tmp_path / "lack.pt")


def test_config_resolves_interpolations_and_rejects_damaged_files(tmp_path):
    """A DictConfig is stored resolved (an interpolation into a dropped node keeps its value); custom ``drop``;
    non-JSON, non-UTF-8, config-less and missing files raise StoreError."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.create({"paths": {"root": "/data"}, "out": "${paths.root}/run", "keep": {"a": 1}, "b": [1, 2]})
    path = save_config(cfg, tmp_path / "c.json")
    assert json.loads(path.read_text())["config"] == {"out": "/data/run", "keep": {"a": 1}, "b": [1, 2]}
    assert load_config(path).out == "/data/run"
    back = load_config(save_config({"keep": 1, "hydra": 2, "z": 3}, tmp_path / "d.json", drop=("z",)))
    assert OmegaConf.to_container(back) == {"keep": 1, "hydra": 2}
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00{")
    doc = {"cfg": {"a": 1}, "schema_version": 1}
    doc[DIGEST_KEY] = payload_digest(doc)
    (tmp_path / "noconfig.json").write_text(json.dumps(doc))
    (tmp_path / "list.json").write_text("[1, 2]")
    for name, match in (("bad.json", "cannot read"), ("bin.json", "cannot read"), ("noconfig.json", "not a stored"),
                        ("list.json", "not a stored"), ("missing.json", "missing")):  # fmt: skip
        with pytest.raises(StoreError, match=match):
            load_config(tmp_path / name)


# ---------------------------------------------------------------------------------------------- violin data
def _table(generator, methods=("b", "a", "c"), n=6):
    rows = []
    for m in methods:
        for k in range(n):
            rows.append({"method": m, "seed": k, "split": "train" if k % 3 == 0 else "test",
                         "E1": float(torch.rand((), generator=generator, dtype=F64))})  # fmt: skip
    return pd.DataFrame(rows)


def test_metric_columns_numeric_non_key_in_table_order():
    """Only numeric, non-bool, non-key, non-provenance columns, in the table's column order."""
    t = pd.DataFrame({"zeta": [1.0], "method": ["m"], "ok": [True], "alpha": [2], "name": ["x"], "seed": [0],
                      "git_sha": ["abc"], "mid": np.array([1.5], dtype=np.float32), "c": [1 + 2j]})  # fmt: skip
    expected = [c for c in t.columns if c in ("zeta", "alpha", "mid", "c")]
    assert metric_columns(t) == expected == ["zeta", "alpha", "mid", "c"]


def test_violin_levels_categories_and_dropped_rows(generator):
    """Ticks follow first appearance, or the category order without unused categories; rows with a missing hue
    are counted in the warning; a wide table widens a small figure to 0.35 in per level + 1.5 in."""
    t = _table(generator)
    assert [x.get_text() for x in violin(t, "E1").axes[0].get_xticklabels()] == ["b", "a", "c"]
    cat = t.assign(method=pd.Categorical(t["method"], categories=["c", "zz", "a", "b"]))
    assert [x.get_text() for x in violin(cat, "E1").axes[0].get_xticklabels()] == ["c", "a", "b"]
    holes = t.astype({"split": object})
    holes.loc[[1, 4, 7], "split"] = None
    with pytest.warns(RuntimeWarning, match="3 of 18 rows"):
        fig = violin(holes, "E1", hue="split")
    pts = [c for c in fig.axes[0].collections if c.get_gid() == "lfd_torch.mean"][0].get_offsets()
    kept = holes.dropna(subset=["split"])
    expected = [kept[(kept.method == m) & (kept.split == s)]["E1"].mean() for m in ("b", "a", "c")
                for s in ("train", "test")]  # fmt: skip
    np.testing.assert_allclose(np.asarray(pts)[:, 1], expected, rtol=1e-12)
    wide = _table(generator, methods=[f"m{i}" for i in range(9)], n=3)
    assert violin(wide, "E1", figsize=(2.0, 3.0)).get_size_inches()[0] == pytest.approx(0.35 * 9 + 1.5)
    assert violin(wide.query("method != 'm8'"), "E1", figsize=(2.0, 3.0)).get_size_inches()[0] == pytest.approx(2.0)


def test_violin_grid_shares_the_levels_of_the_whole_table(generator):
    """A metric without data for one method still leaves that method's slot in its panel; ``metrics`` must be a
    sequence, titles must match, and arguments the grid sets itself are refused."""
    t = _table(generator)
    t["E2"] = t["E1"] * 2
    t.loc[t.method == "a", "E2"] = np.nan
    with pytest.warns(RuntimeWarning):
        fig = violin_grid(t, ["E1", "E2"])
    assert [[x.get_text() for x in ax.get_xticklabels()] for ax in fig.axes] == [["b", "a", "c"]] * 2
    with pytest.raises(PlotError, match="sequence"):
        violin_grid(t, "E1")
    with pytest.raises(PlotError, match="1 titles for 2 metrics"):
        violin_grid(t, ["E1", "E2"], titles=["x"])
    for key in ("ax", "legend", "title"):
        with pytest.raises(PlotError, match=repr(key)):
            violin_grid(t, ["E1"], **{key: None})


def test_save_figure_formats(generator, tmp_path):
    """The extension picks the format in any case; raster size follows dpi; PDFs carry no creation date; an
    unknown extension is refused before anything is drawn or written."""
    t = _table(generator)
    fig = violin(t, "E1")
    png = save_figure(fig, tmp_path / "A.PNG", dpi=40)
    big = save_figure(fig, tmp_path / "b.png", dpi=80)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    def width(p):
        return int.from_bytes(p.read_bytes()[16:20], "big")

    assert abs(width(big) / width(png) - 2.0) < 0.1
    pdf = save_figure(fig, tmp_path / "c.pdf")
    assert pdf.read_bytes()[:5] == b"%PDF-" and b"CreationDate" not in pdf.read_bytes()
    svg = save_figure(fig, tmp_path / "d.svg")
    assert b"<svg" in svg.read_bytes()[:2000]
    from matplotlib.figure import Figure

    ax = Figure().add_subplot()
    with pytest.raises(PlotError, match="format"):
        violin(t, "E1", ax=ax, path=tmp_path / "e.xyz")
    assert len(ax.collections) == 0 and not (tmp_path / "e.xyz").exists()


def test_check_trials_targeted_paths(scene, arm):
    """Hand-built paths: leaving the can sideways through its wall band counts as left only beyond radius + wall;
    a tip above cup_height over the cup is not over it; a cup visit between two scoops is not after scooping; a
    trial finished at tick 0 is finished."""
    crit = SuccessCriteria()
    can, cup = scene.can, scene.cup
    bottom = scene.table_top + can.wall
    cup_rim = scene.table_top + cup.wall + cup.height
    air = [can.center[0] + 0.2, can.center[1], bottom + can.height + 0.1]
    sugar = [can.center[0], can.center[1], bottom + 0.5 * can.fill]
    band = [can.center[0] + can.radius + 0.5 * can.wall, can.center[1], bottom + can.fill + 0.01]
    outside = [can.center[0] + can.radius + can.wall + 0.002, can.center[1], bottom + can.fill + 0.01]
    over = [cup.center[0], cup.center[1], cup_rim + 0.5 * crit.cup_height]
    too_high = [cup.center[0], cup.center[1], cup_rim + crit.cup_height + 0.005]
    goal = torch.tensor(over, dtype=F64)
    task = _stand_in_task(goal)

    def run(*points):
        tip = torch.tensor(points, dtype=F64)[None]
        T = tip.shape[1]
        q = arm.neutral().expand(1, T, 7)
        return check_trials(task, scene, arm, tip, q, torch.tensor([T]), np.array([T - 1]), [[]], crit)[0]

    assert run(air, sugar, band)["reason"] == "never left the can after scooping"
    assert run(air, sugar, outside)["reason"] == "never above the cup after scooping"
    assert run(air, sugar, air, too_high)["reason"] == "never above the cup after scooping"
    assert run(air, sugar, air, over)["success"]
    assert run(air, sugar, air, over, sugar, air)["reason"] == "never above the cup after scooping"
    # a trial that finished at tick 0 (one sample, at the goal) is finished
    one = check_trials(task, scene, arm, goal[None, None], arm.neutral()[None, None], torch.tensor([1]), np.array([0]),
                       [[]], crit)[0]  # fmt: skip
    assert one["finished"] and one["final_error_mm"] == 0.0 and not one["entered_sugar"]


def test_start_configurations_use_the_first_sample(arm):
    """The ring is centred on the demonstration's first tip, with its first orientation and IK seed, not a later
    sample's."""
    qa = arm.neutral()
    qb = qa + torch.tensor([0.3, 0.2, -0.2, -0.3, 0.4, 0.3, 0.5], dtype=F64)
    pose = arm.forward_kinematics(torch.stack([qa, qb]))
    demo = SimpleNamespace(tip=pose[:, :3, 3], rotation=pose[:, :3, :3], q=torch.stack([qa, qb]))
    qs = start_configurations(SimpleNamespace(demonstration=demo), arm, 3, radius=0.05, height=0.0)
    got = arm.forward_kinematics(qs)
    centre = got[:, :3, 3].mean(0)  # the ring's three points are spaced 120 degrees apart
    np.testing.assert_allclose(centre.numpy(), pose[0, :3, 3].numpy(), atol=1e-5)
    np.testing.assert_allclose(got[:, :3, :3].numpy(), pose[0, :3, :3].expand(3, 3, 3).numpy(), atol=1e-4)


def test_jump_target_low_beside_the_cup(arm, scene):
    """A tip 6 cm above the table beside the cup: for several seeds the jump lands on the reference's first
    candidate, which skips points under the 3 cm table band and paths through the cup wall."""
    from lfd_torch.robot import solve_ik

    q_seed = torch.tensor([0.1, -0.45, 0.0, 1.35, 0.0, 0.75, 0.0], dtype=F64)
    R = arm.forward_kinematics(q_seed[None])[0, :3, :3]
    x = torch.tensor([scene.cup.center[0], scene.cup.center[1] - 0.075, scene.table_top + 0.06], dtype=F64)
    q0 = solve_ik(arm, x[None], R[None], q_seed[None])[0]
    x = arm.forward_kinematics(q0[None])[0, :3, 3]
    train = (x + 0.5)[None].float()
    engine = _Engine(x, train)
    free = SimpleNamespace(scene=scene, contacts_at=lambda q: [])
    skipped = {"band": 0, "wall": 0}
    for seed in range(6):
        d = Disturbance("jump", 1, 0.1, 0.05, "small")
        q, why = trials_module._jump_target(free, arm, engine, None, q0, x, R, 1, d,
                                            torch.Generator().manual_seed(seed), 0.005, 12)  # fmt: skip
        j, land = _reference_landing(scene, x.tolist(), 0.05, "small", seed, 12, train.double(), 0.005)
        dirs = torch.randn(12, 3, generator=torch.Generator().manual_seed(seed), dtype=F64)
        lands = x + 0.05 * dirs / dirs.norm(dim=-1, keepdim=True)
        first = (lands[:, 0] >= x[0]).nonzero().flatten().tolist()  # label-valid candidates, in order
        if j is None:
            assert q is None
            continue
        earlier = [k for k in first if k < j]
        skipped["band"] += sum(float(lands[k, 2]) <= scene.table_top + 0.03 for k in earlier)
        skipped["wall"] += sum(_naive_crosses(scene, x.tolist(), lands[k : k + 1])[0] for k in earlier)
        assert q is not None, why
        np.testing.assert_allclose(arm.forward_kinematics(q[None])[0, :3, 3].numpy(), land, atol=2e-3)
    assert skipped["band"] > 0 and skipped["wall"] > 0
