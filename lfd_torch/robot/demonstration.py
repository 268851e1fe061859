"""Kinesthetic-style sugar-scooping demonstration of the Baxter spoon tip (issue 10, item 3).

:func:`scooping_demonstration` stands in for the paper's recording (Sec. V-B, Fig. 12): a person guiding the arm
from a start area over the sugar can, scooping (dip below the sugar surface, drag through it, lift), carrying the
spoon over the coffee cup, tipping it and lifting away. The generator works in joint space:

1. Cartesian via points of the spoon tip (and a spoon orientation) are placed relative to the scene's can and
   cup, each jittered per seed by a few mm; every via point is turned into joint angles by damped-least-squares
   IK on the pytorch-kinematics model (:class:`~lfd_torch.robot.arm.BaxterArm`), warm-started along the motion.
2. Each stage (0 approach, 1 scoop, 2 transport to the cup, tip and lift away) is one minimum-jerk movement
   along a C1 cubic Hermite path through its joint-space via points (chordal knots), so the arm stops only
   between stages, where it settles for a random 0.2-0.5 s, as a teacher would. The stage durations and an
   asymmetric time warp of each minimum-jerk profile vary per seed (human speed variation).
3. A tremor, band-limited white noise (1-8 Hz) of 0.2-0.4 mm RMS per Cartesian axis, is mapped to the joints by
   the position Jacobian's pseudo-inverse and added to the joint trajectory.
4. The joint trajectory is sampled at ``rate`` Hz and recorded through FK (tip position and spoon rotation).

Units: t s, q rad, tip m (torso frame), rotation (3, 3) of the spoon-tip frame in the torso frame.

:func:`load_demonstration` reads a recorded demonstration (CSV or NPZ: time + 7 joint angles, or time + 3-D tip
positions); :func:`save_demonstration` writes one.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, NonIncreasingTimeError, ShapeMismatchError, StoreError
from lfd_torch.robot.arm import NEUTRAL_POSE, BaxterArm
from lfd_torch.robot.controller import orientation_error
from lfd_torch.robot.plant import Scene
from lfd_torch.robot.urdf import DEFAULT_TOOL_OFFSET
from lfd_torch.store.atomic import atomic_path
from lfd_torch.utils import check_generator, check_path, check_int, check_tensor, float_dtype

__all__ = [
    "STAGE_NAMES",
    "ScoopingDemonstration",
    "scooping_demonstration",
    "scooping_via_points",
    "load_demonstration",
    "save_demonstration",
    "solve_ik",
]

STAGE_NAMES: tuple[str, ...] = ("approach", "scoop", "transport")
ANGLE_LENGTH = 0.4  # m of path per rad of spoon rotation when timing the motion along a stage
DENSE_SPACING = 0.01  # m between the joint-space via points of a stage
_ARMS: dict[float, BaxterArm] = {}


def _arm(tool_offset: float) -> BaxterArm:
    key = float(tool_offset)
    if key not in _ARMS:
        _ARMS[key] = BaxterArm(key)
    return _ARMS[key]


@dataclass(frozen=True)
class ScoopingDemonstration:
    """One demonstration of the scooping task.

    Attributes:
        t: (T,) time stamps (s), from 0.
        q: (T, 7) joint angles (rad), or None for a recording of tip positions only.
        tip: (T, 3) spoon-tip positions in the torso frame (m).
        rotation: (T, 3, 3) spoon-tip frame rotation in the torso frame, or None.
        stages: (T,) long ground-truth stage 0..2 of the generator (0 approach, 1 scoop, 2 transport to the cup
            and lift away), or None for a recording.
        via_tip: (K, 3) Cartesian via points of the generator (m), or None.
    """

    t: Tensor
    q: Tensor | None
    tip: Tensor
    rotation: Tensor | None = None
    stages: Tensor | None = None
    via_tip: Tensor | None = None

    def __post_init__(self) -> None:
        check_tensor(self.t, "t", ndim=1, min_rows=2, shape_hint="(T,)")
        if not bool((self.t[1:] > self.t[:-1]).all()):
            raise NonIncreasingTimeError("t must be strictly increasing")
        T = self.t.shape[0]
        check_tensor(self.tip, "tip", ndim=2, last_dim=3, shape_hint="(T, 3)")
        for name, value, shape in (("tip", self.tip, (T, 3)), ("q", self.q, (T, 7)),
                                   ("rotation", self.rotation, (T, 3, 3))):
            if value is not None:
                check_tensor(value, name, shape_hint=str(shape))
                if tuple(value.shape) != shape:
                    raise ShapeMismatchError(f"{name} must have shape {shape} (T = {T} samples of t), got "
                                             f"{tuple(value.shape)}")  # fmt: skip
        if self.stages is not None and (not isinstance(self.stages, Tensor) or self.stages.shape != (T,)):
            raise ShapeMismatchError(f"stages must be a (T,) = ({T},) tensor or None, got "
                                     f"{tuple(getattr(self.stages, 'shape', ())) or type(self.stages).__name__}")

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])

    def demos(self) -> Demos:
        """The tip positions as a :class:`~lfd_torch.data.Demos` of one demonstration (m, s); attractor = the
        last sample."""
        return Demos.from_sequences([self.tip], times=[self.t], dtype=self.tip.dtype, device=self.tip.device)


# ---------------------------------------------------------------------------------------------- geometry
def _axis_angle(axis: Tensor, angle: float) -> Tensor:
    """(3, 3) rotation of ``angle`` rad about the unit ``axis`` (3,) (Rodrigues)."""
    a = axis / axis.norm()
    K = torch.zeros(3, 3, dtype=a.dtype)
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -a[2], a[1], a[2], -a[0], -a[1], a[0]
    return torch.eye(3, dtype=a.dtype) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _spoon_down(yaw: float, dtype: torch.dtype) -> Tensor:
    """(3, 3) spoon frame pointing straight down (z = -z_torso), its x axis at ``yaw`` rad in the table plane."""
    x = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0], dtype=dtype)
    z = torch.tensor([0.0, 0.0, -1.0], dtype=dtype)
    y = torch.linalg.cross(z, x)
    return torch.stack([x, y, z], 1)


def scooping_via_points(
    scene: Scene | Mapping | None = None, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64
) -> tuple[Tensor, Tensor, Tensor]:
    """Cartesian via points of the demonstration, placed relative to the can and the cup.

    Returns:
        tip (K, 3) m, rotation (K, 3, 3), stage (K,) long: the stage each via point ends (point 0 is the start).
        With a generator every point is jittered (start by up to 4 cm, the others by a few mm, tilts by a few
        degrees); without one the nominal points.
    """
    sc = Scene.from_mapping(scene)
    can, cup = sc.can, sc.cup
    g = None if generator is None else check_generator(generator, where="scooping_via_points")

    def u(n: int = 1) -> Tensor:  # uniform in [-1, 1]
        if g is None:
            return torch.zeros(n, dtype=dtype)
        return 2 * torch.rand(n, generator=g, dtype=dtype) - 1

    c = torch.tensor([*can.center, 0.0], dtype=dtype)
    k = torch.tensor([*cup.center, 0.0], dtype=dtype)
    surface = sc.table_top + can.wall + can.fill
    rim = sc.table_top + can.wall + can.height
    cup_rim = sc.table_top + cup.wall + cup.height
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    drag = k - c
    drag = drag / drag.norm()  # the spoon is dragged through the sugar towards the cup side
    tilt_axis = torch.linalg.cross(drag, ez)  # tilting about it raises the bowl's leading edge, hand to the robot
    pour_axis = -drag  # rolling about it empties the bowl sideways over the cup
    r_in = can.radius
    yaw0 = -3 * math.pi / 4 + 0.08 * float(u())

    def jit(scale: float) -> Tensor:
        return torch.cat([u(2) * scale, u(1) * scale * 0.5])

    start = torch.tensor([0.56, 0.76, -0.10], dtype=dtype) + torch.cat([u(2) * 0.04, u(1) * 0.03])
    back = torch.tensor([-0.06, 0.0, 0.0], dtype=dtype)
    pts = [  # (tip, tilt rad, pour rad, stage ended)
        (start, 0.0, 0.0, -1),
        (c - 0.1 * r_in * drag + ez * (rim - c[2] + 0.05) + jit(0.006), 0.0, 0.0, 0),  # above the can
        (c - 0.45 * r_in * drag + ez * (surface + 0.012) + jit(0.003), 0.05, 0.0, 1),  # entering the sugar
        (c - 0.2 * r_in * drag + ez * (surface - 0.022) + jit(0.003), 0.15, 0.0, 1),  # dip
        (c + 0.35 * r_in * drag + ez * (surface - 0.018) + jit(0.003), 0.30, 0.0, 1),  # drag
        (c + 0.2 * r_in * drag + ez * (rim + 0.05) + jit(0.005), 0.25, 0.0, 1),  # lift out of the can
        ((c + k) / 2 + ez * (max(rim, cup_rim) + 0.10) + jit(0.01), 0.25, 0.0, 2),  # carry
        (k - 0.2 * cup.radius * drag + ez * (cup_rim + 0.06) + jit(0.004), 0.25, 0.0, 2),  # over the cup
        (k + ez * (cup_rim + 0.06) + jit(0.004), 0.25, 0.7, 2),  # tip the spoon
        (k + back + ez * (cup_rim + 0.16) + jit(0.01), 0.15, 0.2, 2),  # lift away, up and back to the robot
    ]
    base = _spoon_down(yaw0, dtype)
    tips, rots, stages = [], [], []
    for p, tilt, pour, stage in pts:
        tilt = tilt * (1.0 + 0.1 * float(u())) if tilt else 0.0
        pour = pour * (1.0 + 0.1 * float(u())) if pour else 0.0
        tips.append(p)
        rots.append(_axis_angle(pour_axis, pour) @ _axis_angle(tilt_axis, tilt) @ base)
        stages.append(stage)
    return torch.stack(tips), torch.stack(rots), torch.tensor(stages, dtype=torch.long)


def solve_ik(
    arm: BaxterArm,
    tip: Tensor,
    rotation: Tensor,
    q0: Tensor,
    *,
    iterations: int = 200,
    damping: float = 0.01,
    orientation_weight: float = 0.1,
    null_gain: float = 0.2,
    tol: float = 1e-7,
    strict: bool = True,
) -> Tensor:
    """Batched damped-least-squares IK of the spoon-tip pose.

    Args:
        tip: (K, 3) target positions (m); rotation: (K, 3, 3) target orientations; q0: (K, 7) or (7,) initial
            joint angles (rad), also the null-space posture.
        orientation_weight: m per rad weighing the angular error against the position error.

    Returns:
        (K, 7) joint angles within the joint limits (rad).

    Raises:
        InvalidArgumentError: with ``strict``, a target not reached to 1 mm / 0.01 rad (out of reach); without it
            the best joint angles found are returned and the caller checks the residual. Also ``iterations`` < 1.
        ShapeMismatchError / NonFiniteError: inputs of the wrong shapes, of different dtypes, or not finite.
    """
    check_tensor(tip, "tip", ndim=2, last_dim=3, min_rows=1, shape_hint="(K, 3)")
    K = tip.shape[0]
    check_tensor(rotation, "rotation", ndim=3, shape_hint="(K, 3, 3)")
    check_tensor(q0, "q0", last_dim=7, shape_hint="(K, 7) or (7,)")
    if rotation.shape != (K, 3, 3) or q0.shape not in ((7,), (K, 7)):
        raise ShapeMismatchError(f"tip (K, 3), rotation (K, 3, 3) and q0 (K, 7) or (7,) expected, got "
                                 f"{tuple(tip.shape)}, {tuple(rotation.shape)}, {tuple(q0.shape)}")
    if not tip.dtype == rotation.dtype == q0.dtype:
        raise ShapeMismatchError(f"tip, rotation and q0 must share one dtype, got {tip.dtype}, {rotation.dtype}, "
                                 f"{q0.dtype}")  # fmt: skip
    iterations = check_int(iterations, "iterations", low=1)
    q = q0.expand(K, 7).clone() if q0.ndim == 1 else q0.clone()
    posture = q.clone()
    lo, hi = arm.lower(q.dtype) + 1e-3, arm.upper(q.dtype) - 1e-3
    eye6, eye7 = torch.eye(6, dtype=q.dtype), torch.eye(7, dtype=q.dtype)
    w = torch.tensor([1.0, 1.0, 1.0] + [orientation_weight] * 3, dtype=q.dtype)
    for it in range(iterations):
        pose, J = arm.pose_and_jacobian(q)
        e = torch.cat([tip - pose[:, :3, 3], orientation_error(pose[:, :3, :3], rotation)], -1)
        if float((e * w).abs().max()) < tol:
            break
        Jw = J * w[:, None]
        pinv = Jw.transpose(1, 2) @ torch.linalg.inv(Jw @ Jw.transpose(1, 2) + damping**2 * eye6)
        dq = (pinv @ (e * w)[..., None]).squeeze(-1)
        if it < iterations // 2:  # posture only while far: the damped projector leaks into the task
            dq = dq + ((eye7 - pinv @ Jw) @ (null_gain * (posture - q))[..., None]).squeeze(-1)
        step = dq.abs().amax(-1, keepdim=True).clamp_min(0.2) / 0.2  # at most 0.2 rad per iteration
        q = torch.minimum(torch.maximum(q + dq / step, lo), hi)
    if not strict:
        return q
    pose = arm.forward_kinematics(q)
    err_p = (tip - pose[:, :3, 3]).norm(dim=-1)
    err_r = orientation_error(pose[:, :3, :3], rotation).norm(dim=-1)
    bad = (err_p > 1e-3) | (err_r > 1e-2)
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise InvalidArgumentError(f"tip target {i} {tip[i].tolist()} is out of reach: IK error "
                                   f"{float(err_p[i]) * 1e3:.2f} mm, {float(err_r[i]):.3f} rad")
    return q


# ---------------------------------------------------------------------------------------------- timing
def _hermite(points: Tensor, u: Tensor, knots: Tensor) -> Tensor:
    """C1 cubic Hermite path through ``points`` (K, n) at ``knots`` (K,) increasing from 0 to 1 (Catmull-Rom
    tangents for non-uniform knots, one-sided at the ends), evaluated at ``u`` (N,) in [0, 1]: (N, n)."""
    dk = (knots[1:] - knots[:-1]).clamp_min(1e-9)
    slope = (points[1:] - points[:-1]) / dk[:, None]  # (K-1, n)
    tang = torch.empty_like(points)
    tang[0], tang[-1] = slope[0], slope[-1]
    if points.shape[0] > 2:
        tang[1:-1] = (slope[:-1] * dk[1:, None] + slope[1:] * dk[:-1, None]) / (dk[:-1] + dk[1:])[:, None]
    idx = torch.searchsorted(knots[1:-1].contiguous(), u.contiguous(), right=True)
    s = ((u - knots[idx]) / dk[idx]).clamp(0.0, 1.0)[:, None]
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * points[idx] + h10 * dk[idx, None] * tang[idx] + h01 * points[idx + 1] + h11 * dk[idx, None] * tang[idx + 1]


def _pose_knots(tip: Tensor, rot: Tensor, angle_length: float) -> Tensor:
    """(K,) knots in [0, 1] by cumulative path length |dp| + ``angle_length`` |d theta| (m) between poses."""
    dp = (tip[1:] - tip[:-1]).norm(dim=-1)
    dth = orientation_error(rot[:-1], rot[1:]).norm(dim=-1)
    h = (dp + angle_length * dth).clamp_min(1e-6)
    k = torch.cat([h.new_zeros(1), h.cumsum(0)])
    return k / k[-1]


def _rotation_path(rot: Tensor, knots: Tensor, u: Tensor) -> Tensor:
    """(N, 3, 3) C1 rotation path through ``rot`` (K, 3, 3) at ``knots``, evaluated at ``u`` (N,): the rotation
    vectors of ``rot`` relative to ``rot[0]`` (all within pi of it) interpolated by :func:`_hermite`."""
    w = _hermite(orientation_error(rot[:1].expand_as(rot), rot), u, knots)  # rot(u) = exp([w]) rot[0]
    angle = w.norm(dim=-1).clamp_min(1e-12)
    a = w / angle[:, None]
    K = torch.zeros(u.shape[0], 3, 3, dtype=rot.dtype)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
    K = K - K.transpose(1, 2)
    eye = torch.eye(3, dtype=rot.dtype)
    ex = eye + torch.sin(angle)[:, None, None] * K + (1 - torch.cos(angle))[:, None, None] * (K @ K)
    return ex @ rot[0]


def _path_length(tip: Tensor, rot: Tensor) -> float:
    dth = orientation_error(rot[:-1], rot[1:]).norm(dim=-1)
    return float(((tip[1:] - tip[:-1]).norm(dim=-1) + ANGLE_LENGTH * dth).sum())


def _minimum_jerk(tau: Tensor) -> Tensor:
    return tau**3 * (10 - 15 * tau + 6 * tau**2)


def _band_noise(n: int, rate: float, band: tuple[float, float], g: torch.Generator, dtype: torch.dtype) -> Tensor:
    """(n, 3) white noise band-limited to ``band`` Hz (FFT mask), unit RMS per axis."""
    w = torch.randn(n, 3, generator=g, dtype=dtype)
    spec = torch.fft.rfft(w, dim=0)
    f = torch.fft.rfftfreq(n, d=1.0 / rate).to(dtype)
    spec = spec * ((f >= band[0]) & (f <= band[1])).to(dtype)[:, None]
    x = torch.fft.irfft(spec, n=n, dim=0)
    return x / x.pow(2).mean(0).sqrt().clamp_min(1e-12)


def scooping_demonstration(
    seed: int,
    *,
    scene: Scene | Mapping | None = None,
    tool_offset: float = DEFAULT_TOOL_OFFSET,
    rate: float = 100.0,
    dtype: torch.dtype = torch.float64,
) -> ScoopingDemonstration:
    """A seeded kinesthetic-style scooping demonstration (module docstring), recorded at ``rate`` Hz.

    Args:
        seed: int; the same seed gives the identical demonstration.
        scene: :class:`~lfd_torch.robot.plant.Scene`, a mapping of its fields, or None (defaults).
        tool_offset: spoon-tip offset along the gripper z axis (m).
        rate: sampling rate (Hz), 20..1000.
        dtype: float32 or float64 of the returned tensors (generated in float64).

    Returns:
        :class:`ScoopingDemonstration` with t (T,), q (T, 7), tip (T, 3), rotation (T, 3, 3), stages (T,).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise InvalidArgumentError(f"seed must be an int, got {seed!r}")
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not 20.0 <= rate <= 1000.0:
        raise InvalidArgumentError(f"rate must be a number in [20, 1000] Hz, got {rate!r}")
    if dtype not in (torch.float32, torch.float64):
        raise InvalidArgumentError(f"dtype must be float32 or float64, got {dtype}")
    arm = _arm(tool_offset)
    f64 = torch.float64
    g = torch.Generator().manual_seed(int(seed))
    via_tip, via_rot, via_stage = scooping_via_points(scene, g, f64)
    # IK warm-started along the motion: each via point from the previous solution (one posture branch)
    q_prev = torch.tensor(NEUTRAL_POSE, dtype=f64)
    qs = []
    for i in range(via_tip.shape[0]):
        q_prev = solve_ik(arm, via_tip[i : i + 1], via_rot[i : i + 1], q_prev[None])[0]
        qs.append(q_prev)
    via_q = torch.stack(qs)

    def rnd(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=f64))

    dt = 1.0 / float(rate)
    nominal = {0: 3.0, 1: 4.0, 2: 6.0}  # s per stage at the teacher's mean pace
    pieces_q, pieces_stage = [], []
    n_stages = int(via_stage.max()) + 1
    for m in range(n_stages):
        idx = torch.nonzero(via_stage == m).flatten()
        sel = torch.cat([idx[:1] - 1, idx])
        knots = _pose_knots(via_tip[sel], via_rot[sel], ANGLE_LENGTH)
        # joint-space via points every ~1 cm of the Cartesian path, so that the joint-space interpolation keeps
        # the tip on the intended path (into the can, not through its wall); IK from the coarse joint path
        n_dense = max(int(math.ceil(_path_length(via_tip[sel], via_rot[sel]) / DENSE_SPACING)) + 1, 3)
        u = torch.linspace(0.0, 1.0, n_dense, dtype=f64)
        tip_d = _hermite(via_tip[sel], u, knots)
        rot_d = _rotation_path(via_rot[sel], knots, u)
        q_d = solve_ik(arm, tip_d, rot_d, _hermite(via_q[sel], u, knots))
        q_d[0], q_d[-1] = via_q[sel[0]], via_q[sel[-1]]
        duration = nominal[m] * rnd(0.85, 1.2)
        n = max(int(round(duration * rate)), 4)
        tau = torch.arange(n, dtype=f64) / n
        a = rnd(-0.35, 0.35)  # asymmetric pace: early or late peak speed; monotone for |a| < 1
        pieces_q.append(_hermite(q_d, _minimum_jerk(tau + a * tau * (1 - tau)), u))
        pieces_stage.append(torch.full((n,), m, dtype=torch.long))
        settle = int(round(rnd(0.2, 0.5) * rate)) if m < n_stages - 1 else int(round(0.3 * rate)) + 1
        pieces_q.append(q_d[-1].expand(settle, 7))
        pieces_stage.append(torch.full((settle,), m, dtype=torch.long))
    q = torch.cat(pieces_q)
    stages = torch.cat(pieces_stage)
    T = q.shape[0]
    # tremor: band-limited Cartesian noise mapped to the joints by the position Jacobian's pseudo-inverse
    sigma = rnd(0.2e-3, 0.4e-3)
    tremor = sigma * _band_noise(T, float(rate), (1.0, 8.0), g, f64)
    Jp = arm.jacobian(q)[:, :3]
    q = q + (torch.linalg.pinv(Jp) @ tremor[..., None]).squeeze(-1)
    q = torch.minimum(torch.maximum(q, arm.lower(f64) + 1e-4), arm.upper(f64) - 1e-4)
    pose = arm.forward_kinematics(q)
    t = torch.arange(T, dtype=f64) * dt
    return ScoopingDemonstration(
        t=t.to(dtype), q=q.to(dtype), tip=pose[:, :3, 3].to(dtype), rotation=pose[:, :3, :3].to(dtype),
        stages=stages, via_tip=via_tip.to(dtype),
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------- files
def _from_table(arr: np.ndarray, path: Path, tool_offset: float, dtype: torch.dtype) -> ScoopingDemonstration:
    if arr.ndim != 2 or arr.shape[1] not in (4, 8):
        raise StoreError(f"{path}: expected columns time + 7 joint angles or time + 3 tip coordinates, "
                         f"got an array of shape {arr.shape}")
    if arr.shape[0] < 2:
        raise StoreError(f"{path}: has {arr.shape[0]} samples, at least 2 are needed")
    if not np.isfinite(arr).all():
        raise StoreError(f"{path}: contains NaN or Inf")
    t = torch.as_tensor(arr[:, 0], dtype=torch.float64)
    if not bool((t[1:] > t[:-1]).all()):
        raise StoreError(f"{path}: time stamps are not strictly increasing")
    t = t - t[0]
    vals = torch.as_tensor(arr[:, 1:], dtype=torch.float64)
    if vals.shape[1] == 3:
        return ScoopingDemonstration(t=t.to(dtype), q=None, tip=vals.to(dtype))
    arm = _arm(tool_offset)
    arm.check_limits(vals, f"joint angles in {path}", tol=1e-6)
    pose = arm.forward_kinematics(vals)
    return ScoopingDemonstration(t=t.to(dtype), q=vals.to(dtype), tip=pose[:, :3, 3].to(dtype),
                                 rotation=pose[:, :3, :3].to(dtype))  # fmt: skip


def load_demonstration(
    path: str | os.PathLike[str], *, tool_offset: float = DEFAULT_TOOL_OFFSET, dtype: torch.dtype = torch.float64
) -> ScoopingDemonstration:
    """Read a recorded demonstration.

    Formats: ``.csv`` with columns ``t, q0..q6`` (rad) or ``t, x, y, z`` (m), an optional header line; ``.npz``
    with arrays ``t`` (T,) and ``q`` (T, 7) or ``tip`` (T, 3). Joint recordings are passed through FK
    (``tool_offset`` m) for the tip positions and rotations.

    Raises:
        StoreError: a missing, unreadable or damaged file (naming it): wrong columns, non-numeric cells, NaN,
            time not increasing.
        InvalidArgumentError: joint angles outside the limits; an unknown extension.
    """
    dtype = float_dtype(dtype, allow_none=False)
    p = check_path(path)
    ext = p.suffix.lower()
    if ext not in (".csv", ".npz"):
        raise InvalidArgumentError(f"path must end in .csv or .npz, got {str(p)!r}")
    if not p.is_file():
        raise StoreError(f"{p}: no such file")
    if ext == ".csv":
        try:
            with open(p, encoding="utf-8") as fh:
                lines = [ln.strip() for ln in fh if ln.strip()]
        except (OSError, UnicodeDecodeError) as exc:
            raise StoreError(f"{p}: cannot be read ({exc})") from exc
        if lines and not _numeric(lines[0].split(",")[0]):
            lines = lines[1:]  # header
        try:
            rows = [[float(c) for c in ln.split(",")] for ln in lines]
        except ValueError as exc:
            raise StoreError(f"{p}: a cell is not a number ({exc})") from exc
        if len({len(r) for r in rows}) > 1:
            raise StoreError(f"{p}: rows have different numbers of columns")
        arr = np.asarray(rows, dtype=float).reshape(len(rows), -1 if rows else 0)
        return _from_table(arr, p, tool_offset, dtype)
    try:
        with np.load(p, allow_pickle=False) as z:
            files = set(z.files)
            if "t" not in files or not ({"q", "tip"} & files):
                raise StoreError(f"{p}: needs arrays 't' and 'q' (T, 7) or 'tip' (T, 3), found {sorted(files)}")
            if {"q", "tip"} <= files:
                raise StoreError(f"{p}: holds both 'q' and 'tip'; a demonstration file holds one of them")
            name = "q" if "q" in files else "tip"
            t, v = z["t"], z[name]
    except StoreError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, ValueError, EOFError, OSError: a damaged archive
        raise StoreError(f"{p}: not a readable NPZ archive ({type(exc).__name__}: {exc})") from exc
    width = 7 if name == "q" else 3
    for key, arr in (("t", t), (name, v)):
        if arr.dtype.kind not in "iuf":  # complex, bool, strings, objects: not numbers the file format allows
            raise StoreError(f"{p}: array {key!r} holds {arr.dtype} values, expected real numbers")
    if t.ndim != 1 or v.ndim != 2 or v.shape != (t.shape[0], width):
        raise StoreError(f"{p}: expected 't' (T,) and {name!r} (T, {width}), got shapes {t.shape} and {v.shape}")
    return _from_table(np.concatenate([t.astype(float)[:, None], v.astype(float)], 1), p, tool_offset, dtype)


def _numeric(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def save_demonstration(demo: ScoopingDemonstration, path: str | os.PathLike[str], *, joints: bool = True) -> Path:
    """Write ``demo`` as CSV or NPZ (by the extension): time + joint angles (``joints`` and q known) or time +
    tip positions. The file is replaced atomically (a failed write leaves any earlier file as it was). Returns the
    path.

    Raises:
        InvalidArgumentError: ``demo`` is not a :class:`ScoopingDemonstration`, ``path`` is not a path ending in
            .csv or .npz.
    """
    if not isinstance(demo, ScoopingDemonstration):
        raise InvalidArgumentError(f"demo must be a ScoopingDemonstration, got {type(demo).__name__}")
    p = check_path(path)
    ext = p.suffix.lower()
    if ext not in (".csv", ".npz"):
        raise InvalidArgumentError(f"path must end in .csv or .npz, got {str(p)!r}")
    use_q = joints and demo.q is not None
    vals = (demo.q if use_q else demo.tip).detach().cpu().double().numpy()
    t = demo.t.detach().cpu().double().numpy()
    with atomic_path(p) as tmp, open(tmp, "wb") as fh:  # a handle: np.savez would add ".npz" to a bare name
        if ext == ".csv":
            head = "t," + (",".join(f"q{i}" for i in range(7)) if use_q else "x,y,z")
            np.savetxt(fh, np.concatenate([t[:, None], vals], 1), delimiter=",", header=head, comments="",
                       fmt="%.17g")
        else:
            np.savez(fh, t=t, **({"q": vals} if use_q else {"tip": vals}))
    return p
