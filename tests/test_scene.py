"""The 3D topics of a log (teleop_rt.recording.scene): both robots' URDF, their links' poses,
the environment and the hand target, decoded from the file with the schemas it stores, and
checked against independent computations (Pinocchio on the combined URDF, the logged q, the
config's geometry)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from foxglove_ws import payload_decoder
from mcap.reader import make_reader

from teleop_rt import config
from teleop_rt.model import RobotModel
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.recording.scene import BASES_M, SLAB_DEPTH_M, _MovingJoints, _x_onto
from teleop_rt.session import Session

CONFIG = "configs/paper_experiment.yaml"
MASS = (
    "[{kind: mass, point_m: [0.36, 0.0], normal: [-1, 0], mass_kg: 0.5, "
    "contact_stiffness_n_per_m: 2000, contact_damping_n_s_per_m: 5}]"
)


def run_logged(tmp_path, overrides=(), ticks=5000, observer=None):
    cfg = config.load(CONFIG, list(overrides))
    session = Session(cfg)
    path = tmp_path / "s.mcap"
    recorder = Recorder(session, path, wait_for_room=True)
    session.run(ticks=ticks, recorder=recorder, observer=observer)
    return cfg, path


def decoded(path, topic: str) -> list[tuple[int, dict]]:
    """(log time, message) of every message on ``topic``, decoded from the file's schema."""
    out = []
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(topics=[topic]):
            decode = payload_decoder(
                channel.message_encoding, schema.name, schema.encoding, schema.data
            )
            out.append((message.log_time, decode(message.data)))
    return out


def chain(transforms: list[dict], child: str, static: list[dict] = ()) -> pin.SE3:
    """world -> child, composed from the parent -> child transforms of one /tf message and the
    static ones (the first /tf message: mounts and fixed joints)."""
    by_child = {t["child_frame_id"]: t for t in (*static, *transforms)}
    pose = pin.SE3.Identity()
    while child != "world":
        t = by_child[child]
        v, r = t["translation"], t["rotation"]
        quat = pin.Quaternion(r.get("w", 0.0), r.get("x", 0.0), r.get("y", 0.0), r.get("z", 0.0))
        xyz = np.array([v.get(k, 0.0) for k in "xyz"])
        pose = pin.SE3(quat.matrix(), xyz) * pose
        child = t["parent_frame_id"]
    return pose


@pytest.fixture(scope="module")
def paper_log(tmp_path_factory):
    return run_logged(tmp_path_factory.mktemp("scene"))


def test_tf_places_both_tools_where_the_logged_q_puts_them(paper_log):
    cfg, path = paper_log
    data = read_log(path)
    period = round(cfg.dt * 1e9)
    start = data.start_ns
    models = {side: RobotModel.from_spec(getattr(cfg, side).robot, side) for side in ("hsi", "to")}
    (t0, static), *tf = decoded(path, "/tf")
    assert t0 == start and {t["child_frame_id"] for t in static["transforms"]} == {
        "hsi/base_link", "hsi/tool", "to/base_link", "to/tool"
    }  # fmt: skip
    every = round(cfg.rate_hz / cfg.recording.scene_hz)
    assert len(tf) == len(range(0, data.ticks, every))  # decimated to recording.scene_hz
    for log_time, msg in tf[::10]:
        k = (log_time - start) // period
        assert k % every == 0
        assert len(msg["transforms"]) == 4  # the moving joints only
        for side in ("hsi", "to"):
            q = data.topics[f"/{side}"]["q"][k]
            expected = np.add(BASES_M[side], models[side].ee_position(q))
            got = chain(msg["transforms"], f"{side}/tool", static["transforms"]).translation
            np.testing.assert_allclose(got, expected, atol=1e-12)


