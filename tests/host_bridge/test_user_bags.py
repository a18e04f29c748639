"""Bags users bring: Humble sqlite3 without definitions, MCAPs with service events, metadata.yaml
QoS that disagrees with the storage, compressed files, a relay installed without rosbags.

Each bag is written here in the form its recorder writes (see ``user_bags.py``), then converted
with ``swanky-host --bag`` (the relay's bag source underneath) and read back from the .rrd.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.cli import main as host_main
from host_bridge.core.contract import WARNINGS_PATH
from host_bridge.core.schemas import base_typestore
from host_bridge.inputs.bag import BagExtent, BagInput
from robot_relay.cli import main as relay_main
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource, bag_paths
from tests.host_bridge.user_bags import (
    Recorded,
    humble_qos,
    service_definition,
    write_humble_sqlite3_bag,
)
from tests.rrd import entity_rows

T0 = 1_700_000_000_000_000_000
READING = "my_msgs/msg/Reading"
READING_DEFINITION = "float64 value\n"


def cdr(store: Typestore, msgtype: str, **fields: Any) -> bytes:
    return bytes(store.serialize_cdr(store.types[msgtype](**fields), msgtype))


def costmap_cdr(store: Typestore, costs: list[list[int]], stamp_s: int) -> bytes:
    """A nav2_msgs/Costmap of ``costs`` (row 0 at the origin), 0.5 m cells, origin (1, 2)."""
    t = store.types
    time = t["builtin_interfaces/msg/Time"](sec=stamp_s, nanosec=0)
    origin = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    meta = t["nav2_msgs/msg/CostmapMetaData"](
        map_load_time=time, update_time=time, layer="master", resolution=0.5,
        size_x=len(costs[0]), size_y=len(costs), origin=origin,
    )
    header = t["std_msgs/msg/Header"](stamp=time, frame_id="map")
    return cdr(store, "nav2_msgs/msg/Costmap", header=header, metadata=meta,
               data=np.array(costs, dtype=np.uint8).ravel())


def humble_bag(path: Path) -> Path:
    """``ros2 bag record`` on Humble: chatter, a nav2 costmap_raw and a custom sensor type."""
    humble = base_typestore()  # Humble plus schemas/msg, where nav2_msgs comes from
    custom = get_typestore(Stores.EMPTY)
    custom.register(get_types_from_msg(READING_DEFINITION, READING))
    chatter = [(T0 + i * 10**8, cdr(humble, "std_msgs/msg/String", data=f"hello {i}"))
               for i in range(3)]
    costmap = [(T0 + 5 * 10**7, costmap_cdr(humble, [[0, 128, 253], [254, 255, 1]], 1700000000))]
    readings = [(T0 + i * 10**8, cdr(custom, READING, value=float(i))) for i in range(2)]
    return write_humble_sqlite3_bag(path, [
        Recorded("/chatter", "std_msgs/msg/String", chatter),
        Recorded("/global_costmap/costmap_raw", "nav2_msgs/msg/Costmap", costmap,
                 humble_qos(durability=1, depth=1)),
        Recorded("/sensor/reading", READING, readings),
    ])


def convert(bag: Path, out: Path, *extra: str, code: int = 0) -> dict[str, list[dict[str, Any]]]:
    assert host_main(["--bag", str(bag), "--save", str(out), "--no-blueprint", *extra]) == code
    return entity_rows(out)


def texts(rows: list[dict[str, Any]]) -> list[str]:
    return [row["TextLog:text"][0] for row in rows if row.get("TextLog:text")]


def test_humble_sqlite3_bag_without_definitions(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = humble_bag(tmp_path / "humble")
    with pytest.raises(AnyReaderError, match="Bag contains no type definitions"):
        AnyReader([bag]).open()  # how the progress reader used to open it
    bag_input = BagInput(bag, "robot")
    assert bag_input.extent() == BagExtent(
        messages=6, topics=3, start_ns=T0, end_ns=T0 + 2 * 10**8 + 1, types={
            "/chatter": "std_msgs/msg/String", "/global_costmap/costmap_raw": "nav2_msgs/msg/Costmap",
            "/sensor/reading": "my_msgs/msg/Reading"})
    bag_input.close()

    rows = convert(bag, tmp_path / "out.rrd")

    assert texts(rows["/robot/chatter"]) == ["hello 0", "hello 1", "hello 2"]
    [grid] = [r for r in rows["/robot/global_costmap/costmap_raw"] if r.get("GridMap:data")]
    # nav2's cost translation (0 -> 0, 128 -> 50, 253 -> 99, 254 -> 100, 255 -> -1, 1 -> 1), the
    # ROS row 0 (at the origin) drawn last, as GridMap's image row 0 is the far one.
    assert list(grid["GridMap:data"][0]) == [100, 255, 1, 0, 50, 99]
    assert grid["GridMap:translation"][0] == [1.0, 2.0, 0.0]
    assert grid["GridMap:cell_size"] == [0.5]
    # The custom type is the one topic that cannot be decoded: one warning, naming it.
    warnings = texts(rows[WARNINGS_PATH])
    assert len(warnings) == 1
    assert warnings[0].startswith(
        "[robot] /sensor/reading: type my_msgs/msg/Reading has no definition: the source sent "
        "none (a rosbag2 recorded before Iron, like Humble's sqlite3 bags, stores none)"
    )
    err = capsys.readouterr().err
    assert "100% 6/6 msgs  3/3 topics" in err
    summary = [line.split() for line in err.splitlines() if line.startswith("robot  /")]
    assert [r[1:7] for r in summary] == [
        ["/chatter", "std_msgs/msg/String", "3", "3", "0", "0"],
        ["/global_costmap/costmap_raw", "nav2_msgs/msg/Costmap", "1", "1", "0", "0"],
        ["/sensor/reading", READING, "2", "0", "2", "2"],
    ]


def test_relay_replays_a_humble_bag_as_the_host_reads_it(tmp_path: Path) -> None:
    """The relay's source (the same one ``--bag`` uses) forwards every message, with no
    definition, so the host decodes them with its bundled types exactly as above."""
    bag = humble_bag(tmp_path / "humble")
    with BagSource(bag, "tb3") as source:
        catalog = source.catalog()
        messages = list(source.messages())
    assert {(t.topic, t.msgtype, t.definition) for t in catalog.topics} == {
        ("/chatter", "std_msgs/msg/String", None),
        ("/global_costmap/costmap_raw", "nav2_msgs/msg/Costmap", None),
        ("/sensor/reading", READING, None),
    }
    latched = {t.topic: t.qos.durability for t in catalog.topics}
    assert latched["/global_costmap/costmap_raw"] == "transient_local"
    assert Counter(m.topic for m in messages) == {
        "/chatter": 3, "/global_costmap/costmap_raw": 1, "/sensor/reading": 2,
    }
    assert all(m.definition is None for m in messages)
    stamps = [m.log_ns or 0 for m in messages]
    assert stamps == sorted(stamps)
    assert stamps[0] == T0


# --- service events -------------------------------------------------------------------------

CHANGE_STATE = "lifecycle_msgs/srv/ChangeState"
CHANGE_STATE_DEFINITION = service_definition(
    CHANGE_STATE,
    "Transition transition\n---\nbool success\n",
    {"lifecycle_msgs/Transition": "uint8 TRANSITION_ACTIVATE = 3\nuint8 id\nstring label\n"},
)
# Serialized by rclpy's serialize_message on ROS 2 Jazzy (rmw_fastrtps): a request received and
# its response sent, sequence 7, client gid 01..10, stamps 5.00000025 s and 6.00000025 s.
CHANGE_STATE_EVENTS = [
    "00010000017f000005000000fa0000000102030405060708090a0b0c0d0e0f10000000000700000000000000"
    "01000000030000000900000061637469766174650000000000000000",
    "000100000256000006000000fa0000000102030405060708090a0b0c0d0e0f1065537461070000000000000000"
    "0000000100000001",
]
GID = "0102030405060708090a0b0c0d0e0f10"
# A service whose response uses a type nothing defines: these events cannot be decoded.
ODD_DEFINITION = service_definition("my_srvs/srv/Odd", "int32 a\n---\nmy_msgs/Missing b\n", {})
SCAN = "my_msgs/msg/Scan"
SCAN_DEFINITION = 'string FRAME_NAME="lidar"\nuint8 MODE=2\nfloat32 gain\nfloat32[360] ranges\n'
HASH = "RIHS01_" + "00" * 32


def service_mcap(path: Path) -> Path:
    """A Jazzy ``ros2 bag record --all-topics --all-services`` MCAP: chatter, a custom scan with
    360 ranges, and the service events of two services."""
    humble = get_typestore(Stores.ROS2_HUMBLE)
    custom = get_typestore(Stores.EMPTY)
    custom.register(get_types_from_msg(SCAN_DEFINITION, SCAN))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=humble)
        scan = writer.add_connection("/custom_scan", SCAN, typestore=custom)
        change = writer.add_connection(
            "/camera_driver/change_state/_service_event", f"{CHANGE_STATE}_Event",
            msgdef=CHANGE_STATE_DEFINITION, rihs01=HASH,
        )
        odd = writer.add_connection("/odd/_service_event", "my_srvs/srv/Odd_Event",
                                    msgdef=ODD_DEFINITION, rihs01=HASH)
        for i in range(2):
            writer.write(chatter, T0 + i, cdr(humble, "std_msgs/msg/String", data=f"chat {i}"))
            writer.write(change, T0 + 10 + i, bytes.fromhex(CHANGE_STATE_EVENTS[i]))
            writer.write(odd, T0 + 20 + i, b"\x00\x01\x00\x00" + bytes(8))
            ranges = np.linspace(0.5, 4.0, 360, dtype=np.float32) * (i + 1)
            writer.write(scan, T0 + 30 + i, cdr(custom, SCAN, gain=0.5 + i, ranges=ranges))
    return path


def test_service_events_are_logged_and_an_undecodable_service_costs_only_itself(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = service_mcap(tmp_path / "services")
    with pytest.raises(AnyReaderError, match="Could not parse"):
        AnyReader([bag]).open()  # rosbags' own reader refuses the whole bag

    rows = convert(bag, tmp_path / "out.rrd")

    assert texts(rows["/robot/chatter"]) == ["chat 0", "chat 1"]
    events = rows["/robot/camera_driver/change_state/_service_event"]
    assert texts(events) == [
        f"request received #7 (client {GID}): {{transition: {{id: 3, label: 'activate'}}}}",
        f"response sent #7 (client {GID}): {{success: true}}",
    ]
    assert [r["ros_time"] for r in events] == [5_000_000_250, 6_000_000_250]
    # The custom scan: 360 ranges as a bar chart per message, its constants nowhere.
    bars = [r for r in rows["/robot/custom_scan/ranges"] if r.get("BarChart:values")]
    assert len(bars) == 2
    values = np.asarray(bars[1]["BarChart:values"][0]["buffer"], dtype=np.float32)
    np.testing.assert_allclose(values, np.linspace(0.5, 4.0, 360, dtype=np.float32) * 2)
    assert [r["Scalars:scalars"] for r in rows["/robot/custom_scan/gain"]] == [[0.5], [1.5]]
    assert not [p for p in rows if "FRAME_NAME" in p or p.endswith("/MODE")]

    warnings = texts(rows[WARNINGS_PATH])
    assert warnings == [
        "[robot] /odd/_service_event: service events of my_srvs/srv/Odd (the requests and "
        "responses rosbag2 records with --services) are skipped: definition of "
        "'my_srvs/srv/Odd_Event' uses ['my_msgs/msg/Missing'] which nothing defines "
        "(further UnknownTypeErrors on this topic are counted, not shown)"
    ]
    summary = {line.split()[1]: line.split()[3:7] for line in capsys.readouterr().err.splitlines()
               if line.startswith("robot ")}
    assert summary["/odd/_service_event"] == ["2", "0", "2", "2"]
    assert summary["/camera_driver/change_state/_service_event"] == ["2", "2", "0", "0"]


def test_disabling_service_events_in_the_config_skips_them(tmp_path: Path) -> None:
    bag = service_mcap(tmp_path / "services")
    config = tmp_path / "host.yaml"
    config.write_text(yaml.safe_dump({"topics": {"/odd/_service_event": {"enabled": False}}}))
    rows = convert(bag, tmp_path / "out.rrd", "--strict", "--config", str(config))
    assert WARNINGS_PATH not in rows
    assert len(texts(rows["/robot/camera_driver/change_state/_service_event"])) == 2


# --- metadata.yaml QoS that disagrees with the storage ---------------------------------------


def test_bag_whose_metadata_qos_disagrees_with_its_storage(tmp_path: Path) -> None:
    """Foxy/Galactic wrote a default deadline as 0 in metadata.yaml and INT_MAX in the storage
    file; rosbags then matches no connection and reads 0 messages."""
    bag = tmp_path / "qos"
    humble = get_typestore(Stores.ROS2_HUMBLE)
    from rosbags.rosbag2.metadata import parse_qos

    [storage_qos] = parse_qos(humble_qos())
    with Writer(bag, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        topic = writer.add_connection("/topic", "std_msgs/msg/String", typestore=humble,
                                      offered_qos_profiles=[storage_qos])
        for i in range(20):
            writer.write(topic, T0 + i, cdr(humble, "std_msgs/msg/String", data=f"n {i}"))
    metadata = bag / "metadata.yaml"
    info = yaml.safe_load(metadata.read_text())
    info["rosbag2_bagfile_information"]["topics_with_message_count"][0]["topic_metadata"][
        "offered_qos_profiles"] = humble_qos(deadline={"sec": 0, "nsec": 0})
    metadata.write_text(yaml.safe_dump(info))
    with AnyReader([bag]) as reader:
        assert list(reader.messages()) == []  # what rosbags alone gives

    rows = convert(bag, tmp_path / "out.rrd", "--strict")
    assert texts(rows["/robot/topic"]) == [f"n {i}" for i in range(20)]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_rosbag2_talker_fixtures_read_despite_their_qos(
    shared_data: Path, tmp_path: Path, storage: str
) -> None:
    """rosbag2's own talker fixtures: deadline 0 in metadata.yaml, INT_MAX in the storage."""
    bag = shared_data / "rosbag2_format_fixtures" / f"{storage}_talker"
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        assert list(reader.messages()) == []
    with BagSource(bag, "robot") as source:
        topics = [m.topic for m in source.messages()]
    assert sorted(topics) == ["/rosout"] * 10 + ["/topic"] * 10

    rows = convert(bag, tmp_path / "out.rrd")
    assert texts(rows["/robot/topic"]) == [f"Hello, world! {i}" for i in range(10)]
    rosout = texts(rows.get("/robot/rosout", []))
    if storage == "mcap":
        assert rosout[0] == "[minimal_publisher] Publishing: 'Hello, world! 0'"
        assert len(rosout) == 10
    else:
        # The sqlite3 copy stores placeholder definitions ("uint8 level" for Log): said, not lost
        # silently.
        assert rosout == []
        [warning] = texts(rows[WARNINGS_PATH])
        assert warning.startswith("[robot] /rosout: 176-byte rcl_interfaces/msg/Log payload does "
                                  "not deserialize")


