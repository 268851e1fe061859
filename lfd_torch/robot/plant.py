"""MuJoCo plant of the Baxter left arm with the scooping scene (issue 10, item 2).

The MJCF model is written from :data:`~lfd_torch.robot.urdf.BAXTER_LEFT_TABLE` (the table the pytorch-kinematics
chain is built from), so the MuJoCo spoon-tip site and :class:`~lfd_torch.robot.arm.BaxterArm` agree to rounding.

Physical model (stated here; plausible values, not identified from a real robot):

* Links are capsules from a joint's origin to the next joint's origin. Masses (kg) are close to the published
  Baxter description: upper shoulder 5.70, lower shoulder 3.23, upper elbow 4.31, lower elbow 2.07, upper forearm
  2.25, lower forearm 1.61, wrist 0.35, hand 0.19, gripper 0.30, spoon 0.05 (20.06 kg in all). Each centre of mass is
  at the capsule midpoint and the inertia is that of a solid cylinder of the capsule's radius and length about it
  (:func:`cylinder_inertia`), with a floor of 1e-5 kg m^2.
* Joints: the table's limits as MuJoCo joint ranges (hard limits), rotor armature 0.05 kg m^2 (s0-e1) and 0.01
  (w0-w2), viscous friction 0.1 N m s/rad, actuator torque clamped at the effort limits (50 / 15 N m).
* Controller (:class:`~lfd_torch.robot.controller.ImpedanceController` is the same law in torch): per joint a
  position actuator (stiffness ``kp``) and a velocity actuator (damping ``kv``), their sum clamped at the effort
  limit, plus gravity compensation of every link (MuJoCo ``gravcomp="1"``, exact for this model):
  ``tau = clamp(kp (q_d - q) + kv (qdot_d - qdot)) + g(q)``, evaluated by MuJoCo every physics step (1 kHz). The
  compensation is not clamped: Baxter's shoulder carries a gravity-assist spring, and the stretched arm needs
  up to 55 N m at s1 (54.3 N m at q = 0), more than its 50 N m rating.
* Scene (torso frame, m): a table (box), a sugar can and a coffee cup (open cylinders: a bottom disc and
  ``n_wall`` box staves), the sugar as a non-colliding volume inside the can, the spoon (handle capsule + bowl
  sphere) on the gripper. Arm geoms collide with the scene, not with each other.

Contacts are read from ``MjData.contact`` and named by robot part (``arm``, ``hand``, ``spoon``) and object
(``table``, ``can_wall``, ``can_bottom``, ``cup_wall``, ``cup_bottom``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError, UnknownNameError
from lfd_torch.robot.arm import LIMIT_TOLERANCE
from lfd_torch.robot.urdf import (
    ARM_JOINT_NAMES,
    BAXTER_LEFT_TABLE,
    DEFAULT_TOOL_OFFSET,
    ROOT_LINK,
    TOOL_LINK,
    _check_tool_offset,
    rpy_to_matrix,
)
from lfd_torch.utils import real_array

__all__ = [
    "LinkBody",
    "LINK_BODIES",
    "Vessel",
    "Scene",
    "DEFAULT_STIFFNESS",
    "DEFAULT_DAMPING",
    "cylinder_inertia",
    "baxter_mjcf",
    "BaxterPlant",
    "ROBOT_PARTS",
    "SCENE_OBJECTS",
]

N = len(ARM_JOINT_NAMES)
# Joint-space impedance (N m/rad, N m s/rad). The spoon works with about 20 mm of clearance to the can wall while it
# drags through the sugar (the demonstration's bowl is 18-28 mm from the staves at the bottom of the dip), and the
# disturbed trials shove the forearm or wrist with 15-30 N (small) and 60-90 N (large) pulses of 0.2-0.4 s. The
# stiffness is chosen from that requirement, not from the nominal tracking alone:
# * s0-e1 1600 / 1600 / 1000 / 1000 N m/rad: in the scoop pose the tip's translational stiffness (all 7 joints
#   compliant) is then 0.7-0.8 kN/m in its softest directions (5.5 kN/m along the stretched arm), the range of
#   impedance-controlled arms doing contact-free work; a 15-30 N pulse moves the held tip a median 7 mm (9 in 10
#   below 16 mm). At 400 / 400 / 250 / 250 N m/rad it was 0.17-0.19 kN/m, and the same pulses moved the tip a
#   median 31 mm (9 in 10 below 62 mm): into the wall, under the weakest push of the trials. The PD torque meets the
#   50 N m effort limit at 0.03-0.05 rad of error: a 60-90 N pulse on the wrist can still exceed what the joints
#   may exert (the shoulder lever is about 0.7 m), and then the arm yields at the effort limit.
# * w0, w1 250 N m/rad and w2 120 N m/rad: the wrist holds the spoon's orientation against a push on the wrist body
#   instead of letting the handle swing (15 N m effort limit reached at 0.06-0.13 rad).
# Damping: overdamped, damping ratio zeta = kv / (2 sqrt(kp I)) about 1.7-2.5 for the joint inertia I (armature
# included) in the scoop pose: I about 2.3-3.1 (s0), 2.0-2.7 (s1), 1.0 (e0), 0.77 (e1), 0.05 (w0), 0.067 (w1),
# 0.010 (w2) kg m^2 (w2: zeta 3.6). A pulse of 0.2-0.4 s is shorter than the arm's rise time, so the velocity
# feedback carries much of the resistance, and the overdamped return does not overshoot into the wall; tracking is
# unaffected (the velocity actuator follows the set-point velocity qd_d, not zero). At 1 kHz the stiffest mode
# (w2, about 110 rad/s) is well inside the stable range of the implicit-in-velocity integrator.
DEFAULT_STIFFNESS: tuple[float, ...] = (1600.0, 1600.0, 1000.0, 1000.0, 250.0, 250.0, 120.0)
DEFAULT_DAMPING: tuple[float, ...] = (240.0, 240.0, 140.0, 140.0, 16.0, 16.0, 8.0)
DEFAULT_ARMATURE: tuple[float, ...] = (0.05, 0.05, 0.05, 0.05, 0.01, 0.01, 0.01)
JOINT_FRICTION = 0.1  # viscous damping in every joint (N m s/rad)
ROBOT_PARTS = ("arm", "hand", "spoon")
SCENE_OBJECTS = ("table", "can_wall", "can_bottom", "cup_wall", "cup_bottom")


@dataclass(frozen=True)
class LinkBody:
    """Mass model of one moving link: ``mass`` (kg) on a capsule of ``radius`` (m) spanning the link."""

    link: str
    mass: float
    radius: float


LINK_BODIES: tuple[LinkBody, ...] = (
    LinkBody("left_upper_shoulder", 5.70, 0.070),
    LinkBody("left_lower_shoulder", 3.23, 0.060),
    LinkBody("left_upper_elbow", 4.31, 0.055),
    LinkBody("left_lower_elbow", 2.07, 0.050),
    LinkBody("left_upper_forearm", 2.25, 0.045),
    LinkBody("left_lower_forearm", 1.61, 0.040),
    LinkBody("left_wrist", 0.35, 0.035),
    LinkBody("left_hand", 0.19, 0.035),
    LinkBody("left_gripper", 0.30, 0.030),
)
SPOON_MASS = 0.05  # kg
SPOON_HANDLE_RADIUS = 0.005  # m
SPOON_BOWL_RADIUS = 0.015  # m


@dataclass(frozen=True)
class Vessel:
    """An open cylinder standing on the table: ``center`` (x, y) (m), ``radius`` (inner, m), ``height`` (m),
    ``wall`` thickness (m), ``fill`` height of the content above the bottom (m; the sugar in the can)."""

    center: tuple[float, float]
    radius: float
    height: float
    wall: float = 0.004
    fill: float = 0.0


@dataclass(frozen=True)
class Scene:
    """Scooping scene in the torso frame (m). ``table_top`` z of the table surface; ``table_center`` (x, y) and
    ``table_half`` (half extents x, y) of the table top; ``can`` and ``cup`` :class:`Vessel` s on it; ``n_wall``
    staves per vessel wall."""

    table_top: float = -0.30
    table_center: tuple[float, float] = (0.75, 0.55)
    table_half: tuple[float, float] = (0.35, 0.55)
    can: Vessel = field(default_factory=lambda: Vessel((0.70, 0.55), 0.06, 0.12, fill=0.07))
    cup: Vessel = field(default_factory=lambda: Vessel((0.55, 0.85), 0.045, 0.09))
    n_wall: int = 16

    @classmethod
    def from_mapping(cls, spec: "Scene | Mapping | None") -> "Scene":
        """A :class:`Scene` from a Scene, None (defaults) or a (nested) mapping of its fields."""
        if spec is None:
            return cls()
        if isinstance(spec, Scene):
            return spec
        if not isinstance(spec, Mapping):
            raise InvalidArgumentError(f"scene must be a Scene or a mapping, got {type(spec).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = set(spec) - names
        if unknown:
            raise UnknownNameError("scene field", sorted(unknown)[0], sorted(names))
        kwargs = {}
        base = cls()
        for k, v in spec.items():
            if k in ("can", "cup"):
                if isinstance(v, Mapping):
                    v = replace(getattr(base, k), **{kk: tuple(vv) if kk == "center" else vv for kk, vv in v.items()})
            elif k in ("table_center", "table_half"):
                v = tuple(v)
            kwargs[k] = v
        return cls(**kwargs)

    def to_dict(self) -> dict:
        return asdict(self)


def cylinder_inertia(mass: float, radius: float, length: float) -> tuple[float, float, float]:
    """Principal inertia (kg m^2) of a solid cylinder about its centre: (I_perp, I_perp, I_axis)."""
    i_axis = 0.5 * mass * radius**2
    i_perp = mass * (3.0 * radius**2 + length**2) / 12.0
    return (max(i_perp, 1e-5), max(i_perp, 1e-5), max(i_axis, 1e-5))


def _f(x) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(x))


def _quat(rpy) -> np.ndarray:
    """(w, x, y, z) unit quaternion of the URDF rpy rotation (float64), w >= 0.

    scipy's conversion takes the quaternion from its largest component, so it stays exact for half turns about any
    axis, where w ~ 0 and the signs of x, y, z read off differences of matrix entries would be rounding noise."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.array(rpy_to_matrix(rpy))).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def _segment_inertial(mass: float, radius: float, a: np.ndarray, b: np.ndarray) -> str:
    """<inertial> of a solid cylinder from a to b (body frame)."""
    d = b - a
    length = float(np.linalg.norm(d))
    ip, _, ia = cylinder_inertia(mass, radius, length)
    if length < 1e-9:
        rot = np.eye(3)
    else:
        z = d / length
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z], axis=1)
    full = rot @ np.diag([ip, ip, ia]) @ rot.T
    vals = [full[0, 0], full[1, 1], full[2, 2], full[0, 1], full[0, 2], full[1, 2]]
    return f'<inertial pos="{_f((a + b) / 2)}" mass="{mass!r}" fullinertia="{_f(vals)}"/>'


