"""Hostile and malformed robot descriptions (issue 14): not XML, cut short, entity bombs, joint
loops, two roots, missing links, meshes over the size limit or missing, mimic loops, non-finite
numbers, a 10k-link chain. Each goes through the Dispatcher as a /robot_description message (the
registry's real converter spec) next to a good /odom: one warning names the topic and what was
left out, every other link is drawn with its transform, /odom converts, nothing raises.

The URDFs and meshes are written here; a 200 MB mesh is a sparse file (``truncate``), never
real bytes.
"""

from __future__ import annotations

import logging
import struct
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import rerun as rr
import trimesh
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from host_bridge.cli import main as host_main
from host_bridge.converters.urdf import kinematics
from host_bridge.core.contract import WARNINGS_PATH, ColumnsItem, LogItem
from host_bridge.core.resources import ResourceResolver
from host_bridge.errors import ConvertError
from host_bridge.pipeline.dispatch import Dispatcher
from robot_relay.wire import RawMessage
from tests.host_bridge.test_config import RecordingSink
from tests.reliability import Record
from tests.rrd import entity_rows

STORE = get_typestore(Stores.ROS2_HUMBLE)
STRING, ODOMETRY = "std_msgs/msg/String", "nav_msgs/msg/Odometry"
ROBOT = "r"
T0 = 1_700_000_000_000_000_000
STEP = 100_000_000
AREA = "Malformed robot descriptions"
LIMIT = 'lower="-1" upper="1" effort="1" velocity="1"'


def box_link(name: str, size: str = "0.1 0.2 0.3") -> str:
    return f'<link name="{name}"><visual><geometry><box size="{size}"/></geometry></visual></link>'


def joint(name: str, parent: str, child: str, xyz: str = "0 0 1", *, kind: str = "fixed",
          extra: str = "") -> str:
    return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz}"/>{extra}</joint>')


def robot(*elements: str, name: str = "bad") -> str:
    return f'<?xml version="1.0"?>\n<robot name="{name}">{"".join(elements)}</robot>'


def odom_cdr(step: int) -> bytes:
    t = STORE.types
    sec, nanosec = divmod(T0 + step * STEP, 1_000_000_000)
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                      frame_id="odom")
    vector = t["geometry_msgs/msg/Vector3"]
    msg = t[ODOMETRY](
        header=header, child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=0.1 * step, y=0.0, z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=vector(x=0.5 + step, y=0.0, z=0.0),
                                               angular=vector(x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36)),
    )
    return bytes(STORE.serialize_cdr(msg, ODOMETRY))


def description_cdr(xml: str) -> bytes:
    return bytes(STORE.serialize_cdr(STORE.types[STRING](data=xml), STRING))


@dataclass(frozen=True, slots=True)
class Drawn:
    """What the dispatcher logged for robot ``r``."""

    visuals: dict[str, LogItem]  # link -> its first visual
    # child frame -> (parent frame, translation, quaternion xyzw) of its static relation
    relations: dict[str, tuple[str, list[float], list[float]]]
    warnings: list[str]
    odom_speeds: list[float]
    seconds: float

    def archetype(self, link: str, kind: type[Any]) -> Any:
        (found,) = [a for a in self.visuals[link].archetypes if isinstance(a, kind)]
        return found


def values(batch: Any) -> list[Any]:
    return list(batch.as_arrow_array().to_pylist())


