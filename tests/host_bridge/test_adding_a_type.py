"""CONTRIBUTING.md's "Adding a message type", done once: a made-up type (its definition given as
text, as a robot's catalog or a bag carries it), a converter for it, one row in the table; the
dispatcher converts it with that converter and the layout places it by that row."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from host_bridge.converters._common import stamps_ns
from host_bridge.core.contract import ColumnsItem, LogEntry, Run
from host_bridge.core.destinations import SinkOptions
from host_bridge.outputs.blueprint import BlueprintFollower, TopicEntry, build_blueprint
from host_bridge.outputs.sink import RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.registry import Registry, Row, View, default_registry
from robot_relay.wire import MessageDefinition, RawMessage
from tests.rrd import entity_rows

BEACON_TYPE = "acme_msgs/msg/Beacon"
BEACON_DEFINITION = """\
# A radio beacon the robot has located.
std_msgs/Header header
float64 x
float64 y
float64 z
string label
"""
HEADER_DEFINITION = """\
builtin_interfaces/Time stamp
string frame_id
"""
TIME_DEFINITION = "int32 sec\nuint32 nanosec\n"
SEPARATOR = "=" * 80 + "\n"


# Step 1: the converter, a pure function from a run of the topic's messages to log entries (a
# module of its own in host_bridge/converters/, exporting it). A beacon is a few numbers and a
# header: the run is read as columns, no message decoded, one row per beacon at its stamp.
def convert_beacons(run: Run) -> list[LogEntry]:
    columns = run.columns()
    positions = np.stack([columns[axis] for axis in "xyz"], axis=1)
    labels = columns["label"]
    stamps = stamps_ns(columns)
    entries: list[LogEntry] = []
    for frame_id, rows in columns.groups("header.frame_id"):  # a row is in one frame
        frame = run.frame(str(frame_id))
        for picked, times in run.times(stamps[rows], rows):  # the rows' timelines
            beacons = rows[picked]
            points = rr.Points3D.columns(positions=positions[beacons], labels=labels[beacons].tolist())
            frames = [] if frame is None else rr.CoordinateFrame.columns(frame=[frame] * len(beacons))
            entries.append(ColumnsItem(run.entity_path, [*points, *frames], times))
    return entries


BEACON = convert_beacons


# Step 2: one row in the table (in default_registry(), beside the others).
def registry_with_beacon() -> Registry:
    return Registry([*default_registry().rows(), Row(BEACON_TYPE, BEACON, View.SPATIAL)])


def beacon_message(x: float, label: str, sec: int) -> RawMessage:
    """The CDR bytes and full definition (rosbag2's ros2msg text) a robot would send."""
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(TIME_DEFINITION, "builtin_interfaces/msg/Time"))
    store.register(get_types_from_msg(HEADER_DEFINITION, "std_msgs/msg/Header"))
    store.register(get_types_from_msg(BEACON_DEFINITION, BEACON_TYPE))
    t = store.types
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=0), frame_id="map"
    )
    msg = t[BEACON_TYPE](header=header, x=x, y=2.0, z=0.5, label=label)
    definition = (
        f"{BEACON_DEFINITION}\n{SEPARATOR}MSG: std_msgs/Header\n{HEADER_DEFINITION}\n"
        f"{SEPARATOR}MSG: builtin_interfaces/Time\n{TIME_DEFINITION}"
    )
    return RawMessage("tb3", "/beacon", BEACON_TYPE, bytes(store.serialize_cdr(msg, BEACON_TYPE)),
                      log_ns=sec * 10**9, definition=MessageDefinition("ros2msg", definition))


def views_of(blueprint: rrb.Blueprint) -> dict[str, list[str]]:
    """View name -> contents queries."""
    def walk(part: Any) -> list[rrb.View]:
        if isinstance(part, rrb.View):
            return [part]
        return [v for child in part.contents for v in walk(child)]

    return {str(v.name): list(v.contents) for v in walk(blueprint.root_container)}  # type: ignore[arg-type]


# Step 3: the test. The dispatcher reads the payloads with the definition they came with and
# converts them with the new row's converter; the layout puts the topic where the row says.
def test_a_new_type_is_one_converter_and_one_row(tmp_path: Path) -> None:
    registry = registry_with_beacon()
    sent: list[rrb.Blueprint] = []
    layout = BlueprintFollower(sent.append, interval=60.0, registry=registry)
    out = tmp_path / "beacon.rrd"
    dispatcher = Dispatcher(
        RerunSink(SinkOptions(save=out)), registry=registry, strict=True,
        on_new_topic=layout.topic_seen,
    )
    dispatcher.dispatch([beacon_message(1.0, "dock", 3), beacon_message(1.5, "dock", 4)])
    dispatcher.close()
    layout.close()
    dispatcher.sink.close()

    assert dispatcher.counters[("tb3", "/beacon")].converted == 2
    rows = entity_rows(out, "/tb3/beacon")["/tb3/beacon"]
    assert [r["Points3D:positions"] for r in rows] == [[[1.0, 2.0, 0.5]], [[1.5, 2.0, 0.5]]]
    assert [r["Points3D:labels"] for r in rows] == [["dock"], ["dock"]]
    assert [r["CoordinateFrame:frame"] for r in rows] == [["tb3/map"], ["tb3/map"]]
    assert [r["ros_time"] for r in rows] == [3 * 10**9, 4 * 10**9]

    # A spatial row: in the robot's 3D view, and in no plot (a sent layout, the follower's).
    (blueprint,) = sent
    assert views_of(blueprint) == {"tb3 3D": ["$origin/**"], "Log": ["+ /_swanky/warnings/**"]}


def test_without_its_row_the_type_goes_to_the_generic_converter(tmp_path: Path) -> None:
    """What the row changes: the same message is plotted and charted by the generic converter."""
    dispatcher = Dispatcher(RerunSink(SinkOptions(save=tmp_path / "generic.rrd")), strict=True)
    dispatcher.dispatch([beacon_message(1.0, "dock", 3)])
    dispatcher.close()
    dispatcher.sink.close()
    rows = entity_rows(tmp_path / "generic.rrd")
    assert rows["/tb3/beacon/x"][0]["Scalars:scalars"] == [pytest.approx(1.0)]
    assert rows["/tb3/beacon/label"][0]["TextLog:text"] == ["dock"]
    entry = TopicEntry("tb3", "/beacon", BEACON_TYPE, "/tb3/beacon")
    placed = views_of(build_blueprint([entry]))
    assert placed["Signals"] == ["+ /tb3/beacon/**"]
    assert placed["Arrays"] == ["+ /tb3/beacon/**"]
