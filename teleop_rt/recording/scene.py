"""The session in 3D for Foxglove: both robots side by side, the environment, the hand target.

Built from log rows in the writer process (``teleop_rt.recording.writer``), decimated to
``recording.scene_hz`` (50 by default; 0: no 3D topics): nothing here runs on the tick path.
Topics (beside the four of the schema):

* ``/robot_description`` std_msgs/msg/String (CDR): one URDF holding both robots, their links
  and joints prefixed ``hsi/`` and ``to/``, each robot's root fixed to ``world`` at its offset
  (``BASES_M``: side by side), so that Foxglove's 3D panel shows both without settings. Links
  without a visual of primitive geometry get one drawn from the kinematics (a bar to each child
  joint, a ball at a leaf): a mesh's ``package://`` file would not resolve in Foxglove.
* ``/tf`` foxglove.FrameTransforms: every URDF joint's transform (parent link to child link)
  from Pinocchio's forward kinematics at the logged q, and the two mounts on ``world``.
* ``/environment`` foxglove.SceneUpdate: walls, foam, springs, dampers as slabs behind their
  surfaces near the TO's tool, a pushed mass as a block that moves with it; an element in
  contact turns red. In the TO's frame (``to/<root link>``).
* ``/hand_target`` foxglove.SceneUpdate (an operator hand only): the hand's reference as a ball
  and the spring to the HSI's tool as a line, in the HSI's frame.

Pinocchio's Data here is the writer's own (``Scene`` builds its models from the URDF text):
nothing is shared with the control process.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin
from foxglove.messages import (
    Color,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector3,
)

from teleop_rt.config import MAX_TICKS

if TYPE_CHECKING:
    from teleop_rt.recording.schema import LogLayout
    from teleop_rt.session import Session

SIDES = ("hsi", "to")
BASES_M = {"hsi": (0.0, 0.4, 0.0), "to": (0.0, -0.4, 0.0)}  # each robot's base in ``world``
WORLD = "world"
ROBOT_DESCRIPTION, TF, ENVIRONMENT, HAND_TARGET = (
    "/robot_description", "/tf", "/environment", "/hand_target"
)  # fmt: skip
STRING_TYPE = "std_msgs/msg/String"
STRING_DEFINITION = b"string data\n"
COLORS = {"hsi": (0.20, 0.45, 0.85, 1.0), "to": (0.90, 0.50, 0.15, 1.0)}
ENV_COLORS = {
    "wall": (0.55, 0.55, 0.60, 0.9),
    "foam": (0.95, 0.80, 0.25, 0.55),
    "spring": (0.30, 0.75, 0.40, 0.35),
    "damper": (0.30, 0.55, 0.90, 0.35),
    "mass": (0.55, 0.35, 0.20, 0.95),
}
CONTACT_COLOR = (0.90, 0.15, 0.15, 0.9)
HAND_COLOR = (0.20, 0.80, 0.30, 0.9)
SLAB_DEPTH_M = {"wall": 0.01, "foam": 0.03, "spring": 0.005, "damper": 0.005, "mass": 0.06}
SLAB_SIZE_M = (0.30, 0.10)  # along the surface: horizontal, vertical
MASS_SIZE_M = 0.06
BONE_RADIUS_M = 0.012


@dataclass(frozen=True)
class EnvElement:
    kind: str
    point: tuple[float, float, float]
    normal: tuple[float, float, float]  # unit, towards free space


@dataclass(frozen=True)
class SceneSpec:
    """What the writer needs to draw the session (plain data: picklable for 'spawn')."""

    urdf: dict[str, str]  # side -> the robot's URDF text
    ee_frame: dict[str, str]  # side -> the tool frame
    tool_start: dict[str, tuple[float, float, float]]  # each tool at q0, its robot's frame
    environment: tuple[EnvElement, ...]
    hand: bool  # an operator hand (its reference is in /hsi)
    every: int  # ticks between two scene messages (recording.scene_hz)
    resend: int  # ticks between two sendings of an unchanged environment (about a second)
    sides: tuple[str, ...] = SIDES  # the robots drawn: both (a session's log) or a site's own
    # side -> the joints its config locks (robot.locked_joints): drawn as fixed, at neutral
    locked: dict[str, tuple[str, ...]] = field(default_factory=dict)


def scene_spec(session: Session, sides: tuple[str, ...] = SIDES) -> SceneSpec | None:
    """The scene of a session (or of the robots ``sides`` of it: a site's log, whose source
    has the site under its name); None when a robot's URDF cannot be found or the config's
    ``recording.scene_hz`` is 0 (no 3D topics)."""
    cfg = session.cfg
    if cfg.recording.scene_hz == 0:
        return None
    urdf: dict[str, str] = {}
    ee: dict[str, str] = {}
    start: dict[str, tuple[float, float, float]] = {}
    for side in sides:
        text = _urdf_text(getattr(cfg, side).robot)
        if text is None:
            return None
        site = getattr(session, side)
        urdf[side] = text
        ee[side] = site.model.ee_frame
        q0 = np.asarray(getattr(cfg, side).robot.q0_rad or np.zeros(site.n), dtype=float)
        x, y, z = (float(c) for c in site.model.ee_position(q0))
        start[side] = (x, y, z)
    # the config's operator and environment exist where a simulated world has them (a plant or
    # the drives' emulator); real hardware logs neither
    # a scene_hz below one message per longest session: the start's only (no overflow)
    every = max(1, min(round(cfg.rate_hz / cfg.recording.scene_hz), MAX_TICKS))
    env = tuple(EnvElement(e.kind, _xyz(e.point_m), _unit(_xyz(e.normal))) for e in cfg.environment)
    return SceneSpec(
        urdf=urdf,
        ee_frame=ee,
        tool_start=start,
        environment=env if "to" in sides and _simulated(session.to) else (),
        hand=cfg.operator.kind == "hand" and "hsi" in sides and _simulated(session.hsi),
        every=every,
        resend=every * max(1, round(cfg.rate_hz / every)),
        sides=tuple(sides),
        locked={side: tuple(getattr(cfg, side).robot.locked_joints) for side in sides},
    )


def _simulated(site) -> bool:
    cfg = site.cfg
    return site.backend_name == "sim" or (
        site.backend_name == "can" and cfg.can is not None and cfg.can.emulate
    )


def shift_sources(session: Session) -> np.ndarray:
    """Per environment element, where its surface's shift along -normal (a pushed mass) sits in
    the session's packed state, -1 where there is none to show (a fixed surface, or a plant
    outside the session's buffers: then the mass is drawn where it started)."""
    from teleop_rt.world import PushedMass

    loads = [x for x in getattr(session.to.backend, "loads", []) if not x.is_operator]
    out = np.full(len(session.cfg.environment), -1, dtype=np.int64)
    for e, load in enumerate(loads[: len(out)]):
        if isinstance(load, PushedMass) and any(b is load for b in session.packed.blocks):
            out[e] = session.packed.index_of(load, "s")
    return out


