"""References for :func:`lfd_torch.robot.trials.run_trials`: MuJoCo rollouts checked against properties that do not
reuse its bookkeeping.

One module-level batch of six trials (14-19 s simulated each, all rows finish at different ticks) is the shared
material: rows are independent (a row run alone, with its ``trial_offset``, equals the batch row), a disturbance
changes nothing before it acts, a force pulse lasts the documented number of ticks, the firing sample, the label,
the displacement and the frozen tail of the logs follow from the logs themselves, a skipped jump leaves the trial
undisturbed, and a forked run equals the prefix of the serial one.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from lfd_torch.robot import build_robot, scooping_demonstration
from lfd_torch.robot.task import controller_for, learn_scooping
from lfd_torch.robot.trials import Disturbance, SuccessCriteria, run_trials, start_configurations
from lfd_torch.utils import derive_seed

BUDGET = 21.0  # every row finishes within it (the slowest, the pushed row 1, at 18.5 s)
SEED = 5
DT = 0.01
# rows: (start index, disturbance); the delays and durations sit half a tick off the 10 ms grid
ROWS = [
    (6, None),
    (6, Disturbance("force", 1, 0.305, 30.0, duration=0.105, body="left_wrist", direction=(0.0, 0.0, 1.0))),
    (6, Disturbance("force", 1, 0.305, 30.0, duration=0.205, body="left_wrist", direction=(0.0, 0.0, 1.0))),
    (0, Disturbance("jump", 1, 0.305, 0.015, "small")),
    (1, Disturbance("force", 2, 0.505, 80.0, duration=0.105, body="left_lower_forearm", direction=(0.0, 1.0, 0.0))),
    (2, Disturbance("jump", 0, 0.305, 5.0, "large")),  # 5 m: no reachable landing state, the jump is skipped
]


@pytest.fixture(scope="module")
def setup():
    task = learn_scooping(scooping_demonstration(0), generator=torch.Generator().manual_seed(0))
    robot = build_robot(velocity_map={"null_space": "exact"})
    ctl = controller_for(task, robot, "full")
    starts = start_configurations(task, robot.arm, 7)
    q0 = starts[[i for i, _ in ROWS]]
    dist = [d for _, d in ROWS]
    ticks = []
    res = run_trials(task, ctl, robot.plant, q0, disturbances=dist, budget_s=BUDGET, jump_seed=SEED,
                     progress=SimpleNamespace(update=ticks.append))  # fmt: skip
    return SimpleNamespace(task=task, robot=robot, ctl=ctl, q0=q0, dist=dist, res=res, ticks=ticks)


def _stage_entry(s, i, stage):
    L = int(s.res.lengths[i])
    stages = s.task.step_stage[s.res.steps[i, :L]]
    return int(torch.nonzero(stages == stage)[0])


def _first_diff(a, b, tol=1e-9):
    d = (a - b).norm(dim=-1)
    idx = torch.nonzero(d > tol)
    return int(idx[0]) if idx.numel() else None


def test_disturbances_fire_at_the_documented_sample(setup):
    """A disturbance fires at the first tick whose time is at least ``delay`` after the tick at which the trial
    entered the disturbance's stage (read from the logged steps); ``fired_s`` is that sample times dt."""
    s = setup
    for i in (1, 2, 3, 4):
        d = s.dist[i]
        e = _stage_entry(s, i, d.stage)
        k = e + math.ceil(d.delay / DT)  # delay half a tick off the grid: no rounding question
        assert int(s.res.disturbance_sample[i]) == k, i
        assert s.res.rows[i]["fired_s"] == pytest.approx(k * DT)
        assert s.res.rows[i]["disturbance"] == d.kind
    assert int(s.res.disturbance_sample[0]) == -1