def test_robot_description_is_one_urdf_of_both_robots_matching_tf(paper_log):
    """The combined URDF loads in Pinocchio; its own forward kinematics at the logged q puts
    every link where /tf does."""
    cfg, path = paper_log
    [(_, msg)] = decoded(path, "/robot_description")
    model = pin.buildModelFromXML(msg.data)
    names = list(model.names)[1:]
    assert names == ["hsi/shoulder", "hsi/elbow", "to/shoulder", "to/elbow"]
    data = read_log(path)
    (_, static), *moving = decoded(path, "/tf")
    log_time, tf = moving[7]
    k = (log_time - data.start_ns) // round(cfg.dt * 1e9)
    q = np.concatenate([data.topics["/hsi"]["q"][k], data.topics["/to"]["q"][k]])
    d = model.createData()
    pin.framesForwardKinematics(model, d, q)
    for link in ("hsi/link1", "hsi/tool", "to/link2", "to/tool"):
        frame = d.oMf[model.getFrameId(link, pin.FrameType.BODY)]
        pose = chain(tf["transforms"], link, static["transforms"])
        np.testing.assert_allclose(pose.homogeneous, frame.homogeneous, atol=1e-12)


def test_environment_slabs_sit_behind_their_surfaces_and_show_contact(paper_log):
    cfg, path = paper_log
    data = read_log(path)
    env = decoded(path, "/environment")
    period = round(cfg.dt * 1e9)
    sent = [(log_time - data.start_ns) // period for log_time, _ in env]
    # sent at the start, at every scene frame whose contacts changed, and once a second
    every = round(cfg.rate_hz / cfg.recording.scene_hz)
    contacts = data.topics["/to"]["in_contact"][::every]
    changed = [0] + [
        k * every for k in range(1, len(contacts)) if (contacts[k] != contacts[k - 1]).any()
    ]
    assert set(changed) <= set(sent) and len(changed) >= 2
    assert np.diff(sent).max() <= cfg.rate_hz
    seen_contact = False
    for log_time, msg in env:
        k = (log_time - data.start_ns) // period
        assert [e["id"] for e in msg["entities"]] == ["environment/0", "environment/1"]
        for e, (spec, entity) in enumerate(zip(cfg.environment, msg["entities"], strict=True)):
            assert entity["frame_id"] == "to/base_link"
            cube = entity["cubes"][0]
            n = np.array([*spec.normal, 0.0][:3], float)
            n /= np.linalg.norm(n)
            p0 = np.array([*spec.point_m, 0.0][:3])
            centre = np.array([cube["pose"]["position"].get(a, 0.0) for a in "xyz"])
            assert (centre - p0) @ n == pytest.approx(-SLAB_DEPTH_M[spec.kind] / 2, abs=1e-12)
            touching = bool(data.topics["/to"]["in_contact"][k][e])
            red = cube["color"]["r"] > 0.85 and cube["color"].get("g", 0.0) < 0.2
            assert red == touching
            seen_contact |= touching
    assert seen_contact  # the paper's trajectory is in the foam from about 4 s


def test_hand_target_is_the_logged_reference(paper_log):
    cfg, path = paper_log
    data = read_log(path)
    period = round(cfg.dt * 1e9)
    for log_time, msg in decoded(path, "/hand_target")[::5]:
        k = (log_time - data.start_ns) // period
        [entity] = msg["entities"]
        assert entity["frame_id"] == "hsi/base_link"
        centre = [entity["spheres"][0]["pose"]["position"].get(a, 0.0) for a in "xyz"]
        np.testing.assert_allclose(centre, data.topics["/hsi"]["operator_reference_m"][k])


def test_a_pushed_mass_moves_in_the_scene(tmp_path):
    """The mass block follows the plant's own mass state (carried by the ring's extra columns)."""
    shifts = []

    def watch(session):
        shifts.append(session.to.backend.loads[0].s)

    cfg, path = run_logged(tmp_path, [f"environment={MASS}"], observer=watch)
    data = read_log(path)
    period = round(cfg.dt * 1e9)
    moved = []
    for log_time, msg in decoded(path, "/environment"):
        k = (log_time - data.start_ns) // period
        x = msg["entities"][0]["cubes"][0]["pose"]["position"].get("x", 0.0)
        moved.append((k, x))
    k0, x0 = moved[0]
    assert shifts[k0] == 0.0
    # once pushed, the frictionless mass never stops: sent at every scene frame from then on
    pushed = [k for k, _ in moved if shifts[k] > 0.0]
    every = round(cfg.rate_hz / cfg.recording.scene_hz)
    assert len(pushed) > 50 and set(np.diff(pushed)) == {every}
    for k, x in moved:
        # normal -x: a shift s moves the surface, and the block, by +s along x
        assert x - x0 == pytest.approx(shifts[k], abs=1e-12)
    assert max(shifts) > 0.01  # the hand's trajectory pushes it by centimetres


@pytest.mark.parametrize("n", [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0.6, -0.8, 0), (0, 0, -1)])
def test_x_onto_turns_the_x_axis_onto_the_normal(n):
    x, y, z, w = _x_onto(np.array(n, float))
    np.testing.assert_allclose(pin.Quaternion(w, x, y, z).matrix() @ [1, 0, 0], n, atol=1e-12)


