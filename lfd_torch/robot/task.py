"""Sugar-scooping pipeline (paper Sec. V-B; issue 10, items 4-5): demonstration -> skills -> engine -> arm.

Learning (:func:`learn_scooping`): window smoothing of the spoon-tip positions -> BP-GM-HMM segmentation with no
prior on the number of steps (default settings) -> :meth:`~lfd_torch.skills.SkillLibrary.learn` (one P-QLF LPV-DS
per step on the Cartesian tip position, m) -> :class:`ScoopingTask`, which also holds the spoon-orientation
schedule of every step and the map from steps to the generator's stages (approach, scoop, transport).

Control (:class:`ScoopingController`, 100 Hz, batched over B arms): the decision engine (behaviour tree, vectorised
``step_batch``) turns the MuJoCo tip positions into tip velocities v (m/s); the spoon orientation follows the
demonstration's orientation as a function of the progress through the active step (:class:`OrientationSchedule`),
tracked by an angular velocity w = k_R * log(R_des R^T) (rad/s, capped); [v; w] goes through the DLS velocity map
(pytorch-kinematics Jacobian, 6-D task with ``orientation_weight``, null-space posture, joint limits) and the
impedance set-point rule to the MuJoCo plant at 1 kHz (:mod:`lfd_torch.robot.trials` runs the loop).

Shapes: B arms, M steps, N demonstration samples; x (B, 3) m, R (B, 3, 3), q (B, 7) rad.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
from lfd_torch.modulation import Modulation
from lfd_torch.robot.controller import DLSVelocityMap, ImpedanceController, orientation_error
from lfd_torch.robot.demonstration import STAGE_NAMES, ScoopingDemonstration
from lfd_torch.segmentation import Segmentation
from lfd_torch.skills import Arrival, Decision, SkillEngine, SkillLibrary, SkillSettings
from lfd_torch.utils import check_int, check_tensor, to_arguments

__all__ = ["OrientationSchedule", "ScoopingTask", "learn_scooping", "ControlStep", "ScoopingController"]


class OrientationSchedule:
    """Spoon orientation of the demonstration as a function of the progress through each step.

    The progress of a state x in step m is the arc-length fraction (0 at the step's first demonstrated sample, 1 at
    its last) of the demonstration sample of step m nearest to x; the orientation is that sample's rotation.

    Args:
        positions: (N, 3) demonstration tip positions (m); rotations: (N, 3, 3); steps: (N,) long step of every
            sample (the segmentation's labels); n_steps: M.
    """

    def __init__(self, positions: Tensor, rotations: Tensor, steps: Tensor, n_steps: int):
        check_tensor(positions, "positions", ndim=2, last_dim=3, min_rows=1, shape_hint="(N, 3)")
        check_tensor(rotations, "rotations", ndim=3, shape_hint="(N, 3, 3)")
        N = positions.shape[0]
        if not isinstance(steps, Tensor) or steps.dtype not in (torch.int32, torch.int64):
            raise ShapeMismatchError(f"steps must be an integer tensor (N,), got {getattr(steps, 'dtype', steps)!r}")
        if rotations.shape != (N, 3, 3) or steps.shape != (N,):
            raise ShapeMismatchError(f"positions (N, 3), rotations (N, 3, 3), steps (N,) expected, got "
                                     f"{tuple(positions.shape)}, {tuple(rotations.shape)}, {tuple(steps.shape)}")
        n_steps = check_int(n_steps, "n_steps", low=1)
        present = set(steps.tolist())
        missing = sorted(set(range(n_steps)) - present)
        if missing:
            raise InvalidArgumentError(f"steps has no sample of step {missing[0]} of {n_steps}")
        extra = sorted(present - set(range(n_steps)))
        if extra:
            raise InvalidArgumentError(f"steps holds step {extra[0]}, outside 0..{n_steps - 1} (n_steps={n_steps})")
        self.positions = positions
        self.rotations = rotations
        self.steps = steps.long()
        self.n_steps = int(n_steps)
        seg = torch.cat([positions.new_zeros(1), (positions[1:] - positions[:-1]).norm(dim=-1)])
        seg = torch.where(torch.cat([steps.new_zeros(1, dtype=torch.bool), steps[1:] == steps[:-1]]), seg, 0 * seg)
        progress = torch.empty_like(seg)
        for m in range(self.n_steps):  # M cumulative sums (M is a handful)
            sel = self.steps == m
            c = seg[sel].cumsum(0)
            progress[sel] = c / c[-1].clamp_min(1e-12)
        self.progress_table = progress

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> "OrientationSchedule":
        """A copy cast to ``dtype`` and moved to ``device`` (a device alone as the first argument: moved)."""
        dtype, device = to_arguments(dtype, device)
        return OrientationSchedule(self.positions.to(dtype=dtype, device=device),
                                   self.rotations.to(dtype=dtype, device=device),
                                   self.steps.to(device=device), self.n_steps)  # fmt: skip

    def nearest(self, x: Tensor, step: Tensor) -> Tensor:
        """(B,) index of the demonstration sample of step ``step`` (B,) nearest to ``x`` (B, 3).

        Raises:
            ShapeMismatchError: x not (B, 3) or step not (B,); InvalidArgumentError: a step outside 0..M-1.
        """
        if x.ndim != 2 or x.shape[-1] != 3 or step.shape != x.shape[:1]:
            raise ShapeMismatchError(f"x (B, 3) and step (B,) expected, got {tuple(x.shape)} and {tuple(step.shape)}")
        if bool(((step < 0) | (step >= self.n_steps)).any()):
            raise InvalidArgumentError(f"step must lie in 0..{self.n_steps - 1}, got {step.tolist()}")
        # direct differences, not the matrix-product form: the distances (and a near-tie's argmin) of one arm then
        # do not depend on which other arms share the batch, so split batches (workers) repeat a run exactly
        d2 = torch.cdist(x, self.positions.to(x), compute_mode="donot_use_mm_for_euclid_dist")  # (B, N)
        other = self.steps.to(step.device)[None, :] != step[:, None]
        return d2.masked_fill(other, float("inf")).argmin(-1)

    def progress(self, x: Tensor, step: Tensor) -> Tensor:
        """(B,) progress in [0, 1] through the active step."""
        return self.progress_table.to(x)[self.nearest(x, step)]

    def __call__(self, x: Tensor, step: Tensor) -> Tensor:
        """(B, 3, 3) desired spoon rotation at ``x`` (B, 3) in step ``step`` (B,)."""
        return self.rotations.to(x)[self.nearest(x, step)]


@dataclass(frozen=True, eq=False)
class ScoopingTask:
    """A learned scooping task.

    Attributes:
        demonstration: the raw demonstration; demos: the smoothed tip positions that were segmented (m).
        segmentation: the BP-GM-HMM steps; library: one primitive per step.
        step_stage: (M,) long generator stage (0 approach, 1 scoop, 2 transport) each step mostly covers; without
            ground truth, the steps are mapped onto the three stages in order by their share of the path.
        orientation: the spoon-orientation schedule.
        info: timings (s) of segmentation and learning.
    """

    demonstration: ScoopingDemonstration
    demos: Demos
    segmentation: Segmentation
    library: SkillLibrary
    step_stage: Tensor
    orientation: OrientationSchedule
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_steps(self) -> int:
        return self.library.n_steps

    def engine(self, modulation: Modulation | str = "full", arrival: Arrival | None = None) -> SkillEngine:
        """A :class:`~lfd_torch.skills.SkillEngine` on the library (``modulation`` mode or object)."""
        return SkillEngine(self.library, modulation, arrival)


def _step_stage(seg: Segmentation, demo: ScoopingDemonstration, n_samples: int) -> Tensor:
    labels = seg.labels[0][:n_samples]
    M = seg.n_steps
    out = torch.empty(M, dtype=torch.long)
    if demo.stages is not None and demo.stages.shape[0] == labels.shape[0]:
        for m in range(M):
            out[m] = torch.bincount(demo.stages[labels == m], minlength=len(STAGE_NAMES)).argmax()
        return out
    # no ground truth: the step's mid-sample position along the recording, split into three equal thirds
    for m in range(M):
        mid = torch.nonzero(labels == m).float().mean() / max(labels.shape[0] - 1, 1)
        out[m] = min(int(mid * len(STAGE_NAMES)), len(STAGE_NAMES) - 1)
    return out


def learn_scooping(
    demo: ScoopingDemonstration,
    *,
    generator: torch.Generator,
    preprocess: Callable[[Demos], Demos] | None = None,
    segmenter: Callable[..., Segmentation] | None = None,
    primitive: Callable | None = None,
    settings: SkillSettings | None = None,
) -> ScoopingTask:
    """Learn the scooping task from one demonstration (module docstring).

    Args:
        demo: the demonstration (its ``rotation`` is needed for the orientation schedule).
        generator: randomness of the segmentation and of the primitive fits.
        preprocess: Demos -> Demos (default: Savitzky-Golay window smoothing, 15 samples, order 3).
        segmenter: ``segment(demos, generator=g)`` (default :func:`lfd_torch.segmentation.segment`, default
            settings, no number of steps given).
        primitive: fitter of one step (default P-QLF LPV-DS on a PC-GMM).
        settings: :class:`~lfd_torch.skills.SkillSettings` of the library (default settings).
    """
    from lfd_torch.preprocess import Preprocess
    from lfd_torch.segmentation import segment

    if not isinstance(demo, ScoopingDemonstration):
        raise InvalidArgumentError(f"demo must be a ScoopingDemonstration, got {type(demo).__name__}")
    if demo.rotation is None:
        raise InvalidArgumentError("demo has no spoon rotations: record joint angles (or give rotations)")
    if not isinstance(generator, torch.Generator):
        raise InvalidArgumentError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    pre = Preprocess(smoothing="savgol", window=15, polyorder=3) if preprocess is None else preprocess
    seg_fn = segment if segmenter is None else segmenter
    settings = SkillSettings() if settings is None else settings
    t0 = time.perf_counter()
    demos = pre(demo.demos())
    seg = seg_fn(demos, generator=generator)
    t1 = time.perf_counter()
    lib = SkillLibrary.learn(demos, seg, primitive=primitive, generator=generator, **settings.learn_kwargs)
    t2 = time.perf_counter()
    n = int(demos.lengths[0])
    labels = seg.labels[0][:n]
    rot = demo.rotation.to(demos.positions)[:n] if demo.rotation.shape[0] >= n else demo.rotation.to(demos.positions)
    schedule = OrientationSchedule(demos.positions[0, :n], rot, labels, seg.n_steps)
    return ScoopingTask(demo, demos, seg, lib, _step_stage(seg, demo, n), schedule,
                        {"segment_s": t1 - t0, "learn_s": t2 - t1})  # fmt: skip


class ControlStep(NamedTuple):
    """One 100 Hz control step for B arms: task velocity ``v`` (B, 3) m/s and ``w`` (B, 3) rad/s, joint velocity
    ``qdot`` (B, 7) rad/s, impedance set-point ``q_d`` (B, 7) rad, ``qd_d`` (B, 7) rad/s, the engine's decision,
    branch (B,) int8 and the orientation progress (B,) in [0, 1]."""

    v: Tensor
    w: Tensor
    qdot: Tensor
    q_d: Tensor
    qd_d: Tensor
    decision: Decision
    branch: Tensor
    progress: Tensor


class ScoopingController:
    """Decision engine + orientation schedule + DLS velocity map + impedance set-point, batched over B arms.

    Args:
        engine: the skill engine (its mode decides the modulation).
        orientation: the spoon-orientation schedule.
        velocity_map: DLS map of the 6-D tip task (pytorch-kinematics Jacobian).
        impedance: set-point rule (``reference``).
        dt: control period (s).
        orientation_gain: k_R (1/s) of w = k_R log(R_des R^T).
        max_angular_speed: cap of |w| (rad/s).
        max_gain: cap k (1/s) of |v| <= k ||x - g_m|| about the active attractor g_m (None: off). The impedance-
            controlled arm follows a velocity command with a lag of some 50-150 ms; near an attractor a fitted
            field can turn at 10-20 rad/s (tremor of the demonstration's settling), and such a fast rotation
            under that lag spirals outwards instead of converging. The cap keeps the loop gain below what the
            arm tracks; far from g_m (|v| < k r) it does nothing.
    """

    def __init__(
        self,
        engine: SkillEngine,
        orientation: OrientationSchedule,
        velocity_map: DLSVelocityMap,
        impedance: ImpedanceController,
        *,
        dt: float = 0.01,
        orientation_gain: float = 2.0,
        max_angular_speed: float = 1.5,
        max_gain: float | None = 3.0,
    ):
        if not isinstance(engine, SkillEngine):
            raise InvalidArgumentError(f"engine must be a SkillEngine, got {type(engine).__name__}")
        for name, val in (("dt", dt), ("orientation_gain", orientation_gain), ("max_angular_speed", max_angular_speed)):
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not val > 0:
                raise InvalidArgumentError(f"{name} must be a number > 0, got {val!r}")
        self.engine = engine
        self.orientation = orientation
        self.velocity_map = velocity_map
        self.impedance = impedance
        self.dt = float(dt)
        self.orientation_gain = float(orientation_gain)
        self.max_angular_speed = float(max_angular_speed)
        if max_gain is not None and (isinstance(max_gain, bool) or not isinstance(max_gain, (int, float))
                                     or not max_gain > 0):
            raise InvalidArgumentError(f"max_gain must be a number > 0 or None, got {max_gain!r}")
        self.max_gain = None if max_gain is None else float(max_gain)

    def command(
        self, q: Tensor, x: Tensor, rotation: Tensor, route: Tensor, index: Tensor, q_d_prev: Tensor | None
    ) -> ControlStep:
        """The control step of B arms at joint angles ``q`` (B, 7), tip ``x`` (B, 3), spoon ``rotation``
        (B, 3, 3), progress (``route``, ``index``) (B,) long and last set-point ``q_d_prev`` (B, 7) or None."""
        v, dec, branch = self.engine.step_batch(x, route, index)
        v = v.to(q)
        if self.max_gain is not None:
            r = (x - self.engine.goals[dec.step].to(x)).norm(dim=-1, keepdim=True)
            v = v * (self.max_gain * r / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)).clamp(max=1.0)
        nearest = self.orientation.nearest(x, dec.step)
        r_des = self.orientation.rotations.to(x)[nearest]
        w = self.orientation_gain * orientation_error(rotation, r_des.to(q))
        w = w * (self.max_angular_speed / w.norm(dim=-1, keepdim=True).clamp_min(1e-12)).clamp(max=1.0)
        w = torch.where(dec.done[:, None], torch.zeros_like(w), w)
        qdot = self.velocity_map(q, torch.cat([v, w], -1), dt=self.dt)
        q_d, qd_d = self.impedance.reference(q, qdot, q_d_prev, self.dt)
        return ControlStep(v, w, qdot, q_d, qd_d, dec, branch, self.orientation.progress_table.to(x)[nearest])


def controller_for(task: ScoopingTask, robot: Any, modulation: Modulation | str = "full", *,
                   arrival: Arrival | None = None, options: Mapping[str, Any] | None = None) -> ScoopingController:
    """A :class:`ScoopingController` of ``task`` on ``robot`` (:class:`~lfd_torch.robot.BaxterRobot`)."""
    return ScoopingController(task.engine(modulation, arrival), task.orientation, robot.velocity_map,
                              robot.impedance, dt=robot.plant.control_period, **dict(options or {}))  # fmt: skip
