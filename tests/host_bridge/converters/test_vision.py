"""vision_msgs: the bundled definitions decode real CDR, and detections become labelled boxes."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import rerun as rr
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.converters import vision
from host_bridge.core.schemas import extra_typesdict
from tests.host_bridge.sensor_test_support import ROBOT, archetype, header, log_item, make_ctx

TOPIC = "/detections"
BASE = f"/{ROBOT}{TOPIC}"
VISION_TYPES = {
    f"vision_msgs/msg/{name}"
    for name in (
        "Detection2DArray",
        "Detection2D",
        "Detection3DArray",
        "Detection3D",
        "ObjectHypothesisWithPose",
        "ObjectHypothesis",
        "BoundingBox2D",
        "BoundingBox3D",
        "Pose2D",
        "Point2D",
    )
}


@pytest.fixture(scope="module")
def store() -> Typestore:
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    typestore.register(extra_typesdict())
    return typestore


def values(batch: Any) -> list[Any]:
    return list(batch.pa_array.to_pylist())


def _pose(
    store: Typestore, xyz: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw: float = 0.0
) -> Any:
    t = store.types
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        ),
    )


def _results(store: Typestore, *scored: tuple[str, float]) -> list[Any]:
    t = store.types
    return [
        t["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=t["vision_msgs/msg/ObjectHypothesis"](class_id=class_id, score=score),
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=_pose(store), covariance=np.zeros(36)
            ),
        )
        for class_id, score in scored
    ]


def _detection2d(
    store: Typestore, cx: float, cy: float, w: float, h: float, *scored: tuple[str, float]
) -> Any:
    t = store.types
    center = t["vision_msgs/msg/Pose2D"](
        position=t["vision_msgs/msg/Point2D"](x=cx, y=cy), theta=0.0
    )
    return t["vision_msgs/msg/Detection2D"](
        header=header("camera"),
        results=_results(store, *scored),
        bbox=t["vision_msgs/msg/BoundingBox2D"](center=center, size_x=w, size_y=h),
        id="",
    )


def test_extra_typesdict_parses_the_vision_msgs_definitions() -> None:
    types = extra_typesdict()
    assert set(types) >= VISION_TYPES
    _, fields = types["vision_msgs/msg/BoundingBox2D"]
    assert [name for name, _ in fields] == ["center", "size_x", "size_y"]
    _, fields = types["vision_msgs/msg/Detection3D"]
    assert [name for name, _ in fields] == ["header", "results", "bbox", "id"]


def test_detection2d_array_round_trips_through_cdr_and_converts(store: Typestore) -> None:
    msgtype = "vision_msgs/msg/Detection2DArray"
    sent = store.types[msgtype](
        header=header("camera"),
        detections=[
            _detection2d(store, 320.0, 240.0, 100.0, 50.0, ("cat", 0.4), ("person", 0.9)),
            _detection2d(store, 10.5, 20.0, 4.0, 8.0, ("7", 0.25)),
        ],
    )
    received = store.deserialize_cdr(store.serialize_cdr(sent, msgtype), msgtype)
    entries = vision.convert_detection2d_array(received, make_ctx(TOPIC))
    boxes = archetype(log_item(entries, BASE), rr.Boxes2D)
    assert values(boxes.centers) == [[320.0, 240.0], [10.5, 20.0]]
    assert values(boxes.half_sizes) == [[50.0, 25.0], [2.0, 4.0]]
    assert values(boxes.labels) == ["person 0.90", "7 0.25"]
    assert values(boxes.class_ids) == [0, 7]  # names numbered per topic, numbers kept


def test_class_numbers_are_stable_per_topic(store: Typestore) -> None:
    ctx = make_ctx(TOPIC)
    first = vision.convert_detection2d_array(
        SimpleNamespace(
            detections=[
                _detection2d(store, 0, 0, 1, 1, ("dog", 0.5)),
                _detection2d(store, 0, 0, 1, 1, ("cat", 0.5)),
            ]
        ),
        ctx,
    )
    second = vision.convert_detection2d_array(
        SimpleNamespace(detections=[_detection2d(store, 0, 0, 1, 1, ("cat", 0.5))]), ctx
    )
    assert values(archetype(log_item(first, BASE), rr.Boxes2D).class_ids) == [0, 1]
    assert values(archetype(log_item(second, BASE), rr.Boxes2D).class_ids) == [1]


def test_detection_without_hypotheses_keeps_boxes_and_drops_class_ids(store: Typestore) -> None:
    msg = SimpleNamespace(
        detections=[_detection2d(store, 5, 6, 2, 2), _detection2d(store, 1, 1, 2, 2, ("cup", 0.75))]
    )
    boxes = archetype(
        log_item(vision.convert_detection2d_array(msg, make_ctx(TOPIC)), BASE), rr.Boxes2D
    )
    assert values(boxes.labels) == ["", "cup 0.75"]
    assert values(boxes.class_ids) == []  # logged empty so older ids do not linger


def test_detection3d_array_boxes_rotation_labels_and_frame(store: Typestore) -> None:
    t = store.types
    msgtype = "vision_msgs/msg/Detection3DArray"
    detection = t["vision_msgs/msg/Detection3D"](
        header=header("base_link"),
        results=_results(store, ("chair", 0.8)),
        bbox=t["vision_msgs/msg/BoundingBox3D"](
            center=_pose(store, (2.0, -1.0, 0.5), yaw=math.pi / 2),
            size=t["geometry_msgs/msg/Vector3"](x=0.6, y=0.4, z=1.0),
        ),
        id="track-3",
    )
    sent = t[msgtype](header=header("base_link"), detections=[detection])
    received = store.deserialize_cdr(store.serialize_cdr(sent, msgtype), msgtype)
    item = log_item(vision.convert_detection3d_array(received, make_ctx(TOPIC)), BASE)
    boxes = archetype(item, rr.Boxes3D)
    assert values(boxes.centers) == [[2.0, -1.0, 0.5]]
    assert np.allclose(values(boxes.half_sizes), [[0.3, 0.2, 0.5]])
    assert np.allclose(values(boxes.quaternions), [[0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]])
    assert values(boxes.labels) == ["chair 0.80"]
    assert values(archetype(item, rr.CoordinateFrame).frame) == [f"{ROBOT}/base_link"]


def test_older_vision_msgs_layout_converts() -> None:
    """ROS 1 / Foxy vision_msgs: geometry_msgs/Pose2D centre and id + score on the result."""
    old = SimpleNamespace(
        results=[SimpleNamespace(id=3, score=0.6)],
        bbox=SimpleNamespace(
            center=SimpleNamespace(x=4.0, y=5.0, theta=0.0), size_x=2.0, size_y=6.0
        ),
    )
    boxes = archetype(log_item(vision.convert_detection2d(old, make_ctx(TOPIC)), BASE), rr.Boxes2D)
    assert values(boxes.centers) == [[4.0, 5.0]]
    assert values(boxes.half_sizes) == [[1.0, 3.0]]
    assert values(boxes.labels) == ["3 0.60"]
    assert values(boxes.class_ids) == [3]
