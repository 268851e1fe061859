"""Baxter left arm for the sugar-scooping task (paper Sec. V-B; issue 10): kinematics, MuJoCo plant, controllers.

Notation (symbols, shapes, units; B batch size; frames are the torso frame unless named):
    q, q_d              (B, 7)      joint angles s0, s1, e0, e1, w0, w1, w2: measured, set-point (rad)
    qdot, qd_d          (B, 7)      joint velocities: measured / commanded, set-point (rad/s)
    T                   (B, 4, 4)   homogeneous pose of a frame (rotation, translation in m)
    x                   (B, 3)      spoon-tip position (m); the tip is ``tool_offset`` m (0.12) along the gripper z
    J                   (B, 6, 7)   geometric Jacobian of the tip: rows 0-2 linear (m/rad), 3-5 angular (rad/rad)
    v                   (B, 3|6)    tip velocity command: linear (m/s) [; angular (rad/s)]
    lambda              float       DLS damping (m): J# = J^T (J J^T + lambda^2 I)^-1
    z                   (B, 7)      null-space joint velocity: posture and joint-limit terms (rad/s)
    kp, kv              (7,)        joint stiffness (N m/rad) and damping (N m s/rad)
    tau, g(q)           (B, 7)      joint torque, gravity-compensation torque (N m)
    dt                  float       control period (s): 0.01 (100 Hz decision engine); physics step 0.001 (1 kHz)

Modules: :mod:`~lfd_torch.robot.urdf` (kinematic table, URDF text), :mod:`~lfd_torch.robot.arm` (pytorch-kinematics
FK and Jacobian, limits), :mod:`~lfd_torch.robot.plant` (MuJoCo model and simulation: masses, inertias, geoms,
contacts), :mod:`~lfd_torch.robot.controller` (DLS velocity map, impedance law), :mod:`~lfd_torch.robot.system`
(:func:`build_robot`, the ``conf/robot`` target).
"""

from lfd_torch.robot.arm import FRAME_NAMES, NEUTRAL_POSE, BaxterArm, check_joint_tensor
from lfd_torch.robot.controller import DLSVelocityMap, ImpedanceController, orientation_error
from lfd_torch.robot.plant import (
    DEFAULT_DAMPING,
    DEFAULT_STIFFNESS,
    LINK_BODIES,
    ROBOT_PARTS,
    SCENE_OBJECTS,
    BaxterPlant,
    LinkBody,
    Scene,
    Vessel,
    baxter_mjcf,
    cylinder_inertia,
)
from lfd_torch.robot.system import BaxterRobot, build_robot
from lfd_torch.robot.urdf import (
    ARM_JOINT_NAMES,
    BAXTER_LEFT_TABLE,
    DEFAULT_TOOL_OFFSET,
    ROOT_LINK,
    TOOL_LINK,
    JointSpec,
    baxter_left_urdf,
    rpy_to_matrix,
)

__all__ = [
    "ARM_JOINT_NAMES",
    "BAXTER_LEFT_TABLE",
    "DEFAULT_DAMPING",
    "DEFAULT_STIFFNESS",
    "DEFAULT_TOOL_OFFSET",
    "FRAME_NAMES",
    "LINK_BODIES",
    "NEUTRAL_POSE",
    "ROBOT_PARTS",
    "ROOT_LINK",
    "SCENE_OBJECTS",
    "TOOL_LINK",
    "BaxterArm",
    "BaxterPlant",
    "BaxterRobot",
    "DLSVelocityMap",
    "ImpedanceController",
    "JointSpec",
    "LinkBody",
    "Scene",
    "Vessel",
    "baxter_left_urdf",
    "baxter_mjcf",
    "build_robot",
    "check_joint_tensor",
    "cylinder_inertia",
    "orientation_error",
    "rpy_to_matrix",
]