def _urdf_text(robot) -> str | None:
    if robot.urdf is not None:
        return Path(robot.urdf).read_text()
    try:  # example-robot-data: its loader knows the file
        from example_robot_data.robots_loader import ROBOTS

        return Path(ROBOTS[robot.example_robot]().df_path).read_text()
    except (ImportError, KeyError, AttributeError, OSError, TypeError):
        return None


def _xyz(v) -> tuple[float, float, float]:
    out = [0.0, 0.0, 0.0]
    out[: len(v)] = [float(x) for x in v]
    return (out[0], out[1], out[2])


def _unit(v: tuple[float, float, float]) -> tuple[float, float, float]:
    norm = math.sqrt(sum(x * x for x in v))
    return (v[0] / norm, v[1] / norm, v[2] / norm)


# --- the combined URDF --------------------------------------------------------------------------
@dataclass(frozen=True)
class UrdfJoint:
    name: str
    parent: str
    child: str
    fixed: bool


def _attr(el: ET.Element, name: str) -> str:
    """An attribute the URDF must have (Pinocchio loaded the same file: a missing one is a
    broken file, said in one line)."""
    value = el.get(name)
    if value is None:
        raise ValueError(f"URDF: <{el.tag}> without {name!r}")
    return value


def _child(el: ET.Element, tag: str) -> ET.Element:
    """A child element the URDF must have (see ``_attr``)."""
    found = el.find(tag)
    if found is None:
        raise ValueError(f"URDF: <{el.tag} name={el.get('name')!r}> without <{tag}>")
    return found


