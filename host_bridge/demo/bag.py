"""The demo run recorded as a real rosbag2 directory (MCAP or sqlite3), which a relay replays as
it would a recording of a real robot."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Literal

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer

from host_bridge.demo.messages import TOPICS, simulate, typestore
from host_bridge.errors import InputError


def _qos(durability: QosDurability) -> Qos:
    """What rosbag2 records for a reliable publisher with default deadline and liveliness."""
    infinite = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)
    return Qos(
        history=QosHistory.UNKNOWN,
        depth=0,
        reliability=QosReliability.RELIABLE,
        durability=durability,
        deadline=infinite,
        lifespan=infinite,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=infinite,
        avoid_ros_namespace_conventions=False,
    )


_STORAGE = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


class _AbandonedError(Exception):
    """Leaves the Writer's block, which then aborts the bag instead of closing it."""


def write_demo_bag(
    path: Path,
    duration_s: float = 20.0,
    *,
    storage: Literal["mcap", "sqlite3"] = "mcap",
    route_offset: float = 0.0,
    stop: threading.Event | None = None,
) -> Path:
    """Record ``simulate(duration_s)`` as a rosbag2 directory at ``path``; latched topics are
    offered transient_local so a relay replaying the bag caches them like a live robot's. Once
    ``stop`` is set (the host is stopping: simulating takes seconds) the bag is abandoned
    unfinished, no bag to read: closing it would cost rosbags a second of writing metadata."""
    path = Path(path)
    if path.exists():
        msg = f"demo bag target {path} exists already; remove it or choose another path"
        raise InputError(msg)

    def abandon_if_stopped() -> None:
        if stop is not None and stop.is_set():
            raise _AbandonedError

    try:
        store = typestore()
        with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=_STORAGE[storage]) as writer:
            connections = {}
            for spec in TOPICS:  # rosbags writes YAML for each: a tenth of a second in all
                abandon_if_stopped()
                durability = QosDurability.TRANSIENT_LOCAL if spec.latched else QosDurability.VOLATILE
                connections[spec.topic] = writer.add_connection(
                    spec.topic, spec.msgtype, typestore=store, offered_qos_profiles=[_qos(durability)]
                )
            for message in simulate(duration_s, route_offset=route_offset):
                abandon_if_stopped()
                writer.write(connections[message.topic], message.log_ns, message.data)
    except _AbandonedError:
        pass
    return path
