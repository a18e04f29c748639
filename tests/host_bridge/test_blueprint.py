"""The viewer layout: which views a robot's topics get, how it follows new topics, and that it
reaches a saved recording (or the user's own .rbl, or nothing with --no-blueprint)."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import RrdReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from host_bridge.cli import main as host_main
from host_bridge.core.destinations import SinkOptions
from host_bridge.demo.bag import write_demo_bag
from host_bridge.outputs.blueprint import BlueprintFollower, TopicEntry, build_blueprint
from host_bridge.outputs.sink import APPLICATION_ID, RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.registry import default_registry
from robot_relay.wire import RawMessage
from tests.host_bridge.sensor_test_support import convert, make_ctx
from tests.host_bridge.test_dispatch import float_cdr, string_cdr
from tests.rrd import saved_views

ROBOT_TOPICS = {
    "/scan": "sensor_msgs/msg/LaserScan",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/robot_description": "std_msgs/msg/String",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/camera/image_raw": "sensor_msgs/msg/Image",
    "/camera/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
    "/camera/depth/image_raw": "sensor_msgs/msg/Image",
    "/camera/detections": "vision_msgs/msg/Detection2DArray",
    "/front/image": "sensor_msgs/msg/Image",
    "/gps/fix": "sensor_msgs/msg/NavSatFix",
    "/imu": "sensor_msgs/msg/Imu",
    "/odom": "nav_msgs/msg/Odometry",
    "/battery_state": "sensor_msgs/msg/BatteryState",
    "/temperature": "sensor_msgs/msg/Temperature",
    "/acme/custom": "acme_msgs/msg/Gauge",
    "/instrumentation/timer/loop": "std_msgs/msg/Float32",
    "/rosout": "rcl_interfaces/msg/Log",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}


def entries(robot: str, topics: dict[str, str] = ROBOT_TOPICS) -> list[TopicEntry]:
    return [TopicEntry(robot, topic, msgtype, f"/{robot}{topic}") for topic, msgtype in topics.items()]


def target_frame(view: rrb.View) -> str:
    information: Any = view.properties["SpatialInformation"]
    return str(information.target_frame.as_arrow_array()[0])


def children(container: Any) -> list[Any]:
    return list(container.contents)


def views(part: Any) -> list[rrb.View]:
    """Every view of a blueprint or container, depth first in layout order."""
    if isinstance(part, rrb.Blueprint):
        return views(part.root_container)
    if isinstance(part, rrb.View):
        return [part]
    return [v for child in part.contents for v in views(child)]


def by_name(found: list[rrb.View]) -> dict[str, rrb.View]:
    names = [str(v.name) for v in found]
    assert len(names) == len(set(names)), names
    return dict(zip(names, found, strict=True))


def test_one_robot_gets_3d_images_map_plots_and_log() -> None:
    blueprint = build_blueprint(entries("tb3"))

    found = by_name(views(blueprint))
    kinds = {name: view.class_identifier for name, view in found.items()}
    assert kinds == {
        "tb3 3D": "3D",
        "/camera/depth/image_raw": "2D", "/camera/image_raw": "2D",
        "/camera/image_raw/compressed": "2D", "/front/image": "2D",
        "GPS": "Map",
        "Odometry": "TimeSeries", "IMU": "TimeSeries", "Battery": "TimeSeries",
        "Signals": "TimeSeries", "Timers": "TimeSeries", "Arrays": "BarChart",
        "Log": "TextLog",
    }
    assert found["tb3 3D"].origin == "/tb3"
    # An image with no camera pinhole is 2D content the 3D view cannot place (a red error there).
    assert found["tb3 3D"].contents == ["$origin/**", "- /tb3/front/image/**"]
    # Images of the camera namespace sit under its pinhole (logged at /tb3/camera by the
    # CameraInfo converter), with the camera's detections drawn over them; an image with no
    # CameraInfo is its own 2D space.
    for topic in ("/camera/image_raw", "/camera/image_raw/compressed", "/camera/depth/image_raw"):
        assert found[topic].origin == "/tb3/camera"
        assert found[topic].contents == [f"+ /tb3{topic}/**", "+ /tb3/camera/detections/**"]
        # The pinhole's image plane, not the optical frame the namespace entity names.
        assert target_frame(found[topic]) == "tf#/tb3/camera"
    assert found["/front/image"].origin == "/tb3/front/image"
    assert target_frame(found["/front/image"]) == "tf#/tb3/front/image"
    assert found["/front/image"].contents == ["+ /tb3/front/image/**"]
    assert found["GPS"].contents == ["+ /tb3/gps/fix/**"]
    assert found["Odometry"].contents == ["+ /tb3/odom/twist/**"]
    assert found["IMU"].contents == ["+ /tb3/imu/**"]
    assert found["Battery"].contents == ["+ /tb3/battery_state/**"]
    # Scalars and custom types (generic converter) are signals; timers have their own plot.
    assert found["Signals"].contents == ["+ /tb3/acme/custom/**", "+ /tb3/temperature/**"]
    assert found["Timers"].contents == ["+ /tb3/instrumentation/timer/loop/**"]
    # Time series do not draw the bar charts of custom types' long arrays: a view of their own.
    assert found["Arrays"].contents == ["+ /tb3/acme/custom/**"]
    assert found["Log"].contents == [
        "+ /tb3/diagnostics/**", "+ /tb3/rosout/**", "+ /_swanky/warnings/**",
    ]


def test_one_robot_layout_is_3d_beside_a_column_of_the_rest() -> None:
    root = build_blueprint(entries("tb3")).root_container
    assert isinstance(root, rrb.Horizontal)
    parts = children(root)
    assert [type(p).__name__ for p in parts] == ["Spatial3DView", "Vertical"]
    column = children(parts[1])
    assert [type(p).__name__ for p in column] == ["Grid", "Tabs", "TextLogView"]
    assert [v.name for v in children(column[1])] == [
        "Odometry", "IMU", "Battery", "Signals", "Timers", "Arrays",
    ]


def test_custom_types_long_arrays_land_in_the_bar_chart_view() -> None:
    """The generic converter logs an array longer than 64 as a BarChart under the topic; the
    Arrays view holds every custom topic of the robot, and only those."""
    text = "float64 speed\nfloat32[] histogram\n"
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(text, "acme_msgs/msg/Histogram"))
    message = store.types["acme_msgs/msg/Histogram"](
        speed=1.5, histogram=np.arange(100, dtype=np.float32)
    )
    table = default_registry()
    context = make_ctx("/hist", robot="tb3", times={})
    logged = {
        entry.path: entry for entry in convert(table.get("acme_msgs/msg/Histogram"), message, context)
    }
    (bars,) = logged["/tb3/hist/histogram"].archetypes  # type: ignore[union-attr]
    assert isinstance(bars, rr.BarChart)

    topics = {"/hist": "acme_msgs/msg/Histogram", "/speed": "std_msgs/msg/Float64",
              "/scan": "sensor_msgs/msg/LaserScan"}
    found = by_name(views(build_blueprint(entries("tb3", topics), registry=table)))
    assert found["Arrays"].class_identifier == "BarChart"
    assert found["Arrays"].contents == ["+ /tb3/hist/**"]
    assert found["Signals"].contents == ["+ /tb3/hist/**", "+ /tb3/speed/**"]
    known_only = by_name(views(build_blueprint(entries("tb3", {"/speed": "std_msgs/msg/Float64"}))))
    assert "Arrays" not in known_only


def test_stats_add_a_plot_of_the_robot_stats_root() -> None:
    found = by_name(views(build_blueprint(entries("tb3", {"/scan": "sensor_msgs/msg/LaserScan"}),
                                          stats=True)))
    assert found["Stats"].origin == "/_stats/tb3"
    assert found["Viewer lag"].origin == "/_stats/host"
    assert set(found) == {"tb3 3D", "Stats", "Viewer lag", "Log"}


def test_several_robots_get_a_shared_tab_then_one_tab_each() -> None:
    pupper = {"/scan": "sensor_msgs/msg/LaserScan", "/imu": "sensor_msgs/msg/Imu"}
    blueprint = build_blueprint([*entries("tb3"), *entries("pupper", pupper)])

    root = blueprint.root_container
    assert isinstance(root, rrb.Tabs)
    tabs = children(root)
    assert [str(tab.name) for tab in tabs] == ["All robots", "pupper", "tb3"]
    shared = by_name(views(tabs[0]))
    assert shared["All robots 3D"].origin == "/"
    assert shared["All robots 3D"].contents == ["+ /pupper/**", "+ /tb3/**", "- /tb3/front/image/**"]
    assert shared["All robots GPS"].contents == ["+ /tb3/gps/fix/**"]
    pupper_views = by_name(views(tabs[1]))
    assert set(pupper_views) == {"pupper 3D", "IMU", "Log"}
    assert pupper_views["pupper 3D"].origin == "/pupper"
    assert pupper_views["IMU"].contents == ["+ /pupper/imu/**"]
    assert by_name(views(tabs[2]))["tb3 3D"].origin == "/tb3"


class Sent:
    """A stand-in for RerunSink.send_blueprint that records what it was given."""

    def __init__(self) -> None:
        self.blueprints: list[rrb.Blueprint] = []
        self.event = threading.Event()

    def __call__(self, blueprint: rrb.Blueprint) -> None:
        self.blueprints.append(blueprint)
        self.event.set()

    def wait(self) -> None:
        assert self.event.wait(10.0), "no blueprint was sent"
        self.event.clear()


def test_follower_sends_once_per_burst_and_again_only_when_topics_change() -> None:
    sent = Sent()
    follower = BlueprintFollower(sent, interval=0.2)
    follower.topic_seen("tb3", "/scan", "sensor_msgs/msg/LaserScan", "/tb3/scan")
    follower.topic_seen("tb3", "/imu", "sensor_msgs/msg/Imu", "/tb3/imu")
    sent.wait()
    assert {str(v.name) for v in views(sent.blueprints[-1])} == {"tb3 3D", "IMU", "Log"}

    follower.topic_seen("tb3", "/scan", "sensor_msgs/msg/LaserScan", "/tb3/scan")
    follower.close()
    assert len(sent.blueprints) == 1  # the same topics again: nothing new to send

    follower = BlueprintFollower(sent, interval=60.0)
    follower.topic_seen("tb3", "/scan", "sensor_msgs/msg/LaserScan", "/tb3/scan")
    follower.topic_seen("pupper", "/scan", "sensor_msgs/msg/LaserScan", "/pupper/scan")
    follower.close()  # sends what the long interval still held back
    assert len(sent.blueprints) == 2
    assert isinstance(sent.blueprints[-1].root_container, rrb.Tabs)
    follower.topic_seen("tb3", "/odom", "nav_msgs/msg/Odometry", "/tb3/odom")
    assert len(sent.blueprints) == 2  # closed: nothing more


def test_follower_lays_a_topic_out_as_its_latest_type() -> None:
    """A topic whose type changed (garbage claiming Image on /scan, then the robot's scans) is
    laid out as the type it has now, not as both."""
    sent = Sent()
    follower = BlueprintFollower(sent, interval=60.0)
    follower.topic_seen("tb3", "/scan", "sensor_msgs/msg/Image", "/tb3/scan")
    follower.topic_seen("tb3", "/scan", "sensor_msgs/msg/LaserScan", "/tb3/scan")
    follower.close()
    assert {str(v.name) for v in views(sent.blueprints[-1])} == {"tb3 3D", "Log"}


def test_dispatcher_tells_the_follower_of_each_topic_once(tmp_path: Path) -> None:
    seen: list[tuple[str, str, str, str]] = []
    dispatcher = Dispatcher(
        RerunSink(SinkOptions(save=tmp_path / "out.rrd")),
        on_new_topic=lambda *topic: seen.append(topic),
    )
    for ns in (1, 2):
        dispatcher.dispatch([
            RawMessage("tb3", "/chatter", "std_msgs/msg/String", string_cdr("hi"), log_ns=ns),
            RawMessage("tb3", "/speed", "std_msgs/msg/Float64", float_cdr(0.5), log_ns=ns),
        ])
    dispatcher.close()
    dispatcher.sink.close()
    assert seen == [
        ("tb3", "/chatter", "std_msgs/msg/String", "/tb3/chatter"),
        ("tb3", "/speed", "std_msgs/msg/Float64", "/tb3/speed"),
    ]


# --- through the command line, into a saved recording ---------------------------------------------


@pytest.fixture(scope="module")
def demo_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_demo_bag(tmp_path_factory.mktemp("blueprint") / "demo", 1.0)


def test_save_holds_the_layout_of_the_topics_converted(demo_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "demo.rrd"
    assert host_main(["--bag", str(demo_bag), "--robot", "sim", "--save", str(out)]) == 0

    found = {v["name"]: v for v in saved_views(out)}
    assert found["sim 3D"] == {"class": "3D", "name": "sim 3D", "origin": "/sim",
                               "contents": ["$origin/**"]}
    assert found["/camera/image_raw"]["origin"] == "/sim/camera"
    assert found["/camera/depth/image_raw"]["origin"] == "/sim/camera"
    assert found["Odometry"]["contents"] == ["+ /sim/odom/twist/**"]
    assert found["Log"]["contents"] == ["+ /sim/rosout/**", "+ /_swanky/warnings/**"]
    assert {v["class"] for v in found.values()} == {"3D", "2D", "TimeSeries", "TextLog"}


def test_no_blueprint_saves_none(demo_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "demo.rrd"
    assert host_main(["--bag", str(demo_bag), "--robot", "sim", "--save", str(out),
                      "--no-blueprint"]) == 0
    assert RrdReader(out).blueprints() == []
    assert RrdReader(out).recordings()


def test_blueprint_file_is_sent_instead_of_swankys(demo_bag: Path, tmp_path: Path) -> None:
    mine = tmp_path / "mine.rbl"
    rrb.Blueprint(rrb.Spatial3DView(name="just the scan", origin="/sim/scan")).save(
        APPLICATION_ID, mine
    )
    out = tmp_path / "demo.rrd"
    assert host_main(["--bag", str(demo_bag), "--robot", "sim", "--save", str(out),
                      "--blueprint", str(mine)]) == 0
    assert [(v["name"], v["origin"]) for v in saved_views(out)] == [("just the scan", "/sim/scan")]


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        (("missing.rbl", None), "no such file"),
        (("layout.json", b"{}"), "not an .rbl file"),
        (("garbage.rbl", b"not a blueprint at all"), "not a Rerun blueprint file"),
        (("recording.rbl", "recording"), "the file holds no blueprint"),
        (("other.rbl", "other app"), "the blueprint is for application 'other_app'"),
    ],
)
def test_bad_blueprint_file_is_named_before_anything_opens(
    case: tuple[str, bytes | str | None], expected: str, demo_bag: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    name, content = case
    path = tmp_path / name
    if content == "recording":
        recording = rr.RecordingStream(APPLICATION_ID)
        recording.save(path)
        recording.log("/x", rr.Points3D([[0, 0, 0]]))
        recording.disconnect()
    elif content == "other app":
        rrb.Blueprint(rrb.TextLogView()).save("other_app", path)
    elif isinstance(content, bytes):
        path.write_bytes(content)
    out = tmp_path / "out.rrd"
    assert host_main(["--bag", str(demo_bag), "--save", str(out), "--blueprint", str(path)]) == 2
    error = capsys.readouterr().err
    assert f"--blueprint {path}: {expected}" in error
    assert not out.exists()