def robot_tree(urdf: str) -> tuple[str, list[UrdfJoint]]:
    """A URDF's root link and its joints (parent link, child link), in file order."""
    root = ET.fromstring(urdf)
    joints = [
        UrdfJoint(
            _attr(j, "name"),
            _attr(_child(j, "parent"), "link"),
            _attr(_child(j, "child"), "link"),
            j.get("type") == "fixed",
        )  # fmt: skip
        for j in root.findall("joint")
    ]
    children = {j.child for j in joints}
    links = [_attr(link, "name") for link in root.findall("link")]
    roots = [name for name in links if name not in children]
    return (roots[0] if roots else links[0]), joints


def combined_urdf(spec: SceneSpec) -> str:
    """One URDF of both robots (names prefixed ``hsi/``, ``to/``) mounted on ``world``."""
    out = ET.Element("robot", name="teleop_rt")
    ET.SubElement(out, "link", name=WORLD)
    for side in spec.sides:
        robot = ET.fromstring(spec.urdf[side])
        prefix = f"{side}/"
        root, _ = robot_tree(spec.urdf[side])
        material = ET.SubElement(out, "material", name=f"{prefix}color")
        ET.SubElement(material, "color", rgba=" ".join(f"{c:g}" for c in COLORS[side]))
        offsets = _child_offsets(robot)
        for link in robot.findall("link"):
            name = _attr(link, "name")
            link.set("name", prefix + name)
            for el in link.findall("collision"):  # meshes would not resolve; visuals suffice
                link.remove(el)
            visuals = [v for v in link.findall("visual") if _primitive(v)]
            for v in link.findall("visual"):
                link.remove(v)
            for v in visuals or _bones(offsets.get(name, []), leaf=not offsets.get(name)):
                for mat in v.findall("material"):
                    v.remove(mat)
                ET.SubElement(v, "material", name=f"{prefix}color")
                link.append(v)
            out.append(link)
        for joint in robot.findall("joint"):
            joint.set("name", prefix + _attr(joint, "name"))
            for end in ("parent", "child"):
                el = _child(joint, end)
                el.set("link", prefix + _attr(el, "link"))
            for tag in ("mimic", "transmission"):
                for el in joint.findall(tag):
                    joint.remove(el)
            out.append(joint)
        mount = ET.SubElement(out, "joint", name=f"{prefix}mount", type="fixed")
        ET.SubElement(mount, "parent", link=WORLD)
        ET.SubElement(mount, "child", link=prefix + root)
        ET.SubElement(mount, "origin", xyz=" ".join(f"{x:g}" for x in BASES_M[side]))
    ET.indent(out)
    return ET.tostring(out, encoding="unicode") + "\n"


def _primitive(visual: ET.Element) -> bool:
    geometry = visual.find("geometry")
    return geometry is not None and any(
        geometry.find(kind) is not None for kind in ("box", "cylinder", "sphere")
    )


def _child_offsets(robot: ET.Element) -> dict[str, list[tuple[float, ...]]]:
    """Per link, the origins of its child joints in its frame."""
    out: dict[str, list[tuple[float, ...]]] = {}
    for joint in robot.findall("joint"):
        origin = joint.find("origin")
        xyz = origin.get("xyz", "0 0 0") if origin is not None else "0 0 0"
        out.setdefault(_attr(_child(joint, "parent"), "link"), []).append(
            tuple(float(x) for x in xyz.split())
        )
    return out


