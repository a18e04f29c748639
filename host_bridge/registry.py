"""Converter protocol, log items, the per-message context, and the type -> converter map.

A converter is a pure function ``(msg, ctx) -> list[LogEntry]``: it never calls ``rr.log``; the
sink does. Converters of high-rate small types may also offer a run form that turns many
messages of one topic into columns for ``rr.send_columns``.

The registry is assembled explicitly in :func:`default_registry` from each converter module's
``CONVERTERS`` mapping; nothing registers itself on import, and a type registered twice is an
error.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.errors import ConvertError, PartialConvertError, RegistryError

TIMELINE_ROS = "ros_time"
TIMELINE_RECEIVE = "receive_time"
TIMELINE_LOG = "log_time"


@dataclass(frozen=True, slots=True)
class LogItem:
    """Archetypes to log at one entity path.

    ``times`` replaces the message's timeline values for this item (a TF message carries one
    stamp per transform); ``None`` keeps them. Static items ignore times.
    """

    path: str
    archetypes: tuple[rr.AsComponents, ...]
    static: bool = False
    times: Mapping[str, int] | None = None


@dataclass(frozen=True, slots=True)
class ColumnsItem:
    """Rows for ``rr.send_columns``: one row per entry of each ``times`` array (int64 ns)."""

    path: str
    columns: Iterable[Any]
    times: Mapping[str, npt.NDArray[np.int64]]


LogEntry = LogItem | ColumnsItem


@dataclass(frozen=True, slots=True)
class ConvertContext:
    """What a converter may know beyond the message itself.

    ``state`` is per-topic scratch the dispatcher keeps between messages (odometry trails,
    the last map a grid update patches); ``robot_state`` is shared by all topics of one robot
    (the URDF that /joint_states moves). They are the only things a converter may mutate.
    """

    robot: str
    topic: str
    entity_path: str
    times: Mapping[str, int]
    options: Mapping[str, Any] = field(default_factory=dict)
    state: dict[str, Any] = field(default_factory=dict)
    robot_state: dict[str, Any] = field(default_factory=dict)

    def frame(self, frame_id: str) -> str | None:
        """Rerun frame name of a ROS frame: ``<robot>/<frame_id>``; None for an empty id."""
        frame_id = frame_id.strip("/")
        return f"{self.robot}/{frame_id}" if frame_id else None

    def child_path(self, *parts: str) -> str:
        return "/".join([self.entity_path, *parts])


Converter = Callable[[Any, ConvertContext], list[LogEntry]]
RunConverter = Callable[[Sequence[Any], Sequence[ConvertContext]], list[LogEntry]]


@dataclass(frozen=True, slots=True)
class ConverterSpec:
    convert: Converter
    convert_run: RunConverter | None = None


def combine(*specs: ConverterSpec) -> ConverterSpec:
    """One spec running several converters on the same message (JointState: the robot's
    kinematics and the joint plots); a part that fails does not cost the others' output."""

    def gather(parts: Sequence[Callable[[], list[LogEntry]]]) -> list[LogEntry]:
        entries: list[LogEntry] = []
        errors: list[ConvertError] = []
        for part in parts:
            try:
                entries.extend(part())
            except PartialConvertError as err:
                entries.extend(err.items)
                errors.append(err)
            except ConvertError as err:
                errors.append(err)
        if errors:
            raise PartialConvertError("; ".join(str(e) for e in errors), entries)
        return entries

    def convert(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
        return gather([lambda s=s: s.convert(msg, ctx) for s in specs])  # type: ignore[misc]

    def convert_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
        def run_of(spec: ConverterSpec) -> list[LogEntry]:
            if spec.convert_run is not None:
                return spec.convert_run(msgs, ctxs)
            return [e for m, c in zip(msgs, ctxs, strict=True) for e in spec.convert(m, c)]

        return gather([lambda s=s: run_of(s) for s in specs])  # type: ignore[misc]

    return ConverterSpec(convert, convert_run)


class Registry:
    """Map from full ROS type name (``sensor_msgs/msg/LaserScan``) to its converter."""

    def __init__(self, fallback: ConverterSpec) -> None:
        self._fallback = fallback
        self._specs: dict[str, ConverterSpec] = {}
        self._topic_specs: list[tuple[str, Callable[[str], bool], ConverterSpec]] = []
        self._families: list[tuple[Callable[[str], bool], ConverterSpec]] = []

    def add(self, msgtype: str, spec: ConverterSpec) -> None:
        if msgtype in self._specs:
            msg = f"type {msgtype!r} is registered twice; each type has exactly one converter"
            raise RegistryError(msg)
        self._specs[msgtype] = spec

    def add_all(self, specs: Mapping[str, ConverterSpec]) -> None:
        for msgtype, spec in specs.items():
            self.add(msgtype, spec)

    def add_for_topics(
        self, msgtype: str, topics: Callable[[str], bool], spec: ConverterSpec
    ) -> None:
        """A converter for some topics of a type only (/robot_description is a String)."""
        self._topic_specs.append((msgtype, topics, spec))

    def add_family(self, accepts: Callable[[str], bool], spec: ConverterSpec) -> None:
        """A converter for every type a naming rule accepts, after the exact types (service
        events are ``<pkg>/srv/<Name>_Event``, one type per service)."""
        self._families.append((accepts, spec))

    def get(self, msgtype: str, topic: str = "") -> ConverterSpec:
        for special_type, accepts, spec in self._topic_specs:
            if special_type == msgtype and accepts(topic):
                return spec
        if msgtype in self._specs:
            return self._specs[msgtype]
        family = next((spec for accepts, spec in self._families if accepts(msgtype)), None)
        return family or self._fallback

    def types(self) -> list[str]:
        return sorted(self._specs)


def default_registry() -> Registry:
    from host_bridge.converters import (
        camera,
        diagnostics,
        generic,
        geo,
        geometry,
        images,
        imu,
        joints,
        laser,
        logs,
        markers,
        nav,
        occupancy,
        odometry,
        pointcloud,
        proximity,
        scalars,
        services,
        tf,
        urdf,
        video,
        vision,
    )
    from host_bridge.decode import is_service_event_type

    registry = Registry(generic.SPEC)
    plots = dict(scalars.CONVERTERS)
    kinematics = dict(joints.CONVERTERS)
    joint_state = "sensor_msgs/msg/JointState"
    registry.add(joint_state, combine(kinematics.pop(joint_state), plots.pop(joint_state)))
    registry.add_all(plots)
    registry.add_all(kinematics)
    for module in (tf, laser, odometry, pointcloud, imu, geo, proximity, markers, vision, images,
                   camera, geometry, nav, logs, diagnostics, video):
        registry.add_all(module.CONVERTERS)
    registry.add_for_topics("std_msgs/msg/String", urdf.is_robot_description, urdf.SPEC)
    registry.add_all(occupancy.CONVERTERS)
    registry.add_all(occupancy.COSTMAP_CONVERTERS)
    registry.add_family(is_service_event_type, services.SPEC)
    return registry


def slow_converters() -> dict[str, ConverterSpec]:
    """Converters too heavy for the receive path (wall meshes from a 4000x4000 map): the
    dispatcher runs them after the fast ones, in a worker that keeps only the latest message."""
    from host_bridge.converters import walls

    return dict(walls.SLOW_CONVERTERS)
