"""Types users bring that Swanky has no dedicated converter for, or knows only by name: custom
messages with large arrays and constants (generic converter), nav2's Costmap, service events."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import rerun as rr
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from host_bridge.converters import occupancy
from host_bridge.converters.generic import convert_generic
from host_bridge.converters.services import event_text
from host_bridge.core.contract import ColumnsItem, LogItem, PerMessage, per_message
from host_bridge.core.decode import Decoder
from host_bridge.core.schemas import base_typestore
from host_bridge.errors import PartialConvertError, UnknownTypeError
from host_bridge.table.registry import default_registry
from robot_relay.wire import MessageDefinition, RawMessage
from tests.host_bridge.sensor_test_support import archetype, column_rows, convert, log_item, make_ctx
from tests.host_bridge.test_user_bags import CHANGE_STATE_DEFINITION, CHANGE_STATE_EVENTS, GID
from tests.host_bridge.user_bags import SEPARATOR, service_definition

THING = "my_msgs/msg/Thing"
THING_DEFINITION = """string FRAME_NAME="lidar"
int32 LIMIT=5
float64[3] small
float32[100] ranges
uint8[] blob
bool[70] flags
geometry_msgs/Point[] points
"""


def thing(points: int = 2) -> Any:
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(THING_DEFINITION, THING))
    t = store.types
    return t[THING](
        small=np.array([1.0, 2.0, 3.0]),
        ranges=np.linspace(0.0, 9.9, 100, dtype=np.float32),
        blob=np.arange(500, dtype=np.int64).astype(np.uint8),
        flags=np.arange(70) % 2 == 0,
        points=[t["geometry_msgs/msg/Point"](x=float(i), y=0.0, z=0.0) for i in range(points)],
    )


def bar_values(item: LogItem) -> list[float]:
    [tensor] = archetype(item, rr.BarChart).values.as_arrow_array().to_pylist()
    assert tensor["shape"] == [len(tensor["buffer"])]
    return list(tensor["buffer"])


def test_large_arrays_are_bar_charts_and_constants_are_not_data() -> None:
    entries = convert(convert_generic, thing(), make_ctx("/thing"))
    paths = sorted(e.path for e in entries if not (isinstance(e, LogItem) and e.static))
    assert paths == [
        "/r/thing/blob", "/r/thing/flags", "/r/thing/points/0", "/r/thing/points/1",
        "/r/thing/ranges", "/r/thing/small",
    ]
    # Each Point is one plot of an x, y and z series, named once.
    points = {e.path: np.asarray(column_rows(e, "Scalars:scalars")).tolist() for e in entries
              if e.path.startswith("/r/thing/points/") and isinstance(e, ColumnsItem)}
    assert points == {"/r/thing/points/0": [[0.0, 0.0, 0.0]], "/r/thing/points/1": [[1.0, 0.0, 0.0]]}
    legends = [e for e in entries if isinstance(e, LogItem) and e.static]
    assert sorted(e.path for e in legends) == ["/r/thing/points/0", "/r/thing/points/1"]
    assert all(isinstance(a, rr.SeriesLines) for e in legends for a in e.archetypes)
    np.testing.assert_allclose(bar_values(log_item(entries, "/r/thing/ranges")),
                               np.linspace(0.0, 9.9, 100, dtype=np.float32))
    assert bar_values(log_item(entries, "/r/thing/blob")) == [i % 256 for i in range(500)]
    assert bar_values(log_item(entries, "/r/thing/flags")) == [1, 0] * 35
    [small] = [e for e in entries if e.path == "/r/thing/small" and isinstance(e, ColumnsItem)]
    np.testing.assert_allclose(column_rows(small, "Scalars:scalars"), [[1.0, 2.0, 3.0]])


def test_max_array_option_moves_the_bar_chart_threshold() -> None:
    entries = convert(convert_generic, thing(), make_ctx("/thing", {"max_array": 200}))
    [ranges] = [e for e in entries if e.path == "/r/thing/ranges"]
    assert isinstance(ranges, ColumnsItem)
    assert len(column_rows(ranges, "Scalars:scalars")[0]) == 100


def test_long_message_sequences_show_sixteen_elements_and_say_so() -> None:
    with pytest.raises(PartialConvertError) as caught:
        convert(convert_generic, thing(points=20), make_ctx("/thing"))
    assert str(caught.value) == (
        "/thing: no converter for my_msgs/msg/Thing; the generic one shows the first 16 "
        "elements of points"
    )
    shown = sorted({e.path for e in caught.value.items if e.path.startswith("/r/thing/points/")})
    assert shown == sorted(f"/r/thing/points/{i}" for i in range(16))


# --- nav2 Costmap ---------------------------------------------------------------------------


def costmap(costs: list[list[int]]) -> Any:
    t = base_typestore().types
    time = t["builtin_interfaces/msg/Time"](sec=3, nanosec=0)
    origin = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=-1.0, y=0.5, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=2.0),
    )
    meta = t["nav2_msgs/msg/CostmapMetaData"](
        map_load_time=time, update_time=time, layer="master", resolution=0.05,
        size_x=len(costs[0]), size_y=len(costs), origin=origin,
    )
    return t["nav2_msgs/msg/Costmap"](
        header=t["std_msgs/msg/Header"](stamp=time, frame_id="map"), metadata=meta,
        data=np.array(costs, dtype=np.uint8).ravel(),
    )


def grid_bytes(entries: list[Any], path: str) -> list[int]:
    grid = archetype(log_item(entries, path), rr.GridMap)
    return list(grid.data.as_arrow_array().to_pylist()[0])


def test_cost_translation_is_nav2s() -> None:
    # nav2_costmap_2d costmap_2d_publisher.cpp: cost_translation_table_
    assert occupancy.COST_TO_OCCUPANCY.tolist()[:3] == [0, 1, 1]
    assert occupancy.COST_TO_OCCUPANCY.tolist()[250:] == [97, 97, 98, 99, 100, -1]
    assert occupancy.COST_TO_OCCUPANCY[128] == 50


def test_costmap_is_a_grid_map_in_the_costmap_palette() -> None:
    ctx = make_ctx("/local_costmap/costmap_raw")
    entries = occupancy.convert_costmap(costmap([[0, 1, 128], [252, 253, 254], [255, 0, 0]]), ctx)
    grid = archetype(log_item(entries, "/r/local_costmap/costmap_raw"), rr.GridMap)
    assert grid_bytes(entries, "/r/local_costmap/costmap_raw") == [
        255, 0, 0, 98, 99, 100, 0, 1, 50,  # ROS row 0 (at the origin) is the image's last row
    ]
    assert grid.colormap.as_arrow_array().to_pylist() == [rr.components.Colormap.RvizCostmap.value]
    assert grid.cell_size.as_arrow_array().to_pylist() == [pytest.approx(0.05)]
    assert grid.translation.as_arrow_array().to_pylist() == [[-1.0, 0.5, 0.0]]
    assert grid.quaternion.as_arrow_array().to_pylist() == [[0.0, 0.0, 0.0, 1.0]]
    frame = archetype(log_item(entries, "/r/local_costmap/costmap_raw"), rr.CoordinateFrame)
    assert frame.frame.as_arrow_array().to_pylist() == ["r/map"]


def test_costmap_raw_scheme_shows_the_costs_and_updates_patch_them() -> None:
    grid_ctx = make_ctx("/global_costmap/costmap_raw", {"color_scheme": "raw"})
    occupancy.convert_costmap(costmap([[0, 0, 0], [0, 0, 0]]), grid_ctx)
    t = base_typestore().types
    update = t["nav2_msgs/msg/CostmapUpdate"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=4, nanosec=0),
                                        frame_id="map"),
        x=1, y=1, size_x=2, size_y=1, data=np.array([200, 254], dtype=np.uint8),
    )
    update_ctx = make_ctx("/global_costmap/costmap_raw_updates", robot_state=grid_ctx.robot_state)
    entries = occupancy.convert_costmap_update(update, update_ctx)
    assert grid_bytes(entries, "/r/global_costmap/costmap_raw") == [0, 200, 254, 0, 0, 0]


def test_costmap_types_are_registered_and_bundled() -> None:
    registry = default_registry()
    assert registry.get("nav2_msgs/msg/Costmap") == per_message(occupancy.convert_costmap)
    assert registry.get("nav2_msgs/msg/CostmapUpdate") == per_message(occupancy.convert_costmap_update)
    fields = [name for name, _ in base_typestore().fielddefs["nav2_msgs/msg/CostmapMetaData"][1]]
    assert fields == ["map_load_time", "update_time", "layer", "resolution", "size_x", "size_y",
                      "origin"]


# --- service events ---------------------------------------------------------------------------

EVENT = "lifecycle_msgs/srv/ChangeState_Event"


def raw_event(data: bytes, definition: str | None, msgtype: str = EVENT) -> RawMessage:
    text = None if definition is None else MessageDefinition("ros2msg", definition)
    return RawMessage("r", "/node/change_state/_service_event", msgtype, data, definition=text)


def test_service_event_bytes_from_rclpy_decode_with_rosbag2s_definition() -> None:
    decoder = Decoder()
    request, response = (
        decoder.decode(raw_event(bytes.fromhex(h), CHANGE_STATE_DEFINITION))
        for h in CHANGE_STATE_EVENTS
    )
    assert (request.info.event_type, request.info.sequence_number) == (1, 7)
    assert bytes(request.info.client_gid).hex() == GID
    assert (request.request[0].transition.id, request.request[0].transition.label) == (3, "activate")
    assert list(request.response) == []
    assert bool(response.response[0].success) is True
    assert event_text(response) == f"response sent #7 (client {GID}): {{success: true}}"
    assert not isinstance(default_registry().get(EVENT), PerMessage)


def test_service_with_empty_request_and_idl_dependencies() -> None:
    """std_srvs/Trigger has an empty request (``---`` first); rosbag2 writes an empty MSG block
    then an IDL block for a dependency only found as .idl."""
    definition = service_definition("my_srvs/srv/Check", "---\nState state\n", {}) + (
        f"\n{SEPARATOR}MSG: my_srvs/State\n\n{SEPARATOR}IDL: my_srvs/State\n"
        "module my_srvs {\n  module msg {\n    struct State {\n      uint8 id;\n    };\n  };\n};\n"
    )
    store = Decoder().typestore_for("my_srvs/srv/Check_Event", MessageDefinition("ros2msg", definition))
    t = store.types
    info = t["service_msgs/msg/ServiceEventInfo"](
        event_type=3, stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=2),
        client_gid=np.zeros(16, dtype=np.uint8), sequence_number=9,
    )
    event = t["my_srvs/srv/Check_Event"](
        info=info, request=[],
        response=[t["my_srvs/srv/Check_Response"](state=t["my_srvs/msg/State"](id=4))],
    )
    data = bytes(store.serialize_cdr(event, "my_srvs/srv/Check_Event"))
    decoded = Decoder().decode(raw_event(data, definition, "my_srvs/srv/Check_Event"))
    assert event_text(decoded) == f"response received #9 (client {'00' * 16}): {{state: {{id: 4}}}}"


def test_service_event_without_any_definition_says_it_is_one() -> None:
    with pytest.raises(UnknownTypeError) as caught:
        Decoder().decode(raw_event(b"\x00\x01\x00\x00", None, "my_srvs/srv/Odd_Event"))
    assert str(caught.value) == (
        "service events of my_srvs/srv/Odd (the requests and responses rosbag2 records with "
        "--services) are skipped: no definition of my_srvs/srv/Odd_Event came with them "
        "(rosbag2 stores none when it finds no .srv file for the service while recording)"
    )