def _vessel_xml(name: str, v: Vessel, table_top: float, n_wall: int, sugar: bool) -> list[str]:
    cx, cy = v.center
    out = [f'<body name="{name}" pos="{_f((cx, cy, table_top))}">']
    out.append(f'  <geom name="{name}/bottom" type="cylinder" size="{_f((v.radius + v.wall, v.wall / 2))}" '
               f'pos="0 0 {v.wall / 2!r}" class="scene" rgba="0.6 0.6 0.65 1"/>')
    r_mid = v.radius + v.wall / 2
    half_w = r_mid * math.tan(math.pi / n_wall) * 1.05  # staves overlap slightly: no gaps
    for k in range(n_wall):
        ang = 2 * math.pi * k / n_wall
        pos = (r_mid * math.cos(ang), r_mid * math.sin(ang), v.wall + v.height / 2)
        out.append(f'  <geom name="{name}/wall{k}" type="box" size="{_f((v.wall / 2, half_w, v.height / 2))}" '
                   f'pos="{_f(pos)}" euler="0 0 {ang!r}" class="scene" rgba="0.7 0.7 0.75 0.5"/>')
    if sugar and v.fill > 0:
        out.append(f'  <geom name="{name}/sugar" type="cylinder" size="{_f((v.radius, v.fill / 2))}" '
                   f'pos="0 0 {v.wall + v.fill / 2!r}" contype="0" conaffinity="0" group="2" rgba="1 1 0.95 0.6"/>')
        out.append(f'  <site name="{name}/sugar_surface" pos="0 0 {v.wall + v.fill!r}" size="0.005"/>')
    out.append(f'  <site name="{name}/rim" pos="0 0 {v.wall + v.height!r}" size="0.005"/>')
    out.append("</body>")
    return out


