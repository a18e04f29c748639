"""vision_msgs detections -> Rerun boxes, labelled with their best hypothesis.

2D boxes are in pixels and are logged at the topic entity with no frame: to draw them over an
image, map the detection topic under the camera's image entity in the host config so both
share the image's 2D space. 3D boxes are in metres in the header frame, which the entity gets
as its ``CoordinateFrame``.

Labels read ``"<class_id> <score>"`` of the best-scoring hypothesis. Class ids give each class
a stable colour: numeric ids are used as they are, names get a per-topic number in first-seen
order. ``Boxes2D`` is axis aligned, so a 2D box's ``theta`` is not drawn.

Both vision_msgs layouts decode: 4.x (ROS 2 Humble: ``center.position.x``,
``results[i].hypothesis.class_id``) and the older one of ROS 1 and Foxy (``center.x``,
``results[i].id``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.converters._common import frame_components, xyz, xyzw
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message

_MAX_CLASS_ID = 0xFFFF  # Rerun class ids are u16


def _hypothesis(result: Any) -> tuple[str, float]:
    hypothesis = getattr(result, "hypothesis", result)  # pre-4.x keeps class and score inline
    class_id = getattr(hypothesis, "class_id", None)
    return str(hypothesis.id if class_id is None else class_id), float(hypothesis.score)


@dataclass(slots=True)
class _ClassNumbers:
    """Per topic: the class id given to each class name that is not a number, in order seen."""

    by_name: dict[str, int] = field(default_factory=dict)


def _class_number(class_id: str, ctx: ConvertContext) -> int:
    if class_id.isdecimal() and int(class_id) <= _MAX_CLASS_ID:
        return int(class_id)
    names = ctx.state(_ClassNumbers).by_name
    return names.setdefault(class_id, len(names))


def _labels(detections: Sequence[Any], ctx: ConvertContext) -> tuple[list[str], list[int]]:
    """Label per detection, and class ids (none at all when a detection has no hypothesis,
    since class ids must pair with every box)."""
    best = [max(map(_hypothesis, d.results), key=lambda h: h[1], default=None)
            for d in detections]
    labels = ["" if b is None else f"{b[0]} {b[1]:.2f}" for b in best]
    if any(b is None for b in best):
        return labels, []
    return labels, [_class_number(b[0], ctx) for b in best if b is not None]


def _center2d(center: Any) -> tuple[float, float]:
    position = getattr(center, "position", center)  # 4.x nests x/y in a Point2D
    return float(position.x), float(position.y)


def _boxes2d(detections: Sequence[Any], ctx: ConvertContext) -> list[LogEntry]:
    centers = np.array([_center2d(d.bbox.center) for d in detections]).reshape(-1, 2)
    sizes = np.array([(d.bbox.size_x, d.bbox.size_y) for d in detections],
                     dtype=np.float64).reshape(-1, 2)
    labels, class_ids = _labels(detections, ctx)
    boxes = rr.Boxes2D.from_fields(clear_unset=True, centers=centers, half_sizes=sizes / 2,
                                   labels=labels, class_ids=class_ids)
    return [LogItem(ctx.entity_path, (boxes,))]


def _boxes3d(detections: Sequence[Any], frame_id: str, ctx: ConvertContext) -> list[LogEntry]:
    centers = np.array([xyz(d.bbox.center.position) for d in detections]).reshape(-1, 3)
    sizes = np.array([xyz(d.bbox.size) for d in detections]).reshape(-1, 3)
    quaternions = np.array([xyzw(d.bbox.center.orientation) for d in detections]).reshape(-1, 4)
    labels, class_ids = _labels(detections, ctx)
    boxes = rr.Boxes3D.from_fields(clear_unset=True, centers=centers, half_sizes=sizes / 2,
                                   quaternions=quaternions, labels=labels, class_ids=class_ids)
    return [LogItem(ctx.entity_path, (boxes, *frame_components(ctx.frame(frame_id))))]


def convert_detection2d_array(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return _boxes2d(msg.detections, ctx)


def convert_detection2d(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return _boxes2d([msg], ctx)


def convert_detection3d_array(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return _boxes3d(msg.detections, msg.header.frame_id, ctx)


def convert_detection3d(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return _boxes3d([msg], msg.header.frame_id, ctx)


DETECTION_2D_ARRAY = per_message(convert_detection2d_array)
DETECTION_2D = per_message(convert_detection2d)
DETECTION_3D_ARRAY = per_message(convert_detection3d_array)
DETECTION_3D = per_message(convert_detection3d)
