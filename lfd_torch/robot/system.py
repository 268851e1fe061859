"""One object holding the arm model, the MuJoCo plant and the controllers, built from a config (conf/robot)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from lfd_torch.errors import UnknownNameError
from lfd_torch.robot.arm import BaxterArm
from lfd_torch.robot.controller import DLSVelocityMap, ImpedanceController
from lfd_torch.robot.plant import DEFAULT_ARMATURE, DEFAULT_DAMPING, DEFAULT_STIFFNESS, BaxterPlant, Scene
from lfd_torch.robot.urdf import DEFAULT_TOOL_OFFSET

__all__ = ["BaxterRobot", "build_robot"]

_VELOCITY_KEYS = ("damping", "null_gain", "posture", "limit_margin", "limit_gain", "limit_buffer",
                  "orientation_weight", "iterations", "null_space")


@dataclass
class BaxterRobot:
    """The pieces of issue 10's robot: ``arm`` (pytorch-kinematics model), ``plant`` (MuJoCo), ``velocity_map``
    (DLS, 100 Hz) and ``impedance`` (PD + gravity compensation law and set-point rule)."""

    arm: BaxterArm
    plant: BaxterPlant
    velocity_map: DLSVelocityMap
    impedance: ImpedanceController


def build_robot(
    tool_offset: float = DEFAULT_TOOL_OFFSET,
    stiffness=DEFAULT_STIFFNESS,
    damping=DEFAULT_DAMPING,
    armature=DEFAULT_ARMATURE,
    max_lag: float = 0.05,
    timestep: float = 0.001,
    control_period: float = 0.01,
    interpolate: bool = True,
    scene: Scene | Mapping | None = None,
    velocity_map: Mapping | None = None,
) -> BaxterRobot:
    """Build arm, plant and controllers sharing one ``tool_offset`` and one set of gains.

    Args:
        tool_offset: spoon tip along the gripper z axis (m). stiffness, damping: (7,) joint impedance
            (N m/rad, N m s/rad). armature: (7,) rotor inertia (kg m^2). max_lag: set-point lag bound (rad).
        timestep: physics step (s). control_period: decision-engine period (s). interpolate: ramp the position
            set-point at the commanded velocity within the period (see :class:`~lfd_torch.robot.plant.BaxterPlant`).
        scene: :class:`~lfd_torch.robot.plant.Scene` fields (nested mapping). velocity_map: keyword arguments
            of :class:`~lfd_torch.robot.controller.DLSVelocityMap` (except ``arm``).
    """
    if velocity_map is not None and not isinstance(velocity_map, Mapping):
        from lfd_torch.errors import InvalidArgumentError

        raise InvalidArgumentError(f"velocity_map must be a mapping of DLSVelocityMap options or None, got {velocity_map!r}")
    spec = dict(velocity_map or {})
    unknown = set(spec) - set(_VELOCITY_KEYS)
    if unknown:
        raise UnknownNameError("velocity_map option", sorted(unknown)[0], _VELOCITY_KEYS)
    if "posture" in spec and spec["posture"] is not None:
        spec["posture"] = list(spec["posture"])
    arm = BaxterArm(tool_offset)
    plant = BaxterPlant(tool_offset, scene, stiffness, damping, armature, timestep, control_period, interpolate)
    return BaxterRobot(
        arm=arm,
        plant=plant,
        velocity_map=DLSVelocityMap(arm, **spec),
        impedance=ImpedanceController(plant.stiffness, plant.damping, arm.effort_limits(), max_lag),
    )
