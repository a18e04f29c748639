"""rmw_zenoh's keys, liveliness tokens and attachments (Humble 0.1.x, Jazzy and later), which
the host reads directly from robots without a relay (schemas/wire.md, "rmw_zenoh robots").

Not Swanky's format but rmw_zenoh's, and only the host reads it, so it lives here rather than in
the relay's wire module (which a robot runs). Every ROS message is raw CDR (encapsulation header
included) on ``<domain>/<topic>/<dds type>/<type hash>``, with the type hash
``TypeHashNotSupported`` on Humble and ``RIHS01_<sha256>`` from Jazzy on. The graph is a set of
liveliness tokens ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/
<node>`` followed, for publishers (kind ``MP``), by ``/<topic>/<dds type>/<type hash>/<qos>``;
names are mangled (``/`` -> ``%``). The attachment holds the sequence number, the source
timestamp and the publisher gid.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from host_bridge.errors import GraphError
from robot_relay.wire import QosProfile

RMW_LIVELINESS_PREFIX = "@ros2_lv"
RMW_TYPE_HASH_NOT_SUPPORTED = "TypeHashNotSupported"
RMW_NODE = "NN"
RMW_PUBLISHER = "MP"

_I64 = struct.Struct("<q")
_GID_SIZE = 16


def rmw_data_selector(domain: int) -> str:
    """Key expression matching every rmw_zenoh data sample of a ROS domain."""
    return f"{domain}/**"


def rmw_liveliness_selector(domain: int) -> str:
    """Key expression matching every rmw_zenoh liveliness token (the graph) of a ROS domain."""
    return f"{RMW_LIVELINESS_PREFIX}/{domain}/**"


@dataclass(frozen=True, slots=True)
class RmwDataKey:
    domain: int
    topic: str
    msgtype: str
    type_hash: str | None  # None: Humble's TypeHashNotSupported


@dataclass(frozen=True, slots=True)
class RmwGraphEntity:
    """One liveliness token: a node (``NN``) or an endpoint (``MP``, ``MS``, ``SS``, ``SC``)."""

    domain: int
    session: str
    node_id: str
    entity_id: str
    kind: str
    namespace: str
    node: str
    topic: str | None = None
    msgtype: str | None = None
    type_hash: str | None = None
    qos: QosProfile | None = None


@dataclass(frozen=True, slots=True)
class RmwAttachment:
    sequence: int
    source_ns: int
    gid: bytes


def rmw_demangle(name: str) -> str:
    """rmw_zenoh writes ``/`` as ``%`` inside one key chunk (``%tb3%scan`` -> ``/tb3/scan``)."""
    return name.replace("%", "/")


def rmw_ros_type(dds_type: str) -> str:
    """``sensor_msgs::msg::dds_::LaserScan_`` -> ``sensor_msgs/msg/LaserScan``."""
    parts = dds_type.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        msg = f"type {dds_type!r} is not an rmw_zenoh type name (<pkg>::msg::dds_::<Name>_)"
        raise GraphError(msg)
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _rmw_type_hash(text: str) -> str | None:
    return None if text == RMW_TYPE_HASH_NOT_SUPPORTED else text


def _is_number(text: str) -> bool:
    # ASCII only: str.isdigit() also holds for '²', which int() refuses.
    return text.isascii() and text.isdigit()


def parse_rmw_data_key(key: str) -> RmwDataKey:
    """``0/tb3/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_...`` -> its parts."""
    parts = key.split("/")
    if len(parts) < 4 or not _is_number(parts[0]):
        msg = f"key {key!r} is not an rmw_zenoh data key (<domain>/<topic>/<type>/<hash>)"
        raise GraphError(msg)
    try:
        msgtype = rmw_ros_type(parts[-2])
    except GraphError as err:
        msg = f"key {key!r}: {err}"
        raise GraphError(msg) from err
    return RmwDataKey(int(parts[0]), "/" + "/".join(parts[1:-2]), msgtype, _rmw_type_hash(parts[-1]))


def parse_rmw_qos(text: str) -> QosProfile:
    """The reliability, durability and depth of an rmw_zenoh QoS chunk; empty fields are the
    rmw defaults (reliable, volatile, depth 10)."""
    fields = text.split(":")
    if len(fields) < 3:
        msg = f"QoS {text!r} is not an rmw_zenoh QoS string (<rel>:<dur>:<hist>,<depth>:...)"
        raise GraphError(msg)
    _, _, depth = fields[2].partition(",")
    if depth and not _is_number(depth):
        msg = f"QoS {text!r}: history depth {depth!r} is not a number"
        raise GraphError(msg)
    return QosProfile(
        reliability="best_effort" if fields[0] == "2" else "reliable",
        durability="transient_local" if fields[1] == "1" else "volatile",
        depth=int(depth) if depth else 10,
    )


def parse_rmw_token(key: str) -> RmwGraphEntity:
    """A liveliness token key -> the node or endpoint it announces."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != RMW_LIVELINESS_PREFIX or not _is_number(parts[1]):
        msg = (
            f"liveliness token {key!r} is not an rmw_zenoh one ({RMW_LIVELINESS_PREFIX}/<domain>/"
            "<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>[/<topic>/<type>/"
            "<hash>/<qos>])"
        )
        raise GraphError(msg)
    entity = RmwGraphEntity(
        domain=int(parts[1]), session=parts[2], node_id=parts[3], entity_id=parts[4],
        kind=parts[5], namespace=rmw_demangle(parts[7]), node=rmw_demangle(parts[8]),
    )
    if parts[5] == RMW_NODE:
        return entity
    if len(parts) < 13:
        msg = f"liveliness token {key!r} of a {parts[5]} lacks <topic>/<type>/<hash>/<qos>"
        raise GraphError(msg)
    try:
        msgtype = rmw_ros_type(parts[10])
        qos = parse_rmw_qos(parts[12])
    except GraphError as err:
        msg = f"liveliness token {key!r}: {err}"
        raise GraphError(msg) from err
    return RmwGraphEntity(
        domain=entity.domain, session=entity.session, node_id=entity.node_id,
        entity_id=entity.entity_id, kind=entity.kind, namespace=entity.namespace,
        node=entity.node, topic=rmw_demangle(parts[9]), msgtype=msgtype,
        type_hash=_rmw_type_hash(parts[11]), qos=qos,
    )


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """zenoh-ext's LEB128 length prefix."""
    value = shift = 0
    while pos < len(data):
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7
    raise IndexError("truncated length")