def test_a_force_changes_nothing_before_it_acts_and_lasts_its_duration(setup):
    """Causality and pulse length: the pushed rows equal the undisturbed row (same start) through the firing
    sample k and differ at k + 1; the 0.105 s and 0.205 s pulses act in ticks k .. k + 10 and k .. k + 20, so their
    logs agree through sample k + 11 and differ at k + 12."""
    s = setup
    k = int(s.res.disturbance_sample[1])
    assert int(s.res.disturbance_sample[2]) == k
    tip = s.res.tip
    assert _first_diff(tip[0], tip[1]) == k + 1
    assert _first_diff(tip[0], tip[2]) == k + 1
    assert _first_diff(tip[1], tip[2]) == k + 12


def test_force_label_and_displacement_follow_from_the_logs(setup):
    """A force's label is the engine's test at the tip when the pulse ends (first sample at or after fire +
    duration) for the step active before it; the displacement is the largest tip distance from the firing tip up to
    duration + 0.5 s after firing."""
    s = setup
    for i in (1, 2, 4):
        d, row = s.dist[i], s.res.rows[i]
        k = int(s.res.disturbance_sample[i])
        end = k + math.ceil(d.duration / DT)
        own, other = s.ctl.engine.own_other(s.res.tip[i, end : end + 1], s.res.steps[i, end - 1 : end])
        assert row["label"] == ("large" if bool(own[0] < other[0]) else "small"), i
        last = k + math.floor((d.duration + 0.5) / DT)
        ref = float((s.res.tip[i, k : last + 1] - s.res.tip[i, k]).norm(dim=-1).max()) * 1e3
        assert row["displacement_mm"] == pytest.approx(ref, rel=1e-9, abs=1e-9), i
    assert s.res.rows[4]["displacement_mm"] > 3.0  # 80 N sideways moves the tip


def test_small_jump_lands_as_requested(setup):
    """A small jump moves the tip by its magnitude (+ one tick of motion, 2 mm IK tolerance) to a point inside the
    active step's subtask space and at least ``away`` from that step's training positions; it lands at rest with the
    set-point moved along (nothing pulls it back to the pre-jump state): the first tick after the jump moves the tip
    less than the last tick before it."""
    s = setup
    k = int(s.res.disturbance_sample[3])
    assert k > 0 and s.res.rows[3]["label"] == "small" and s.res.rows[3]["note"] == ""
    land = s.res.tip[3, k]
    assert float((land - s.res.tip[3, k - 1]).norm()) == pytest.approx(0.015, abs=4e-3)
    m = s.res.steps[3, k - 1]
    assert int(s.task.step_stage[m]) == 1
    own, other = s.ctl.engine.own_other(land[None], m[None])
    assert bool(own[0] >= other[0])
    train = s.ctl.engine.library.skills[int(m)].train_positions.to(land)
    assert float((train - land).norm(dim=-1).min()) >= 0.005 - 2e-3
    after = float((s.res.tip[3, k + 1] - land).norm())
    before = float((s.res.tip[3, k - 1] - s.res.tip[3, k - 2]).norm())
    assert after < before, (after, before)


def test_skipped_jump_is_reported_as_no_disturbance(setup):
    """An unreachable jump is skipped: no firing sample, ``disturbance`` none, no label, the reason in ``note``."""
    row = setup.res.rows[5]
    assert int(setup.res.disturbance_sample[5]) == -1 and math.isnan(row["fired_s"])
    assert row["disturbance"] == "none" and row["label"] == "none" and row["requested"] == "large"
    assert row["note"].startswith("jump skipped: ")


