"""--record-mcap: the recorded MCAP reads back with Foxglove's mcap + mcap-ros2-support readers
(identical bytes, counts, topics, schemas) and with Rerun's own importer (`rerun mcap convert`)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore

from host_bridge.cli import main as host_main
from host_bridge.inputs.bag import bag_runs
from host_bridge.outputs.recorder import McapRecorder, may_hold_several_robots
from robot_relay.wire import RawMessage
from tests.rrd import entity_rows

NAV2 = Path("tf_nav2_sim_evo") / "nav2_turtlebot.mcap"
ROS_NUMPY = Path("ros_numpy_msgs_synthetic") / "ros_numpy_test.bag"


def record_bag(bag: Path, out: Path) -> list[RawMessage]:
    recorder = McapRecorder(out, prefix_robot=False)
    messages: list[RawMessage] = []
    for run in bag_runs(bag, "tb4"):
        recorder(run)
        messages += run
    recorder.close()
    return messages


def read_mcap(path: Path) -> tuple[Any, list[tuple[Any, Any, Any]]]:
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        header = reader.get_header()
        messages = list(reader.iter_messages(log_time_order=False))
    return (header, summary), messages


def rerun_convert(mcap: Path, out: Path) -> dict[str, list[dict[str, Any]]]:
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if rerun is None:
        pytest.skip("rerun CLI not found")
    subprocess.run([rerun, "mcap", "convert", str(mcap), "-o", str(out)], check=True,
                   capture_output=True, timeout=120)
    return entity_rows(out)


@pytest.fixture(scope="module")
def nav2_recording(shared_data: Path, tmp_path_factory: pytest.TempPathFactory,
                   ) -> tuple[Path, list[RawMessage]]:
    out = tmp_path_factory.mktemp("rec") / "nav2.mcap"
    return out, record_bag(shared_data / NAV2, out)


def test_recorded_bag_reads_back_with_identical_bytes(
    nav2_recording: tuple[Path, list[RawMessage]],
) -> None:
    out, sent = nav2_recording
    (header, summary), records = read_mcap(out)
    assert header.profile == "ros2"
    assert len(sent) == 8197
    assert len(records) == len(sent)
    assert [bytes(m.data) for m in sent] == [message.data for _, _, message in records]
    assert [(m.log_ns, m.log_ns) for m in sent] == [
        (message.log_time, message.publish_time) for _, _, message in records
    ]
    counts = Counter(channel.topic for _, channel, _ in records)
    assert counts == {"/tf": 5422, "/odom": 2639, "/amcl_pose": 135, "/tf_static": 1}
    schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    assert {t: s.name for t, s in schemas.items()} == {
        "/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage",
        "/odom": "nav_msgs/msg/Odometry",
        "/amcl_pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    }
    assert all(s.encoding == "ros2msg" for s in schemas.values())
    by_topic = {m.topic: m.definition for m in sent}
    assert all(s.data.decode() == by_topic[t].text for t, s in schemas.items())  # type: ignore[union-attr]
    assert all(c.message_encoding == "cdr" for c in summary.channels.values())
    assert summary.statistics.message_count == 8197


def test_recorded_bag_decodes_with_mcap_ros2(nav2_recording: tuple[Path, list[RawMessage]]) -> None:
    out, _ = nav2_recording
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        odom = [m for _, c, _, m in reader.iter_decoded_messages(topics=["/odom"])]
    assert len(odom) == 2639
    assert odom[0].header.frame_id == "odom"
    assert odom[0].child_frame_id == "base_link"


def test_rerun_importer_reads_the_same_transforms_as_from_the_original(
    shared_data: Path, nav2_recording: tuple[Path, list[RawMessage]], tmp_path: Path,
) -> None:
    out, _ = nav2_recording
    recorded = rerun_convert(out, tmp_path / "recorded.rrd")
    original = rerun_convert(shared_data / NAV2, tmp_path / "original.rrd")

    def transforms(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
        return [{k: v for k, v in r.items() if k.startswith("Transform3D")} for r in rows]

    assert len(recorded["/tf"]) > 5422  # several transforms per message
    assert transforms(recorded["/tf"]) == transforms(original["/tf"])
    static = transforms(recorded["/tf_static"])
    assert sum(1 for r in static if r) == 29
    assert static == transforms(original["/tf_static"])


def test_cli_records_a_ros1_bag_that_rerun_imports_with_the_same_points(
    shared_data: Path, tmp_path: Path,
) -> None:
    mcap = tmp_path / "numpy.mcap"
    rrd = tmp_path / "swanky.rrd"
    assert host_main(["--bag", str(shared_data / ROS_NUMPY), "--save", str(rrd),
                      "--record-mcap", str(mcap)]) == 0
    (_, summary), records = read_mcap(mcap)
    # Every message is recorded, also the degenerate OccupancyGrid the host could not convert.
    assert len(records) == 9
    assert len(summary.channels) == 9
    # ROS 1 messages are recorded as the CDR the host decoded, with the definition it used.
    sent = [m for run in bag_runs(shared_data / ROS_NUMPY, "robot") for m in run]
    assert sorted(message.data for *_, message in records) == sorted(bytes(m.data) for m in sent)
    imported = rerun_convert(mcap, tmp_path / "imported.rrd")
    theirs = [r["Points3D:positions"] for r in imported["/pointcloud"] if "Points3D:positions" in r]
    ours = [r["Points3D:positions"] for r in entity_rows(rrd)["/robot/pointcloud"]]
    assert len(theirs) == 1
    assert len(theirs[0]) == 100
    np.testing.assert_array_equal(np.asarray(theirs[0]), np.asarray(ours[0]))


def test_several_robots_are_prefixed_and_live_times_kept(tmp_path: Path) -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    data = bytes(store.serialize_cdr(store.types["std_msgs/msg/String"](data="hi"),
                                     "std_msgs/msg/String"))
    out = tmp_path / "live.mcap"
    recorder = McapRecorder(out, prefix_robot=True)
    # No definition (catalog not there yet): the host's bundled one is recorded.
    recorder([
        RawMessage("tb3", "/chat", "std_msgs/msg/String", data, receive_ns=2_000, log_ns=1_000,
                   sequence=7),
        RawMessage("pupper", "/chat", "std_msgs/msg/String", memoryview(data), receive_ns=3_000),
    ])
    recorder.close()
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        got = [(c.topic, c.metadata["swanky.robot"], m.log_time, m.publish_time, m.sequence, d.data)
               for _, c, m, d in reader.iter_decoded_messages(log_time_order=False)]
    assert got == [("/tb3/chat", "tb3", 2_000, 1_000, 7, "hi"),
                   ("/pupper/chat", "pupper", 3_000, 3_000, 0, "hi")]


def test_topic_prefix_only_when_several_robots_may_arrive() -> None:
    assert may_hold_several_robots(bag=False, demo_robots=None, robots="*")
    assert may_hold_several_robots(bag=False, demo_robots=None, robots="east-$*")
    assert not may_hold_several_robots(bag=False, demo_robots=None, robots="tb3_left-1")
    assert not may_hold_several_robots(bag=True, demo_robots=None, robots="*")
    # --demo: --robots is the count (a live filter of "2" would name one robot called 2).
    assert not may_hold_several_robots(bag=False, demo_robots=1, robots="*")
    assert not may_hold_several_robots(bag=False, demo_robots=1, robots="1")
    assert may_hold_several_robots(bag=False, demo_robots=2, robots="2")


def test_unwritable_path_is_named(tmp_path: Path) -> None:
    from host_bridge.errors import RecorderError

    with pytest.raises(RecorderError, match="no-such-dir"):
        McapRecorder(tmp_path / "no-such-dir" / "x.mcap", prefix_robot=False)
