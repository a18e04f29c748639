"""How each topic is forwarded: rate cap, Zenoh priority, congestion control, compression.

Three layers, the later winning field by field: built-in defaults by message type and QoS, the
relay config's ``defaults``, then the one most specific ``policy`` entry matching the topic
(an exact name beats a glob, then fewer wildcards, then the longer glob:
:func:`robot_relay.configfile.first_match`). Entries do not merge with each other; a key an
entry leaves out comes from ``defaults`` and then the built-ins.

Built-ins, by message type (:data:`TRAFFIC`): transforms and laser scans go first
(``data_high``), images, point clouds and video last (``data_low``); sensor streams drop under
congestion (a stale scan is worth nothing), and so do best-effort topics of other types, while
reliable and latched ones block. Video blocks whatever its QoS: a lost frame spoils the picture
until the next keyframe. Latched topics are never rate-capped, whatever the config says: a
latched topic is state (static transforms from several broadcasters, the map) and keeping only
the newest message would lose part of it.

Pure: no Zenoh, no threads, no clock. The relay maps names to Zenoh enums and owns the timing.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, Generic, Literal, TypeVar

from robot_relay.configfile import first_match
from robot_relay.wire import QosProfile

# Zenoh's priorities, highest first (zenoh.Priority member names in lower case).
PRIORITIES = (
    "real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low", "background",
)

Congestion = Literal["drop", "block"]
Compression = Literal["none", "lz4", "zstd"]


@dataclass(frozen=True, slots=True)
class TrafficClass:
    """A type's built-in share of the link. ``congestion`` None: as the QoS says (best-effort
    drops, reliable blocks); latched topics always block (they are state)."""

    priority: str
    congestion: Congestion | None = None


DEFAULT_TRAFFIC = TrafficClass("data")
FRAMES = TrafficClass("data_high")
SCANS = TrafficClass("data_high", "drop")
BULK = TrafficClass("data_low", "drop")
SENSOR = TrafficClass("data", "drop")
VIDEO = TrafficClass("data_low", "block")

# The types forwarded other than DEFAULT_TRAFFIC: a copy of the traffic column of the host's type
# table (host_bridge/table/registry.py), which the robot does not have; tests/host_bridge/test_registry.py
# checks the two agree.
TRAFFIC: Mapping[str, TrafficClass] = {
    "tf2_msgs/msg/TFMessage": FRAMES,
    "sensor_msgs/msg/LaserScan": SCANS,
    "sensor_msgs/msg/Image": BULK,
    "sensor_msgs/msg/CompressedImage": BULK,
    "sensor_msgs/msg/PointCloud2": BULK,
    "sensor_msgs/msg/PointCloud": BULK,
    "foxglove_msgs/msg/CompressedVideo": VIDEO,
    "sensor_msgs/msg/Imu": SENSOR,
    "sensor_msgs/msg/MagneticField": SENSOR,
    "sensor_msgs/msg/Range": SENSOR,
    "sensor_msgs/msg/CameraInfo": SENSOR,
}


@dataclass(frozen=True, slots=True)
class Policy:
    """``max_rate`` in Hz (None: every message), a name of :data:`PRIORITIES`."""

    max_rate: float | None = None
    priority: str = "data"
    congestion: Congestion = "block"
    compression: Compression = "none"


POLICY_KEYS = frozenset(f.name for f in fields(Policy))


def builtin_policy(msgtype: str, qos: QosProfile) -> Policy:
    traffic = TRAFFIC.get(msgtype, DEFAULT_TRAFFIC)
    congestion: Congestion = traffic.congestion or (
        "drop" if qos.reliability == "best_effort" else "block"
    )
    if qos.durability == "transient_local":
        congestion = "block"
    return Policy(priority=traffic.priority, congestion=congestion)


@dataclass(frozen=True, slots=True)
class PolicyTable:
    """The ``defaults`` and ``policy`` sections of a relay config (already schema-checked)."""

    defaults: Mapping[str, Any] = field(default_factory=dict)
    topics: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def entry(self, topic: str) -> str | None:
        """The glob (or exact name) of ``policy`` that applies to ``topic``."""
        return first_match(list(self.topics), topic)

    def resolve(self, topic: str, msgtype: str, qos: QosProfile) -> Policy:
        glob = self.entry(topic)
        chosen = {**self.defaults, **(self.topics[glob] if glob is not None else {})}
        policy = replace(builtin_policy(msgtype, qos), **{k: chosen[k] for k in POLICY_KEYS & chosen.keys()})
        if qos.durability == "transient_local":
            policy = replace(policy, max_rate=None)
        return policy


T = TypeVar("T")


class RateLimiter(Generic[T]):
    """Keep-latest rate cap: at most one item per ``1 / max_rate`` seconds, always the newest.

    An item arriving inside the period waits (replacing, and so dropping, the one waiting
    before it) until the period ends; the owner asks :meth:`take_due` at :attr:`due_at`, so the
    last item of a burst goes out even when nothing follows it. Times are the caller's
    (monotonic seconds); not thread-safe, the owner holds a lock.
    """

    def __init__(self, max_rate: float) -> None:
        if max_rate <= 0:
            msg = f"max_rate must be > 0 Hz, got {max_rate}"
            raise ValueError(msg)
        self.period = 1.0 / max_rate
        self.dropped = 0
        self._last: float | None = None
        self._pending: T | None = None

    @property
    def due_at(self) -> float | None:
        """When the waiting item may go out, or None when nothing waits."""
        if self._pending is None or self._last is None:
            return None
        return self._last + self.period

    def offer(self, item: T, now: float) -> T | None:
        """``item`` if it may go out now; otherwise it waits and None is returned."""
        if self._last is None or now - self._last >= self.period:
            if self._pending is not None:  # its flush came late: the new item is newer
                self.dropped += 1
                self._pending = None
            self._last = now
            return item
        if self._pending is not None:
            self.dropped += 1
        self._pending = item
        return None

    def take_due(self, now: float) -> T | None:
        """The waiting item once its time has come (None before, or when nothing waits)."""
        due = self.due_at
        if due is None or now < due:
            return None
        item, self._pending = self._pending, None
        self._last = now
        return item

    def take_any(self) -> T | None:
        """The waiting item regardless of time (shutdown: the newest message is never lost)."""
        item, self._pending = self._pending, None
        return item
