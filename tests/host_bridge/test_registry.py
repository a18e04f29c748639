"""The type table: which converter each type gets, the rows routed by topic or family, the
columns others read (view, lane, slow), the table's own rules, and that the relay's traffic
table agrees with its traffic column."""

from __future__ import annotations

import subprocess
import sys

import pytest

from host_bridge.converters import (
    camera,
    generic,
    images,
    joints,
    logs,
    markers,
    occupancy,
    pointcloud,
    services,
    video,
    vision,
    walls,
)
from host_bridge.converters.urdf import description
from host_bridge.core.contract import Converter, PerMessage, per_message
from host_bridge.core.options import GenericOptions
from host_bridge.errors import RegistryError
from host_bridge.table.registry import (
    CATCH_ALL,
    Lane,
    Registry,
    Row,
    View,
    default_registry,
    is_robot_description,
    loaded,
)
from robot_relay.policy import DEFAULT_TRAFFIC, TRAFFIC

TABLE = default_registry()

# Forwarded with a traffic class by the relay, converted by the generic converter on the host:
# the ROS 1-era cloud (points as a list of Point32 messages) has no converter of its own yet.
RELAY_ONLY = {"sensor_msgs/msg/PointCloud"}


@pytest.mark.parametrize(
    ("msgtype", "converter"),
    [
        ("sensor_msgs/msg/PointCloud2", pointcloud.SPEC),
        ("sensor_msgs/msg/Image", images.IMAGE),
        ("sensor_msgs/msg/CompressedImage", images.COMPRESSED_IMAGE),
        ("foxglove_msgs/msg/CompressedVideo", video.SPEC),
        ("sensor_msgs/msg/CameraInfo", camera.SPEC),
        ("visualization_msgs/msg/Marker", markers.MARKER),
        ("visualization_msgs/msg/MarkerArray", markers.MARKER_ARRAY),
        ("vision_msgs/msg/Detection2D", vision.DETECTION_2D),
        ("vision_msgs/msg/Detection2DArray", vision.DETECTION_2D_ARRAY),
        ("vision_msgs/msg/Detection3D", vision.DETECTION_3D),
        ("vision_msgs/msg/Detection3DArray", vision.DETECTION_3D_ARRAY),
        ("nav_msgs/msg/OccupancyGrid", occupancy.GRID),
        ("map_msgs/msg/OccupancyGridUpdate", occupancy.GRID_UPDATE),
        ("nav2_msgs/msg/Costmap", occupancy.COSTMAP),
        ("nav2_msgs/msg/CostmapUpdate", occupancy.COSTMAP_UPDATE),
        ("trajectory_msgs/msg/JointTrajectory", joints.JOINT_TRAJECTORY),
    ],
)
def test_each_type_gets_its_converter(msgtype: str, converter: Converter) -> None:
    assert TABLE.get(msgtype) is converter
    assert msgtype in TABLE.types()


def test_special_cases_are_plain_rows() -> None:
    # std_msgs/String: a robot model on /robot_description (namespaced too), text elsewhere.
    assert TABLE.get("std_msgs/msg/String", "/robot_description") is description.SPEC
    assert TABLE.get("std_msgs/msg/String", "/tb1/robot_description") is description.SPEC
    assert TABLE.get("std_msgs/msg/String", "/chatter") is logs.STRING
    assert TABLE.row("std_msgs/msg/String", "/robot_description").view is View.SPATIAL
    assert TABLE.row("std_msgs/msg/String", "/chatter").view is View.LOG
    # Service events: one type per service, a family rule.
    assert TABLE.get("lifecycle_msgs/srv/ChangeState_Event") is services.SPEC
    assert TABLE.row("lifecycle_msgs/srv/ChangeState_Event").view is View.LOG
    assert TABLE.get("lifecycle_msgs/srv/ChangeState_Request") is generic.SPEC
    # JointState moves the model and is plotted: both converters, with a run form.
    assert TABLE.row("sensor_msgs/msg/JointState").view is View.JOINTS
    assert not isinstance(TABLE.get("sensor_msgs/msg/JointState"), PerMessage)
    # Anything else: the generic converter.
    assert TABLE.get("acme_msgs/msg/Gauge") is generic.SPEC
    assert TABLE.row("acme_msgs/msg/Gauge").view is View.CUSTOM
    assert [t for t in TABLE.types() if set(t) & set("*?[")] == []


def test_robot_description_topic_names() -> None:
    assert is_robot_description("/robot_description")
    assert is_robot_description("/tb1/robot_description")
    assert not is_robot_description("/robot_description_semantic")