# --- files users hand over ---------------------------------------------------------------------


def test_compressed_storage_file_points_to_its_bag_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = tmp_path / "compressed"
    humble = get_typestore(Stores.ROS2_HUMBLE)
    writer = Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    with writer:
        topic = writer.add_connection("/topic", "std_msgs/msg/String", typestore=humble)
        writer.write(topic, T0, cdr(humble, "std_msgs/msg/String", data="zipped"))
    [zstd_file] = bag.glob("*.mcap.zstd")

    assert host_main(["--bag", str(zstd_file), "--save", str(tmp_path / "x.rrd")]) == 2
    assert capsys.readouterr().err.strip() == (
        f"swanky-host: error: {zstd_file} is one zstd-compressed file of a rosbag2 recorded "
        f"with compression: give its bag directory {bag} instead"
    )
    lone = tmp_path / "lone.mcap.zstd"
    lone.write_bytes(zstd_file.read_bytes())
    with pytest.raises(SourceError, match=r"or decompress it \(zstd -d .*lone.mcap.zstd\)"):
        bag_paths(lone)
    assert texts(convert(bag, tmp_path / "out.rrd", "--strict")["/robot/topic"]) == ["zipped"]


def test_relay_without_rosbags_says_what_to_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``pip install ".[relay]"`` has no rosbags: replaying a bag names the extra to add."""
    bag = humble_bag(tmp_path / "humble")
    for name in [m for m in sys.modules if m == "rosbags" or m.startswith("rosbags.")]:
        monkeypatch.setitem(sys.modules, name, None)
    # Imported by an earlier test, they would not import rosbags again.
    for module in ("rosbag2", "mcap_stream", "sqlite"):
        monkeypatch.delitem(sys.modules, f"robot_relay.sources.{module}", raising=False)
    assert relay_main(["--bag", str(bag), "--robot", "tb3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        'swanky-relay: error: reading bags needs rosbags: pip install ".[relay,bag]" '
        "(import of rosbags.interfaces halted; None in sys.modules)"
    ]
