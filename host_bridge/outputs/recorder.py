"""``--record-mcap``: every raw CDR message the host receives, into a standard ROS 2 MCAP file.

The file follows the MCAP ``ros2`` profile exactly as rosbag2's MCAP storage plugin writes it
(message encoding ``cdr``, schema name = full ROS type, schema encoding ``ros2msg`` or
``ros2idl`` with the definition text the source sent), so ``ros2 bag``, Foxglove and
``rerun mcap convert`` read it. Payloads are written byte for byte as the host received them
(after undoing wire compression): nothing is decoded or re-serialised.

Written with Foxglove's reference ``mcap`` library (pure Python, zstd chunks, summary and
indexes, CRCs): rosbags' writer would produce a rosbag2 directory (metadata.yaml + file) and
wants every type registered in a typestore, while a bare MCAP only needs the definition text
the catalog already carries.

Topic names: when the recording may hold several robots (live input whose ``--robots`` is not
one name, a ``--demo`` of several robots), each channel is named ``/<robot><topic>``
(``/tb3/scan``), which is also the robot's Rerun entity path: ``ros2 bag play`` and ``rerun mcap
convert`` read channels by name, and would merge two robots' ``/scan``. A recording of one robot
by construction (``--bag``, ``--robots`` naming a single robot, a one-robot ``--demo``) keeps the
ROS names. Every channel carries ``swanky.robot`` and ``swanky.topic`` metadata either way.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO, Protocol

from host_bridge.errors import RecorderError
from robot_relay.wire import ROBOT_NAME_PATTERN, MessageDefinition, RawMessage

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

log = logging.getLogger("swanky.host")

PROFILE = "ros2"
MESSAGE_ENCODING = "cdr"


class RawOutput(Protocol):
    """An output of the raw messages themselves, before decoding: a dispatcher tap closed when
    the host ends (the MCAP recorder, the ``/_stats`` tap). Called from each robot's thread."""

    def __call__(self, batch: Sequence[RawMessage]) -> None: ...

    def close(self) -> None: ...


def may_hold_several_robots(*, bag: bool, demo_robots: int | None, robots: str) -> bool:
    """Whether the input may bring more than one robot: a demo of ``demo_robots`` (None: no
    demo) when it has several, live input when its ``robots`` key chunk is not a single name.
    With a demo, ``robots`` is the robot count, not a name, and is not read here."""
    if bag:
        return False
    if demo_robots is not None:
        return demo_robots > 1
    return ROBOT_NAME_PATTERN.match(robots) is None


def channel_topic(robot: str, topic: str, prefix_robot: bool) -> str:
    return f"/{robot}{topic}" if prefix_robot else topic


def mcap_times(raw: RawMessage) -> tuple[int, int]:
    """(log_time, publish_time): relay receive time and source/bag time, each standing in for
    the other when only one is known (a bag converted offline has no receive time)."""
    receive = raw.receive_ns if raw.receive_ns is not None else raw.log_ns
    source = raw.log_ns if raw.log_ns is not None else receive
    return receive or 0, source or 0


class McapRecorder:
    """Appends RawMessage runs to one MCAP file; ``close`` writes its summary and index."""

    def __init__(self, path: Path, *, prefix_robot: bool) -> None:
        self.path = path
        self.prefix_robot = prefix_robot
        self.written = 0
        try:
            self._file: BinaryIO = path.open("wb")
        except OSError as err:
            msg = f"--record-mcap {path}: cannot write: {err.strerror}"
            raise RecorderError(msg) from err
        # Imported here: every host imports this module, few record (18 ms of each start-up).
        from mcap.writer import CompressionType, Writer

        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="swanky")
        self._schemas: dict[tuple[str, MessageDefinition | None], int] = {}
        self._channels: dict[tuple[str, str, str, MessageDefinition | None], int] = {}
        self._sequences: dict[int, int] = {}
        self._fallback: Typestore | None = None
        self._closed = False
        # Live robots are dispatched from one thread each; the MCAP writer is not thread-safe.
        self._lock = threading.Lock()

    def __call__(self, batch: Sequence[RawMessage]) -> None:
        """A dispatcher tap: record the run before it is decoded."""
        with self._lock:
            if self._closed:
                return
            for raw in batch:
                self._write(raw)

    def _write(self, raw: RawMessage) -> None:
        channel = self._channel(raw)
        log_time, publish_time = mcap_times(raw)
        sequence = raw.sequence if raw.sequence is not None else self._sequences.get(channel, 0)
        self._sequences[channel] = sequence + 1
        self._writer.add_message(
            channel, log_time=log_time, publish_time=publish_time, data=bytes(raw.data),
            sequence=sequence & 0xFFFFFFFF,
        )
        self.written += 1

    def _channel(self, raw: RawMessage) -> int:
        key = (raw.robot, raw.topic, raw.msgtype, raw.definition)
        channel = self._channels.get(key)
        if channel is None:
            channel = self._channels[key] = self._writer.register_channel(
                topic=channel_topic(raw.robot, raw.topic, self.prefix_robot),
                message_encoding=MESSAGE_ENCODING,
                schema_id=self._schema(raw.msgtype, raw.definition),
                metadata={"swanky.robot": raw.robot, "swanky.topic": raw.topic},
            )
        return channel

    def _schema(self, msgtype: str, definition: MessageDefinition | None) -> int:
        key = (msgtype, definition)
        schema = self._schemas.get(key)
        if schema is None:
            if definition is None:
                definition = self._bundled_definition(msgtype)
            schema = self._schemas[key] = self._writer.register_schema(
                name=msgtype, encoding=definition.encoding, data=definition.text.encode()
            )
        return schema

    def _bundled_definition(self, msgtype: str) -> MessageDefinition:
        """The source sent no definition (no catalog yet): the one the host decodes with."""
        from host_bridge.core.schemas import base_typestore

        if self._fallback is None:
            self._fallback = base_typestore()
        try:
            text = self._fallback.generate_msgdef(msgtype, ros_version=2)[0]
        except Exception:
            log.warning(
                "--record-mcap: no definition for %s; its channel is recorded with an empty "
                "schema (bytes kept, readers cannot decode it)", msgtype,
            )
            text = ""
        return MessageDefinition("ros2msg", text)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._writer.finish()  # type: ignore[no-untyped-call]
            self._file.close()
        log.info("recorded %d messages to %s", self.written, self.path)
