"""Controllers of the Baxter arm (issue 10, item 2): task velocity -> joint velocity -> impedance set-point.

* :class:`DLSVelocityMap` (100 Hz, the controller's own pytorch-kinematics model): damped least squares
  ``qdot = J# v + (I - J# J) z`` with ``J# = J^T (J J^T + lambda^2 I)^-1``, a null-space posture / joint-limit
  term ``z``, joint speed limits (uniform scaling, keeps the Cartesian direction) and position limits (joints
  that would cross a limit within one period are saturated and the task is re-solved with the others).
* :class:`ImpedanceController`: the joint-space PD law with gravity compensation,
  ``tau = clamp(kp (q_d - q) + kv (qdot_d - qdot), +-tau_max) + g(q)``, in torch; the MuJoCo plant evaluates the
  same law with its actuators at 1 kHz. :meth:`ImpedanceController.reference` turns the joint velocity into the
  set-point ``(q_d, qdot_d)`` held over one control period.

Shapes: q (B, 7) rad, v (B, 3) m/s (position task) or (B, 6) [m/s; rad/s] (pose task), qdot (B, 7) rad/s.
"""

from __future__ import annotations

import math

import torch

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
from lfd_torch.robot.arm import BaxterArm, check_joint_tensor
from lfd_torch.robot.urdf import BAXTER_LEFT_TABLE

__all__ = ["DLSVelocityMap", "ImpedanceController", "orientation_error"]


