"""nav_msgs converters: Path vertices (real Nav plans) and GridCells boxes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr

from host_bridge.converters.nav import GRID_CELLS, PATH
from tests.host_bridge.sensor_test_support import (
    TYPES,
    archetype,
    header,
    log_item,
    make_ctx,
    read_topic,
)


def _pylist(batch: Any) -> list[Any]:
    return list(batch.as_arrow_array().to_pylist())


def _point(x: float, y: float, z: float = 0.0) -> Any:
    return TYPES["geometry_msgs/msg/Point"](x=x, y=y, z=z)


def _stamped_pose(x: float, y: float, yaw_quarter_turns: int = 0) -> Any:
    half = np.sqrt(0.5)
    z, w = [(0.0, 1.0), (half, half)][yaw_quarter_turns]
    pose = TYPES["geometry_msgs/msg/Pose"](
        position=_point(x, y), orientation=TYPES["geometry_msgs/msg/Quaternion"](x=0, y=0, z=z, w=w),
    )
    return TYPES["geometry_msgs/msg/PoseStamped"](header=header(""), pose=pose)


@pytest.mark.parametrize(
    ("topic", "count", "frame", "pose_range"),
    # The data README says 51-87 poses per /plan; the bag really holds 2-293.
    [("/plan", 74, "tb3/map", (2, 293)), ("/local_plan", 1453, "tb3/odom", (0, 70))],
)
def test_real_plans_become_one_strip_through_every_pose(
    shared_data: Path, topic: str, count: int, frame: str, pose_range: tuple[int, int],
) -> None:
    plans = list(read_topic(shared_data / "tb3_nav_sim_paths_amr" / "rosbag_demo.bag", topic))
    assert len(plans) == count
    lengths = []
    for plan in plans:
        item = log_item(PATH.convert(plan, make_ctx(topic, robot="tb3")), f"/tb3{topic}")
        strips = _pylist(archetype(item, rr.LineStrips3D).strips)
        expected = np.array(
            [(p.pose.position.x, p.pose.position.y, p.pose.position.z) for p in plan.poses],
            dtype=np.float32,  # Rerun stores positions as float32
        )
        assert len(strips) == (1 if len(expected) else 0)  # an empty plan clears the line
        if strips:
            np.testing.assert_array_equal(np.array(strips[0], dtype=np.float32), expected)
        assert _pylist(archetype(item, rr.CoordinateFrame).frame) == [frame]
        lengths.append(len(expected))
    assert (min(lengths), max(lengths)) == pose_range


def test_path_arrows_are_optional() -> None:
    msg = TYPES["nav_msgs/msg/Path"](
        header=header("odom"), poses=[_stamped_pose(0.0, 0.0), _stamped_pose(1.0, 0.0, 1)],
    )
    assert [e.path for e in PATH.convert(msg, make_ctx("/local_plan", robot="tb3"))] == ["/tb3/local_plan"]
    entries = PATH.convert(msg, make_ctx("/local_plan", {"arrows": True, "arrow_length": 0.5}, robot="tb3"))
    assert [e.path for e in entries] == ["/tb3/local_plan", "/tb3/local_plan/poses"]
    line, arrows = log_item(entries, "/tb3/local_plan"), log_item(entries, "/tb3/local_plan/poses")
    drawn = archetype(arrows, rr.Arrows3D)
    np.testing.assert_allclose(_pylist(drawn.origins), [[0, 0, 0], [1, 0, 0]])
    np.testing.assert_allclose(_pylist(drawn.vectors), [[0.5, 0, 0], [0, 0.5, 0]], atol=1e-6)
    assert _pylist(archetype(arrows, rr.CoordinateFrame).frame) == ["tb3/odom"]
    assert _pylist(archetype(line, rr.LineStrips3D).strips) == [[[0, 0, 0], [1, 0, 0]]]


def test_grid_cells_are_thin_boxes_of_the_cell_size() -> None:
    msg = TYPES["nav_msgs/msg/GridCells"](
        header=header("map"), cell_width=0.05, cell_height=0.1,
        cells=[_point(1.0, 2.0), _point(1.05, 2.0), _point(-3.0, 0.5, 0.2)],
    )
    item = log_item(GRID_CELLS.convert(msg, make_ctx("/obstacles", robot="tb3")), "/tb3/obstacles")
    boxes = archetype(item, rr.Boxes3D)
    np.testing.assert_allclose(
        _pylist(boxes.centers), [[1.0, 2.0, 0.0], [1.05, 2.0, 0.0], [-3.0, 0.5, 0.2]], rtol=1e-6,
    )
    (half_size,) = _pylist(boxes.half_sizes)  # one size shared by every cell
    np.testing.assert_allclose(half_size, [0.025, 0.05, 0.005], rtol=1e-6)
    assert _pylist(archetype(item, rr.CoordinateFrame).frame) == ["tb3/map"]
    empty = TYPES["nav_msgs/msg/GridCells"](header=header(""), cell_width=1, cell_height=1, cells=[])
    item = log_item(GRID_CELLS.convert(empty, make_ctx("/obstacles", robot="tb3")), "/tb3/obstacles")
    assert _pylist(archetype(item, rr.Boxes3D).centers) == []
    assert len(item.archetypes) == 1  # empty frame_id: no CoordinateFrame
