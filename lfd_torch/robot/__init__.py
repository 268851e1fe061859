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
(:func:`build_robot`, the ``conf/robot`` target), :mod:`~lfd_torch.robot.demonstration` (seeded kinesthetic-style
scooping demonstration, recorded-demonstration loader), :mod:`~lfd_torch.robot.task` (learning the task,
orientation schedule, the batched controller), :mod:`~lfd_torch.robot.trials` (disturbed MuJoCo trials, success
checks, Wilson intervals).
"""

from lfd_torch.robot.arm import FRAME_NAMES, NEUTRAL_POSE, BaxterArm, check_joint_tensor
from lfd_torch.robot.demonstration import (
    STAGE_NAMES,
    ScoopingDemonstration,
    load_demonstration,
    save_demonstration,
    scooping_demonstration,
    scooping_via_points,
    solve_ik,
)
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
from lfd_torch.robot.task import (
    ControlStep,
    OrientationSchedule,
    ScoopingController,
    ScoopingTask,
    controller_for,
    learn_scooping,
)
from lfd_torch.robot.trials import (
    DISTURBANCE_KINDS,
    FORBIDDEN_CONTACTS,
    Disturbance,
    SuccessCriteria,
    TrialBatch,
    check_trials,
    plan_disturbances,
    run_trials,
    start_configurations,
    wilson_interval,
)
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
    "BaxterArm",
    "BaxterPlant",
    "BaxterRobot",
    "ControlStep",
    "DEFAULT_DAMPING",
    "DEFAULT_STIFFNESS",
    "DEFAULT_TOOL_OFFSET",
    "DISTURBANCE_KINDS",
    "DLSVelocityMap",
    "Disturbance",
    "FORBIDDEN_CONTACTS",
    "FRAME_NAMES",
    "ImpedanceController",
    "JointSpec",
    "LINK_BODIES",
    "LinkBody",
    "NEUTRAL_POSE",
    "OrientationSchedule",
    "ROBOT_PARTS",
    "ROOT_LINK",
    "SCENE_OBJECTS",
    "STAGE_NAMES",
    "Scene",
    "ScoopingController",
    "ScoopingDemonstration",
    "ScoopingTask",
    "SuccessCriteria",
    "TOOL_LINK",
    "TrialBatch",
    "Vessel",
    "baxter_left_urdf",
    "baxter_mjcf",
    "build_robot",
    "check_joint_tensor",
    "check_trials",
    "controller_for",
    "cylinder_inertia",
    "learn_scooping",
    "load_demonstration",
    "orientation_error",
    "plan_disturbances",
    "rpy_to_matrix",
    "run_trials",
    "save_demonstration",
    "scooping_demonstration",
    "scooping_via_points",
    "solve_ik",
    "start_configurations",
    "wilson_interval",
]
