"""Batched scooping trials on the MuJoCo plant: start configurations, disturbances, success checks (issue 10).

:func:`run_trials` runs B trials at once: one :meth:`~lfd_torch.robot.BaxterPlant.fork` per trial (one ``MjData``
each), one :class:`~lfd_torch.robot.task.ScoopingController` step for all running trials every 10 ms tick (the
engine's ``step_batch``, the batched pytorch-kinematics Jacobian), then 10 physics steps (1 kHz) per trial.

Disturbances (:class:`Disturbance`, at most one per trial, fired a delay after the trial enters the target stage):

* ``force``: an external force pulse of ``magnitude`` N on the forearm, hand or spoon body for ``duration`` s, in a
  random direction (MuJoCo ``xfrc_applied``);
* ``jump``: a position jump; the joints are teleported to a state at rest whose tip lies ``magnitude`` m from the
  current tip, in the first of ``n_candidates`` random directions whose landing point satisfies the requested
  label and whose joint state (IK from the current q, same spoon orientation) is within the limits and touches
  nothing.

Labels (the engine's own test at the landing point, x = the tip when a jump lands or when a force pulse ends):
``large`` when x lies outside the active step's subtask space A_m (log p(x|A_m) < log p(x|A_m-)), ``small`` when
it lies inside A_m; a small jump must also land at least ``away`` m from the step's training positions.

Success (:class:`SuccessCriteria`, checked per trial; the first failed check is the stored reason): the tip went
more than ``sugar_depth`` m inside the sugar (the least of its depth below the surface, its distance inside the can
wall and its height above the bottom: :func:`sugar_depth`) and later left the can (above its rim or outside
its wall); it then
reached the region above the cup (within the cup radius, between the rim and ``cup_height`` m above it); no contact
of spoon, hand or arm with the can walls, the cup walls or the table at any time of the trial, whatever caused it (a
force pulse that shoves the spoon into the wall fails the trial as any other contact does); joint limits held
(``limit_tol`` rad); the engine finished the task within the time budget, ending within ``final_tol`` m of the final
attractor.

Diagnostic only (never part of ``success``): contacts that begin while a force pulse acts or within
``push_grace`` s after it are also listed in ``push_contacts``, and ``lenient_success`` is the verdict that would
excuse them (the former, lenient rule); it shows how many failures a push causes directly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError, UnknownNameError
from lfd_torch.robot.arm import BaxterArm
from lfd_torch.robot.demonstration import STAGE_NAMES, solve_ik
from lfd_torch.robot.plant import LINK_BODIES, BaxterPlant, Scene
from lfd_torch.robot.task import ScoopingController, ScoopingTask
from lfd_torch.utils import check_choice, check_float, check_generator, check_int, derive_seed

__all__ = [
    "DISTURBANCE_KINDS",
    "FORBIDDEN_CONTACTS",
    "Disturbance",
    "SuccessCriteria",
    "TrialBatch",
    "plan_disturbances",
    "run_trials",
    "start_configurations",
    "sugar_depth",
    "check_trials",
    "wilson_interval",
]

DISTURBANCE_KINDS = ("force", "jump")
FORBIDDEN_CONTACTS = ("can_wall", "cup_wall", "table")
FORCE_BODIES = ("left_lower_elbow", "left_upper_forearm", "left_lower_forearm", "left_wrist")
#: Bodies of the plant a force may act on: the arm's links and the spoon.
DISTURBANCE_BODIES = tuple(b.link for b in LINK_BODIES) + ("spoon",)


@dataclass(frozen=True)
class Disturbance:
    """One disturbance of a trial (module docstring).

    Attributes:
        kind: ``force`` or ``jump``.
        stage: generator stage in which it acts (0 approach, 1 scoop, 2 transport).
        delay: s after the trial enters that stage.
        magnitude: N (force) or m (jump).
        label: requested label of a jump, ``large`` or ``small`` (forces: the label is measured, this is ignored).
        duration: s (force pulse).
        body: body the force acts on.
        direction: (3,) unit direction of a force.
    """

    kind: str
    stage: int
    delay: float
    magnitude: float
    label: str = "large"
    duration: float = 0.3
    body: str = "left_hand"
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        check_choice(self.kind, "disturbance kind", DISTURBANCE_KINDS)
        check_choice(self.label, "disturbance label", ("large", "small"))
        check_choice(self.body, "disturbance body", DISTURBANCE_BODIES)
        check_int(self.stage, "stage", low=0, high=len(STAGE_NAMES) - 1)
        for name in ("delay", "magnitude", "duration"):
            check_float(getattr(self, name), name, low=0.0)
        d = self.direction
        if not (isinstance(d, (tuple, list)) and len(d) == 3):
            raise InvalidArgumentError(f"direction must be 3 numbers (a unit vector), got {d!r}")
        norm = math.sqrt(sum(check_float(v, "direction") ** 2 for v in d))
        if abs(norm - 1.0) > 1e-6:
            raise InvalidArgumentError(f"direction must be a unit vector, got {d!r} (norm {norm:.6g})")


def plan_disturbances(
    n_trials: int,
    generator: torch.Generator,
    *,
    kinds: Sequence[str] = DISTURBANCE_KINDS,
    stages: Sequence[int] = (0, 1, 2),
    force_large: tuple[float, float] = (60.0, 90.0),
    force_small: tuple[float, float] = (15.0, 30.0),
    jump_large: tuple[float, float] = (0.05, 0.10),
    jump_small: tuple[float, float] = (0.01, 0.025),
    duration: tuple[float, float] = (0.2, 0.4),
    delay_fraction: tuple[float, float] = (0.15, 0.6),
    stage_durations: Sequence[float] = (3.0, 4.0, 6.0),
) -> list[Disturbance]:
    """One disturbance per trial, cycling through (stage, kind, strength) so every combination gets its share.

    ``force_*`` N, ``jump_*`` m, ``duration`` s: uniform ranges; a force's ``large``/``small`` range is a request
    only (its label is measured). The delay is ``delay_fraction`` (uniform) of the stage's nominal duration
    ``stage_durations`` (s).
    """
    if isinstance(n_trials, bool) or not isinstance(n_trials, int) or n_trials < 0:
        raise InvalidArgumentError(f"n_trials must be an int >= 0, got {n_trials!r}")
    check_generator(generator, where="plan_disturbances")
    for name, rng, low in (("force_large", force_large, 0.0), ("force_small", force_small, 0.0),
                           ("jump_large", jump_large, 0.0), ("jump_small", jump_small, 0.0),
                           ("duration", duration, 0.0), ("delay_fraction", delay_fraction, 0.0)):
        if not (isinstance(rng, (tuple, list)) and len(rng) == 2):
            raise InvalidArgumentError(f"{name} must be a (low, high) pair, got {rng!r}")
        lo = check_float(rng[0], f"{name}[0]", low=low)
        check_float(rng[1], f"{name}[1]", low=lo)
    for j, v in enumerate(stage_durations):
        check_float(v, f"stage_durations[{j}]", low=0.0)
    if not kinds or any(k not in DISTURBANCE_KINDS for k in kinds):
        raise InvalidArgumentError(f"kinds must name at least one of {DISTURBANCE_KINDS}, got {tuple(kinds)!r}")
    if not stages or any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < len(stage_durations)
                         for s in stages):
        raise InvalidArgumentError(f"stages must name at least one stage in 0..{len(stage_durations) - 1} "
                                   f"(one per stage duration), got {tuple(stages)!r}")
    combos = [(s, k, lab) for s in stages for k in kinds for lab in ("large", "small")]

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=generator, dtype=torch.float64))

    out = []
    for i in range(n_trials):
        s, k, lab = combos[i % len(combos)]
        if k == "force":
            mag = u(*(force_large if lab == "large" else force_small))
        else:
            mag = u(*(jump_large if lab == "large" else jump_small))
        d = torch.randn(3, generator=generator, dtype=torch.float64)
        d = d / d.norm()
        body = FORCE_BODIES[int(torch.randint(len(FORCE_BODIES), (), generator=generator))]
        out.append(Disturbance(k, int(s), u(*delay_fraction) * stage_durations[s], mag, lab, u(*duration), body,
                               tuple(d.tolist())))  # fmt: skip
    return out


@dataclass(frozen=True)
class SuccessCriteria:
    """Thresholds of the per-trial success checks (module docstring); lengths m, angles rad, time s.

    Every contact of the robot with an object in ``forbidden`` fails ``no_contact``, also one that a force pulse
    causes. ``push_grace`` only sets the diagnostic attribution: a contact that begins while a force pulse acts
    or ``push_grace`` s after it (and lasts without a break) is listed in ``push_contacts``, and
    ``lenient_success`` would excuse it; ``success`` does not.
    """

    sugar_depth: float = 0.005
    cup_height: float = 0.12
    cup_margin: float = 0.005
    limit_tol: float = 0.005
    final_tol: float = 0.01
    forbidden: tuple[str, ...] = FORBIDDEN_CONTACTS
    push_grace: float = 0.2


@dataclass(eq=False)
class TrialBatch:
    """Results of :func:`run_trials`.

    Attributes:
        rows: one dict per trial: success, reason, the checks, time to finish (s), disturbance and its label,
            ``contacts`` (every robot-scene contact pair seen), ``push_contacts`` (those a force pulse began) and
            ``lenient_success`` (diagnostic: the verdict that excuses ``push_contacts``; not the success rate).
        tip: (B, T, 3) tip positions at 100 Hz (m); lengths: (B,) valid samples (frozen after finishing).
        q: (B, T, 7) joint angles (rad); steps: (B, T) long active step; branches: (B, T) int8 branch.
        disturbance_sample: (B,) long sample at which the disturbance started (-1: none).
        dt: s between samples.
    """

    rows: list[dict[str, Any]]
    tip: Tensor
    q: Tensor
    lengths: Tensor
    steps: Tensor
    branches: Tensor
    disturbance_sample: Tensor
    dt: float
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def success(self) -> Tensor:
        return torch.tensor([bool(r["success"]) for r in self.rows])


def start_configurations(
    task: ScoopingTask, arm: BaxterArm, n: int = 7, *, radius: float = 0.08, height: float = 0.04
) -> Tensor:
    """(n, 7) joint angles of ``n`` start configurations spread in the start area (paper Fig. 14): tips on a ring of
    ``radius`` m about the demonstration's start, heights within +- ``height`` m, the demonstration's starting
    spoon orientation, IK from its first joint state."""
    demo = task.demonstration
    if demo.q is None or demo.rotation is None:
        raise InvalidArgumentError("the task's demonstration has no joint angles")
    k = torch.arange(n, dtype=torch.float64)
    theta = 2 * math.pi * k / n
    x0 = demo.tip[0].double()
    tips = x0 + torch.stack([radius * torch.cos(theta), radius * torch.sin(theta), height * torch.sin(2 * theta)], -1)
    rot = demo.rotation[0].double().expand(n, 3, 3)
    return solve_ik(arm, tips, rot, demo.q[0].double().expand(n, 7).clone())


def _read(plants: Sequence[BaxterPlant], rows: Sequence[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    q = np.stack([plants[i].data.qpos[plants[i].qpos_adr] for i in rows])
    x = np.stack([plants[i].data.site_xpos[plants[i].tip_site] for i in rows])
    r = np.stack([plants[i].data.site_xmat[plants[i].tip_site].reshape(3, 3) for i in rows])
    return q, x, r


def _crosses_walls(scene: Scene, x: Tensor, land: Tensor, margin: float = 0.02, n: int = 32) -> Tensor:
    """(C,) bool: the straight tip path from ``x`` (3,) to ``land`` (C, 3) passes within ``margin`` m of a vessel
    wall (below its rim + margin): a jump cannot carry the spoon through the can or the cup."""
    s = torch.linspace(0.0, 1.0, n, dtype=x.dtype)
    path = x + s[None, :, None] * (land - x)[:, None, :]  # (C, n, 3)
    hit = torch.zeros(land.shape[0], dtype=torch.bool)
    for v in (scene.can, scene.cup):
        c = torch.tensor(v.center, dtype=x.dtype)
        r = (path[..., :2] - c).norm(dim=-1)
        rim = scene.table_top + v.wall + v.height
        near = ((r - v.radius - v.wall / 2).abs() < margin) & (path[..., 2] < rim + margin)
        hit |= near.any(-1)
    return hit


def _jump_target(
    plant: BaxterPlant, arm: BaxterArm, engine: Any, task: ScoopingTask, q: Tensor, x: Tensor, R: Tensor,
    step: int, dist: Disturbance, generator: torch.Generator, away: float, n_candidates: int,
) -> tuple[Tensor | None, str]:
    """Joint angles of a jump (or None) and the reason of a skipped jump."""
    dirs = torch.randn(n_candidates, 3, generator=generator, dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    land = x[None] + dist.magnitude * dirs
    st = torch.full((n_candidates,), step, dtype=torch.long)
    own, other = engine.own_other(land, st)
    train = engine.library.skills[step].train_positions
    near = torch.cdist(land, train.to(land)).amin(-1)
    sc = plant.scene
    ok = (land[:, 2] > sc.table_top + 0.03) & ~_crosses_walls(sc, x, land)
    ok &= (own < other) if dist.label == "large" else ((own >= other) & (near >= away))
    if not bool(ok.any()):
        return None, f"no {dist.label} landing point among {n_candidates} directions"
    cand = torch.nonzero(ok).flatten()
    qs = solve_ik(arm, land[cand], R.expand(cand.numel(), 3, 3), q.expand(cand.numel(), 7).clone(),
                  iterations=100, strict=False)  # fmt: skip
    pose = arm.forward_kinematics(qs)
    err = (pose[:, :3, 3] - land[cand]).norm(dim=-1)
    for j in range(cand.numel()):
        if float(err[j]) > 2e-3 or not bool(arm.within_limits(qs[j]).item()):
            continue
        if plant.contacts_at(qs[j].numpy()):
            continue
        return qs[j], ""
    return None, "no reachable collision-free landing state"


def run_trials(
    task: ScoopingTask,
    controller: ScoopingController,
    plant: BaxterPlant,
    q0: Tensor,
    *,
    disturbances: Sequence[Disturbance | None] | None = None,
    budget_s: float = 30.0,
    jump_seed: int = 0,
    criteria: SuccessCriteria | None = None,
    away: float = 0.005,
    n_candidates: int = 128,
    progress: Any = None,
    workers: int = 1,
    trial_offset: int = 0,
) -> TrialBatch:
    """Run B trials from the joint states ``q0`` (B, 7) rad (module docstring).

    Args:
        task: the learned task; controller: its controller (engine mode decides the modulation).
        plant: the template plant; every trial runs on its own :meth:`~lfd_torch.robot.BaxterPlant.fork`.
        disturbances: B entries (None: undisturbed trial), or None for no disturbances.
        budget_s: time budget of a trial (s).
        jump_seed: seed of the jump directions; trial i draws them from its own generator (seeded from
            (``jump_seed``, i)), so the same trial gets the same candidate directions in every mode.
        criteria: success thresholds. away: a small jump's least distance to the step's training data (m).
        progress: optional tqdm-like object with ``update(n)`` called once per tick.
        workers: processes (``fork``) that split the trials; each runs its share with one torch thread, the
            results are merged in trial order and equal those of ``workers=1`` up to rounding (the batched
            engine's last bits depend on how many trials share a batch; its grouped path for >= 256 rows and its
            per-row path agree to rounding).
        trial_offset: index of the first trial (seeds the jump directions of trial ``trial_offset + i``).
    """
    if not isinstance(q0, Tensor) or q0.ndim != 2 or q0.shape[1] != 7:
        raise ShapeMismatchError(f"q0 must have shape (B, 7), got {getattr(q0, 'shape', None)}")
    B = q0.shape[0]
    dist = list(disturbances) if disturbances is not None else [None] * B
    if len(dist) != B:
        raise ShapeMismatchError(f"{len(dist)} disturbances for {B} trials")
    if isinstance(jump_seed, bool) or not isinstance(jump_seed, int):
        raise InvalidArgumentError(f"jump_seed must be an int, got {jump_seed!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidArgumentError(f"workers must be an int >= 1, got {workers!r}")
    if workers > 1 and B > 1:
        kw = dict(budget_s=budget_s, jump_seed=jump_seed, criteria=criteria, away=away, n_candidates=n_candidates)
        return _run_forked(task, controller, plant, q0, dist, kw, min(workers, B), trial_offset, progress)
    crit = SuccessCriteria() if criteria is None else criteria
    arm = controller.velocity_map.arm
    engine = controller.engine
    dt = plant.control_period
    n_ticks = int(round(budget_s / dt))
    f64 = torch.float64
    plants = [plant.fork() for _ in range(B)]
    for p, q in zip(plants, q0.double().numpy()):
        p.reset(q)
    step_stage = task.step_stage
    route = torch.full((B,), -1, dtype=torch.long)
    index = torch.zeros(B, dtype=torch.long)
    q_d = torch.as_tensor(q0, dtype=f64).clone()
    running = np.ones(B, dtype=bool)
    finished_at = np.full(B, -1)
    T = n_ticks + 1
    tip_log = torch.zeros(B, T, 3, dtype=f64)
    q_log = torch.zeros(B, T, 7, dtype=torch.float32)  # float32 keeps 500 trials x 40 s in memory
    step_log = torch.zeros(B, T, dtype=torch.long)
    branch_log = torch.zeros(B, T, dtype=torch.int8)
    contacts: list[list[tuple[str, str, float]]] = [[] for _ in range(B)]  # every contact (p, o, t)
    push_contacts: list[list[tuple[str, str, float]]] = [[] for _ in range(B)]  # those a force pulse began (diagnostic)
    pushed_pairs: list[set[tuple[str, str]]] = [set() for _ in range(B)]
    stage_now = torch.zeros(B, dtype=torch.long)
    stage_since = np.zeros(B)
    fired = np.zeros(B, dtype=bool)
    fire_sample = np.full(B, -1)
    force_until = np.full(B, -1.0)
    origin = np.full((B, 3), np.nan)  # tip when the disturbance started
    displacement = np.zeros(B)  # largest tip distance from it within the pulse (or the jump) + 0.5 s (m)
    labels: list[str | None] = [None] * B
    notes: list[str] = [""] * B
    lengths = np.full(B, T)
    for k in range(T):
        t = k * dt
        rows = np.flatnonzero(running)
        rt = torch.from_numpy(rows)
        if rows.size == 0:
            lengths[:] = np.where(finished_at >= 0, finished_at + 1, T)
            break
        qn, xn, rn = _read(plants, rows)
        q, x, R = (torch.from_numpy(a) for a in (qn, xn, rn))
        # disturbances: forces ending, new ones firing
        for j, i in enumerate(rows.tolist()):
            d = dist[i]
            if force_until[i] >= 0 and t >= force_until[i]:
                plants[i].clear_forces()
                force_until[i] = -1.0
                st = torch.tensor([int(step_log[i, max(k - 1, 0)])])
                own, other = engine.own_other(x[j : j + 1], st)
                labels[i] = "large" if bool(own[0] < other[0]) else "small"
            if d is None or fired[i] or int(stage_now[i]) != d.stage or t - stage_since[i] < d.delay:
                continue
            fired[i] = True
            fire_sample[i] = k
            origin[i] = xn[j]
            if d.kind == "force":
                plants[i].apply_force(d.body, np.asarray(d.direction) * d.magnitude)
                force_until[i] = t + d.duration
            else:
                m = int(step_log[i, max(k - 1, 0)])
                gen = torch.Generator().manual_seed(derive_seed("jump", jump_seed, trial_offset + i))
                q_new, why = _jump_target(plants[i], arm, engine, task, q[j], x[j], R[j], m, d, gen, away,
                                          n_candidates)  # fmt: skip
                if q_new is None:
                    notes[i] = f"jump skipped: {why}"
                    fire_sample[i] = -1
                    continue
                plants[i].teleport(q_new.numpy())
                labels[i] = d.label
                q_d[i] = q_new
                qj, xj, rj = _read(plants, [i])
                q[j], x[j], R[j] = torch.from_numpy(qj[0]), torch.from_numpy(xj[0]), torch.from_numpy(rj[0])
        ctl = controller.command(q, x, R, route[rt], index[rt], q_d[rt])
        dec = ctl.decision
        route[rt], index[rt] = dec.route, dec.index
        q_d[rt] = ctl.q_d
        tip_log[rt, k], q_log[rt, k] = x, q.float()
        step_log[rt, k], branch_log[rt, k] = dec.step, ctl.branch
        new_stage = step_stage[dec.step]
        changed = (new_stage != stage_now[rt]).numpy()
        stage_since[rows[changed]] = t
        stage_now[rt] = new_stage
        done = dec.done.numpy()
        for j, i in enumerate(rows.tolist()):
            if fire_sample[i] >= 0 and t <= fire_sample[i] * dt + (dist[i].duration if dist[i].kind == "force" else 0.0) + 0.5:
                displacement[i] = max(displacement[i], float(np.linalg.norm(x[j].numpy() - origin[i])))
            c = set(plants[i].contacts())
            if c or pushed_pairs[i]:
                pushing = force_until[i] >= 0 or (fire_sample[i] >= 0 and dist[i].kind == "force"
                                                  and t < fire_sample[i] * dt + dist[i].duration + crit.push_grace)
                # diagnostic attribution: a contact that starts while the push acts is the push's, until it ends
                pushed_pairs[i] = (c if pushing else c & pushed_pairs[i])
                push_contacts[i].extend((p, o, t) for p, o in pushed_pairs[i])
                contacts[i].extend((p, o, t) for p, o in c)
            if done[j]:
                running[i] = False
                finished_at[i] = k
                continue
            plants[i].set_command(ctl.q_d[j].numpy(), ctl.qd_d[j].numpy())
            plants[i].step()
        if progress is not None:
            progress.update(1)
    else:
        lengths[:] = np.where(finished_at >= 0, finished_at + 1, T)
    lengths_t = torch.as_tensor(lengths, dtype=torch.long)
    # freeze the logs after the last valid sample
    idx = torch.minimum(torch.arange(T)[None, :], (lengths_t - 1)[:, None])
    tip_log = tip_log.gather(1, idx[..., None].expand(B, T, 3))
    q_log = q_log.gather(1, idx[..., None].expand(B, T, 7))
    step_log = step_log.gather(1, idx)
    branch_log = branch_log.gather(1, idx)
    checks = check_trials(task, plant.scene, arm, tip_log, q_log, lengths_t, finished_at, contacts, crit,
                          push_contacts=push_contacts, dt=dt)  # fmt: skip
    rows_out = []
    for i in range(B):
        d = dist[i]
        row = dict(checks[i])
        row.update(trial=i, finished_s=float(finished_at[i] * dt) if finished_at[i] >= 0 else math.nan,
                   disturbance=d.kind if d is not None and fire_sample[i] >= 0 else "none",
                   requested=d.label if d is not None else "none",
                   label=labels[i] if labels[i] is not None else "none",
                   stage=STAGE_NAMES[d.stage] if d is not None else "none",
                   magnitude=d.magnitude if d is not None else 0.0,
                   fired_s=float(fire_sample[i] * dt) if fire_sample[i] >= 0 else math.nan, note=notes[i],
                   displacement_mm=float(displacement[i]) * 1e3,
                   push_contacts=";".join(sorted({f"{p}-{o}" for p, o, _ in push_contacts[i]})))  # fmt: skip
        rows_out.append(row)
    return TrialBatch(rows_out, tip_log, q_log, lengths_t, step_log, branch_log,
                      torch.as_tensor(fire_sample, dtype=torch.long), dt)  # fmt: skip


_FORK_ARGS: dict[str, Any] = {}


def _forked_part(bounds: tuple[int, int]) -> TrialBatch:
    a, b = bounds
    f = _FORK_ARGS
    torch.set_num_threads(1)
    return run_trials(f["task"], f["controller"], f["plant"], f["q0"][a:b], disturbances=f["dist"][a:b],
                      trial_offset=f["offset"] + a, **f["kw"])  # fmt: skip


def _run_forked(task, controller, plant, q0, dist, kw, workers, offset, progress) -> TrialBatch:
    """:func:`run_trials` split over ``workers`` forked processes (they inherit the task, model and controller)."""
    import multiprocessing as mp

    B = q0.shape[0]
    edges = np.linspace(0, B, workers + 1).round().astype(int)
    parts = [(int(edges[k]), int(edges[k + 1])) for k in range(workers)]
    _FORK_ARGS.update(task=task, controller=controller, plant=plant, q0=q0, dist=dist, kw=kw, offset=offset)
    try:
        with mp.get_context("fork").Pool(workers) as pool:
            res = pool.map(_forked_part, parts)
    finally:
        _FORK_ARGS.clear()
    if progress is not None:
        progress.update(res[0].tip.shape[1])
    rows = []
    for (a, _), r in zip(parts, res):
        for row in r.rows:
            rows.append({**row, "trial": row["trial"] + a})
    cat = lambda name: torch.cat([getattr(r, name) for r in res])  # noqa: E731
    return TrialBatch(rows, cat("tip"), cat("q"), cat("lengths"), cat("steps"), cat("branches"),
                      cat("disturbance_sample"), res[0].dt)  # fmt: skip


def sugar_depth(scene: Scene, x: Tensor) -> Tensor:
    """(...,) depth (m) of ``x`` (..., 3) below the sugar surface inside the can (negative outside), as
    :meth:`~lfd_torch.robot.BaxterPlant.sugar_depth`."""
    can = scene.can
    bottom = scene.table_top + can.wall
    c = torch.tensor(can.center, dtype=x.dtype, device=x.device)
    radial = can.radius - (x[..., :2] - c).norm(dim=-1)
    return torch.minimum(torch.minimum(bottom + can.fill - x[..., 2], radial), x[..., 2] - bottom)


def check_trials(
    task: ScoopingTask, scene: Scene, arm: BaxterArm, tip: Tensor, q: Tensor, lengths: Tensor,
    finished_at: np.ndarray, contacts: Sequence[Sequence[tuple[str, str, float]]], crit: SuccessCriteria,
    push_contacts: Sequence[Sequence[tuple[str, str, float]]] | None = None, dt: float = 0.01,
) -> list[dict[str, Any]]:
    """Per-trial success checks (module docstring) on the logs (B, T, .) of :func:`run_trials`, ``dt`` s apart.

    ``contacts``: per trial every (part, object, time s) contact seen; each forbidden one fails ``no_contact``.
    ``push_contacts``: the subset a force pulse began (diagnostic): ``lenient_success`` ignores those, ``success``
    does not.
    """
    B, T, _ = tip.shape
    valid = torch.arange(T)[None, :] < lengths[:, None]
    depth = sugar_depth(scene, tip)
    in_sugar = (depth > crit.sugar_depth) & valid
    rim = scene.table_top + scene.can.wall + scene.can.height
    c = torch.tensor(scene.can.center, dtype=tip.dtype)
    out_of_can = ((tip[..., 2] > rim) | ((tip[..., :2] - c).norm(dim=-1) > scene.can.radius + scene.can.wall)) & valid
    cup_c = torch.tensor(scene.cup.center, dtype=tip.dtype)
    cup_rim = scene.table_top + scene.cup.wall + scene.cup.height
    over_cup = (((tip[..., :2] - cup_c).norm(dim=-1) < scene.cup.radius - crit.cup_margin)
                & (tip[..., 2] > cup_rim) & (tip[..., 2] < cup_rim + crit.cup_height) & valid)  # fmt: skip
    ar = torch.arange(T)[None, :].expand(B, T)
    big = T + 1
    first_in = torch.where(in_sugar, ar, big).amin(-1)
    last_in = torch.where(in_sugar, ar, -1).amax(-1)
    left = (out_of_can & (ar > last_in[:, None])).any(-1)
    cup_after = (over_cup & (ar > last_in[:, None])).any(-1)
    lo, hi = arm.lower(q.dtype), arm.upper(q.dtype)
    viol = (((q < lo - crit.limit_tol) | (q > hi + crit.limit_tol)).any(-1) & valid)
    g = task.library.segmentation.attractors[task.library.routes[0][-1]].to(tip)
    final_err = (tip.gather(1, (lengths - 1)[:, None, None].expand(B, 1, 3))[:, 0] - g).norm(dim=-1)
    out = []
    for i in range(B):
        bad = [(p, o, t) for p, o, t in contacts[i] if o in crit.forbidden]
        excused = set(push_contacts[i]) if push_contacts is not None else set()
        unexcused = [c for c in bad if c not in excused]
        checks = {
            "entered_sugar": bool(first_in[i] <= T),
            "left_sugar": bool(first_in[i] <= T) and bool(left[i]),
            "reached_cup": bool(cup_after[i]) and bool(first_in[i] <= T),
            "no_contact": not bad,
            "joint_limits": not bool(viol[i].any()),
            "finished": bool(finished_at[i] >= 0) and float(final_err[i]) < crit.final_tol,
        }
        reason = ""
        for name, ok in checks.items():
            if not ok:
                if name == "no_contact":
                    p, o, t = bad[0]
                    reason = f"contact {p}-{o} at {t:.2f} s" + (" (begun by a force pulse)" if bad[0] in excused else "")
                elif name == "joint_limits":
                    k = int(torch.nonzero(viol[i])[0])
                    reason = f"joint limit violated at {k * dt:.2f} s"
                elif name == "finished":
                    reason = (f"final error {float(final_err[i]) * 1e3:.1f} mm" if finished_at[i] >= 0
                              else "not finished within the budget")  # fmt: skip
                else:
                    reason = {"entered_sugar": "never below the sugar surface",
                              "left_sugar": "never left the can after scooping",
                              "reached_cup": "never above the cup after scooping"}[name]  # fmt: skip
                break
        lenient = all(ok for name, ok in checks.items() if name != "no_contact") and not unexcused
        row = {"success": all(checks.values()), "reason": reason, **checks, "lenient_success": lenient,
               "max_depth_mm": float(depth[i][valid[i]].max()) * 1e3, "final_error_mm": float(final_err[i]) * 1e3,
               "contacts": ";".join(sorted({f"{p}-{o}" for p, o, _ in contacts[i]}))}  # fmt: skip
        out.append(row)
    return out


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval (lower, upper) of a binomial proportion; ``z`` = 1.96 for 95 %. (nan, nan) for n = 0.

    Raises:
        InvalidArgumentError: ``successes`` or ``n`` not an integer, n < 0, successes outside [0, n], or ``z`` not a
            finite number > 0.
    """
    n = check_int(n, "n", low=0)
    successes = check_int(successes, "successes")
    z = check_float(z, "z", low=0.0, low_open=True)
    if n == 0:
        return (math.nan, math.nan)
    if not 0 <= successes <= n:
        raise InvalidArgumentError(f"successes must lie in [0, n={n}], got {successes}")
    p = successes / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))
