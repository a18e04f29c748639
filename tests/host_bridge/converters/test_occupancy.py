"""OccupancyGrid -> GridMap: pose, cell size, row order, colour schemes, updates, bad grids."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from host_bridge.converters import occupancy
from host_bridge.core.contract import ConvertContext
from host_bridge.errors import ConvertError
from tests.host_bridge.sensor_test_support import (
    archetype,
    flat,
    header,
    log_item,
    make_ctx,
    msg,
    read_topic,
)

# map_msgs is not in the rosbags Humble store; this is its ROS 2 definition.
UPDATE_DEFINITION = """std_msgs/Header header
int32 x
int32 y
uint32 width
uint32 height
int8[] data
"""
UPDATE_TYPE = "map_msgs/msg/OccupancyGridUpdate"


def grid_msg(
    cells: npt.NDArray[np.int8],
    *,
    resolution: float = 0.05,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    yaw: float = 0.0,
    frame_id: str = "map",
) -> Any:
    """An OccupancyGrid whose row 0 is ``cells[0]`` (ROS order: row 0 at the origin)."""
    height, width = cells.shape
    pose = msg(
        "geometry_msgs/msg/Pose",
        position=msg("geometry_msgs/msg/Point", x=origin[0], y=origin[1], z=origin[2]),
        orientation=msg(
            "geometry_msgs/msg/Quaternion",
            x=0.0,
            y=0.0,
            z=math.sin(yaw / 2.0),
            w=math.cos(yaw / 2.0),
        ),
    )
    info = msg(
        "nav_msgs/msg/MapMetaData",
        map_load_time=header().stamp,
        resolution=resolution,
        width=width,
        height=height,
        origin=pose,
    )
    return msg("nav_msgs/msg/OccupancyGrid", header=header(frame_id), info=info, data=cells.ravel())


def update_msg(x: int, y: int, patch: npt.NDArray[np.int8]) -> Any:
    """An OccupancyGridUpdate, through a CDR round trip with the definition above."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(UPDATE_DEFINITION, UPDATE_TYPE))
    height, width = patch.shape
    message = store.types[UPDATE_TYPE](
        header=header("map"), x=x, y=y, width=width, height=height, data=patch.ravel()
    )
    return store.deserialize_cdr(store.serialize_cdr(message, UPDATE_TYPE), UPDATE_TYPE)


def grid_map_of(entries: list[Any], path: str) -> rr.GridMap:
    return archetype(log_item(entries, path), rr.GridMap)  # type: ignore[no-any-return]


def image_format(grid_map: rr.GridMap) -> dict[str, Any]:
    assert grid_map.format is not None
    fmt: dict[str, Any] = grid_map.format.as_arrow_array().to_pylist()[0]
    return fmt


def image_rows(grid_map: rr.GridMap) -> npt.NDArray[np.int8]:
    """The logged buffer as int8 cells, in Rerun's image order (row 0 drawn at the top)."""
    fmt = image_format(grid_map)
    data = flat(grid_map.data).astype(np.uint8)
    return data.view(np.int8).reshape(fmt["height"], fmt["width"])


def test_grid_map_sits_at_the_origin_pose_with_the_cell_size() -> None:
    yaw = math.radians(30.0)
    cells = np.zeros((4, 6), dtype=np.int8)
    ctx = make_ctx("/map")
    entries = occupancy.convert_grid(
        grid_msg(cells, resolution=0.05, origin=(-3.0, -2.0, 0.1), yaw=yaw), ctx
    )
    item = log_item(entries, "/r/map")
    grid_map = archetype(item, rr.GridMap)
    assert flat(archetype(item, rr.CoordinateFrame).frame).tolist() == ["r/map"]
    np.testing.assert_allclose(flat(grid_map.translation, 3), [[-3.0, -2.0, 0.1]], atol=1e-6)
    np.testing.assert_allclose(
        flat(grid_map.quaternion, 4), [[0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]], atol=1e-6
    )
    np.testing.assert_allclose(flat(grid_map.cell_size), [0.05], rtol=1e-6)
    fmt = image_format(grid_map)
    assert (fmt["width"], fmt["height"]) == (6, 4)
    stored = ctx.robot_state.grids["/map"]
    assert stored.cells.shape == (4, 6)
    assert not stored.cells.flags.writeable


