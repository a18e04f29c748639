"""Typed converter state: records per topic found by class, one RobotState per robot made by the
dispatcher with the host's resolver bound to that robot, and marker meshes found through it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr
import trimesh
from rosbags.typesys import Stores, get_typestore

from host_bridge.converters import markers
from host_bridge.core.resources import ResourceResolver
from host_bridge.core.state import TopicState
from host_bridge.pipeline.dispatch import Dispatcher
from robot_relay.wire import RawMessage
from tests.host_bridge.converters.test_markers import marker
from tests.host_bridge.sensor_test_support import make_ctx
from tests.host_bridge.test_config import RecordingSink

STORE = get_typestore(Stores.ROS2_HUMBLE)
MARKERS = "visualization_msgs/msg/MarkerArray"
URI = "package://mypkg/meshes/x.stl"


@dataclass(slots=True)
class Counter:
    count: int = 0


@dataclass(slots=True)
class Names:
    seen: set[str] = field(default_factory=set)


def test_a_topic_keeps_one_record_per_class_across_its_messages() -> None:
    state = TopicState()
    first, second = (make_ctx("/joint_states", topic_state=state) for _ in range(2))
    first.state(Counter).count += 1
    second.state(Counter).count += 1
    assert second.state(Counter).count == 2
    # Another converter of the same topic (JointState: kinematics and plots) has its own.
    assert first.state(Names) == Names()
    assert make_ctx("/joint_states").state(Counter).count == 0  # another topic


def test_each_robot_has_its_own_state_and_its_files_come_from_its_own_relay() -> None:
    asked: list[tuple[str, str]] = []

    def robot_fetch(robot: str, uri: str) -> bytes:
        asked.append((robot, uri))
        return robot.encode()

    dispatcher = Dispatcher(RecordingSink(), resolver=ResourceResolver(robot_fetch=robot_fetch))
    tb1, tb2 = dispatcher.robot_state("tb1"), dispatcher.robot_state("tb2")
    assert dispatcher.robot_state("tb1") is tb1
    assert tb1 is not tb2
    tb1.tf_children.add("base_link")
    assert tb2.tf_children == set()
    assert tb2.resolver.read(URI) == b"tb2"
    assert asked == [("tb2", URI)]


def marker_array_cdr() -> bytes:
    mesh = marker(markers.MESH_RESOURCE, mesh_resource=URI, scale=(2.0, 2.0, 2.0))
    array = STORE.types[MARKERS](markers=[mesh])
    return bytes(STORE.serialize_cdr(array, MARKERS))


def test_a_marker_mesh_is_found_through_the_package_paths_the_host_was_given(tmp_path: Path) -> None:
    """The resolver the host hands every robot reads package:// marker meshes (it once was the
    robot model's alone, under a key the marker converter did not read)."""
    stl = trimesh.creation.box(extents=(0.1, 0.2, 0.3)).export(file_type="stl")
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "x.stl").write_bytes(stl)
    sink = RecordingSink()
    dispatcher = Dispatcher(sink, strict=True, resolver=ResourceResolver({"mypkg": tmp_path}))
    dispatcher.dispatch([RawMessage("bot", "/markers", MARKERS, marker_array_cdr(), log_ns=5)])
    [(item, _)] = sink.items("/bot/markers/ns/0")
    [asset] = [a for a in item.archetypes if isinstance(a, rr.Asset3D)]
    assert asset.blob is not None
    assert bytes(asset.blob.as_arrow_array().to_pylist()[0]) == stl
    [poses] = [a for a in item.archetypes if isinstance(a, rr.InstancePoses3D)]
    assert poses.scales is not None
    np.testing.assert_allclose(poses.scales.as_arrow_array().to_pylist(), [[2.0, 2.0, 2.0]])