def _positive(value: float, name: str, allow_zero: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InvalidArgumentError(f"{name} must be a finite number, got {value!r}")
    if value < 0 or (value == 0 and not allow_zero):
        raise InvalidArgumentError(f"{name} must be {'>=' if allow_zero else '>'} 0, got {value}")
    return float(value)


def _vec7(values, name: str, dtype=torch.float64) -> torch.Tensor:
    try:
        t = torch.as_tensor(values, dtype=dtype).reshape(-1)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ShapeMismatchError(f"{name} must be 7 real numbers (or 1), got {values!r}") from exc
    if t.numel() == 1:
        t = t.expand(7).clone()
    if t.shape != (7,):
        raise ShapeMismatchError(f"{name} must have 7 entries (or 1), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise InvalidArgumentError(f"{name} must be finite and >= 0, got {values!r}")
    return t


def _same_shape(q: torch.Tensor, **others: torch.Tensor) -> None:
    """Raise ShapeMismatchError naming the first of ``others`` whose shape is not that of ``q``."""
    for name, x in others.items():
        if x.shape != q.shape:
            raise ShapeMismatchError(f"{name} must have the shape of q {tuple(q.shape)}, got {tuple(x.shape)}")


def orientation_error(rot: torch.Tensor, rot_des: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vector (rad, base frame) of ``rot_des rot^T``: the angular displacement from ``rot``
    (..., 3, 3) to ``rot_des`` (..., 3, 3); ``w = k * orientation_error`` is a proportional orientation command.

    Raises:
        ShapeMismatchError: either is not a float tensor (..., 3, 3), their dtypes differ, or their leading shapes
            do not broadcast.
    """
    for name, x in (("rot", rot), ("rot_des", rot_des)):
        if not isinstance(x, torch.Tensor) or not x.is_floating_point() or x.ndim < 2 or x.shape[-2:] != (3, 3):
            raise ShapeMismatchError(f"{name} must be a float tensor of rotation matrices (..., 3, 3), got "
                                     f"{tuple(getattr(x, 'shape', ())) or type(x).__name__}")  # fmt: skip
    try:
        torch.broadcast_shapes(rot.shape, rot_des.shape)
    except RuntimeError as exc:
        raise ShapeMismatchError(f"rot {tuple(rot.shape)} and rot_des {tuple(rot_des.shape)} do not broadcast"
                                 ) from exc
    if rot.dtype != rot_des.dtype:
        raise ShapeMismatchError(f"rot is {rot.dtype} and rot_des {rot_des.dtype}: convert one with .to(dtype=...)")
    r = rot_des @ rot.transpose(-1, -2)
    axis = torch.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    cos = ((r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    sin = axis.norm(dim=-1) / 2
    angle = torch.atan2(sin, cos)
    scale = torch.where(sin > 1e-8, angle / (2 * sin).clamp_min(1e-30), torch.full_like(angle, 0.5))
    # near pi the axis from the skew part is ill-conditioned: take it from the symmetric part
    near_pi = cos < -0.999
    if bool(near_pi.any()):
        sym = (r + r.transpose(-1, -2)) / 2 + torch.eye(3, dtype=r.dtype, device=r.device) * (-cos[..., None, None])
        col = sym.norm(dim=-2).argmax(-1)
        ax = torch.gather(sym, -1, col[..., None, None].expand(*col.shape, 3, 1)).squeeze(-1)
        ax = ax / ax.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        ax = torch.where((ax * axis).sum(-1, keepdim=True) < 0, -ax, ax)
        return torch.where(near_pi[..., None], ax * angle[..., None], axis * scale[..., None])
    return axis * scale[..., None]


class DLSVelocityMap:
    """Spoon-tip velocity -> joint velocity by damped least squares with null-space posture and joint limits.

    Args:
        arm: the kinematic model (pytorch-kinematics); a new :class:`BaxterArm` when None.
        damping: lambda (m) of ``J^T (J J^T + lambda^2 I)^-1``. It also scales the gain of a task direction of
            singular value sigma by sigma^2 / (sigma^2 + lambda^2): in a pose task the weighted angular rows have
            the smallest ones (0.055 and 0.032 at the neutral pose with the defaults), so there the arm realises
            about 80 % of a commanded angular velocity (0.5 rad/s about x gives 0.41, with about 6 degrees of
            cross-coupling), while position tasks keep their gain. Lower it, or raise ``orientation_weight``, where
            orientations must be tracked closely.
        null_gain: gain (1/s) of the posture term ``z = null_gain (posture - q)``.
        posture: (7,) rest posture (rad); default the arm's neutral pose.
        limit_margin: width (rad) of the zone inside each position limit where ``z`` also pushes away from it.
        limit_gain: gain (1/s) of that push.
        limit_buffer: distance (rad) kept from the hard limits by the position-limit saturation.
        orientation_weight: length (m) that weighs the angular rows of a pose task (v of shape (B, 6)).
        iterations: saturation passes (a joint saturated in a pass is fixed at its bound in the next).
        null_space: projector of ``z``: ``damped`` ``I - J# J`` with the damped J# (the damping leaks a share
            lambda^2 / (sigma^2 + lambda^2) of J z into the task along weak directions), or ``exact``: the
            orthogonal projector onto the null space of J (from its SVD; singular values below 1e-9 count as 0),
            which leaves the task velocity untouched by ``z`` (the damped J# itself still scales it, see
            ``damping``): needed when the task velocity is small (close to an
            attractor) and the posture far, where the leak would otherwise hold the tip off the target.
    """

    def __init__(
        self,
        arm: BaxterArm | None = None,
        damping: float = 0.02,
        null_gain: float = 1.0,
        posture=None,
        limit_margin: float = 0.15,
        limit_gain: float = 2.0,
        limit_buffer: float = 0.01,
        orientation_weight: float = 0.1,
        iterations: int = 3,
        null_space: str = "damped",
    ):
        if null_space not in ("damped", "exact"):
            from lfd_torch.errors import UnknownNameError

            raise UnknownNameError("null_space projector", str(null_space), ("damped", "exact"))
        self.null_space = null_space
        self.arm = BaxterArm() if arm is None else arm
        if not isinstance(self.arm, BaxterArm):
            raise InvalidArgumentError(f"arm must be a BaxterArm, got {type(arm).__name__}")
        self.damping = _positive(damping, "damping")
        self.null_gain = _positive(null_gain, "null_gain")
        self.limit_margin = _positive(limit_margin, "limit_margin")
        self.limit_gain = _positive(limit_gain, "limit_gain")
        self.limit_buffer = _positive(limit_buffer, "limit_buffer")
        self.orientation_weight = _positive(orientation_weight, "orientation_weight", allow_zero=False)
        if isinstance(iterations, bool) or not isinstance(iterations, int) or not 1 <= iterations <= 100:
            raise InvalidArgumentError(f"iterations must be an int in [1, 100] (saturation passes), got {iterations!r}")
        self.iterations = iterations
        p = self.arm.neutral() if posture is None else torch.as_tensor(posture, dtype=torch.float64)
        self.posture = self.arm.check_limits(p.reshape(7), "posture")

    def null_velocity(self, q: torch.Tensor) -> torch.Tensor:
        """(B, 7) secondary joint velocity z (rad/s): posture attraction plus a push out of the limit margins."""
        lo, hi = self.arm.lower(q.dtype, q.device), self.arm.upper(q.dtype, q.device)
        m = self.limit_margin
        push = torch.relu(lo + m - q) - torch.relu(q - (hi - m))
        return self.null_gain * (self.posture.to(q) - q) + self.limit_gain * push

    def __call__(self, q: torch.Tensor, v: torch.Tensor, dt: float = 0.01, jacobian: torch.Tensor | None = None) -> torch.Tensor:
        """Joint velocity (B, 7) rad/s realising the task velocity ``v`` (B, 3) or (B, 6) at ``q`` (B, 7) rad.

        ``dt`` (s) is the control period over which the position limits must hold: every returned qdot keeps
        ``q + dt qdot`` within ``[lower + limit_buffer, upper - limit_buffer]`` (or moves towards it) and
        ``|qdot| <= velocity_limits``. ``jacobian`` (B, 6, 7) may be passed when already computed at ``q``.

        Raises:
            ShapeMismatchError: ``q`` not (B, 7), ``v`` not (B, 3)/(B, 6) or batch sizes that differ.
            InvalidArgumentError / NonFiniteError: bad dtype, NaN, ``dt <= 0``.
        """
        q = check_joint_tensor(q, "q")
        if not isinstance(v, torch.Tensor) or v.dtype != q.dtype or v.device != q.device:
            raise InvalidArgumentError("v must be a tensor of the same dtype and device as q")
        if v.ndim != q.ndim or v.shape[:-1] != q.shape[:-1] or v.shape[-1] not in (3, 6):
            raise ShapeMismatchError(f"v must have shape {tuple(q.shape[:-1])} + (3,) or (6,), got {tuple(v.shape)}")
        if not bool(torch.isfinite(v).all()):
            from lfd_torch.errors import NonFiniteError

            raise NonFiniteError("v contains NaN or Inf")
        dt = _positive(dt, "dt", allow_zero=False)
        batch = q.shape[:-1]
        q2, v2 = q.reshape(-1, 7), v.reshape(-1, v.shape[-1])
        J = self.arm.jacobian(q2) if jacobian is None else jacobian.reshape(-1, 6, 7).to(q2)
        if v2.shape[-1] == 3:
            J = J[:, :3]
        else:
            w = self.orientation_weight
            J = torch.cat([J[:, :3], w * J[:, 3:]], 1)
            v2 = torch.cat([v2[:, :3], w * v2[:, 3:]], -1)
        qdot = self._solve(q2, v2, J, dt)
        return qdot.reshape(*batch, 7)

    def _solve(self, q: torch.Tensor, v: torch.Tensor, J: torch.Tensor, dt: float) -> torch.Tensor:
        m = J.shape[1]
        eye_m = torch.eye(m, dtype=q.dtype, device=q.device)
        eye7 = torch.eye(7, dtype=q.dtype, device=q.device)
        lam2 = self.damping**2
        vmax = self.arm.velocity_limits(q.dtype, q.device)
        lo = self.arm.lower(q.dtype, q.device) + self.limit_buffer
        hi = self.arm.upper(q.dtype, q.device) - self.limit_buffer
        # bounds of qdot for one period: speed limits and position limits (towards the range when outside it)
        qd_lo = torch.maximum(-vmax, (lo - q) / dt).clamp(max=vmax)
        qd_hi = torch.minimum(vmax, (hi - q) / dt).clamp(min=-vmax)
        qd_hi = torch.maximum(qd_hi, qd_lo)
        z = self.null_velocity(q)

        def dls(Jw: torch.Tensor, rhs: torch.Tensor, zw: torch.Tensor) -> torch.Tensor:
            A = Jw @ Jw.transpose(1, 2) + lam2 * eye_m
            pinv = Jw.transpose(1, 2) @ torch.linalg.solve(A, eye_m.expand_as(A))  # (B, 7, m)
            if self.null_space == "exact":
                _, sv, vh = torch.linalg.svd(Jw, full_matrices=True)  # vh (B, 7, 7); rows beyond rank: null space
                rank_mask = torch.cat([sv > 1e-9, sv.new_zeros(sv.shape[0], 7 - sv.shape[1], dtype=torch.bool)], -1)
                vr = vh * rank_mask[..., None].to(vh.dtype)
                proj = eye7 - vr.transpose(1, 2) @ vr
            else:
                proj = eye7 - pinv @ Jw
            return (pinv @ rhs[..., None]).squeeze(-1) + (proj @ zw[..., None]).squeeze(-1)

        qdot = dls(J, v, z)
        # speed limits: scale the whole qdot (and the task) so that the direction is kept
        scale = (vmax / qdot.abs().clamp_min(1e-12)).amin(-1, keepdim=True).clamp(max=1.0)
        # the clamp removes the rounding step past +-vmax that the product can leave on the joint that set the scale:
        # flagged as a violation, it would fix that joint and re-solve the others (qdot jumping with q by 1e-12 rad)
        v, z, qdot = v * scale, z * scale, torch.minimum(torch.maximum(qdot * scale, -vmax), vmax)
        free = torch.ones_like(q)
        fixed = torch.zeros_like(q)
        for _ in range(self.iterations):
            out = (qdot < qd_lo) | (qdot > qd_hi)
            redo = out.any(-1, keepdim=True)  # only the arms with a violated bound are re-solved: the others keep
            if not bool(redo.any()):  # their qdot bit for bit, whatever else shares the batch
                break
            fixed = torch.where(out & (free > 0), qdot.clamp(qd_lo, qd_hi), fixed)
            free = free * (~out).to(q.dtype)
            Jw = J * free[:, None, :]
            rhs = v - (J @ (fixed * (1 - free))[..., None]).squeeze(-1)
            qdot = torch.where(redo, free * dls(Jw, rhs, z * free) + (1 - free) * fixed, qdot)
        return torch.minimum(torch.maximum(qdot, qd_lo), qd_hi)


class ImpedanceController:
    """Joint-space PD impedance with gravity compensation (the law the MuJoCo plant evaluates at 1 kHz).

    Args:
        stiffness: (7,) kp (N m/rad) or one value; damping: (7,) kv (N m s/rad) or one value.
        effort_limits: (7,) |tau_PD| bound (N m); default the arm's effort limits.
        max_lag: bound (rad) on ``q_d - q`` carried from one period to the next by :meth:`reference`
            (0: the set-point restarts at the measured q every period; inf: a pure integrator).
    """

    def __init__(self, stiffness=None, damping=None, effort_limits=None, max_lag: float = 0.05):
        from lfd_torch.robot.plant import DEFAULT_DAMPING, DEFAULT_STIFFNESS

        self.stiffness = _vec7(DEFAULT_STIFFNESS if stiffness is None else stiffness, "stiffness")
        self.damping = _vec7(DEFAULT_DAMPING if damping is None else damping, "damping")
        if effort_limits is None:
            effort_limits = [j.effort for j in BAXTER_LEFT_TABLE if j.kind == "revolute"]
        self.effort_limits = _vec7(effort_limits, "effort_limits")
        joints = [j for j in BAXTER_LEFT_TABLE if j.kind == "revolute"]
        # the plant's position and velocity actuators clip their controls to these ranges (ctrlrange)
        self._q_range = torch.tensor([[j.lower for j in joints], [j.upper for j in joints]], dtype=torch.float64)
        self._qd_limit = torch.tensor([j.velocity for j in joints], dtype=torch.float64)
        if isinstance(max_lag, bool) or not isinstance(max_lag, (int, float)) or not max_lag >= 0:
            raise InvalidArgumentError(f"max_lag must be a number >= 0, got {max_lag!r}")
        self.max_lag = float(max_lag)

    def torque(self, q, qd, q_d, qd_d, gravity=None) -> torch.Tensor:
        """(B, 7) joint torque (N m): ``clamp(kp (q_d - q) + kv (qd_d - qd)) + gravity`` for (B, 7) inputs, with q_d
        clipped to the joint range and qd_d to the velocity limits first, as the plant's actuators clip their controls."""
        q = check_joint_tensor(q, "q")
        qd, q_d, qd_d = (check_joint_tensor(x, n) for x, n in ((qd, "qd"), (q_d, "q_d"), (qd_d, "qd_d")))
        _same_shape(q, qd=qd, q_d=q_d, qd_d=qd_d)
        kp, kv, tmax = (t.to(q) for t in (self.stiffness, self.damping, self.effort_limits))
        (lo, hi), vmax = self._q_range.to(q), self._qd_limit.to(q)
        q_d = torch.minimum(torch.maximum(q_d, lo), hi)
        qd_d = torch.minimum(torch.maximum(qd_d, -vmax), vmax)
        tau = torch.maximum(torch.minimum(kp * (q_d - q) + kv * (qd_d - qd), tmax), -tmax)
        if gravity is None:
            return tau
        gravity = check_joint_tensor(gravity, "gravity")
        _same_shape(q, gravity=gravity)
        return tau + gravity

    def reference(self, q, qdot, q_d_prev=None, dt: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
        """Set-point for the next period: ``q_d = q + clamp(q_d_prev - q, +-max_lag) + dt qdot``, ``qd_d = qdot``.

        ``q`` measured (B, 7) rad, ``qdot`` commanded (B, 7) rad/s, ``q_d_prev`` last set-point (B, 7) or None.
        """
        q = check_joint_tensor(q, "q")
        qdot = check_joint_tensor(qdot, "qdot")
        _same_shape(q, qdot=qdot)
        dt = _positive(dt, "dt", allow_zero=False)
        if q_d_prev is not None:
            q_d_prev = check_joint_tensor(q_d_prev, "q_d_prev")
            _same_shape(q, q_d_prev=q_d_prev)
        lag = torch.zeros_like(q) if q_d_prev is None else q_d_prev - q
        lag = lag.clamp(-self.max_lag, self.max_lag)
        return q + lag + dt * qdot, qdot