def draw(xml: str, resolver: ResourceResolver | None = None) -> Drawn:
    """``xml`` as /robot_description, then 3 /odom messages, through a Dispatcher."""
    sink = RecordingSink()
    dispatcher = Dispatcher(sink, resolver=resolver or ResourceResolver())
    started = time.perf_counter()
    dispatcher.dispatch([RawMessage(ROBOT, "/robot_description", STRING, description_cdr(xml),
                                    log_ns=T0)])
    seconds = time.perf_counter() - started
    from_description = len(sink.logged)
    dispatcher.dispatch([RawMessage(ROBOT, "/odom", ODOMETRY, odom_cdr(i), log_ns=T0 + i * STEP)
                         for i in range(3)])
    dispatcher.close()
    visuals: dict[str, LogItem] = {}
    relations: dict[str, tuple[str, list[float], list[float]]] = {}
    warnings: list[str] = []
    speeds: list[float] = []
    for index, (entry, _) in enumerate(sink.logged):
        if isinstance(entry, ColumnsItem):
            if entry.path == f"/{ROBOT}/odom/twist/linear":  # x, y and z per row
                speeds += [float(v) for col in entry.columns for v in np.reshape(values(col), (-1, 3))[:, 0]]
            continue
        if entry.path == WARNINGS_PATH:
            warnings += [text for a in entry.archetypes for text in values(cast(Any, a).text)]
        elif entry.path.startswith(f"/{ROBOT}/robot_model/") and entry.path.endswith("/visual_0"):
            visuals[entry.path.split("/")[3]] = entry
        elif entry.path.startswith(f"/{ROBOT}/tf_static/") and index < from_description:
            (transform,) = entry.archetypes
            assert isinstance(transform, rr.Transform3D)
            (child,) = values(transform.child_frame)
            (parent,) = values(transform.parent_frame)
            translation = values(transform.translation)[0] if transform.translation else [0.0] * 3
            quaternion = values(transform.quaternion)[0] if transform.quaternion else [0, 0, 0, 1]
            relations[child] = (parent, translation, quaternion)
    counters = dispatcher.counters[(ROBOT, "/odom")]
    assert (counters.received, counters.converted, counters.dropped) == (3, 3, 0)
    return Drawn(visuals, relations, warnings, speeds, seconds)


def one_warning(drawn: Drawn) -> str:
    (warning,) = drawn.warnings
    assert warning.startswith(f"[{ROBOT}] /robot_description: ")
    assert warning.endswith(" (further PartialConvertErrors on this topic are counted, not shown)")
    return warning.removeprefix(f"[{ROBOT}] /robot_description: ").split(" (further ")[0]


def at(parent: str, xyz: list[float], quaternion: tuple[float, ...] = (0, 0, 0, 1)) -> Any:
    # Rerun stores float32.
    return (f"{ROBOT}/{parent}", pytest.approx(xyz, abs=1e-6),
            pytest.approx(list(quaternion), abs=1e-6))


ROOT = f"tf#/{ROBOT}"  # where frames.py puts a frame no relation places


@pytest.mark.parametrize(
    ("case", "xml", "problem"),
    [
        ("not XML", "this is not a robot", "syntax error: line 1, column 0"),
        ("binary bytes", "\x00\x01\x02", "not well-formed (invalid token): line 1, column 0"),
        ("an entity bomb (10^9 expansions)",
         '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY a0 "0123456789">'
         + "".join(f'<!ENTITY a{i} "{("&a" + str(i - 1) + ";") * 10}">' for i in range(1, 10))
         + ']><robot name="&a9;"><link name="a"/></robot>',
         "limit on input amplification factor (from DTD and entities) breached: line 1, column"),
    ],
)
def test_text_that_is_no_urdf_is_one_warning_and_odom_still_converts(
    case: str, xml: str, problem: str, reliability: Record
) -> None:
    drawn = draw(xml)
    (warning,) = drawn.warnings
    assert warning.startswith(
        f"[{ROBOT}] /robot_description: the robot description is not well-formed XML ({problem}")
    assert drawn.visuals == {}
    assert drawn.relations == {}
    assert drawn.odom_speeds == [0.5, 1.5, 2.5]
    assert drawn.seconds < 30
    reliability(AREA, f"/robot_description that is {case}", tried="1 message",
                survived="one warning naming the topic and the parser's error; 3 of 3 /odom "
                "converted", lost="the model (nothing of it is XML)")


