"""RobotModel: a Pinocchio ``Model`` with its preallocated ``Data`` and the few algorithms the
stack needs, each writing into arrays owned by the caller or by this object.

Joint friction is taken from the URDF ``<dynamics damping friction>`` tags (Pinocchio stores
them in ``model.damping`` and ``model.friction``) and modelled as
``tau_f = damping * v + friction * tanh(v / v_s)``: the plant applies it, the computed torque
compensates it (it is part of the paper's n(q, v)).
"""

from __future__ import annotations

import math
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pinocchio as pin

from teleop_rt.config import RobotSpec
from teleop_rt.errors import ModelError
from teleop_rt.flat import jit
from teleop_rt.inputs import file_problem, shown

MAX_URDF_BYTES = 10_000_000  # a URDF is text; meshes are separate files


@jit
def friction_torque(damping: float, coulomb: float, inv_v_s: float, v: float) -> float:
    """One joint's friction torque: viscous plus tanh-smoothed Coulomb."""
    return damping * v + coulomb * math.tanh(v * inv_v_s)


class RobotModel:
    """Kinematics and dynamics of one robot (HSI or TO).

    Pinocchio needs numpy arrays for q, v, a, tau; what it returns is converted to lists where
    the tick path goes on with scalar arithmetic (cheaper than numpy for a few joints).
    """

    def __init__(
        self,
        model: pin.Model,
        ee_frame: str | None = None,
        name: str = "robot",
        coulomb_smoothing_rad_s: float = 0.01,
    ) -> None:
        self.model = model
        self.data = model.createData()
        self.name = name
        self.nq, self.nv = model.nq, model.nv
        if self.nq != self.nv:
            raise ModelError(f"{name}: only revolute/prismatic joints are supported (nq != nv)")
        if self.nv == 0:
            raise ModelError(f"{name}.robot: the robot has no moving joint")
        self.joint_names = list(model.names)[1:]
        frame = ee_frame or model.frames[model.nframes - 1].name
        if not model.existFrame(frame):
            raise ModelError(f"{name}: the robot has no frame named {frame!r}")
        self.ee_frame = frame
        self.ee_frame_id = model.getFrameId(frame)
        self.damping = [float(x) for x in model.damping]
        self.coulomb = [float(x) for x in model.friction]
        self.has_coulomb = any(self.coulomb)
        self.inv_v_s = 1.0 / coulomb_smoothing_rad_s
        # A view into data.oMf: updated in place by Pinocchio, read without a binding call.
        self._ee_translation = self.data.oMf[self.ee_frame_id].translation
        # End-effector kinematics filled by update_ee(): position (m), velocity (m/s) and the
        # Jacobian rows as lists (rows 0-2: translational, world-aligned).
        self.ee_pos = [0.0, 0.0, 0.0]
        self.ee_vel = [0.0, 0.0, 0.0]
        self.ee_jac: list[list[float]] = [[0.0] * self.nv for _ in range(3)]

    @classmethod
    def from_spec(
        cls, spec: RobotSpec, name: str, coulomb_smoothing_rad_s: float = 0.01
    ) -> RobotModel:
        """Load the robot named by a config section (URDF path or example-robot-data name)."""
        model = load_pinocchio_model(spec, name)
        return cls(model, spec.ee_frame, name, coulomb_smoothing_rad_s)

    # --- dynamics -------------------------------------------------------------------------
    def rnea(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """M(q) a + n(q, v) without friction (one RNEA call; n: Coriolis, centrifugal, gravity).
        A fresh array from Pinocchio's binding."""
        return pin.rnea(self.model, self.data, q, v, a)

    def forward_dynamics(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> list[float]:
        """Joint acceleration for the total joint torque tau (one ABA call)."""
        return pin.aba(self.model, self.data, q, v, tau).tolist()

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M(q), symmetric (a fresh copy; not for the tick path)."""
        m = pin.crba(self.model, self.data, np.asarray(q, dtype=float)).copy()
        return np.triu(m) + np.triu(m, 1).T

    def nonlinear_effects(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """n(q, v) without friction (a fresh copy; not for the tick path)."""
        return pin.nonLinearEffects(
            self.model, self.data, np.asarray(q, dtype=float), np.asarray(v, dtype=float)
        ).copy()

    # --- kinematics -----------------------------------------------------------------------
    def update_ee(self, q: np.ndarray, v: list[float]) -> None:
        """Fill ee_pos, ee_vel (world frame, m and m/s) and ee_jac (3 x nv) at (q, v).

        One Pinocchio call: computeFrameJacobian runs the forward kinematics and also updates
        data.oMf of the frame, which ``_ee_translation`` views."""
        jac = pin.computeFrameJacobian(
            self.model, self.data, q, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED
        )
        rows = jac.tolist() if self.nv > 1 else [[x] for x in jac.tolist()]  # 1 DoF: flat
        self.ee_jac = rows
        self.ee_pos[:] = self._ee_translation.tolist()
        jx, jy, jz = rows[0], rows[1], rows[2]
        x = y = z = 0.0
        for j, vj in enumerate(v):
            x += jx[j] * vj
            y += jy[j] * vj
            z += jz[j] * vj
        vel = self.ee_vel
        vel[0], vel[1], vel[2] = x, y, z

    def tool_position(self, q: np.ndarray) -> list[float]:
        """End-effector position at q (m, world frame) as a list: one Pinocchio call (tick path)."""
        pin.framesForwardKinematics(self.model, self.data, q)
        return self._ee_translation.tolist()

    def ee_position(self, q: np.ndarray) -> np.ndarray:
        """End-effector position at q (a fresh array, from any sequence of angles)."""
        return np.array(self.tool_position(np.asarray(q, dtype=float)))

    # --- limits ---------------------------------------------------------------------------
    @property
    def position_limits(self) -> tuple[np.ndarray, np.ndarray]:
        return self.model.lowerPositionLimit.copy(), self.model.upperPositionLimit.copy()

    @property
    def effort_limits(self) -> np.ndarray:
        return self.model.effortLimit.copy()


def load_pinocchio_model(spec: RobotSpec, name: str) -> pin.Model:
    """Build a Pinocchio model from a URDF file or an example-robot-data robot name, with the
    joints ``spec.locked_joints`` names locked (``locked_model``)."""
    model = _loaded_model(spec, name)
    return locked_model(model, spec.locked_joints, name) if spec.locked_joints else model


def locked_model(model: pin.Model, joints: list[str], name: str) -> pin.Model:
    """``model`` with ``joints`` locked at its neutral configuration: Pinocchio's
    ``buildReducedModel`` (the locked joints become fixed joints, their bodies' inertia merged
    into their parents', the other joints' limits kept)."""
    names = list(model.names)[1:]  # (0: the universe, no joint to lock)
    unknown = [joint for joint in joints if joint not in names]
    if unknown:
        raise ModelError(
            f"{name}.robot.locked_joints: no joint {unknown[0]!r} in the model "
            f"(its joints: {', '.join(names)})"
        )
    if len(joints) == len(names):
        raise ModelError(f"{name}.robot.locked_joints: locks every joint of the model")
    ids = [model.getJointId(joint) for joint in joints]
    return pin.buildReducedModel(model, ids, pin.neutral(model))


def _loaded_model(spec: RobotSpec, name: str) -> pin.Model:
    if spec.urdf is not None:
        path = Path(spec.urdf)
        problem = file_problem(path)  # before Pinocchio opens it (a FIFO would block it)
        if problem == "no such file":
            raise ModelError(f"{name}.robot.urdf: no such file: {shown(path)}")
        if problem is not None:
            raise ModelError(f"{name}.robot.urdf: {shown(path)}: {problem}")
        if path.stat().st_size > MAX_URDF_BYTES:
            raise ModelError(
                f"{name}.robot.urdf: {shown(path)}: larger than {MAX_URDF_BYTES} bytes"
            )
        try:
            with _c_stderr_captured() as diagnostics:
                return pin.buildModelFromUrdf(str(path))
        except (ValueError, RuntimeError) as err:
            why = _first_urdfdom_error(diagnostics.text) or str(err).strip().split("\n")[0]
            raise ModelError(
                f"{name}.robot.urdf: {path.name} is not a valid URDF: {why or type(err).__name__}"
            ) from None
    try:
        import example_robot_data
    except ImportError:  # pragma: no cover - a declared dependency
        raise ModelError(
            f"{name}.robot.example_robot: example_robot_data is not installed"
        ) from None
    try:
        return example_robot_data.load(spec.example_robot).model
    except (ValueError, KeyError, AttributeError, OSError) as err:
        raise ModelError(
            f"{name}.robot.example_robot: cannot load {spec.example_robot!r} ({err})"
        ) from None


class _Captured:
    text = ""


@contextmanager
def _c_stderr_captured() -> Iterator[_Captured]:
    """File descriptor 2 into a temporary file while inside. urdfdom reports what is wrong with
    a URDF through console_bridge, which writes to the C-level stderr before Pinocchio raises;
    an exception out of the block keeps that text for its one line (``.text``); a success
    passes it on."""
    captured = _Captured()
    if sys.stderr is not None:  # None when the process was started without a stderr
        sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no stderr at all: nothing to keep apart
        yield captured
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        failed = True
        try:
            yield captured
            failed = False
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            data = tmp.read()
            captured.text = data.decode(errors="replace")
            if data and not failed:
                os.write(2, data)  # warnings of a URDF that loaded: not ours to hide


_TINYXML = re.compile(r"Error=XML_ERROR_(\w+) ErrorID=\d+ \(0x[0-9a-f]+\) Line number=(\d+)(: .*)?")


def _first_urdfdom_error(text: str) -> str:
    """urdfdom's first message ('Error:   Joint [j] ... limits' / '   at line 607 in ...'),
    TinyXML's codes in words ('XML mismatched element at line 1: XMLElement name=link')."""
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("Error:"):
            message = " ".join(line.removeprefix("Error:").split())
            xml = _TINYXML.fullmatch(message)
            if xml:
                kind, number, rest = xml.groups()
                return f"XML {kind.lower().replace('_', ' ')} at line {number}{rest or ''}"
            return message
    return ""
