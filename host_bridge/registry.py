"""The type -> converter map.

The registry is assembled explicitly in :func:`default_registry` from each converter module's
``CONVERTERS`` mapping; nothing registers itself on import, and a type registered twice is an
error. The contract converters follow is :mod:`host_bridge.contract`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from host_bridge.contract import ConverterSpec, combine
from host_bridge.errors import RegistryError


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