def test_a_description_cut_short_draws_the_elements_before_the_cut(reliability: Record) -> None:
    whole = robot(box_link("base"), box_link("arm", "1 2 3"), joint("shoulder", "base", "arm"),
                  box_link("hand"), joint("wrist", "arm", "hand"))
    xml = whole[: whole.index('<joint name="wrist"') + 30]
    drawn = draw(xml)
    assert one_warning(drawn) == (
        "robot model 'bad': the description is not well-formed XML (unclosed token: line 2, "
        "column 380): only the 4 elements complete before that point are drawn; 2 root links "
        "(a URDF has one): 'base' is the model's root, 'hand' drawn at the robot's root")
    assert sorted(drawn.visuals) == ["arm", "base", "hand"]
    assert values(drawn.archetype("arm", rr.Boxes3D).half_sizes) == [[0.5, 1.0, 1.5]]
    assert drawn.relations == {"r/arm": at("base", [0, 0, 1]), "r/base": (ROOT, [0] * 3, [0, 0, 0, 1]),
                               "r/hand": (ROOT, [0] * 3, [0, 0, 0, 1])}
    reliability(AREA, "/robot_description cut short inside its last joint", tried="1 message",
                survived="3 of 3 links and the 1 complete joint drawn, one warning naming the "
                "XML error", lost="the cut joint 'wrist' (its link drawn at the robot's root)")


def test_joint_loops_and_missing_links_leave_the_rest_one_tree(reliability: Record) -> None:
    xml = robot(
        box_link("base"), box_link("a"), box_link("b"), box_link("c"),
        joint("base_a", "base", "a", "1 0 0"),
        joint("a_b", "a", "b", "0 1 0"),
        joint("b_c", "b", "c", "0 0 1"),
        joint("c_a", "c", "a", "5 5 5"),       # a would be its own ancestor (and has a parent)
        joint("c_b", "c", "b"),                # b again
        joint("self", "c", "c"),               # a link its own parent
        joint("to_ghost", "c", "ghost"),       # no such link
        joint("from_ghost", "ghost", "base"),
    )
    drawn = draw(xml)
    assert one_warning(drawn) == (
        "robot model 'bad': joints not drawn: joint 'c_a' (link 'a' already has parent joint "
        "'base_a'), joint 'c_b' (link 'b' already has parent joint 'a_b'), joint 'self' (it "
        "makes link 'c' its own parent), joint 'to_ghost' (no <link> defines 'ghost'), joint "
        "'from_ghost' (no <link> defines 'ghost')")
    assert sorted(drawn.visuals) == ["a", "b", "base", "c"]
    assert drawn.relations == {"r/a": at("base", [1, 0, 0]), "r/b": at("a", [0, 1, 0]),
                               "r/c": at("b", [0, 0, 1]), "r/base": (ROOT, [0] * 3, [0, 0, 0, 1])}
    reliability(AREA, "URDF with a joint loop, a second parent, a self-parent joint and joints "
                "naming a missing link", tried="1 model, 5 bad joints",
                survived="4 of 4 links and the 3 good joints (one tree), one warning naming "
                "the 5 joints; 3 of 3 /odom", lost="the 5 bad joints")


def test_a_loop_without_a_second_parent_is_named_as_a_loop(reliability: Record) -> None:
    drawn = draw(robot(box_link("a"), box_link("b"), joint("ab", "a", "b", "1 0 0"),
                       joint("ba", "b", "a")))
    assert one_warning(drawn) == (
        "robot model 'bad': joints not drawn: joint 'ba' (it makes link 'a' its own ancestor)")
    assert drawn.relations == {"r/b": at("a", [1, 0, 0]), "r/a": (ROOT, [0] * 3, [0, 0, 0, 1])}
    reliability(AREA, "URDF whose two joints make each link the other's parent",
                tried="1 model", survived="2 of 2 links, 1 of 2 joints, one warning",
                lost="the joint closing the loop")