@pytest.mark.parametrize("hz", [20.0, 0.0])
def test_the_scene_has_the_configs_rate(tmp_path, hz):
    """recording.scene_hz sets the 3D topics' rate (0: none); the four topics stay whole."""
    cfg, path = run_logged(tmp_path, [f"recording.scene_hz={hz}"], ticks=1000)
    data = read_log(path)
    assert data.ticks == 1000 and not data.gaps
    if hz == 0:
        assert data.other_topics == {}
        return
    period = round(cfg.dt * 1e9)
    (t0, _), *tf = decoded(path, "/tf")
    ticks = [(log_time - data.start_ns) // period for log_time, _ in tf]
    assert ticks == list(range(0, 1000, 50))  # 20 Hz at 1 kHz: every 50th tick
    assert data.other_topics["/hand_target"][1] == len(ticks)


MOVING_URDF = """<robot name="r">
  <link name="base"/><link name="a"/><link name="b"/><link name="c"/>
  <joint name="turn" type="revolute"><parent link="base"/><child link="a"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0.4 -0.7 1.1"/><axis xyz="1 2 -2"/>
    <limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
  <joint name="slide" type="prismatic"><parent link="a"/><child link="b"/>
    <origin xyz="0.5 0 0" rpy="-0.3 0.2 0.9"/><axis xyz="0 0.6 0.8"/>
    <limit lower="-1" upper="1" velocity="1" effort="1"/></joint>
  <joint name="z" type="revolute"><parent link="b"/><child link="c"/>
    <limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
</robot>"""


def test_moving_joints_are_pinocchios_relative_placements():
    """The scene's batched transforms (origin, then a turn about or a slide along a tilted
    axis, the default axis x) equal Pinocchio's oMf[parent]^-1 oMf[child] at random q."""
    model = pin.buildModelFromXML(MOVING_URDF)
    data = model.createData()
    body = {f.name: i for i, f in enumerate(model.frames) if f.type == pin.FrameType.BODY}
    joints = _MovingJoints(model, MOVING_URDF, "x", body)
    q = np.random.default_rng(3).uniform(-2.5, 2.5, (6, model.nq))
    names, t, r = joints.at(q)
    assert names == [("x/base", "x/a"), ("x/a", "x/b"), ("x/b", "x/c")]
    for f in range(len(q)):
        pin.framesForwardKinematics(model, data, q[f])
        for j, (parent, child) in enumerate(names):
            rel = data.oMf[body[parent[2:]]].actInv(data.oMf[body[child[2:]]])
            x, y, z, w = r[f][j]
            np.testing.assert_allclose(t[f][j], rel.translation, atol=1e-12)
            rotation = pin.Quaternion(w, x, y, z).matrix()
            np.testing.assert_allclose(rotation, rel.rotation, atol=1e-12)