def test_rows_are_flipped_so_ros_row_zero_lands_next_to_the_origin() -> None:
    # Asymmetric: one occupied cell at ROS (col 2, row 0), one unknown at (col 0, row 2).
    cells = np.zeros((3, 4), dtype=np.int8)
    cells[0, 2] = 100
    cells[2, 0] = -1
    grid_map = grid_map_of(occupancy.convert_grid(grid_msg(cells), make_ctx("/map")), "/r/map")
    image = image_rows(grid_map)
    # Rerun puts image row 0 at y = height * cell and walks down -y (grid_map.rs), so image row
    # i covers grid-local y in [(h - 1 - i) * cell, (h - i) * cell].
    height = image.shape[0]
    occupied_rows, occupied_cols = np.nonzero(image == 100)
    assert (occupied_cols.tolist(), (height - 1 - occupied_rows).tolist()) == ([2], [0])
    unknown_rows, unknown_cols = np.nonzero(image == -1)
    assert (unknown_cols.tolist(), (height - 1 - unknown_rows).tolist()) == ([0], [2])


def test_map_scheme_sends_the_raw_values_with_rviz_map_colours() -> None:
    cells = np.array([[-1, 0, 100, 50]], dtype=np.int8)
    grid_map = grid_map_of(occupancy.convert_grid(grid_msg(cells), make_ctx("/map")), "/r/map")
    # One byte per cell: unknown -1 is 255, the viewer's RViz map palette colours them (free
    # white, occupied black, grey ramp between, unknown grey-green).
    assert flat(grid_map.data).tolist() == [255, 0, 100, 50]
    fmt = image_format(grid_map)
    assert (fmt["color_model"], fmt["channel_datatype"]) == (
        rr.ColorModel.L.value,
        rr.ChannelDatatype.U8.value,
    )
    assert flat(grid_map.colormap).tolist() == [rr.components.Colormap.RvizMap.value]
    assert flat(grid_map.opacity).tolist() == [1.0]
    assert flat(grid_map.draw_order).tolist() == [0.0]


@pytest.mark.parametrize(
    ("topic", "options", "colormap", "opacity", "draw_order"),
    [
        ("/global_costmap/costmap", {}, rr.components.Colormap.RvizCostmap, 0.7, 1.0),
        ("/local_costmap/costmap", {}, rr.components.Colormap.RvizCostmap, 0.7, 2.0),
        (
            "/map",
            {"color_scheme": "costmap", "opacity": 0.4, "draw_order": 5},
            rr.components.Colormap.RvizCostmap,
            0.4,
            5.0,
        ),
        ("/costmap", {"color_scheme": "raw"}, None, 0.7, 1.0),
        ("/map", {"color_scheme": "raw"}, None, 1.0, 0.0),
    ],
)
def test_colour_scheme_follows_topic_name_and_options(
    topic: str,
    options: dict[str, Any],
    colormap: rr.components.Colormap | None,
    opacity: float,
    draw_order: float,
) -> None:
    cells = np.array([[0, 99, 100]], dtype=np.int8)
    entries = occupancy.convert_grid(grid_msg(cells), make_ctx(topic, options))
    grid_map = grid_map_of(entries, f"/r{topic}")
    if colormap is None:
        assert grid_map.colormap is None
    else:
        assert flat(grid_map.colormap).tolist() == [colormap.value]
    np.testing.assert_allclose(flat(grid_map.opacity), [opacity], rtol=1e-6)
    np.testing.assert_allclose(flat(grid_map.draw_order), [draw_order], rtol=1e-6)


def test_unknown_colour_scheme_is_a_convert_error() -> None:
    cells = np.zeros((2, 2), dtype=np.int8)
    with pytest.raises(ConvertError, match=r"/map: option color_scheme is 'jet'"):
        occupancy.convert_grid(grid_msg(cells), make_ctx("/map", {"color_scheme": "jet"}))


def test_resolution_zero_in_the_real_bag_is_a_convert_error(shared_data: Path) -> None:
    bag = shared_data / "ros_numpy_msgs_synthetic" / "ros_numpy_test.bag"
    (grid,) = read_topic(bag, "/occupancygrid")
    assert (grid.info.width, grid.info.height, grid.info.resolution) == (30, 30, 0.0)
    with pytest.raises(ConvertError, match=r"^/occupancygrid: info.resolution is 0.0"):
        occupancy.convert_grid(grid, make_ctx("/occupancygrid"))


