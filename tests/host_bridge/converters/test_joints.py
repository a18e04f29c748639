"""Joint values -> link transforms, checked against yourdfpy's and Rerun's own kinematics."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
import trimesh
import yourdfpy
from rerun.urdf import UrdfTree

from host_bridge.converters import joints
from host_bridge.converters.urdf import description, kinematics
from host_bridge.core.contract import ColumnsItem, ConvertContext, LogEntry, LogItem
from host_bridge.core.resources import ResourceResolver
from host_bridge.core.state import RobotState
from host_bridge.errors import ConvertError, PartialConvertError
from tests.host_bridge.sensor_test_support import convert, convert_run, header, make_ctx, msg


@pytest.fixture
def burger_file(shared_data: Path) -> Path:
    return shared_data / "turtlebot3_description/turtlebot3_description/urdf/turtlebot3_burger.urdf"


def joints_ctx(robot: str, xml: str, topic: str = "/joint_states", stamp: int = 0) -> ConvertContext:
    """A JointState topic context of a robot whose model is loaded from ``xml`` (no meshes)."""
    state = RobotState(ResourceResolver())
    model_ctx = make_ctx("/robot_description", robot=robot, times={}, robot_state=state)
    with contextlib.suppress(PartialConvertError):  # the meshes are not needed for kinematics
        description.convert(SimpleNamespace(data=xml), model_ctx)
    return make_ctx(topic, stamp_ns=stamp, robot=robot, robot_state=state)


def joint_state(names: list[str], positions: list[float], stamp: int = 0) -> Any:
    return msg(
        "sensor_msgs/msg/JointState",
        header=header(stamp_ns=stamp),
        name=names,
        position=np.array(positions, dtype=np.float64),
        velocity=np.array([]),
        effort=np.array([]),
    )


def by_path(items: list[LogEntry]) -> dict[str, LogItem]:
    """Each entity's transform as a LogItem; the columns of one message have one row."""
    found: dict[str, LogItem] = {}
    for item in items:
        if isinstance(item, LogItem):
            found[item.path] = item
            continue
        columns = {str(c.component_descriptor()): c.as_arrow_array().to_pylist() for c in item.columns}
        assert len(columns["Transform3D:translation"]) == 1, item
        transform = rr.Transform3D(
            translation=columns["Transform3D:translation"][0][0],
            quaternion=rr.Quaternion(xyzw=columns["Transform3D:quaternion"][0][0]),
            parent_frame=columns["Transform3D:parent_frame"][0][0],
            child_frame=columns["Transform3D:child_frame"][0][0],
        )
        found[item.path] = LogItem(item.path, (transform,))
    return found


def values(batch: Any) -> npt.NDArray[Any]:
    return np.asarray(batch.as_arrow_array().to_pylist())


