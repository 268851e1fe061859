"""Batched kinematics of the Baxter left arm with pytorch-kinematics (issue 10, item 1).

:class:`BaxterArm` loads :func:`~lfd_torch.robot.urdf.baxter_left_urdf` with
``pytorch_kinematics.build_serial_chain_from_urdf`` (root ``torso``, end ``spoon_tip``) and gives forward
kinematics and the geometric Jacobian for joint angles ``q`` of shape (B, 7) (or (..., 7)), float32 or float64, on
the CPU or CUDA. One chain is kept per (dtype, device); the input's dtype and device choose it.

pytorch-kinematics parses URDF origins in float32. For float64 chains the static frame offsets are re-set from
:data:`~lfd_torch.robot.urdf.BAXTER_LEFT_TABLE` in float64, so float64 FK is exact to rounding (1e-15 m), which
the MuJoCo agreement test (1e-6 m) relies on; float32 chains keep pytorch-kinematics' own offsets.
"""

from __future__ import annotations

import torch

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, UnknownNameError
from lfd_torch.robot.urdf import (
    ARM_JOINT_NAMES,
    BAXTER_LEFT_TABLE,
    DEFAULT_TOOL_OFFSET,
    ROOT_LINK,
    TOOL_LINK,
    _check_tool_offset,
    baxter_left_urdf,
    rpy_to_matrix,
)
from lfd_torch.utils import check_float

__all__ = ["BaxterArm", "check_joint_tensor", "FRAME_NAMES", "LIMIT_TOLERANCE", "NEUTRAL_POSE"]

N_JOINTS = len(ARM_JOINT_NAMES)
#: rad beyond a joint limit that the limit checks still accept: angles stored in float32 (a log of a trial) are
#: the float64 ones rounded by up to 2e-7 rad on Baxter's ranges, and a limit reached exactly must pass both ways.
LIMIT_TOLERANCE = 1e-6
FRAME_NAMES: tuple[str, ...] = (ROOT_LINK,) + tuple(j.child for j in BAXTER_LEFT_TABLE) + (TOOL_LINK,)
# A comfortable pose in front of the robot, away from the limits (rad): spoon pointing down over the table.
NEUTRAL_POSE: tuple[float, ...] = (0.0, -0.55, 0.0, 1.25, 0.0, 0.85, 0.0)
_FLOATS = (torch.float32, torch.float64)


def check_joint_tensor(q: object, name: str = "q", n: int = N_JOINTS) -> torch.Tensor:
    """Validate joint-space input: a float32/float64 tensor of shape (..., n) without NaN or Inf.

    Raises:
        InvalidArgumentError: not a tensor, or a dtype other than float32/float64.
        ShapeMismatchError: last dimension is not ``n``.
        NonFiniteError: NaN or Inf entries.
    """
    if not isinstance(q, torch.Tensor):
        raise InvalidArgumentError(f"{name} must be a torch.Tensor of shape (B, {n}), got {type(q).__name__}")
    if q.dtype not in _FLOATS:
        raise InvalidArgumentError(f"{name} must be float32 or float64, got {q.dtype}")
    if q.ndim == 0 or q.shape[-1] != n:
        raise ShapeMismatchError(f"{name} must have shape (B, {n}), got {tuple(q.shape)}")
    if not bool(torch.isfinite(q).all()):
        raise NonFiniteError(f"{name} contains NaN or Inf")
    return q


def _origin_matrix(xyz, rpy) -> list[list[float]]:
    rot = rpy_to_matrix(rpy)
    return [rot[0] + [xyz[0]], rot[1] + [xyz[1]], rot[2] + [xyz[2]], [0.0, 0.0, 0.0, 1.0]]