def _bones(offsets: list[tuple[float, ...]], leaf: bool) -> list[ET.Element]:
    """Visuals drawn from the kinematics: a bar from the link's origin to each child joint, a
    ball at the origin of a leaf (a tool)."""
    out = []
    for x, y, z in offsets:
        length = math.sqrt(x * x + y * y + z * z)
        if length < 1e-6:
            continue
        pitch, yaw = math.atan2(math.hypot(x, y), z), math.atan2(y, x)  # z axis onto the bar
        v = ET.Element("visual")
        ET.SubElement(v, "origin", xyz=f"{x / 2:g} {y / 2:g} {z / 2:g}", rpy=f"0 {pitch:g} {yaw:g}")
        geometry = ET.SubElement(v, "geometry")
        ET.SubElement(geometry, "cylinder", radius=f"{BONE_RADIUS_M:g}", length=f"{length:g}")
        out.append(v)
    if leaf:
        v = ET.Element("visual")
        geometry = ET.SubElement(v, "geometry")
        ET.SubElement(geometry, "sphere", radius=f"{1.5 * BONE_RADIUS_M:g}")
        out.append(v)
    return out


def string_message(text: str) -> bytes:
    """A std_msgs/msg/String in CDR (little endian): length with the NUL, bytes, NUL."""
    data = text.encode()
    return b"\x00\x01\x00\x00" + (len(data) + 1).to_bytes(4, "little") + data + b"\x00"


# --- the scene from rows (writer process) -------------------------------------------------------
class Scene:
    """Pinocchio models of both robots (the writer's own) and the scene's foxglove messages.

    The moving joints' transforms are computed for a whole batch of frames at once with numpy,
    from the URDF itself (parent link to child link: the joint's origin, then its motion, a
    rotation about its axis or a translation along it): a Pinocchio call and its SE3 and
    quaternion objects per joint and frame cost 7 us each, most of the scene's CPU."""

    def __init__(self, spec: SceneSpec) -> None:
        self.spec = spec
        self.robots = {}
        self.moving = {}
        for side in spec.sides:
            model = pin.buildModelFromXML(spec.urdf[side])
            locked = spec.locked.get(side, ())
            if locked:  # (as the session's model has them: teleop_rt.model)
                from teleop_rt.model import locked_model

                model = locked_model(model, list(locked), side)
            root, joints = robot_tree(spec.urdf[side])
            joints = [UrdfJoint(j.name, j.parent, j.child, j.fixed or j.name in locked)
                      for j in joints]  # fmt: skip
            body = {f.name: i for i, f in enumerate(model.frames) if f.type == pin.FrameType.BODY}
            pairs = [
                (f"{side}/{j.parent}", f"{side}/{j.child}", body[j.parent], body[j.child], j.fixed)
                for j in joints
                if j.parent in body and j.child in body
            ]
            ee = model.getFrameId(spec.ee_frame[side])
            self.robots[side] = (model, model.createData(), pairs, ee, f"{side}/{root}")
            self.moving[side] = _MovingJoints(model, spec.urdf[side], side, body, locked)
        self.frames = {side: self.robots[side][4] for side in spec.sides}
        self._environment = [_Slab(el, spec.tool_start["to"]) for el in spec.environment]
        self._hand_size = _vector((0.025, 0.025, 0.025))
        self._hand_color = _color(HAND_COLOR)
        self._no_turn = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)

    def static_transforms(self, stamp_ns: int):
        """foxglove.FrameTransforms of what never moves: the mounts on ``world`` and the
        fixed joints (sent once, as ROS sends /tf_static, and to a live client that
        subscribes)."""

        out = []
        for side in self.spec.sides:
            model, data, pairs, _, root = self.robots[side]
            pin.framesForwardKinematics(model, data, pin.neutral(model))
            out.append(_transform(WORLD, root, np.array(BASES_M[side]), (0, 0, 0, 1), stamp_ns))
            out += [self._relative(data, p, stamp_ns) for p in pairs if p[4]]
        return FrameTransforms(transforms=out)

    def transforms(self, q: dict[str, np.ndarray], stamps: list[int]) -> list:
        """foxglove.FrameTransforms of the moving joints, one per frame: q maps a side to its
        joint angles, one row per frame, stamps the frames' times (ns)."""
        per_side = [self.moving[side].at(q[side]) for side in self.spec.sides]
        out = []
        for f, stamp in enumerate(stamps):
            ts = _timestamp(stamp)
            out.append(FrameTransforms(transforms=[
                FrameTransform(
                    timestamp=ts, parent_frame_id=parent, child_frame_id=child,
                    translation=Vector3(x=t[0], y=t[1], z=t[2]),
                    rotation=Quaternion(x=r[0], y=r[1], z=r[2], w=r[3]),
                )
                for names, t_all, r_all in per_side
                for (parent, child), t, r in zip(names, t_all[f], r_all[f], strict=True)
            ]))  # fmt: skip
        return out

    def _relative(self, data, pair, stamp_ns: int):
        parent, child, i, j, _ = pair
        rel = data.oMf[i].actInv(data.oMf[j])
        return _transform(
            parent, child, rel.translation, pin.Quaternion(rel.rotation).coeffs(), stamp_ns
        )

    def tool(self, side: str, q: np.ndarray) -> np.ndarray:
        """The tool's position at joint angles q (its robot's frame)."""
        model, data, _, ee, _ = self.robots[side]
        pin.framesForwardKinematics(model, data, q)
        return data.oMf[ee].translation.copy()

    def environment(self, shifts: np.ndarray, contacts: np.ndarray, stamp_ns: int):
        """foxglove.SceneUpdate of the environment: each element's slab (or the mass block,
        moved by its shift along -normal), red while in contact."""

        stamp, frame = _timestamp(stamp_ns), self.frames["to"]
        entities = [
            SceneEntity(
                timestamp=stamp,
                frame_id=frame,
                id=f"environment/{e}",
                frame_locked=True,
                cubes=[slab.cube(float(shifts[e]), bool(contacts[e]))],
            )  # fmt: skip
            for e, slab in enumerate(self._environment)
        ]
        return SceneUpdate(entities=entities)

    def hand(self, target: np.ndarray, tool: np.ndarray, stamp_ns: int):
        """foxglove.SceneUpdate of the hand's reference and its spring to the HSI's tool."""

        x, y, z = (float(c) for c in target)
        ball = SpherePrimitive(
            pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=self._no_turn),
            size=self._hand_size,
            color=self._hand_color,
        )
        spring = LinePrimitive(
            type=LinePrimitiveLineType.LineStrip,
            thickness=0.004,
            points=[Point3(x=float(tool[0]), y=float(tool[1]), z=float(tool[2])),
                    Point3(x=x, y=y, z=z)],
            color=self._hand_color,
        )  # fmt: skip
        entity = SceneEntity(
            timestamp=_timestamp(stamp_ns), frame_id=self.frames["hsi"], id="hand_target",
            frame_locked=True, spheres=[ball], lines=[spring],
        )  # fmt: skip
        return SceneUpdate(entities=[entity])