def matrix(translation: npt.NDArray[Any], quaternion_xyzw: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    x, y, z, w = quaternion_xyzw
    result: npt.NDArray[np.float64] = trimesh.transformations.quaternion_matrix([w, x, y, z])  # type: ignore[no-untyped-call]
    result[:3, 3] = translation
    return result


def transform_matrix(item: LogItem) -> npt.NDArray[np.float64]:
    """4x4 of a logged Transform3D; Rerun keeps float32, hence the 1e-6 tolerances."""
    (transform,) = item.archetypes
    assert isinstance(transform, rr.Transform3D)
    return matrix(values(transform.translation)[0], values(transform.quaternion)[0])


def frames(item: LogItem) -> tuple[str, str]:
    (transform,) = item.archetypes
    assert isinstance(transform, rr.Transform3D)
    return values(transform.parent_frame)[0], values(transform.child_frame)[0]


def test_wheel_angle_matches_yourdfpy_and_rerun(burger_file: Path) -> None:
    ctx = joints_ctx("tb1", burger_file.read_text())
    items = by_path(
        convert(joints.JOINT_STATE, joint_state(["wheel_left_joint", "wheel_right_joint"], [0.7, -0.3]), ctx)
    )
    assert sorted(items) == [
        "/tb1/robot_model/joints/wheel_left_joint",
        "/tb1/robot_model/joints/wheel_right_joint",
    ]
    left = items["/tb1/robot_model/joints/wheel_left_joint"]
    assert not left.static
    assert frames(left) == ("tb1/base_link", "tb1/wheel_left_link")

    reference = yourdfpy.URDF.load(str(burger_file), load_meshes=False)
    reference.update_cfg({"wheel_left_joint": 0.7, "wheel_right_joint": -0.3})
    for joint, child in (
        ("wheel_left_joint", "wheel_left_link"),
        ("wheel_right_joint", "wheel_right_link"),
    ):
        expected = reference.get_transform(child, "base_link")
        np.testing.assert_allclose(
            transform_matrix(items[f"/tb1/robot_model/joints/{joint}"]), expected, atol=1e-6
        )

    # Rerun's own URDF kinematics (Rust) agrees too, frames prefixed the same way.
    rerun_joint = UrdfTree.from_file_path(burger_file, frame_prefix="tb1/").get_joint_by_name(
        "wheel_left_joint"
    )
    assert rerun_joint is not None
    rerun_transform = rerun_joint.compute_transform(0.7)
    assert frames(LogItem("x", (rerun_transform,))) == frames(left)
    np.testing.assert_allclose(
        transform_matrix(LogItem("x", (rerun_transform,))), transform_matrix(left), atol=1e-6
    )


ARM = """<robot name="arm">
  <link name="base"/><link name="slider"/><link name="arm"/><link name="finger"/><link name="tip"/>
  <joint name="lift" type="prismatic">
    <parent link="base"/><child link="slider"/>
    <origin xyz="0.1 0 0.2" rpy="0.3 0 0.5"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="shoulder" type="revolute">
    <parent link="slider"/><child link="arm"/>
    <origin xyz="0 0.05 0" rpy="0 0.2 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="grip" type="revolute">
    <parent link="arm"/><child link="finger"/>
    <origin xyz="0.3 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
    <mimic joint="shoulder" multiplier="-2" offset="0.1"/>
  </joint>
  <joint name="tip_joint" type="revolute">
    <parent link="finger"/><child link="tip"/>
    <origin xyz="0.05 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
    <mimic joint="grip" multiplier="0.5"/>
  </joint>
</robot>
"""


def rotation_about(angle: float, axis: list[float], translation: list[float]) -> npt.NDArray[np.float64]:
    result: npt.NDArray[np.float64] = trimesh.transformations.rotation_matrix(angle, axis)  # type: ignore[no-untyped-call]
    result[:3, 3] = translation
    return result


def test_prismatic_and_mimic_match_yourdfpy() -> None:
    ctx = joints_ctx("arm1", ARM)
    items = by_path(convert(joints.JOINT_STATE, joint_state(["shoulder", "lift"], [0.4, 0.05]), ctx))
    assert len(items) == 4
    reference = yourdfpy.URDF.load(io.StringIO(ARM), load_meshes=False)
    reference.update_cfg({"lift": 0.05, "shoulder": 0.4})
    for joint, parent, child in (
        ("lift", "base", "slider"),
        ("shoulder", "slider", "arm"),
        ("grip", "arm", "finger"),
    ):
        item = items[f"/arm1/robot_model/joints/{joint}"]
        assert frames(item) == (f"arm1/{parent}", f"arm1/{child}")
        expected = reference.get_transform(child, parent)
        np.testing.assert_allclose(transform_matrix(item), expected, atol=1e-6)
    # grip = -2 * 0.4 + 0.1 = -0.7 about x at its origin.
    grip = transform_matrix(items["/arm1/robot_model/joints/grip"])
    np.testing.assert_allclose(grip, rotation_about(-0.7, [1, 0, 0], [0.3, 0, 0]), atol=1e-6)
    # tip mimics grip (a chain yourdfpy does not follow): 0.5 * -0.7 = -0.35 about z.
    tip = transform_matrix(items["/arm1/robot_model/joints/tip_joint"])
    np.testing.assert_allclose(tip, rotation_about(-0.35, [0, 0, 1], [0.05, 0, 0]), atol=1e-6)
    # The prismatic joint moves along its axis in the joint frame: origin rotation applied.
    lift = transform_matrix(items["/arm1/robot_model/joints/lift"])
    origin: npt.NDArray[np.float64] = trimesh.transformations.euler_matrix(0.3, 0, 0.5)  # type: ignore[no-untyped-call]
    np.testing.assert_allclose(lift[:3, 3], [0.1, 0, 0.2] + origin[:3, :3] @ [0, 0, 0.05], atol=1e-6)


def test_model_stands_at_zero_with_mimic_chains_at_their_offsets() -> None:
    """No /joint_states yet: every joint at 0 as RViz shows it, static on the child's /tf_static
    entity (the joint states' temporal rows win from their first stamp on)."""
    state = RobotState(ResourceResolver())
    ctx = make_ctx("/robot_description", robot="arm1", times={}, robot_state=state)
    items = by_path(description.convert(SimpleNamespace(data=ARM), ctx))
    assert sorted(items) == [f"/arm1/tf_static/{link}" for link in ("arm", "finger", "slider", "tip")]
    assert all(item.static for item in items.values())
    reference = yourdfpy.URDF.load(io.StringIO(ARM), load_meshes=False)
    reference.update_cfg({"lift": 0.0, "shoulder": 0.0})
    for parent, child in (("base", "slider"), ("slider", "arm"), ("arm", "finger")):
        item = items[f"/arm1/tf_static/{child}"]
        assert frames(item) == (f"arm1/{parent}", f"arm1/{child}")
        np.testing.assert_allclose(transform_matrix(item), reference.get_transform(child, parent), atol=1e-6)
    # grip = -2 * 0 + 0.1 about x; tip follows grip (a chain): 0.5 * 0.1 about z.
    np.testing.assert_allclose(transform_matrix(items["/arm1/tf_static/finger"]),
                               rotation_about(0.1, [1, 0, 0], [0.3, 0, 0]), atol=1e-6)
    np.testing.assert_allclose(transform_matrix(items["/arm1/tf_static/tip"]),
                               rotation_about(0.05, [0, 0, 1], [0.05, 0, 0]), atol=1e-6)
    model = state.model
    assert model is not None
    assert kinematics.zero_positions(model) == {"lift": 0.0, "shoulder": 0.0, "grip": 0.1, "tip_joint": 0.05}
    assert model.root == "base"


def test_published_mimic_value_is_overridden_by_its_driver() -> None:
    ctx = joints_ctx("arm1", ARM)
    items = by_path(convert(joints.JOINT_STATE, joint_state(["shoulder", "grip"], [0.4, 2.0]), ctx))
    grip = transform_matrix(items["/arm1/robot_model/joints/grip"])
    np.testing.assert_allclose(grip, rotation_about(-0.7, [1, 0, 0], [0.3, 0, 0]), atol=1e-6)


def test_unknown_joints_reported_once_known_ones_still_logged(burger_file: Path) -> None:
    ctx = joints_ctx("tb1", burger_file.read_text())
    message = joint_state(["wheel_left_joint", "gripper_joint"], [0.1, 0.2])
    with pytest.raises(PartialConvertError, match=r"\['gripper_joint'\]") as caught:
        convert(joints.JOINT_STATE, message, ctx)
    assert "wheel_left_joint" not in str(caught.value).split("it has")[0]
    assert sorted(by_path(caught.value.items)) == ["/tb1/robot_model/joints/wheel_left_joint"]
    again = convert(joints.JOINT_STATE, message, ctx)
    assert sorted(by_path(again)) == ["/tb1/robot_model/joints/wheel_left_joint"]


def test_joints_on_tf_are_left_to_tf(burger_file: Path) -> None:
    ctx = joints_ctx("tb1", burger_file.read_text())
    message = joint_state(["wheel_left_joint", "wheel_right_joint"], [0.1, 0.2])
    ctx.robot_state.tf_children = {"wheel_left_link"}
    assert sorted(by_path(convert(joints.JOINT_STATE, message, ctx))) == [
        "/tb1/robot_model/joints/wheel_right_joint"
    ]
    ctx.robot_state.tf_children = {"tb1/wheel_left_link", "tb1/wheel_right_link"}
    assert convert(joints.JOINT_STATE, message, ctx) == []


def test_two_robots_same_urdf_are_prefixed(burger_file: Path) -> None:
    xml = burger_file.read_text()
    message = joint_state(["wheel_left_joint"], [0.7])
    first = by_path(convert(joints.JOINT_STATE, message, joints_ctx("tb1", xml)))
    second = by_path(convert(joints.JOINT_STATE, message, joints_ctx("tb2", xml)))
    assert frames(first["/tb1/robot_model/joints/wheel_left_joint"]) == (
        "tb1/base_link",
        "tb1/wheel_left_link",
    )
    assert frames(second["/tb2/robot_model/joints/wheel_left_joint"]) == (
        "tb2/base_link",
        "tb2/wheel_left_link",
    )
    np.testing.assert_array_equal(
        transform_matrix(first["/tb1/robot_model/joints/wheel_left_joint"]),
        transform_matrix(second["/tb2/robot_model/joints/wheel_left_joint"]),
    )


def test_without_a_model_messages_are_refused() -> None:
    ctx = make_ctx("/joint_states", robot="tb1", times={})
    with pytest.raises(ConvertError, match="no robot model"):
        convert(joints.JOINT_STATE, joint_state(["a"], [0.0]), ctx)


def test_position_count_must_match_names() -> None:
    ctx = joints_ctx("arm1", ARM)
    with pytest.raises(ConvertError, match="2 values for 1 joint names"):
        convert(joints.JOINT_STATE, joint_state(["shoulder"], [0.1, 0.2]), ctx)
    # Velocity-only states and NaN positions move nothing.
    assert convert(joints.JOINT_STATE, joint_state(["shoulder"], []), ctx) == []
    assert convert(joints.JOINT_STATE, joint_state(["shoulder"], [float("nan")]), ctx) == []


def test_run_form_matches_single_messages() -> None:
    messages = [
        joint_state(["shoulder", "lift"], [0.1, 0.01], 100),
        joint_state(["lift"], [0.02], 200),
        joint_state(["shoulder", "lift"], [0.3, 0.03], 300),
    ]
    ctxs = [joints_ctx("arm1", ARM, stamp=stamp) for stamp in (100, 200, 300)]
    items = {item.path: item for item in convert_run(joints.JOINT_STATE, messages, ctxs)}
    assert all(isinstance(item, ColumnsItem) for item in items.values())
    shoulder = items["/arm1/robot_model/joints/shoulder"]
    lift = items["/arm1/robot_model/joints/lift"]
    assert isinstance(shoulder, ColumnsItem)
    assert isinstance(lift, ColumnsItem)
    assert shoulder.times["ros_time"].tolist() == [100, 300]
    assert lift.times["ros_time"].tolist() == [100, 200, 300]
    columns = {str(column.component_descriptor()): column for column in shoulder.columns}
    translations = np.asarray(columns["Transform3D:translation"].as_arrow_array().to_pylist())
    quaternions = np.asarray(columns["Transform3D:quaternion"].as_arrow_array().to_pylist())
    assert columns["Transform3D:parent_frame"].as_arrow_array().to_pylist() == [["arm1/slider"]] * 2
    for row, (message, ctx) in enumerate(((messages[0], ctxs[0]), (messages[2], ctxs[2]))):
        single = by_path(convert(joints.JOINT_STATE, message, ctx))["/arm1/robot_model/joints/shoulder"]
        np.testing.assert_allclose(
            matrix(translations[row][0], quaternions[row][0]), transform_matrix(single), atol=1e-7
        )


def test_trajectory_uses_its_first_point() -> None:
    point = SimpleNamespace(positions=np.array([0.4]))
    later = SimpleNamespace(positions=np.array([1.0]))
    trajectory = SimpleNamespace(joint_names=["shoulder"], points=[point, later])
    ctx = joints_ctx("arm1", ARM, topic="/arm_controller/joint_trajectory")
    items = by_path(joints.convert_joint_trajectory(trajectory, ctx))
    state = by_path(convert(joints.JOINT_STATE, joint_state(["shoulder"], [0.4]), ctx))
    assert (
        sorted(items)
        == sorted(state)
        == [
            "/arm1/robot_model/joints/grip",
            "/arm1/robot_model/joints/shoulder",
            "/arm1/robot_model/joints/tip_joint",
        ]
    )
    for path, item in items.items():
        np.testing.assert_array_equal(transform_matrix(item), transform_matrix(state[path]))
    empty = SimpleNamespace(joint_names=["shoulder"], points=[])
    assert joints.convert_joint_trajectory(empty, ctx) == []