def test_the_table_imports_a_converter_when_its_type_is_first_met() -> None:
    """A fresh interpreter: building the table imports no converter module, asking it for
    TFMessage's converter imports tf.py and the helpers it imports, nothing of the others."""
    script = (
        "import sys\n"
        "from host_bridge.table.registry import default_registry\n"
        "ours = lambda: sorted(m for m in sys.modules if m.startswith('host_bridge.converters.'))\n"
        "table = default_registry()\n"
        "table.slow_converters()\n"
        "print(ours())\n"
        "table.get('tf2_msgs/msg/TFMessage')\n"
        "print(ours())\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                          timeout=120)
    built, after_tf = done.stdout.splitlines()
    assert built == "[]"
    assert after_tf == "['host_bridge.converters._common', 'host_bridge.converters.tf']"


def test_slow_and_lane_columns() -> None:
    assert {msgtype: loaded(slow) for msgtype, slow in TABLE.slow_converters().items()} == {
        "nav_msgs/msg/OccupancyGrid": walls.GRID_WALLS,
        "map_msgs/msg/OccupancyGridUpdate": walls.UPDATE_WALLS,
    }
    lanes = {lane: sorted(row.msgtype for row in TABLE.rows() if row.lane is lane) for lane in Lane}
    assert lanes[Lane.HEAVY] == [
        "nav2_msgs/msg/Costmap", "nav_msgs/msg/OccupancyGrid", "sensor_msgs/msg/Image",
        "sensor_msgs/msg/PointCloud2",
    ]  # never video, which a lost frame spoils: CompressedImage may carry it
    assert lanes[Lane.PATCH] == ["map_msgs/msg/OccupancyGridUpdate", "nav2_msgs/msg/CostmapUpdate"]


def test_the_relay_s_traffic_table_is_the_rows_traffic_column() -> None:
    """The relay's traffic table (robot_relay/policy.py) cannot import the host's (the robot has
    no host code): it must name exactly the rows whose class is not the default, with their
    class; a type spelt differently in one of them would silently get the defaults."""
    classed = {row.msgtype: row.traffic for row in TABLE.rows() if row.traffic != DEFAULT_TRAFFIC}
    assert not [t for t in classed if TABLE.row(t).is_family]  # the relay's table names types
    assert {t: c for t, c in TRAFFIC.items() if t not in RELAY_ONLY} == classed
    assert sorted(set(TRAFFIC) - set(TABLE.types())) == sorted(RELAY_ONLY)
    assert TABLE.get("sensor_msgs/msg/PointCloud") is generic.SPEC


SPEC = per_message(lambda msg, ctx: [])
CATCH = Row(CATCH_ALL, SPEC, View.CUSTOM)


def test_a_type_registered_twice_is_an_error() -> None:
    with pytest.raises(RegistryError, match="'acme_msgs/msg/Gauge' is registered twice"):
        Registry([Row("acme_msgs/msg/Gauge", SPEC, View.SIGNALS),
                  Row("acme_msgs/msg/Gauge", SPEC, View.SPATIAL), CATCH])
    with pytest.raises(RegistryError, match="'sensor_msgs/msg/Image' is registered twice"):
        Registry([*TABLE.rows(), Row("sensor_msgs/msg/Image", SPEC, View.IMAGE)])


def test_table_rules() -> None:
    with pytest.raises(RegistryError, match=r"needs a '\*' row last"):
        Registry([Row("acme_msgs/msg/Gauge", SPEC, View.SIGNALS)])
    with pytest.raises(RegistryError, match=r"'acme_msgs/\*' comes after the '\*' row"):
        Registry([CATCH, Row("acme_msgs/*", SPEC, View.SIGNALS)])
    with pytest.raises(RegistryError, match="a slow converter is run per type"):
        Registry([Row("acme_msgs/*", SPEC, View.SIGNALS, slow=SPEC), CATCH])
    # The configuration sets options per type, not per topic.
    with pytest.raises(RegistryError, match="'acme_msgs/msg/Gauge': all rows of a type take one options"):
        Registry([Row("acme_msgs/msg/Gauge", SPEC, View.SIGNALS, topics=lambda topic: topic == "/gauge",
                      options=GenericOptions),
                  Row("acme_msgs/msg/Gauge", SPEC, View.SIGNALS), CATCH])
    # An exact row after the catch-all is fine: exact names are looked up first.
    table = Registry([CATCH, Row("acme_msgs/msg/Gauge", SPEC, View.SIGNALS)])
    assert table.row("acme_msgs/msg/Gauge").view is View.SIGNALS