class _MovingJoints:
    """A robot's moving URDF joints (revolute or prismatic: a model has nq == nv) as arrays;
    ``at`` gives their parent-to-child transforms for many frames at once.

    A joint's transform is its origin (translation t0, rotation quaternion r0) then its motion:
    a turn by theta about the unit axis a, whose quaternion is (a sin(theta/2), cos(theta/2)),
    so the product is r0 * (a, 0) sin(theta/2) + r0 cos(theta/2); or a slide by theta along a,
    which moves the child by theta R0 a in the parent's frame."""

    def __init__(
        self, model, urdf: str, side: str, body: dict[str, int], locked: tuple[str, ...] = ()
    ) -> None:  # fmt: skip
        """``locked``: joints the model has locked (static transforms, like fixed ones)."""
        self.names: list[tuple[str, str]] = []
        t0, r0, r0_axis, slide, half, cols = [], [], [], [], [], []
        for joint in ET.fromstring(urdf).findall("joint"):
            kind = joint.get("type")
            parent = _attr(_child(joint, "parent"), "link")
            child = _attr(_child(joint, "child"), "link")
            if kind == "fixed" or joint.get("name") in locked:
                continue
            if parent not in body or child not in body:
                continue
            if kind not in ("revolute", "continuous", "prismatic"):
                raise ValueError(f"URDF: joint {joint.get('name')!r} of type {kind!r}")
            origin = joint.find("origin")
            xyz = origin.get("xyz", "0 0 0") if origin is not None else "0 0 0"
            rpy = origin.get("rpy", "0 0 0") if origin is not None else "0 0 0"
            axis_el = joint.find("axis")
            axis = np.array((axis_el.get("xyz", "1 0 0") if axis_el is not None else "1 0 0")
                            .split(), float)  # fmt: skip
            axis /= np.linalg.norm(axis)
            rotation = pin.rpy.rpyToMatrix(*(float(a) for a in rpy.split()))
            quat = pin.Quaternion(rotation)
            turns = kind != "prismatic"
            self.names.append((f"{side}/{parent}", f"{side}/{child}"))
            t0.append([float(a) for a in xyz.split()])
            r0.append(quat.coeffs().copy())  # x y z w
            r0_axis.append((quat * pin.Quaternion(0.0, *axis)).coeffs().copy() if turns else 0)
            slide.append(0.0 if turns else rotation @ axis)
            half.append(0.5 if turns else 0.0)
            cols.append(model.joints[model.getJointId(_attr(joint, "name"))].idx_q)
        m = len(cols)
        self.t0 = np.array(t0, float).reshape(m, 3)
        self.r0 = np.array(r0, float).reshape(m, 4)
        self.r0_axis = np.array([r * np.ones(4) for r in r0_axis]).reshape(m, 4)
        self.slide = np.array([s * np.ones(3) for s in slide]).reshape(m, 3)
        self.half = np.array(half, float)
        self.cols = np.array(cols, dtype=np.int64)

    def at(self, q: np.ndarray) -> tuple[list[tuple[str, str]], list, list]:
        """(parent, child) names, and translations and quaternions (x y z w) as nested lists
        (frame, joint, component), for joint angles q (a row per frame)."""
        theta = q[:, self.cols]
        half = theta * self.half  # 0 for a slide: no turn
        r = np.sin(half)[..., None] * self.r0_axis + np.cos(half)[..., None] * self.r0
        t = self.t0 + theta[..., None] * self.slide  # slide 0 for a turn
        return self.names, t.tolist(), r.tolist()