def test_two_root_links_draw_both_trees_the_largest_as_the_model(reliability: Record) -> None:
    drawn = draw(robot(box_link("tool"), box_link("base"), box_link("arm"),
                       joint("shoulder", "base", "arm", "0 0 0.5")))
    assert one_warning(drawn) == (
        "robot model 'bad': 2 root links (a URDF has one): 'base' is the model's root, 'tool' "
        "drawn at the robot's root")
    assert sorted(drawn.visuals) == ["arm", "base", "tool"]
    assert drawn.relations == {"r/arm": at("base", [0, 0, 0.5]),
                               "r/base": (ROOT, [0] * 3, [0, 0, 0, 1]),
                               "r/tool": (ROOT, [0] * 3, [0, 0, 0, 1])}
    reliability(AREA, "URDF with two root links", tried="1 model",
                survived="3 of 3 links, both trees, one warning naming the roots", lost="0")


def write_stl_claiming(path: Path, triangles: int, written: int) -> None:
    """A binary STL whose header declares ``triangles`` and holds ``written`` of them."""
    facet = struct.pack("<12fH", 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0)
    path.write_bytes(b"\0" * 80 + struct.pack("<I", triangles) + facet * written)


def test_huge_and_missing_meshes_cost_their_visual_only(tmp_path: Path, reliability: Record) -> None:
    huge = tmp_path / "huge.stl"
    with huge.open("wb") as file:
        file.truncate(200 << 20)  # sparse: no bytes written
    write_stl_claiming(tmp_path / "claims.stl", 10**9, 2)
    trimesh.creation.box(extents=[1.0, 2.0, 3.0]).export(tmp_path / "good.stl")
    links = [f'<link name="{name}"><visual><geometry><mesh filename="file://{tmp_path}/{file}"/>'
             "</geometry></visual></link>"
             for name, file in (("lidar", "huge.stl"), ("camera", "missing.stl"),
                                ("bumper", "claims.stl"), ("base", "good.stl"))]
    xml = robot(*links, joint("lidar_joint", "base", "lidar"), joint("camera_joint", "base", "camera"),
                joint("bumper_joint", "base", "bumper", "0.2 0 0"))
    tracemalloc.start()
    try:
        drawn = draw(xml)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert one_warning(drawn) == (
        f"robot model 'bad': 3 of 4 visuals not drawn: mesh files not found: "
        f"file://{tmp_path}/missing.stl for link 'camera'; looked in no --package-path and no "
        "ROS_PACKAGE_PATH/AMENT_PREFIX_PATH; no robot file server to ask; link 'lidar': "
        f"file://{tmp_path}/huge.stl: 209715200 bytes (200 MiB) is over the mesh size limit of "
        "64 MiB (urdf.meshes.MAX_MESH_BYTES), not loaded; reduce the mesh (MeshLab, Blender's "
        f"Decimate); link 'bumper': file://{tmp_path}/claims.stl: the file holds no triangles")
    assert sorted(drawn.visuals) == ["base"]
    positions = np.asarray(values(drawn.archetype("base", rr.Mesh3D).vertex_positions))
    assert np.ptp(positions, axis=0) == pytest.approx([1.0, 2.0, 3.0])
    assert drawn.relations["r/bumper"] == at("base", [0.2, 0, 0])
    assert {"r/lidar", "r/camera"} <= set(drawn.relations)
    assert peak < 50 << 20  # the 200 MB file is measured, not read (it was read: +629 MB)
    assert drawn.seconds < 30
    reliability(AREA, "URDF meshes: a 200 MB sparse STL, a missing file, an STL header "
                "declaring 10^9 triangles", tried="1 model, 3 bad meshes",
                survived=f"the good mesh, 4 of 4 link frames; one warning naming each file "
                f"(and the 200 MB size); peak Python memory {peak / 2**20:.0f} MiB",
                lost="the 3 bad visuals")