def baxter_mjcf(
    tool_offset: float = DEFAULT_TOOL_OFFSET,
    scene: Scene | Mapping | None = None,
    stiffness: tuple[float, ...] = DEFAULT_STIFFNESS,
    damping: tuple[float, ...] = DEFAULT_DAMPING,
    armature: tuple[float, ...] = DEFAULT_ARMATURE,
    timestep: float = 0.001,
) -> str:
    """MJCF text of the Baxter left arm, spoon and scene (see the module docstring for the physical model)."""
    tool_offset = _check_tool_offset(tool_offset)
    scene = Scene.from_mapping(scene)
    kp, kv, arm_ = (_gains(v, name) for v, name in ((stiffness, "stiffness"), (damping, "damping"), (armature, "armature")))
    if not (isinstance(timestep, (int, float)) and 0 < timestep <= 0.01):
        raise InvalidArgumentError(f"timestep must lie in (0, 0.01] s, got {timestep!r}")
    rows = list(BAXTER_LEFT_TABLE)
    mass = {b.link: b for b in LINK_BODIES}
    out = [
        '<mujoco model="baxter_left_scooping">',
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{float(timestep)!r}" integrator="implicitfast" gravity="0 0 -9.81"/>',
        "  <default>",
        '    <default class="arm"><geom contype="1" conaffinity="2" condim="3" rgba="0.75 0.1 0.1 1"/></default>',
        '    <default class="scene"><geom contype="2" conaffinity="1" condim="3"/></default>',
        "  </default>",
        "  <worldbody>",
        f'    <body name="{ROOT_LINK}">',
        f'      <geom name="table" type="box" class="scene" rgba="0.55 0.4 0.25 1" '
        f'size="{_f((*scene.table_half, 0.02))}" pos="{_f((*scene.table_center, scene.table_top - 0.02))}"/>',
    ]
    out += ["      " + s for s in _vessel_xml("can", scene.can, scene.table_top, scene.n_wall, sugar=True)]
    out += ["      " + s for s in _vessel_xml("cup", scene.cup, scene.table_top, scene.n_wall, sugar=False)]
    depth = 3
    k = 0
    for i, j in enumerate(rows):
        ind = "  " * depth
        out.append(f'{ind}<body name="{j.child}" pos="{_f(j.xyz)}" quat="{_f(_quat(j.rpy))}" gravcomp="1">')
        if j.kind == "revolute":
            out.append(f'{ind}  <joint name="{j.name}" type="hinge" axis="0 0 1" range="{_f((j.lower, j.upper))}" '
                       f'armature="{arm_[k]!r}" damping="{JOINT_FRICTION!r}" actuatorfrcrange="{_f((-j.effort, j.effort))}" '
                       '/>')
            k += 1
        if j.child == "left_gripper":  # two fingers, 4 cm long, ending at the gripper frame
            b = mass[j.child]
            out.append(f"{ind}  {_segment_inertial(b.mass, b.radius, np.array([0, 0, -0.04]), np.zeros(3))}")
            for side in (-1, 1):
                out.append(f'{ind}  <geom name="hand/finger{(side + 1) // 2}" type="box" class="arm" '
                           f'size="0.01 0.005 0.02" pos="0 {0.015 * side!r} -0.02"/>')
        elif j.child in mass:
            b = mass[j.child]
            nxt, a = np.array(rows[i + 1].xyz), np.zeros(3)
            out.append(f"{ind}  {_segment_inertial(b.mass, b.radius, a, nxt)}")
            part = "hand" if j.child == "left_hand" else "arm"
            out.append(f'{ind}  <geom name="{part}/{j.child}" type="capsule" class="arm" size="{b.radius!r}" '
                       f'fromto="{_f((*a, *nxt))}"/>')
        depth += 1
        if j.child == "left_gripper":
            ind = "  " * depth
            bowl = max(tool_offset - SPOON_BOWL_RADIUS, 0.0)
            out.append(f'{ind}<body name="spoon" gravcomp="1">')
            out.append(f"{ind}  {_segment_inertial(SPOON_MASS, SPOON_HANDLE_RADIUS, np.zeros(3), np.array([0, 0, tool_offset]))}")
            if bowl > 1e-9:
                out.append(f'{ind}  <geom name="spoon/handle" type="capsule" class="arm" rgba="0.8 0.8 0.85 1" '
                           f'size="{SPOON_HANDLE_RADIUS!r}" fromto="0 0 0 0 0 {bowl!r}"/>')
            out.append(f'{ind}  <geom name="spoon/bowl" type="sphere" class="arm" rgba="0.8 0.8 0.85 1" '
                       f'size="{SPOON_BOWL_RADIUS!r}" pos="0 0 {bowl!r}"/>')
            out.append(f'{ind}  <site name="{TOOL_LINK}" pos="0 0 {tool_offset!r}" size="0.004" rgba="0 0 1 1"/>')
            out.append(f"{ind}</body>")
    for d in range(depth - 1, 2, -1):
        out.append("  " * d + "</body>")
    out += ["    </body>", "  </worldbody>", "  <actuator>"]
    for i, j in enumerate(r for r in rows if r.kind == "revolute"):
        out.append(f'    <position name="kp_{j.name}" joint="{j.name}" kp="{kp[i]!r}" ctrlrange="{_f((j.lower, j.upper))}"/>')
    for i, j in enumerate(r for r in rows if r.kind == "revolute"):
        out.append(f'    <velocity name="kv_{j.name}" joint="{j.name}" kv="{kv[i]!r}" ctrlrange="{_f((-j.velocity, j.velocity))}"/>')
    out += ["  </actuator>", "</mujoco>"]
    return "\n".join(out) + "\n"