class _Slab:
    """One environment element as a cube behind its surface, near the TO tool's start: what
    does not change is made once."""

    def __init__(self, el: EnvElement, tool_start: tuple[float, float, float]) -> None:

        n = np.array(el.normal)
        x0, p0 = np.array(tool_start), np.array(el.point)
        depth = SLAB_DEPTH_M[el.kind]
        self.normal = n
        self.centre = x0 - ((x0 - p0) @ n) * n - n * depth / 2  # the tool's start, onto it
        x, y, z, w = _x_onto(n)
        self.orientation = Quaternion(x=x, y=y, z=z, w=w)
        size = (depth, MASS_SIZE_M, MASS_SIZE_M) if el.kind == "mass" else (depth, *SLAB_SIZE_M)
        self.size = _vector(size)
        self.colors = (_color(ENV_COLORS[el.kind]), _color(CONTACT_COLOR))

    def cube(self, shift: float, contact: bool):

        pose = Pose(
            position=_vector(self.centre - self.normal * shift), orientation=self.orientation
        )
        return CubePrimitive(pose=pose, size=self.size, color=self.colors[contact])


def _transform(parent: str, child: str, t, quat, stamp_ns: int):

    x, y, z, w = (float(c) for c in quat)
    return FrameTransform(
        timestamp=_timestamp(stamp_ns), parent_frame_id=parent, child_frame_id=child,
        translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        rotation=Quaternion(x=x, y=y, z=z, w=w),
    )  # fmt: skip


def _timestamp(ns: int):

    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Timestamp(sec, nsec)


def _vector(v):

    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _color(c):

    return Color(r=c[0], g=c[1], b=c[2], a=c[3])


def _x_onto(n: np.ndarray) -> tuple[float, float, float, float]:
    """The quaternion (x, y, z, w) of the shortest rotation taking the x axis onto unit n."""
    axis = np.cross((1.0, 0.0, 0.0), n)
    s, c = float(np.linalg.norm(axis)), float(n[0])
    if s < 1e-12:
        return (0.0, 0.0, 0.0, 1.0) if c > 0 else (0.0, 0.0, 1.0, 0.0)  # pi about z
    half = math.atan2(s, c) / 2
    ax = axis / s * math.sin(half)
    return (float(ax[0]), float(ax[1]), float(ax[2]), math.cos(half))