class BaxterArm:
    """Baxter left arm + spoon: batched FK and Jacobian through pytorch-kinematics.

    Args:
        tool_offset: spoon-tip distance along the gripper z axis (m), in [0, 1]; default 0.12.

    Attributes:
        joint_names: the 7 joint names s0, s1, e0, e1, w0, w1, w2.
        urdf: the URDF text the chains were built from.
    """

    def __init__(self, tool_offset: float = DEFAULT_TOOL_OFFSET):
        self.tool_offset = _check_tool_offset(tool_offset)
        self.urdf = baxter_left_urdf(self.tool_offset)
        self.joint_names = ARM_JOINT_NAMES
        self._chains: dict[tuple[torch.dtype, str], object] = {}
        rows = [j for j in BAXTER_LEFT_TABLE if j.kind == "revolute"]
        self._lower = [j.lower for j in rows]
        self._upper = [j.upper for j in rows]
        self._velocity = [j.velocity for j in rows]
        self._effort = [j.effort for j in rows]
        chain = self.chain(torch.float64)
        names = tuple(chain.get_joint_parameter_names())
        if names != ARM_JOINT_NAMES:  # pragma: no cover - guards the URDF writer
            raise InvalidArgumentError(f"URDF joint order {names} differs from {ARM_JOINT_NAMES}")

    # ------------------------------------------------------------------ chains and limits
    def chain(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        """The ``pytorch_kinematics.SerialChain`` (torso -> spoon_tip) for ``dtype`` and ``device`` (cached)."""
        import pytorch_kinematics as pk

        if dtype not in _FLOATS:
            raise InvalidArgumentError(f"dtype must be float32 or float64, got {dtype}")
        device = torch.device(device)
        key = (dtype, str(device))
        if key not in self._chains:
            chain = pk.build_serial_chain_from_urdf(self.urdf, TOOL_LINK, ROOT_LINK).to(dtype=dtype, device=device)
            if dtype == torch.float64:
                self._set_exact_offsets(chain)
            self._chains[key] = chain
        return self._chains[key]

    def _set_exact_offsets(self, chain) -> None:
        rows = {j.child: j for j in BAXTER_LEFT_TABLE}
        offsets = chain._static_offsets.clone()
        for name, idx in chain.frame_to_idx.items():
            if name == ROOT_LINK:
                mat = _origin_matrix((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            elif name == TOOL_LINK:
                mat = _origin_matrix((0.0, 0.0, self.tool_offset), (0.0, 0.0, 0.0))
            else:
                mat = _origin_matrix(rows[name].xyz, rows[name].rpy)
            offsets[idx] = torch.tensor(mat, dtype=torch.float64, device=offsets.device)
        chain._static_offsets = offsets

    def lower(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
        """(7,) lower position limits (rad)."""
        return torch.tensor(self._lower, dtype=dtype, device=device)

    def upper(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
        """(7,) upper position limits (rad)."""
        return torch.tensor(self._upper, dtype=dtype, device=device)

    def velocity_limits(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
        """(7,) joint speed limits |qdot| (rad/s): 2.5 for s0-e1, 5 for w0-w2."""
        return torch.tensor(self._velocity, dtype=dtype, device=device)

    def effort_limits(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
        """(7,) joint torque limits |tau| (N m)."""
        return torch.tensor(self._effort, dtype=dtype, device=device)

    def neutral(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
        """(7,) :data:`NEUTRAL_POSE` (rad)."""
        return torch.tensor(NEUTRAL_POSE, dtype=dtype, device=device)

    def check_limits(self, q: torch.Tensor, name: str = "q", tol: float = LIMIT_TOLERANCE) -> torch.Tensor:
        """Validate ``q`` (..., 7) and check ``lower - tol <= q <= upper + tol``.

        Raises:
            InvalidArgumentError: naming ``name``, the first violating joint and its value; ``tol`` not a finite
                number >= 0.
        """
        q = check_joint_tensor(q, name)
        tol = check_float(tol, "tol", low=0.0)
        lo, hi = self.lower(q.dtype, q.device), self.upper(q.dtype, q.device)
        bad = (q < lo - tol) | (q > hi + tol)
        if bool(bad.any()):
            j = int(bad.reshape(-1, N_JOINTS).any(0).nonzero()[0])
            worst = q[..., j].reshape(-1)[bad[..., j].reshape(-1)][0].item()
            raise InvalidArgumentError(
                f"{name} violates the joint limits: {self.joint_names[j]} = {worst:.9g} rad outside "
                f"[{self._lower[j]:.9g}, {self._upper[j]:.9g}] (+- {tol:g})"
            )
        return q

    def within_limits(self, q: torch.Tensor, tol: float = 0.0) -> torch.Tensor:
        """(...,) bool: every joint of ``q`` (..., 7) within its position limits (+- ``tol`` rad)."""
        q = check_joint_tensor(q)
        tol = check_float(tol, "tol", low=0.0)
        return ((q >= self.lower(q.dtype, q.device) - tol) & (q <= self.upper(q.dtype, q.device) + tol)).all(-1)

    # ------------------------------------------------------------------ kinematics
    def _flat(self, q: torch.Tensor, name: str = "q") -> tuple[torch.Tensor, torch.Size]:
        q = check_joint_tensor(q, name)
        return q.reshape(-1, N_JOINTS), q.shape[:-1]

    def frame_transforms(self, q: torch.Tensor, analytical_grad: bool = True) -> torch.Tensor:
        """(..., F, 4, 4) poses of all :data:`FRAME_NAMES` (F = 12) in the torso frame (m), for ``q`` (..., 7) rad.

        ``analytical_grad=False`` makes autograd replay the forward ops instead of pytorch-kinematics' analytical
        backward (needed for second derivatives).
        """
        flat, batch = self._flat(q)
        chain = self.chain(flat.dtype, flat.device)
        mats = chain.forward_kinematics_tensor(flat, analytical_grad=analytical_grad)  # (F', B, 4, 4)
        order = [chain.frame_to_idx[n] for n in FRAME_NAMES]
        return mats[order].transpose(0, 1).reshape(*batch, len(FRAME_NAMES), 4, 4)

    def forward_kinematics(self, q: torch.Tensor, frame: str = TOOL_LINK, analytical_grad: bool = True) -> torch.Tensor:
        """(..., 4, 4) pose of ``frame`` (default the spoon tip) in the torso frame (m) for ``q`` (..., 7) rad."""
        if frame not in FRAME_NAMES:
            raise UnknownNameError("frame", frame, FRAME_NAMES)
        flat, batch = self._flat(q)
        chain = self.chain(flat.dtype, flat.device)
        mats = chain.forward_kinematics_tensor(flat, analytical_grad=analytical_grad)
        return mats[chain.frame_to_idx[frame]].reshape(*batch, 4, 4)

    def tip_position(self, q: torch.Tensor) -> torch.Tensor:
        """(..., 3) spoon-tip position in the torso frame (m) for ``q`` (..., 7) rad."""
        return self.forward_kinematics(q)[..., :3, 3]

    def jacobian(self, q: torch.Tensor) -> torch.Tensor:
        """(..., 6, 7) geometric Jacobian of the spoon tip in the torso frame: rows 0-2 linear (m/rad), 3-5
        angular (rad/rad), so [v; w] = J qdot."""
        return self.pose_and_jacobian(q)[1]

    def pose_and_jacobian(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Spoon-tip pose (..., 4, 4) and geometric Jacobian (..., 6, 7) from one FK pass, for ``q`` (..., 7)."""
        flat, batch = self._flat(q)
        chain = self.chain(flat.dtype, flat.device)
        jac, pose = chain.jacobian_tensor(flat, ret_eef_pose=True)
        return pose.reshape(*batch, 4, 4), jac.reshape(*batch, 6, N_JOINTS)

    def __repr__(self) -> str:
        return f"BaxterArm(tool_offset={self.tool_offset})"
