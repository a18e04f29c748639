"""sensor_msgs/CameraInfo -> ``rr.Pinhole`` at the camera namespace, so images sit in its frustum.

How the pinhole and the images find each other (why this scheme):

ROS puts a camera's image topics and its ``camera_info`` side by side in one namespace
(``/camera/image_raw``, ``/camera/image_raw/compressed``, ``/camera/camera_info``);
image_transport's CameraSubscriber relies on exactly that. Rerun shows 2D content in 3D only
when it lies in the *child* (image-plane) frame of a pinhole. So the pinhole is logged at the
namespace entity (``/tb3/camera``), and every image entity below it (``/tb3/camera/image_raw``
...) keeps its implicit entity-path frame, which is connected to the namespace's implicit frame
by identity: the images are in the pinhole's image plane with no frame name to agree on. The
pinhole's ``parent_frame`` is the named ROS frame of the CameraInfo header
(``<robot>/<frame_id>``, an optical frame: x right, y down, z forward, i.e. Rerun's RDF), so TF
places the frustum in 3D; the namespace entity also gets that frame as its ``CoordinateFrame``,
as Rerun's importer does.

Rerun's own ROS importer instead names an ``<frame_id>_image_plane`` frame and points every
image at it; that breaks as soon as two cameras share an optical frame (a colour camera and the
depth image registered to it both publish CameraInfo in ``camera_color_optical_frame``), which
the namespace scheme does not, and it leaves images without a CameraInfo in a frame nothing
reaches. A CameraInfo topic without a namespace (``/camera_info``) gets its pinhole on its own
entity: putting it on the robot's root entity would turn everything else into image space.

Intrinsics follow image_geometry: K, shifted by the ROI and divided by the binning, with the
resolution of the image actually published. Distortion (D) is not modelled by Rerun's pinhole.
ROS 1 bags spell the matrices ``K D R P``; both spellings are read.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import frame_components, header_frame
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.errors import ConvertError


def pinhole_path(ctx: ConvertContext) -> str:
    """Entity of the camera namespace: the parent of the CameraInfo topic's entity."""
    if "/" not in ctx.topic.strip("/"):
        return ctx.entity_path
    return ctx.entity_path.rsplit("/", 1)[0]


def _intrinsics(msg: Any, ctx: ConvertContext) -> tuple[npt.NDArray[np.float64], int, int]:
    """K and (width, height) of the image as published (after ROI and binning)."""
    k = getattr(msg, "k", None)
    if k is None:
        k = msg.K
    matrix = np.asarray(k, dtype=np.float64).reshape(3, 3).copy()
    if not np.any(matrix):
        msg_ = (
            f"{ctx.topic}: CameraInfo K is all zeros, i.e. the camera is not calibrated; no "
            "pinhole is logged. Calibrate it (ros2 run camera_calibration cameracalibrator) or "
            "give the driver a camera_info_url"
        )
        raise ConvertError(msg_)
    width, height = int(msg.width), int(msg.height)
    roi = msg.roi
    if roi.width and roi.height:
        matrix[0, 2] -= roi.x_offset
        matrix[1, 2] -= roi.y_offset
        width, height = int(roi.width), int(roi.height)
    binning_x, binning_y = max(int(msg.binning_x), 1), max(int(msg.binning_y), 1)
    matrix[0] /= binning_x
    matrix[1] /= binning_y
    return matrix, width // binning_x, height // binning_y


def convert_camera_info(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    matrix, width, height = _intrinsics(msg, ctx)
    frame = header_frame(msg, ctx)
    pinhole = rr.Pinhole(
        image_from_camera=matrix,
        # Drivers that do not know their size publish 0x0; the frustum then has no extent.
        resolution=[width, height] if width and height else None,
        camera_xyz=rr.ViewCoordinates.RDF,
        parent_frame=frame,
    )
    return [LogItem(pinhole_path(ctx), (pinhole, *frame_components(frame)))]


SPEC = per_message(convert_camera_info)