def scene_columns(layout: LogLayout) -> dict[str, slice]:
    """Where the scene reads a ring row: both robots' q, the hand reference, the contacts, and
    the shifts (the columns after the log's own, ``LogLayout.ring_width``)."""
    out = {}
    for topic, fields in (("/hsi", ("q", "operator_reference_m")), ("/to", ("q", "in_contact"))):
        for name in fields:
            found = layout.field_columns(topic, name)
            if found is not None:
                out[f"{topic[1:]}.{name}"] = found
    out["shift"] = slice(layout.row_width, layout.ring_width)
    return out


def scene_topics(spec: SceneSpec) -> list[tuple[str, str, tuple[str, str, bytes]]]:
    """The scene's channels: (topic, message encoding, (schema name, encoding, data)), the
    protobuf schemas the Foxglove SDK's own (``get_schema``: what its typed channels use)."""
    tf, update = FrameTransforms.get_schema(), SceneUpdate.get_schema()
    out = [
        (ROBOT_DESCRIPTION, "cdr", (STRING_TYPE, "ros2msg", STRING_DEFINITION)),
        (TF, "protobuf", (tf.name, tf.encoding, bytes(tf.data))),
    ]
    if spec.environment:
        out.append((ENVIRONMENT, "protobuf", (update.name, update.encoding, bytes(update.data))))
    if spec.hand:
        out.append((HAND_TARGET, "protobuf", (update.name, update.encoding, bytes(update.data))))
    return out


class SceneChannels:
    """The scene's messages from a batch of ring rows, encoded (the SDK's message classes,
    ``encode``) and handed to ``out(topic, data, log_time_ns)`` (the writer puts them in the
    log file and, with a live view, on the server). The environment is sent when it changes
    (a contact, a moving mass) and once a second besides."""

    def __init__(
        self, spec: SceneSpec, layout: LogLayout, out: Callable[[str, bytes, int], None]
    ) -> None:
        self.scene = Scene(spec)
        self.out = out
        self.every = spec.every
        self.cols = scene_columns(layout)
        self.urdf = string_message(combined_urdf(spec))
        self.env, self.hand = bool(spec.environment), spec.hand
        self._env_shown: bytes | None = None  # the environment's state when last sent
        self._env_due = 0  # the tick by which it is sent again regardless
        self._env_period = spec.resend

    def describe(self, stamp_ns: int) -> None:
        """What is sent once (at the start, and again for a live client that subscribes): the
        URDF and the transforms that never move; the environment is sent at the next frame."""
        self.out(ROBOT_DESCRIPTION, self.urdf, stamp_ns)
        self.out(TF, self.scene.static_transforms(stamp_ns).encode(), stamp_ns)
        self._env_shown = None

    def emit(self, rows: np.ndarray, start_ns: int, period_ns: int) -> None:
        """The scene at every ``every``-th tick of the batch."""
        ticks = rows[:, 0].astype(np.int64)
        frames = np.flatnonzero(ticks % self.every == 0)
        if not len(frames):
            return
        cols, scene, sel, out = self.cols, self.scene, rows[frames], self.out
        stamps = (start_ns + ticks[frames] * period_ns).tolist()
        q = {side: sel[:, cols[f"{side}.q"]] for side in scene.spec.sides}
        for message, stamp in zip(scene.transforms(q, stamps), stamps, strict=True):
            out(TF, message.encode(), stamp)
        for f, stamp in enumerate(stamps):
            row = sel[f]
            if self.env:
                k = int(row[0])
                shifts, contacts = row[cols["shift"]], row[cols["to.in_contact"]]
                state = shifts.tobytes() + contacts.tobytes()
                if state != self._env_shown or k >= self._env_due:
                    out(ENVIRONMENT, scene.environment(shifts, contacts, stamp).encode(), stamp)
                    self._env_shown, self._env_due = state, k + self._env_period
            if self.hand:
                tool = scene.tool("hsi", q["hsi"][f])
                target = row[cols["hsi.operator_reference_m"]]
                out(HAND_TARGET, scene.hand(target, tool, stamp).encode(), stamp)