def test_logs_freeze_after_finishing_and_progress_counts_ticks(setup):
    """Every row finished: ``lengths`` is the finishing sample + 1, the logs repeat the last valid sample after it,
    the undisturbed row ends at the final attractor; ``progress.update(1)`` was called once per tick run."""
    s = setup
    r = s.res
    T = int(round(BUDGET / DT)) + 1
    assert r.tip.shape[1] == T
    for i in range(len(ROWS)):
        L = int(r.lengths[i])
        assert L < T and r.rows[i]["finished_s"] == pytest.approx((L - 1) * DT)
        assert torch.equal(r.tip[i, L:], r.tip[i, L - 1].expand(T - L, 3))
        assert torch.equal(r.steps[i, L:], r.steps[i, L - 1].expand(T - L))
        assert torch.equal(r.q[i, L:], r.q[i, L - 1].expand(T - L, 7))
    assert r.rows[0]["success"] and r.rows[5]["success"]
    final = s.task.library.attractors[s.task.library.routes[0][-1]].to(r.tip)
    assert float((r.tip[0, int(r.lengths[0]) - 1] - final).norm()) < SuccessCriteria().final_tol
    assert s.ticks == [1] * int(r.lengths.max())


def test_forked_run_equals_the_serial_prefix(setup):
    """A forked run (more workers than trials) with ``trial_offset`` equals the first samples of the serial batch
    rows with the same jump-seed index: the budget only truncates, the jump row (in the second worker) draws the
    same directions; progress gets the number of samples."""
    s = setup
    budget = 3.0
    T = int(round(budget / DT)) + 1
    ticks = []
    two = run_trials(s.task, s.ctl, s.robot.plant, s.q0[[2, 3]], disturbances=[s.dist[2], s.dist[3]],
                     budget_s=budget, jump_seed=SEED, trial_offset=2, workers=5,
                     progress=SimpleNamespace(update=ticks.append))  # fmt: skip
    assert int(s.res.disturbance_sample[3]) < T - 5  # the jump happens inside the short run
    torch.testing.assert_close(two.tip, s.res.tip[2:4, :T], atol=1e-9, rtol=0)
    assert torch.equal(two.steps, s.res.steps[2:4, :T])
    assert two.disturbance_sample.tolist() == s.res.disturbance_sample[2:4].tolist()
    assert [r["trial"] for r in two.rows] == [0, 1]
    assert [r["label"] for r in two.rows] == [r["label"] for r in s.res.rows[2:4]]
    assert sum(ticks) == T
    # the seed index of the jump row is trial_offset + 1 = 3: another offset draws other directions
    g3 = torch.randn(4, 3, generator=torch.Generator().manual_seed(derive_seed("jump", SEED, 3)), dtype=torch.float64)
    g1 = torch.randn(4, 3, generator=torch.Generator().manual_seed(derive_seed("jump", SEED, 1)), dtype=torch.float64)
    assert not torch.equal(g3, g1)


def test_every_row_equals_the_row_run_alone(setup):
    """Rows are independent: each row run alone (same seed, ``trial_offset`` = its index) gives the batch row's
    logs, lengths and verdict, although the batch rows finish at different ticks; a skipped jump gives the
    undisturbed trial."""
    s = setup
    assert len(set(s.res.lengths.tolist())) > 2  # rows leave the batch at different ticks
    for i in (0, 3, 4, 5):
        d = [None] if i == 5 else s.dist[i : i + 1]
        one = run_trials(s.task, s.ctl, s.robot.plant, s.q0[i : i + 1], disturbances=d, budget_s=BUDGET,
                         jump_seed=SEED, trial_offset=i)  # fmt: skip
        L = int(one.lengths[0])
        assert L == int(s.res.lengths[i]), i
        torch.testing.assert_close(s.res.tip[i], one.tip[0], atol=1e-9, rtol=0)
        torch.testing.assert_close(s.res.q[i], one.q[0], atol=1e-5, rtol=0)
        assert torch.equal(s.res.steps[i], one.steps[0]) and torch.equal(s.res.branches[i], one.branches[0])
        for key in ("success", "reason", "label", "finished_s", "contacts"):
            a, b = s.res.rows[i][key], one.rows[0][key]
            assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), (i, key)
        if i != 5:
            assert int(one.disturbance_sample[0]) == int(s.res.disturbance_sample[i])