def parse_rmw_attachment(data: bytes, key: str) -> RmwAttachment:
    """The publisher attachment, in either form rmw_zenoh has used: zenoh-ext serialized
    ``"sequence_number", i64, "source_timestamp", i64, "source_gid", gid`` (rmw_zenoh Humble
    and Jazzy releases) or the same without the names (ros-z, zenoh-ros2-sdk). The gid is 16
    bytes, with or without its length prefix."""
    pos = 0

    def label(name: bytes) -> None:
        nonlocal pos
        length, start = _varint(data, pos)
        if data[start:start + length] != name:
            raise ValueError(f"expected {name.decode()!r}")
        pos = start + length

    def int64() -> int:
        nonlocal pos
        (value,) = _I64.unpack_from(data, pos)
        pos += _I64.size
        return int(value)

    keyed = data.startswith(b"\x0fsequence_number")
    try:
        if keyed:
            label(b"sequence_number")
        sequence = int64()
        if keyed:
            label(b"source_timestamp")
        source_ns = int64()
        if keyed:
            label(b"source_gid")
        if len(data) - pos != _GID_SIZE:
            length, pos = _varint(data, pos)
            if length != len(data) - pos:
                raise ValueError(f"gid of {length} bytes in {len(data) - pos}")
        gid = data[pos:]
    except (ValueError, IndexError, struct.error) as err:
        msg = f"attachment on {key!r} ({len(data)} bytes) is not an rmw_zenoh attachment: {err}"
        raise GraphError(msg) from err
    return RmwAttachment(sequence, source_ns, gid)
