"""Baxter left-arm kinematic table and the URDF string written from it (issue 10, item 1).

The numbers are the published Baxter left-arm parameters (parent -> child origin ``xyz`` in m, ``rpy`` in rad,
every revolute axis is the child's z). Nothing is downloaded: :func:`baxter_left_urdf` writes the URDF text from
:data:`BAXTER_LEFT_TABLE`, and the MuJoCo plant (:mod:`lfd_torch.robot.plant`) is built from the same table.

Frames (root ``torso``): torso -> left_arm_mount -> s0 ... w2 (7 revolute) -> left_hand (fixed) ->
left_gripper (fixed) -> spoon_tip (fixed, ``tool_offset`` m along the gripper z axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lfd_torch.errors import InvalidArgumentError

__all__ = [
    "JointSpec",
    "BAXTER_LEFT_TABLE",
    "ARM_JOINT_NAMES",
    "ROOT_LINK",
    "TOOL_LINK",
    "DEFAULT_TOOL_OFFSET",
    "baxter_left_urdf",
    "rpy_to_matrix",
]

HALF_PI = math.pi / 2.0
ROOT_LINK = "torso"
TOOL_LINK = "spoon_tip"
DEFAULT_TOOL_OFFSET = 0.12  # m along the gripper z axis (issue 10)


@dataclass(frozen=True)
class JointSpec:
    """One row of the kinematic table.

    Attributes:
        name: joint name (``left_s0`` ...); ``parent``/``child``: link names.
        xyz: (3,) child origin in the parent frame (m); ``rpy``: (3,) fixed-axis roll, pitch, yaw (rad).
        kind: ``"revolute"`` (about the child z axis) or ``"fixed"``.
        lower, upper: position limits (rad); ``velocity``: |qdot| limit (rad/s); ``effort``: |tau| limit (N m).
    """

    name: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    kind: str = "fixed"
    lower: float = 0.0
    upper: float = 0.0
    velocity: float = 0.0
    effort: float = 0.0


# Published Baxter left-arm parameters (issue 10). Effort limits: Baxter's rated 50 N m (s0-e1), 15 N m (w0-w2).
BAXTER_LEFT_TABLE: tuple[JointSpec, ...] = (
    JointSpec("left_torso_arm_mount", "torso", "left_arm_mount", (0.024645, 0.219645, 0.118588), (0.0, 0.0, 0.7854)),
    JointSpec("left_s0", "left_arm_mount", "left_upper_shoulder", (0.055695, 0.0, 0.011038), (0.0, 0.0, 0.0),
              "revolute", -1.70168, 1.70168, 2.5, 50.0),
    JointSpec("left_s1", "left_upper_shoulder", "left_lower_shoulder", (0.069, 0.0, 0.27035), (-HALF_PI, 0.0, 0.0),
              "revolute", -2.147, 1.047, 2.5, 50.0),
    JointSpec("left_e0", "left_lower_shoulder", "left_upper_elbow", (0.102, 0.0, 0.0), (HALF_PI, 0.0, HALF_PI),
              "revolute", -3.05418, 3.05418, 2.5, 50.0),
    JointSpec("left_e1", "left_upper_elbow", "left_lower_elbow", (0.069, 0.0, 0.26242), (-HALF_PI, -HALF_PI, 0.0),
              "revolute", -0.05, 2.618, 2.5, 50.0),
    JointSpec("left_w0", "left_lower_elbow", "left_upper_forearm", (0.10359, 0.0, 0.0), (HALF_PI, 0.0, HALF_PI),
              "revolute", -3.059, 3.059, 5.0, 15.0),
    JointSpec("left_w1", "left_upper_forearm", "left_lower_forearm", (0.01, 0.0, 0.2707), (-HALF_PI, -HALF_PI, 0.0),
              "revolute", -HALF_PI, 2.094, 5.0, 15.0),
    JointSpec("left_w2", "left_lower_forearm", "left_wrist", (0.115975, 0.0, 0.0), (HALF_PI, 0.0, HALF_PI),
              "revolute", -3.059, 3.059, 5.0, 15.0),
    JointSpec("left_hand", "left_wrist", "left_hand", (0.0, 0.0, 0.11355)),
    JointSpec("left_gripper", "left_hand", "left_gripper", (0.0, 0.0, 0.05)),
)

ARM_JOINT_NAMES: tuple[str, ...] = tuple(j.name for j in BAXTER_LEFT_TABLE if j.kind == "revolute")


def rpy_to_matrix(rpy: tuple[float, float, float]) -> list[list[float]]:
    """URDF fixed-axis roll-pitch-yaw (rad) -> 3x3 rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` as nested lists."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]


def _fmt(v: tuple[float, ...]) -> str:
    return " ".join(repr(float(x)) for x in v)


def _check_tool_offset(tool_offset: float) -> float:
    if isinstance(tool_offset, bool) or not isinstance(tool_offset, (int, float)) or not math.isfinite(tool_offset):
        raise InvalidArgumentError(f"tool_offset must be a finite number (m), got {tool_offset!r}")
    if not 0.0 <= tool_offset <= 1.0:
        raise InvalidArgumentError(f"tool_offset must lie in [0, 1] m, got {tool_offset}")
    return float(tool_offset)


def baxter_left_urdf(tool_offset: float = DEFAULT_TOOL_OFFSET) -> str:
    """The URDF text of the Baxter left arm with a spoon-tip frame ``tool_offset`` m along the gripper z axis.

    Kinematics only (links carry no inertia: the controller's model is kinematic; the MuJoCo plant carries the
    dynamics). Joint limits, velocity and effort limits are those of :data:`BAXTER_LEFT_TABLE`.
    """
    tool_offset = _check_tool_offset(tool_offset)
    rows = list(BAXTER_LEFT_TABLE) + [JointSpec("spoon", "left_gripper", TOOL_LINK, (0.0, 0.0, tool_offset))]
    links = [ROOT_LINK] + [j.child for j in rows]
    out = ['<?xml version="1.0"?>', '<robot name="baxter_left_arm">']
    out += [f'  <link name="{name}"/>' for name in links]
    for j in rows:
        out.append(f'  <joint name="{j.name}" type="{j.kind}">')
        out.append(f'    <parent link="{j.parent}"/>')
        out.append(f'    <child link="{j.child}"/>')
        out.append(f'    <origin xyz="{_fmt(j.xyz)}" rpy="{_fmt(j.rpy)}"/>')
        if j.kind == "revolute":
            out.append('    <axis xyz="0 0 1"/>')
            out.append(f'    <limit lower="{j.lower!r}" upper="{j.upper!r}" velocity="{j.velocity!r}" effort="{j.effort!r}"/>')
        out.append("  </joint>")
    out.append("</robot>")
    return "\n".join(out) + "\n"