def test_mimic_rules_that_loop_are_ignored(reliability: Record) -> None:
    def revolute(name: str, parent: str, child: str, mimic: str | None) -> str:
        rule = "" if mimic is None else f'<mimic joint="{mimic}" offset="0.5"/>'
        return joint(name, parent, child, "0 0 0", kind="revolute",
                     extra=f'<axis xyz="0 0 1"/><limit {LIMIT}/>{rule}')

    drawn = draw(robot(*(box_link(n) for n in ("base", "a", "b", "c", "d", "e")),
                       revolute("self", "base", "a", "self"),
                       revolute("one", "base", "b", "two"), revolute("two", "base", "c", "one"),
                       revolute("ghostly", "base", "d", "ghost"),
                       revolute("follower", "base", "e", "one")))
    assert one_warning(drawn) == (
        "robot model 'bad': joint 'ghostly' mimics joint 'ghost', which the model does not have: "
        "moves on its own; joint 'self' mimics itself: its <mimic> is ignored; joints 'one' -> "
        "'two' -> 'one' mimic each other in a loop: their <mimic> is ignored")
    # At zero; the follower of the (now free) joint 'one' is at its offset, 0.5 rad about z.
    for link in ("a", "b", "c", "d"):
        assert drawn.relations[f"r/{link}"] == at("base", [0, 0, 0])
    assert drawn.relations["r/e"] == at("base", [0, 0, 0], (0, 0, np.sin(0.25), np.cos(0.25)))
    reliability(AREA, "URDF mimic joints: one mimicking itself, two mimicking each other, one "
                "mimicking a missing joint", tried="1 model, 4 bad mimic rules",
                survived="6 of 6 links and 5 of 5 joints drawn at zero, a good mimic follower "
                "at its offset, one warning", lost="the 4 bad mimic rules (those joints move "
                "on their own)")


def test_non_finite_origins_axes_limits_and_sizes_are_named(reliability: Record) -> None:
    drawn = draw(robot(
        box_link("base"), box_link("a"), box_link("b"), box_link("c"), box_link("d", "nan 1 1"),
        '<joint name="nan_origin" type="fixed"><parent link="base"/><child link="a"/>'
        '<origin xyz="nan 0 1" rpy="0 inf 0"/></joint>',
        joint("nan_limits", "base", "b", "0 1 0", kind="revolute", extra=
              '<axis xyz="0 0 1"/><limit lower="nan" upper="inf" effort="1" velocity="-inf"/>'),
        joint("nan_axis", "base", "c", "0 0 2", kind="revolute",
              extra=f'<axis xyz="nan 0 1"/><limit {LIMIT}/>'),
        joint("to_d", "base", "d", "3 0 0"),
    ))
    assert one_warning(drawn) == (
        "robot model 'bad': joint 'nan_origin': its <origin> is not finite: taken as identity; "
        "joint 'nan_limits': its <limit> is not finite (lower=nan, upper=inf, effort=1.0, "
        "velocity=-inf): ignored, as every limit (joint states are drawn as given); joint "
        "'nan_axis': its <axis> [nan, 0.0, 1.0] is not a direction: drawn as fixed, its joint "
        "states are ignored; 1 of 5 visuals not drawn: link 'd': its <box> size [nan, 1.0, 1.0] "
        "is not finite and >= 0")
    assert sorted(drawn.visuals) == ["a", "b", "base", "c"]
    assert drawn.relations["r/a"] == at("base", [0, 0, 0])
    assert drawn.relations["r/b"] == at("base", [0, 1, 0])
    assert drawn.relations["r/c"] == at("base", [0, 0, 2])
    assert drawn.relations["r/d"] == at("base", [3, 0, 0])
    reliability(AREA, "URDF with NaN/inf in a joint origin, limits, axis and a box size",
                tried="1 model, 4 bad values", survived="5 of 5 link frames, 4 of 5 visuals, "
                "one warning naming each joint and link", lost="the NaN box's visual")