def _gains(values, name: str) -> tuple[float, ...]:
    arr = real_array(values, name)
    if arr.shape not in ((), (1,), (N,)):
        raise ShapeMismatchError(f"{name} must have {N} entries (or 1), got shape {arr.shape}")
    vals = tuple(float(v) for v in np.broadcast_to(arr, (N,)))
    if not all(math.isfinite(v) and v >= 0 for v in vals):
        raise InvalidArgumentError(f"{name} must be 7 finite values >= 0, got {values!r}")
    return vals


class BaxterPlant:
    """The MuJoCo simulation of the Baxter left arm in the scooping scene; one ``MjData`` per instance.

    Args:
        tool_offset: spoon-tip distance along the gripper z axis (m).
        scene: :class:`Scene`, a mapping of its fields, or None (defaults).
        stiffness, damping: (7,) joint impedance ``kp`` (N m/rad), ``kv`` (N m s/rad) (or one value for all).
        armature: (7,) rotor inertia (kg m^2).
        timestep: physics step (s); 0.001 = 1 kHz.
        control_period: period of :meth:`step` (s); 0.01 = the 100 Hz decision engine. A multiple of ``timestep``.
        interpolate: ramp the position set-point over the period at the commanded velocity, one value per physics
            step (``q_d - qd_d (period - t)``, reaching ``q_d`` at the end), instead of holding ``q_d``.
    """

    def __init__(
        self,
        tool_offset: float = DEFAULT_TOOL_OFFSET,
        scene: Scene | Mapping | None = None,
        stiffness=DEFAULT_STIFFNESS,
        damping=DEFAULT_DAMPING,
        armature=DEFAULT_ARMATURE,
        timestep: float = 0.001,
        control_period: float = 0.01,
        interpolate: bool = True,
    ):
        import mujoco

        self._mj = mujoco
        self.scene = Scene.from_mapping(scene)
        self.tool_offset = _check_tool_offset(tool_offset)
        self.stiffness = _gains(stiffness, "stiffness")
        self.damping = _gains(damping, "damping")
        self.xml = baxter_mjcf(self.tool_offset, self.scene, self.stiffness, self.damping, armature, timestep)
        self.model = mujoco.MjModel.from_xml_string(self.xml)
        n_sub = control_period / timestep if isinstance(control_period, (int, float)) else float("nan")
        if not (math.isfinite(n_sub) and n_sub >= 1 and abs(n_sub - round(n_sub)) < 1e-9):
            raise InvalidArgumentError(
                f"control_period must be a positive multiple of timestep={timestep}, got {control_period!r}")
        self.n_substeps = int(round(n_sub))
        self.timestep = float(timestep)
        self.control_period = float(control_period)
        self.interpolate = bool(interpolate)
        self.data = mujoco.MjData(self.model)
        self._setpoint = np.zeros(N)
        m = self.model
        self.joint_ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ARM_JOINT_NAMES])
        self.qpos_adr = m.jnt_qposadr[self.joint_ids]
        self.dof_adr = m.jnt_dofadr[self.joint_ids]
        self.tip_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, TOOL_LINK)
        self.lower = m.jnt_range[self.joint_ids, 0].copy()
        self.upper = m.jnt_range[self.joint_ids, 1].copy()
        self.body_ids = {m.body(i).name: i for i in range(m.nbody)}
        self._geom_class = self._classify_geoms()
        self._geom_part = np.full(m.ngeom, -1)
        self._geom_object = np.full(m.ngeom, -1)
        for g, (kind, name) in self._geom_class.items():
            if kind == "robot":
                self._geom_part[g] = ROBOT_PARTS.index(name)
            else:
                self._geom_object[g] = SCENE_OBJECTS.index(name)
        self.reset()

    # ------------------------------------------------------------------ state
    def _classify_geoms(self) -> dict[int, tuple[str, str]]:
        out = {}
        for g in range(self.model.ngeom):
            name = self.model.geom(g).name
            head = name.split("/")[0]
            if head in ROBOT_PARTS:
                out[g] = ("robot", head)
            elif name == "table":
                out[g] = ("scene", "table")
            elif head in ("can", "cup"):
                tail = name.split("/")[1]
                out[g] = ("scene", f"{head}_{'bottom' if tail == 'bottom' else 'wall'}")
        return out

    def new_data(self):
        """A fresh ``MjData`` of the same model."""
        return self._mj.MjData(self.model)

    def fork(self) -> "BaxterPlant":
        """A plant sharing this one's (read-only) model with its own fresh ``MjData``, reset to the neutral pose:
        one per parallel trial, without recompiling the model."""
        other = object.__new__(BaxterPlant)
        other.__dict__.update(self.__dict__)
        other.data = self.new_data()
        other._setpoint = np.zeros(N)
        other.reset()
        return other

    def reset(self, q=None, qd=None) -> None:
        """Set the arm to ``q`` (7,) rad (default the neutral pose), ``qd`` (7,) rad/s (default 0), hold ``q``."""
        from lfd_torch.robot.arm import NEUTRAL_POSE

        q = np.array(NEUTRAL_POSE, dtype=float) if q is None else real_array(q, "q")
        qd = np.zeros(N) if qd is None else real_array(qd, "qd")
        self._check7(q, "q")
        self._check7(qd, "qd")
        bad = (q < self.lower - LIMIT_TOLERANCE) | (q > self.upper + LIMIT_TOLERANCE)
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise InvalidArgumentError(f"q violates the joint limits: {ARM_JOINT_NAMES[j]} = {q[j]:.9g} rad outside "
                                       f"[{self.lower[j]:.9g}, {self.upper[j]:.9g}] (+- {LIMIT_TOLERANCE:g})")
        self._mj.mj_resetData(self.model, self.data)
        self.data.qpos[self.qpos_adr] = q
        self.data.qvel[self.dof_adr] = qd
        self.set_command(q, np.zeros(N))
        self._mj.mj_forward(self.model, self.data)

    @staticmethod
    def _check7(x: np.ndarray, name: str) -> None:
        if x.shape != (N,):
            raise ShapeMismatchError(f"{name} must have shape ({N},), got {x.shape}")
        if not np.isfinite(x).all():
            from lfd_torch.errors import NonFiniteError

            raise NonFiniteError(f"{name} contains NaN or Inf")

    @property
    def q(self) -> np.ndarray:
        """(7,) joint angles (rad), a copy."""
        return self.data.qpos[self.qpos_adr].copy()

    @property
    def qd(self) -> np.ndarray:
        """(7,) joint velocities (rad/s), a copy."""
        return self.data.qvel[self.dof_adr].copy()

    @property
    def time(self) -> float:
        return float(self.data.time)

    def set_command(self, q_d, qd_d) -> None:
        """Impedance set-point: desired joint angles ``q_d`` (7,) rad and velocities ``qd_d`` (7,) rad/s (clamped
        by MuJoCo to the joint range and the velocity limits)."""
        q_d, qd_d = real_array(q_d, "q_d"), real_array(qd_d, "qd_d")
        self._check7(q_d, "q_d")
        self._check7(qd_d, "qd_d")
        self._setpoint = q_d.copy()
        self.data.ctrl[:N] = q_d
        self.data.ctrl[N:] = qd_d

    def step(self, n_substeps: int | None = None) -> None:
        """Advance ``n_substeps`` physics steps (default one control period) with the current set-point, then
        update the kinematics so that :meth:`tip_position` and the contacts are those of the new state.

        With ``interpolate``, the position set-point ramps at the commanded joint velocity over the call's substeps
        and reaches ``q_d`` of :meth:`set_command` at the last one; a further call without a new command continues
        the ramp at that velocity (the velocity set-point still commands it), so the position set-point never jumps
        back."""
        from lfd_torch.utils import check_int

        # bound: 10^6 substeps (1000 s of simulated time at the default 1 kHz) keeps one call finite
        n = self.n_substeps if n_substeps is None else check_int(n_substeps, "n_substeps", low=1, high=10**6)
        if self.interpolate:
            qd_d = self.data.ctrl[N:].copy()
            for k in range(n):
                self.data.ctrl[:N] = self._setpoint - qd_d * (n - 1 - k) * self.timestep
                self._mj.mj_step(self.model, self.data)
            self.data.ctrl[:N] = self._setpoint
            self._setpoint = self._setpoint + qd_d * n * self.timestep  # where a next call without a command ends
        else:
            self._mj.mj_step(self.model, self.data, n)
        self._mj.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ readings
    def tip_position(self) -> np.ndarray:
        """(3,) spoon-tip site position in the torso frame (m)."""
        return self.data.site_xpos[self.tip_site].copy()

    def tip_pose(self) -> np.ndarray:
        """(4, 4) spoon-tip site pose in the torso frame (m)."""
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[self.tip_site].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[self.tip_site]
        return T

    def tip_kinematics(self, q) -> np.ndarray:
        """(3,) MuJoCo tip site position for joint angles ``q`` (7,) rad (scratch data; the state is unchanged)."""
        q = np.asarray(q, dtype=float)
        self._check7(q, "q")
        d = self.new_data()
        d.qpos[self.qpos_adr] = q
        self._mj.mj_kinematics(self.model, d)
        return d.site_xpos[self.tip_site].copy()

    def gravity_torque(self, q=None) -> np.ndarray:
        """(7,) joint torques (N m) that hold the arm still against gravity at ``q`` (default the current q):
        MuJoCo's bias force at zero velocity (an independent check of the gravity compensation)."""
        d = self.new_data()
        d.qpos[:] = self.data.qpos
        if q is not None:
            q = np.asarray(q, dtype=float)
            self._check7(q, "q")
            d.qpos[self.qpos_adr] = q
        self._mj.mj_forward(self.model, d)
        return d.qfrc_bias[self.dof_adr].copy()

    def actuator_torque(self) -> np.ndarray:
        """(7,) PD actuator torque of the last evaluation, clamped at the effort limits (N m)."""
        return self.data.qfrc_actuator[self.dof_adr].copy()

    def compensation_torque(self) -> np.ndarray:
        """(7,) gravity-compensation torque of the last evaluation (N m)."""
        return self.data.qfrc_gravcomp[self.dof_adr].copy()

    def contacts(self, min_depth: float = 0.0) -> list[tuple[str, str]]:
        """Sorted distinct (robot part, scene object) pairs in contact now (penetration > ``min_depth`` m)."""
        ncon = int(self.data.ncon)
        if ncon == 0:
            return []
        con = self.data.contact
        geoms = np.asarray(con.geom[:ncon])
        hit = np.asarray(con.dist[:ncon]) < -min_depth
        part, obj = self._geom_part[geoms], self._geom_object[geoms]
        # a contact pairs one robot geom with one scene geom, in either order
        p = np.where(part[:, 0] >= 0, part[:, 0], part[:, 1])
        o = np.where(obj[:, 0] >= 0, obj[:, 0], obj[:, 1])
        ok = hit & (p >= 0) & (o >= 0)
        return sorted({(ROBOT_PARTS[i], SCENE_OBJECTS[j]) for i, j in zip(p[ok].tolist(), o[ok].tolist())})

    def sugar_depth(self, point=None) -> float:
        """Depth (m) of ``point`` (3,) (default the spoon tip) below the sugar surface, positive inside the sugar
        volume (within the can radius and above the bottom), negative otherwise (the distance to it, roughly)."""
        p = self.tip_position() if point is None else np.asarray(point, dtype=float)
        can = self.scene.can
        bottom = self.scene.table_top + can.wall
        surface = bottom + can.fill
        radial = can.radius - math.hypot(p[0] - can.center[0], p[1] - can.center[1])
        return float(min(surface - p[2], radial, p[2] - bottom))

    def contacts_at(self, q, min_depth: float = 0.0) -> list[tuple[str, str]]:
        """:meth:`contacts` of the arm at joint angles ``q`` (7,) rad (scratch data; the state is unchanged)."""
        q = np.asarray(q, dtype=float)
        self._check7(q, "q")
        d = self.new_data()
        d.qpos[:] = self.data.qpos
        d.qpos[self.qpos_adr] = q
        self._mj.mj_fwdPosition(self.model, d)  # kinematics and collision only: no forces on the scratch data
        saved, self.data = self.data, d
        try:
            return self.contacts(min_depth)
        finally:
            self.data = saved

    # ------------------------------------------------------------------ disturbances
    def teleport(self, q) -> None:
        """Position jump: set the arm to ``q`` (7,) rad at rest (time, forces and the rest of the state kept), and
        hold ``q`` as the set-point."""
        q = np.asarray(q, dtype=float)
        self._check7(q, "q")
        if ((q < self.lower - LIMIT_TOLERANCE) | (q > self.upper + LIMIT_TOLERANCE)).any():
            raise InvalidArgumentError("q violates the joint limits")
        self.data.qpos[self.qpos_adr] = q
        self.data.qvel[self.dof_adr] = 0.0
        self.data.qacc_warmstart[:] = 0.0
        self.set_command(q, np.zeros(N))
        self._mj.mj_forward(self.model, self.data)

    def apply_force(self, body: str, force, torque=None) -> None:
        """Apply an external Cartesian ``force`` (3,) N (and ``torque`` (3,) N m) at the centre of mass of ``body``
        until :meth:`clear_forces`."""
        if body not in self.body_ids:
            raise UnknownNameError("body", body, tuple(self.body_ids))
        from lfd_torch.errors import NonFiniteError

        f = real_array(force, "force")
        t = np.zeros(3) if torque is None else real_array(torque, "torque")
        if f.shape != (3,) or t.shape != (3,):
            raise ShapeMismatchError(f"force and torque must have shape (3,), got {f.shape}, {t.shape}")
        if not (np.abs(f) <= 1e6).all() or not (np.abs(t) <= 1e6).all():  # NaN fails too
            raise NonFiniteError(f"force and torque must be finite, below 1e6 N (N m), got {f.tolist()}, {t.tolist()}")
        self.data.xfrc_applied[self.body_ids[body]] = np.concatenate([f, t])

    def clear_forces(self) -> None:
        self.data.xfrc_applied[:] = 0.0

    def __repr__(self) -> str:
        return f"BaxterPlant(tool_offset={self.tool_offset}, kp={self.stiffness}, kv={self.damping})"
