"""CameraInfo -> Pinhole at the camera namespace: intrinsics, resolution, frames, and where the
pinhole sits relative to the image entities that must appear inside its frustum."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr

from host_bridge.converters.camera import convert_camera_info
from host_bridge.core.contract import LogItem
from host_bridge.errors import ConvertError
from tests.host_bridge.converters.test_images import ROBOT, T, first_message, header, pylist
from tests.host_bridge.sensor_test_support import make_ctx

INFO_TOPIC = "/camera/camera_info"
K_640 = np.array([525.0, 0.0, 319.5, 0.0, 526.0, 239.5, 0.0, 0.0, 1.0])


def camera_info(
    k: npt.NDArray[np.float64] = K_640,
    *,
    width: int = 640,
    height: int = 480,
    frame_id: str = "camera_optical_frame",
    binning: tuple[int, int] = (0, 0),
    roi: tuple[int, int, int, int] = (0, 0, 0, 0),
) -> Any:
    """A Humble CameraInfo; ``roi`` is (x_offset, y_offset, width, height)."""
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(frame_id),
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=np.array([0.1, -0.2, 0.0, 0.0, 0.0]),
        k=k,
        r=np.eye(3).ravel(),
        p=np.zeros(12),
        binning_x=binning[0],
        binning_y=binning[1],
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=roi[0], y_offset=roi[1], width=roi[2], height=roi[3], do_rectify=False
        ),
    )


def pinhole_item(msg: Any, topic: str = INFO_TOPIC) -> tuple[str, rr.Pinhole, list[str]]:
    """(entity path, the Pinhole, the CoordinateFrame names logged with it)."""
    (item,) = convert_camera_info(msg, make_ctx(topic, robot=ROBOT))
    assert isinstance(item, LogItem)
    assert not item.static
    pinholes = [a for a in item.archetypes if isinstance(a, rr.Pinhole)]
    frames = [a for a in item.archetypes if isinstance(a, rr.CoordinateFrame)]
    assert len(pinholes) == 1
    assert len(pinholes) + len(frames) == len(item.archetypes)
    return item.path, pinholes[0], [name for f in frames for name in pylist(f.frame)]


def intrinsics(pinhole: rr.Pinhole) -> npt.NDArray[np.float64]:
    """image_from_camera as the row-major 3x3 K (Rerun stores it column-major)."""
    (column_major,) = pylist(pinhole.image_from_camera)
    matrix: npt.NDArray[np.float64] = np.reshape(column_major, (3, 3), order="F")
    return matrix


def test_pinhole_is_logged_at_the_camera_namespace_above_its_images() -> None:
    path, pinhole, frames = pinhole_item(camera_info())
    assert path == f"/{ROBOT}/camera"
    np.testing.assert_allclose(intrinsics(pinhole), K_640.reshape(3, 3), rtol=1e-6)
    assert pylist(pinhole.resolution) == [[640.0, 480.0]]
    assert pylist(pinhole.parent_frame) == [f"{ROBOT}/camera_optical_frame"]
    # The child (image-plane) frame is the namespace's implicit frame, which the image entities
    # below it inherit: that is what puts them inside the frustum.
    assert pinhole.child_frame is None
    assert pylist(pinhole.camera_xyz) == pylist(rr.components.ViewCoordinatesBatch(rr.ViewCoordinates.RDF))
    assert frames == [f"{ROBOT}/camera_optical_frame"]
    for image_topic in ("/camera/image_raw", "/camera/image_raw/compressed", "/camera/image_rect"):
        assert make_ctx(image_topic, robot=ROBOT).entity_path.startswith(path + "/")


def test_ros1_field_names_are_read() -> None:
    humble = camera_info()
    ros1 = SimpleNamespace(
        header=humble.header,
        height=480,
        width=640,
        distortion_model="plumb_bob",
        D=humble.d,
        K=K_640,
        R=humble.r,
        P=humble.p,
        binning_x=0,
        binning_y=0,
        roi=humble.roi,
    )
    _, pinhole, _ = pinhole_item(ros1)
    np.testing.assert_allclose(intrinsics(pinhole), K_640.reshape(3, 3), rtol=1e-6)
    assert pylist(pinhole.resolution) == [[640.0, 480.0]]


def test_uncalibrated_camera_raises_one_clear_error() -> None:
    with pytest.raises(ConvertError, match=INFO_TOPIC) as info:
        convert_camera_info(camera_info(np.zeros(9)), make_ctx(INFO_TOPIC, robot=ROBOT))
    assert "not calibrated" in str(info.value)


def test_roi_and_binning_give_the_published_image_geometry() -> None:
    msg = camera_info(binning=(2, 2), roi=(100, 40, 400, 300))
    _, pinhole, _ = pinhole_item(msg)
    expected = np.array([[262.5, 0.0, 109.75], [0.0, 263.0, 99.75], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(intrinsics(pinhole), expected, rtol=1e-6)
    assert pylist(pinhole.resolution) == [[200.0, 150.0]]


def test_frameless_and_sizeless_camera_info() -> None:
    _, pinhole, frames = pinhole_item(camera_info(frame_id="", width=0, height=0))
    assert pinhole.parent_frame is None
    assert frames == []
    assert pinhole.resolution is None
    np.testing.assert_allclose(intrinsics(pinhole), K_640.reshape(3, 3), rtol=1e-6)


def test_camera_info_without_namespace_stays_on_its_own_entity() -> None:
    path, _, _ = pinhole_item(camera_info(), topic="/camera_info")
    assert path == f"/{ROBOT}/camera_info"


def test_real_ros1_camera_info_matches_its_image(shared_data: Path) -> None:
    bag = shared_data / "raspicam_aruco_ubiquity/aruco_images.bag"
    topic = "/raspicam_node/camera_info"
    msg = first_message(bag, topic)
    assert not hasattr(msg, "k")  # the bag's own ROS 1 definition: upper-case matrices
    path, pinhole, frames = pinhole_item(msg, topic)
    assert path == f"/{ROBOT}/raspicam_node"
    np.testing.assert_allclose(intrinsics(pinhole), np.asarray(msg.K).reshape(3, 3), rtol=1e-6)
    assert intrinsics(pinhole)[0, 0] == pytest.approx(1014.3431, rel=1e-6)
    assert pylist(pinhole.resolution) == [[1280.0, 960.0]]
    assert pylist(pinhole.parent_frame) == [f"{ROBOT}/raspicam"] == frames
    image_entity = make_ctx("/raspicam_node/image/compressed", robot=ROBOT).entity_path
    assert image_entity.startswith(path + "/")