def test_elements_yourdfpy_refuses_are_left_out_alone(reliability: Record) -> None:
    drawn = draw(robot(box_link("base"), box_link("a"), box_link("b"),
                       joint("good", "base", "a", "1 0 0"),
                       '<joint name="no_parent" type="fixed"><child link="b"/></joint>',
                       joint("words", "base", "b", "1 two 3"), name="x"))
    assert one_warning(drawn) == (
        "robot model 'x': not valid URDF, not drawn: <joint name='no_parent'> (AttributeError: "
        "'NoneType' object has no attribute 'get'), <joint name='words'> (ValueError: could not "
        "convert string to float: 'two'); 2 root links (a URDF has one): 'base' is the model's "
        "root, 'b' drawn at the robot's root")
    assert sorted(drawn.visuals) == ["a", "b", "base"]
    assert drawn.relations["r/a"] == at("base", [1, 0, 0])
    reliability(AREA, "URDF with a joint without <parent> and one with xyz=\"1 two 3\"",
                tried="1 model", survived="3 of 3 links, the good joint, one warning",
                lost="the 2 unreadable joints (before: the whole model)")


CHAIN = 10_000


def test_a_ten_thousand_link_mimic_chain_is_drawn_in_bounded_time(reliability: Record) -> None:
    """Each revolute joint mimics the one before (+0.001 rad), listed followers first: the mimic
    order was recursive and lost the whole model to a RecursionError."""
    links = [box_link("l0"), *(f'<link name="l{i}"/>' for i in range(1, CHAIN - 1)),
             box_link(f"l{CHAIN - 1}")]
    joints = [joint(f"j{i}", f"l{i}", f"l{i + 1}", "0 0 0.01", kind="revolute",
                    extra=f'<axis xyz="0 0 1"/><limit {LIMIT}/>'
                    + (f'<mimic joint="j{i - 1}" offset="0.001"/>' if i else ""))
              for i in reversed(range(CHAIN - 1))]
    drawn = draw(robot(*links, *joints))
    assert drawn.warnings == []
    assert sorted(drawn.visuals) == ["l0", f"l{CHAIN - 1}"]
    assert len(drawn.relations) == CHAIN  # 9999 joints and the root placed at the robot's root
    last = CHAIN - 2  # j9998 stands at 9998 * 0.001 rad, followed down the whole chain
    angle = last * 0.001
    assert drawn.relations[f"r/l{CHAIN - 1}"] == at(
        f"l{last}", [0, 0, 0.01], (0, 0, np.sin(angle / 2), np.cos(angle / 2)))
    assert drawn.seconds < 180  # about 5 s alone; generous for a loaded 2-core machine
    reliability(AREA, f"URDF chain of {CHAIN} links, each joint mimicking the one before",
                tried="1 model", survived=f"{CHAIN} of {CHAIN} link frames, the last joint at "
                f"{angle:.3f} rad (followed through the whole chain), {drawn.seconds:.1f} s",
                lost="0 (before: the whole model, RecursionError)")


def test_robot_kinematics_of_a_loop_is_the_tree() -> None:
    """The demo's entry point takes the same checks, without the warning."""
    model = kinematics.robot_kinematics(robot(box_link("a"), box_link("b"), joint("ab", "a", "b"),
                                        joint("ba", "b", "a")), "x.urdf")
    assert sorted(model.joints) == ["ab"]
    assert model.root == "a"


def write_bag(path: Path, description: str) -> Path:
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as writer:
        model = writer.add_connection("/robot_description", STRING, typestore=STORE)
        odom = writer.add_connection("/odom", ODOMETRY, typestore=STORE)
        writer.write(model, T0, description_cdr(description))
        for i in range(10):
            writer.write(odom, T0 + i * STEP, odom_cdr(i))
    return path