def test_cell_count_not_matching_the_size_is_a_convert_error() -> None:
    message = grid_msg(np.zeros((2, 3), dtype=np.int8))
    message.info.width = 4
    with pytest.raises(ConvertError, match=r"/map: data has 6 cells but info says 4x2 = 8"):
        occupancy.convert_grid(message, make_ctx("/map"))


def test_empty_grid_logs_nothing() -> None:
    assert occupancy.convert_grid(grid_msg(np.zeros((0, 0), dtype=np.int8)), make_ctx("/map")) == []


def shared_contexts(
    grid_topic: str, update_topic: str, update_options: dict[str, Any] | None = None
) -> tuple[ConvertContext, ConvertContext]:
    """Contexts of a grid topic and its update topic on one robot (shared robot_state)."""
    grid_ctx = make_ctx(grid_topic, {"color_scheme": "costmap", "opacity": 0.5})
    return grid_ctx, make_ctx(update_topic, update_options, robot_state=grid_ctx.robot_state)


def test_update_patches_the_cells_of_the_grid_topic() -> None:
    grid_ctx, update_ctx = shared_contexts("/costmap", "/costmap_updates")
    cells = np.zeros((4, 5), dtype=np.int8)
    occupancy.convert_grid(grid_msg(cells, origin=(1.0, 2.0, 0.0)), grid_ctx)
    before = update_ctx.robot_state.grids["/costmap"].cells

    patch = np.array([[100, 50, -1]], dtype=np.int8)
    entries = occupancy.convert_update(update_msg(1, 2, patch), update_ctx)

    # The patched grid is re-logged at the grid's entity, with the grid topic's options.
    grid_map = grid_map_of(entries, "/r/costmap")
    expected = np.zeros((4, 5), dtype=np.int8)
    expected[2, 1:4] = [100, 50, -1]
    np.testing.assert_array_equal(image_rows(grid_map), np.flipud(expected))
    assert flat(grid_map.colormap).tolist() == [rr.components.Colormap.RvizCostmap.value]
    np.testing.assert_allclose(flat(grid_map.opacity), [0.5])
    np.testing.assert_allclose(flat(grid_map.translation, 3), [[1.0, 2.0, 0.0]])
    np.testing.assert_array_equal(
        update_ctx.robot_state.grids["/costmap"].cells, expected
    )
    # Copy on write: the grid a wall worker may still hold is untouched.
    np.testing.assert_array_equal(before, np.zeros((4, 5), dtype=np.int8))


def test_update_names_its_grid_with_the_grid_topic_option() -> None:
    grid_ctx, update_ctx = shared_contexts("/map", "/map_patch", {"grid_topic": "/map"})
    occupancy.convert_grid(grid_msg(np.zeros((2, 2), dtype=np.int8)), grid_ctx)
    entries = occupancy.convert_update(update_msg(1, 1, np.array([[100]], np.int8)), update_ctx)
    np.testing.assert_array_equal(image_rows(grid_map_of(entries, "/r/map")), [[0, 100], [0, 0]])


@pytest.mark.parametrize(
    ("update_topic", "x", "y", "patch", "message"),
    [
        ("/costmap_updates", 0, 0, np.zeros((1, 1), np.int8), "no OccupancyGrid received yet"),
        ("/costmap_patch", 0, 0, np.zeros((1, 1), np.int8), "cannot tell which grid"),
        ("/map_updates", 4, 0, np.zeros((1, 2), np.int8), "x=4 y=0 2x1 does not fit the 5x4"),
        ("/map_updates", 0, -1, np.zeros((1, 1), np.int8), "x=0 y=-1 1x1 does not fit"),
    ],
)
def test_bad_updates_are_convert_errors_naming_the_topic(
    update_topic: str, x: int, y: int, patch: npt.NDArray[np.int8], message: str
) -> None:
    grid_ctx, update_ctx = shared_contexts("/map", update_topic)
    occupancy.convert_grid(grid_msg(np.zeros((4, 5), dtype=np.int8)), grid_ctx)
    with pytest.raises(ConvertError, match=rf"^{update_topic}: .*{message}"):
        occupancy.convert_update(update_msg(x, y, patch), update_ctx)