def test_swanky_host_bag_with_a_bad_description_draws_the_rest(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    xml = robot(box_link("base"), box_link("arm", "1 1 1"),
                '<link name="lidar"><visual><geometry><mesh filename="package://gone/l.stl"/>'
                "</geometry></visual></link>",
                joint("shoulder", "base", "arm", "0 0 0.5"), joint("lidar_joint", "base", "lidar"),
                joint("loop", "arm", "base"))
    bag = write_bag(tmp_path / "bag", xml)
    out = tmp_path / "out.rrd"
    with caplog.at_level(logging.WARNING, logger="swanky.host"):
        code = host_main(["--bag", str(bag), "--save", str(out), "--no-blueprint"])
    assert code == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert warnings[0].startswith(
        "[robot] /robot_description: robot model 'bad': joints not drawn: joint 'loop' (it makes "
        "link 'base' its own ancestor); 1 of 3 visuals not drawn: mesh files not found: "
        "package://gone/l.stl for link 'lidar'")
    rows = entity_rows(out)
    assert {"/robot/robot_model/base/visual_0", "/robot/robot_model/arm/visual_0"} <= set(rows)
    assert "/robot/robot_model/lidar/visual_0" not in rows
    [arm] = rows["/robot/robot_model/arm/visual_0"]
    assert arm["Boxes3D:half_sizes"] == [[0.5, 0.5, 0.5]]
    [shoulder] = rows["/robot/tf_static/arm"]
    assert shoulder["Transform3D:parent_frame"] == ["robot/base"]
    assert shoulder["Transform3D:translation"] == [pytest.approx([0, 0, 0.5])]
    twist = [row for row in rows["/robot/odom/twist/linear"] if "Scalars:scalars" in row]
    speeds = [row["Scalars:scalars"][0] for row in twist]
    assert speeds == [0.5 + i for i in range(10)]
    reliability(AREA, "swanky-host --bag of a bag whose /robot_description has a joint loop and "
                "a missing mesh", tried="1 bag (1 description, 10 /odom)",
                survived="exit 0, 2 of 3 visuals and 2 of 3 joints in the .rrd, 10 of 10 /odom "
                "rows, one warning", lost="the loop joint and the missing mesh's visual")


def test_a_relay_reply_over_the_size_limit_is_refused_not_kept(
    tmp_path: Path, reliability: Record
) -> None:
    """A relay that sends more than a relay may (not Swanky's, or hostile) costs that visual,
    and its bytes are not cached for the host's lifetime."""
    import zenoh

    from host_bridge.inputs.robot_files import RobotFiles
    from robot_relay.files import serve_files

    big = trimesh.creation.icosphere(subdivisions=3).export(file_type="stl")
    (tmp_path / "pkg" / "meshes").mkdir(parents=True)
    (tmp_path / "pkg" / "meshes" / "big.stl").write_bytes(big)
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", "[]")
    with zenoh.open(config) as session:
        service = serve_files(session, ROBOT, [f"pkg={tmp_path / 'pkg'}"], environ={})
        files = RobotFiles(timeout=5.0, max_bytes=len(big) - 1)
        files.attach(session)
        try:
            xml = robot(box_link("base"),
                        '<link name="dome"><visual><geometry><mesh filename="package://pkg/'
                        'meshes/big.stl"/></geometry></visual></link>', joint("j", "base", "dome"))
            drawn = draw(xml, ResourceResolver(robot_fetch=files.fetch))
            with pytest.raises(ConvertError, match="not kept"):
                files.fetch(ROBOT, "package://pkg/meshes/big.stl")  # asked again: not cached
        finally:
            service.close()
    assert one_warning(drawn) == (
        "robot model 'bad': 1 of 2 visuals not drawn: mesh files not found: "
        "package://pkg/meshes/big.stl for link 'dome'; looked in no --package-path and no "
        f"ROS_PACKAGE_PATH/AMENT_PREFIX_PATH; robot r sent {len(big)} bytes for "
        f"package://pkg/meshes/big.stl, over the limit of {len(big) - 1} bytes a relay serves; "
        "not kept; pass --package-path pkg=DIR")
    assert sorted(drawn.visuals) == ["base"]
    assert drawn.relations["r/dome"] == at("base", [0, 0, 1])
    reliability(AREA, "a relay answering a mesh request with more bytes than a relay serves",
                tried="2 requests", survived="the rest of the model, one warning naming the "
                "robot, file and size", lost="that visual; nothing cached")
