"""Raw replay of rosbag2 (sqlite3, MCAP, split, bare .mcap) and ROS 1 bags; nothing is decoded.

ROS 1 payloads are turned into CDR here with rosbags' ``ros1_to_cdr`` (a byte-level re-layout
driven by the bag's own definitions, not a decode into objects), so the wire always carries CDR
and the host has one decoding path. Like ``rosbags-convert``, it drops ``Header.seq`` (rosbags
expects the ROS 2 Header there); every other field keeps the bag's layout and names (CameraInfo
``D K R P``), and the definition sent along is generated from exactly those types.

A rosbag2 is read with rosbags' plain rosbag2 ``Reader`` (its sqlite3 files opened without
counting rows, a file recorded with ``--compression-mode file`` streamed rather than decompressed
at open: :class:`~robot_relay.sources.rosbag2.Rosbag2Reader`), not ``AnyReader``: AnyReader
parses every definition in the bag when it opens, so one it cannot parse (a Jazzy service event's
``SRV:`` text) would refuse the whole bag, and a bag without definitions (Humble's sqlite3) would
need a typestore. Forwarding raw CDR needs neither; the host decodes, topic by topic.
``swanky-host --bag`` (also its progress line) and ``swanky-relay --bag`` open bags only here.
Their messages are read from a rosbag2 whose files are all indexed MCAP by the bulk reader of
:mod:`robot_relay.sources.mcap`, or all sqlite3 by that of :mod:`robot_relay.sources.sqlite` (the
same messages in the same order, with no Python per record unpaced; a bag recorded with
``--compression-mode file`` too, as it is decompressed: :mod:`robot_relay.sources.mcap_stream`);
:meth:`BagSource.messages` reads every bag through rosbags, the reference.

Needs rosbags (``pip install ".[relay,bag]"``); the live ROS 2 source does not.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robot_relay.errors import SourceError
from robot_relay.sources.base import Outlet, SourceThread, TopicFilter
from robot_relay.sources.qos import adapted_qos
from robot_relay.sources.salvage import McapSalvage, Ros1Salvage
from robot_relay.wire import (
    Catalog,
    MessageDefinition,
    QosProfile,
    RawMessage,
    TopicInfo,
    absolute_topic,
)

if TYPE_CHECKING:  # they import numpy (rosbags brings it): opening a rosbag2 imports them
    from robot_relay.sources.mcap import McapFile
    from robot_relay.sources.sqlite import Sqlite3File

log = logging.getLogger("swanky.relay")

# Bags recorded without QoS metadata (ROS 1, old rosbag2) still have these latched in ROS.
CONVENTIONALLY_LATCHED = frozenset({"/tf_static", "/robot_description", "/map"})
ROSBAGS_MISSING = 'reading bags needs rosbags: pip install ".[relay,bag]"'
# An unpaced (or late) replay hands the relay what it read of this many messages at once,
# a run per topic: enough for a topic's bundles to fill (MAX_BUNDLE_MESSAGES, robot_relay/relay.py)
# where it shares the bag with others, yet little reading before the first is sent (12 ms in
# bulk, 60 ms record by record) ...
RUN_WINDOW = 16384
# ... and, read in bulk (an indexed MCAP), no more payload than this: a window of images or
# clouds must not hold much of the bag.
RUN_BYTES = 16 * 1024 * 1024


def _all_topics(topic: str) -> bool:
    return True


def bag_paths(path: Path) -> list[Path]:
    """The paths to open: a rosbag2 directory or .mcap/.db3 file, or ROS 1 .bag files."""
    if not path.exists():
        msg = f"bag {path} does not exist"
        raise SourceError(msg)
    if path.is_file() and path.suffix == ".zstd":
        # rosbag2's compression_mode "file" writes xxx.mcap.zstd / xxx.db3.zstd; only the
        # metadata.yaml beside it says how to decompress it.
        where = (
            f"give its bag directory {path.parent} instead"
            if (path.parent / "metadata.yaml").exists()
            else f"give the bag directory with its metadata.yaml, or decompress it (zstd -d {path})"
        )
        msg = f"{path} is one zstd-compressed file of a rosbag2 recorded with compression: {where}"
        raise SourceError(msg)
    if path.is_dir() and not (path / "metadata.yaml").exists():
        bags = sorted(path.glob("*.bag"))
        if bags:
            return bags
        msg = f"{path} is a directory without metadata.yaml and without .bag files: not a bag"
        raise SourceError(msg)
    return [path]


def _qos(connection: Any, topic: str) -> QosProfile:
    profiles = getattr(connection.ext, "offered_qos_profiles", None) or []
    if profiles:
        return adapted_qos([
            (p.reliability.name.lower(), p.durability.name.lower(), p.depth) for p in profiles
        ])
    if getattr(connection.ext, "latching", None) or topic in CONVENTIONALLY_LATCHED:
        return QosProfile(durability="transient_local", depth=1)
    return QosProfile()


def _definition(connection: Any) -> MessageDefinition | None:
    fmt = connection.msgdef.format.name
    if fmt == "MSG" and connection.msgdef.data:
        return MessageDefinition("ros2msg", connection.msgdef.data)
    if fmt == "IDL":
        return MessageDefinition("ros2idl", connection.msgdef.data)
    return None


def _ros1_conversion_store(bag_store: Any) -> Any:
    """The bag's own types, but with the ROS 2 Header, as ``ros1_to_cdr`` requires."""
    from rosbags.typesys import Stores, get_typestore

    types = dict(bag_store.fielddefs)
    humble = get_typestore(Stores.ROS2_HUMBLE)
    for name in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time"):
        types[name] = humble.fielddefs[name]
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


def _open_reader(paths: Sequence[Path], stack: ExitStack) -> Any:
    """An open rosbags reader: rosbag2's own for ROS 2 (see the module docstring), AnyReader for
    ROS 1 bags (several files merged; their definitions are always there and parse)."""
    ros1 = paths[0].suffix == ".bag"
    try:
        if ros1:  # AnyReader's import costs a rosbag2 run 6 ms it does not need
            from rosbags.highlevel import AnyReader
        else:
            from robot_relay.sources.rosbag2 import Rosbag2Reader
    except ModuleNotFoundError as err:
        msg = f"{ROSBAGS_MISSING} ({err})"
        raise SourceError(msg) from err
    try:
        if ros1:
            return stack.enter_context(AnyReader(list(paths)))
        return stack.enter_context(Rosbag2Reader(paths[0]))
    except Exception as err:
        msg = f"bag {paths[0]} cannot be opened: {err}"
        raise SourceError(msg) from err


def _mcap_files(paths: Sequence[Path]) -> list[Path]:
    """The MCAP files of a bag: a bare .mcap, or those of a rosbag2 directory."""
    if paths[0].is_dir():
        return sorted(paths[0].glob("*.mcap"))
    return [paths[0]] if paths[0].suffix == ".mcap" else []


class _SalvagedBag:
    """A damaged bag that rosbags refuses, read from its start by the salvagers of
    :mod:`~robot_relay.sources.salvage` (everything up to the damage, and the intact chunks
    after it), shaped like the rosbags reader BagSource uses. Its messages come file by file in
    file order. Subclasses fill ``connections`` and ``_connections``."""

    storage = None
    compression_mode = ""

    def __init__(self, files: Sequence[McapSalvage | Ros1Salvage], refusal: SourceError) -> None:
        self.refusal = str(refusal)
        self.files = files
        self.connections: list[Any] = []
        # (file index, the file's own connection or channel id) -> connection
        self._connections: dict[tuple[int, int], Any] = {}
        scans = [salvage.scan() for salvage in self.files]
        self.message_count = sum(count for count, _, _ in scans)
        self.start_time = min((first for count, first, _ in scans if count), default=0)
        self.end_time = max((last for count, _, last in scans if count), default=0)

    @property
    def topics(self) -> set[str]:
        return {c.topic for c in self.connections}

    def messages(self, connections: Sequence[Any]) -> Iterator[tuple[Any, int, bytes]]:
        wanted = {c.id for c in connections}
        for index, salvage in enumerate(self.files):
            for channel, log_ns, data in salvage.messages():
                connection = self._connections.get((index, channel))
                if connection is not None and connection.id in wanted:
                    yield connection, log_ns, data

    def damage(self) -> str:
        """What of the bag could not be read, file by file."""
        return "; ".join(
            f"{salvage.path.name}: {salvage.damage.describe()}"
            for salvage in self.files if salvage.damage
        )


class _SalvagedReader(_SalvagedBag):
    """A damaged MCAP bag; QoS come from the channels' metadata."""

    def __init__(self, files: Sequence[Path], refusal: SourceError) -> None:
        from rosbags.interfaces import (
            Connection,
            ConnectionExtRosbag2,
            MessageDefinitionFormat,
        )
        from rosbags.interfaces import MessageDefinition as RosbagsDefinition
        from rosbags.rosbag2.metadata import parse_qos

        salvages = [McapSalvage(path) for path in files]
        super().__init__(salvages, refusal)
        formats = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
        for index, salvage in enumerate(salvages):
            for channel in salvage.channels.values():
                schema = channel.schema
                fmt = formats.get(schema.encoding) if schema is not None else None
                try:
                    qos = parse_qos(channel.metadata.get("offered_qos_profiles", ""))
                except Exception:  # whatever a damaged YAML makes rosbags' parser raise
                    qos = []
                connection = Connection(
                    id=len(self.connections) + 1,
                    topic=channel.topic,
                    msgtype=schema.name if schema is not None else "",
                    msgdef=RosbagsDefinition(
                        fmt or MessageDefinitionFormat.NONE,
                        schema.data.decode("utf-8", errors="replace") if fmt and schema else "",
                    ),
                    digest="",
                    msgcount=0,
                    ext=ConnectionExtRosbag2("cdr", qos),
                    owner=None,
                )
                self.connections.append(connection)
                self._connections[(index, channel.id)] = connection


class _SalvagedRos1Reader(_SalvagedBag):
    """Damaged ROS 1 bags, with the typestore of their own definitions as AnyReader builds it
    (BagSource turns their payloads into CDR with it). A connection whose definition does not
    parse is left out and named with the damage."""

    def __init__(self, files: Sequence[Path], refusal: SourceError) -> None:
        from rosbags.interfaces import Connection, ConnectionExtRosbag1, MessageDefinitionFormat
        from rosbags.interfaces import MessageDefinition as RosbagsDefinition
        from rosbags.rosbag1.reader import normalize
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        from rosbags.typesys.msg import normalize_msgtype

        salvages = [Ros1Salvage(path) for path in files]
        super().__init__(salvages, refusal)
        types: dict[str, Any] = {}
        self._undefined: list[str] = []
        for index, salvage in enumerate(salvages):
            for found in salvage.connections.values():
                msgtype = normalize_msgtype(found.msgtype)
                try:
                    types.update(get_types_from_msg(found.definition, msgtype))
                except Exception as err:  # rosbags' parser on a damaged definition
                    self._undefined.append(f"{found.topic} ({found.msgtype}: {err})")
                    continue
                latching = found.latching
                connection = Connection(
                    id=len(self.connections) + 1,
                    topic=normalize(found.topic),
                    msgtype=msgtype,
                    msgdef=RosbagsDefinition(MessageDefinitionFormat.MSG, found.definition),
                    digest=found.md5sum,
                    msgcount=0,
                    ext=ConnectionExtRosbag1(
                        found.callerid, int(latching) if latching and latching.isdigit() else None
                    ),
                    owner=None,
                )
                self.connections.append(connection)
                self._connections[(index, found.id)] = connection
        self.typestore = get_typestore(Stores.EMPTY)
        self.typestore.register(types)

    def damage(self) -> str:
        lost = [super().damage()] if any(salvage.damage for salvage in self.files) else []
        if self._undefined:
            lost.append(f"topics whose definition does not parse: {', '.join(self._undefined)}")
        return "; ".join(lost)


def _open_damaged(paths: Sequence[Path], refusal: SourceError) -> _SalvagedBag:
    """The readable part of an MCAP or ROS 1 bag rosbags refuses (``refusal``, raised again
    when the bag is neither or nothing of it can be read)."""
    reader: _SalvagedBag
    if paths[0].suffix == ".bag":
        reader = _SalvagedRos1Reader(paths, refusal)
    else:
        files = _mcap_files(paths)
        if not files:
            raise refusal
        reader = _SalvagedReader(files, refusal)
    if not reader.message_count:
        msg = f"{refusal}; nothing of it can be read ({reader.damage() or 'no messages'})"
        raise SourceError(msg) from refusal
    return reader


def _storage_connections(reader: Any, wanted: Sequence[Any]) -> list[Any]:
    """The connections to ask a rosbag2 directory for, carrying each storage file's own QoS.

    rosbags hands a metadata.yaml connection only the messages of a storage connection with the
    same topic, type *and* QoS. rosbag2 writes the QoS of metadata.yaml and of the storage file
    separately, and they disagree in real bags (Foxy/Galactic wrote a default deadline as 0 in
    one and as INT_MAX in the other), which would read no message at all: match by topic and type.
    """
    storages = getattr(reader.storage, "storages", None)
    if storages is None:  # a bare .mcap/.db3 or a salvaged bag: its connections are its own
        return list(wanted)
    asked: list[Any] = []
    for connection in wanted:
        exts: list[Any] = []
        for storage in storages:
            for stored in storage.connections:
                same = stored.topic == connection.topic and stored.msgtype == connection.msgtype
                if same and stored.ext not in exts:
                    exts.append(stored.ext)
        if any(ext != connection.ext for ext in exts):
            log.debug("%s: metadata.yaml's QoS differs from the storage file's; reading by "
                      "topic and type", connection.topic)
        asked.extend(connection._replace(ext=ext) for ext in exts or [connection.ext])
    return asked


class BagSource:
    """Yields a bag's messages as RawMessages in log-time order, optionally paced.

    Opened as a context manager (``with BagSource(...) as bag: bag.messages()``), or, as the
    relay's :class:`~robot_relay.sources.base.Source`, entered once and then :meth:`start`-ed:
    it replays on its own thread until its end or :meth:`close`. Pacing waits end at ``close``.
    """

    def __init__(
        self,
        path: Path,
        robot: str,
        *,
        rate: float = 0.0,
        loop: bool = False,
        topics: TopicFilter = _all_topics,
        sleep: Callable[[float], object] | None = None,
    ) -> None:
        self.paths = bag_paths(path)
        self.robot = robot
        self.rate = rate
        self.loop = loop
        self.topics = topics
        self._closing = threading.Event()
        self._sleep = self._closing.wait if sleep is None else sleep
        self._replay: SourceThread | None = None
        self._stack = ExitStack()
        self._reader: Any = None
        self._malformed = 0
        self._ros1_store: Any = None
        self._warned: set[str] = set()
        self._bulk: list[McapFile] | list[Sqlite3File] | None = None

    def __enter__(self) -> BagSource:
        return self.open()

    def open(self) -> BagSource:
        """Open the bag and read its connections (nothing of the messages yet)."""
        try:
            self._reader = _open_reader(self.paths, self._stack)
        except SourceError as refusal:
            self._reader = _open_damaged(self.paths, refusal)
        self.is_ros1 = self.paths[0].suffix == ".bag"
        self.connections = [c for c in self._reader.connections if self.topics(c.topic)]
        if self.is_ros1:
            self._ros1_store = _ros1_conversion_store(self._reader.typestore)
            self._asked = self.connections
        else:
            self._asked = _storage_connections(self._reader, self.connections)
        self._infos = {
            c.id: TopicInfo(
                topic=absolute_topic(c.topic),
                msgtype=c.msgtype,
                definition=self._ros1_definition(c.msgtype) if self.is_ros1 else _definition(c),
                qos=_qos(c, absolute_topic(c.topic)),
            )
            for c in self.connections
        }
        self._bulk = self._open_bulk()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, outlet: Outlet) -> None:
        """Replay on a thread of its own, to the end or until :meth:`close`."""

        def replay() -> None:
            for info, payloads, log_ns in self.runs():
                if self._closing.is_set():
                    return
                outlet.publish_run(info, payloads, log_ns)

        self._replay = SourceThread("bag-replay", replay)
        self._replay.start()

    def ended(self) -> bool:
        return self._replay is not None and self._replay.ended()

    def on_demand(self, topic: str, wanted: bool) -> None:
        """A replay sends every message whoever listens."""

    def drop_counts(self) -> Mapping[str, int]:
        return {}

    def close(self) -> None:
        """Stop the replay (after the message being sent) and close the bag."""
        self._closing.set()
        if self._replay is not None:
            self._replay.join()
        self._stack.close()

    @property
    def message_count(self) -> int:
        """Messages in the whole bag, from its index or metadata (nothing is read)."""
        return int(self._reader.message_count)

    @property
    def start_ns(self) -> int:
        return int(self._reader.start_time)

    @property
    def end_ns(self) -> int:
        return int(self._reader.end_time)

    @property
    def topic_count(self) -> int:
        return len(self._reader.topics)

    def catalog(self) -> Catalog:
        unique = {(i.topic, i.msgtype): i for i in self._infos.values()}
        return Catalog(robot=self.robot, source="bag", topics=tuple(unique.values()))

    def _ros1_definition(self, msgtype: str) -> MessageDefinition:
        return MessageDefinition("ros2msg", self._ros1_store.generate_msgdef(msgtype, ros_version=2)[0])

    def _cdr(self, raw: bytes | memoryview, info: TopicInfo) -> bytes | memoryview | None:
        """CDR of a bag payload; None (warned once per topic) when a ROS 1 one is broken."""
        if not self.is_ros1:
            return raw
        try:
            return self._ros1_store.ros1_to_cdr(raw, info.msgtype)  # type: ignore[no-any-return]
        except Exception as err:
            if info.topic not in self._warned:
                self._warned.add(info.topic)
                log.warning(
                    "%s (%s): ROS 1 message does not convert to CDR, skipped: %s",
                    info.topic, info.msgtype, err,
                )
            return None

    def mcap_storages(self) -> list[tuple[Path, dict[int, TopicInfo]]] | None:
        """A rosbag2 stored as MCAP without message compression: :meth:`_storages` as each MCAP
        file's path with its channels (a bag recorded with ``--compression-mode file``: rosbags'
        decompressed copy, when the streaming reader did not take it). None for any other bag."""
        from rosbags.rosbag2.storage_mcap import McapReader

        storages = self._storages()
        if storages is None or not all(isinstance(s, McapReader) for s, _ in storages):
            return None
        return [(Path(str(storage.path)), channels) for storage, channels in storages]

    def _storages(self) -> list[tuple[Any, dict[int, TopicInfo]]] | None:
        """A rosbag2 without message compression: its storage files, as rosbags opened them, in
        the order :meth:`messages` reads them, each with the info of every connection id read
        from it, as rosbags matches them to the bag's connections. None for any other bag. A bag
        recorded with ``--compression-mode file`` gives its file as streamed (:class:`~robot_relay.
        sources.mcap_stream.StreamedMcap`), or, where the stream reader does not take it, the
        file rosbags decompressed when it opened the bag (into a temporary directory it removes
        when closed).

        For the bulk readers (:meth:`bulk_files`), which must yield what :meth:`messages`
        would."""
        if self.is_ros1 or self._reader.compression_mode == "message" or self._reader.storage is None:
            return None
        storage = self._reader.storage
        stored_files = getattr(storage, "storages", None)
        if stored_files is None:  # a bare .mcap/.db3: the file's connections are the connections
            return [(storage, {c.id: self._infos[c.id] for c in self._asked})]
        files = []
        for stored in stored_files:
            channels = {}
            for channel in stored.connections:  # rosbags' DirectoryReader.messages match
                asked = next((
                    c for c in self._asked
                    if c.topic == channel.topic and c.msgtype == channel.msgtype
                    and c.ext == channel.ext
                    and (not channel.digest or not c.digest or c.digest == channel.digest)
                ), None)
                if asked is not None:
                    channels[channel.id] = self._infos[asked.id]
            files.append((stored, channels))
        return files or None

    def log_undefined(self) -> None:
        """Say once which topics come without a message definition (Humble's sqlite3 bags)."""
        undefined = sorted({i.topic for i in self._infos.values() if i.definition is None})
        if undefined:
            log.info(
                "bag %s stores no message definitions for %s (rosbag2 stores them from Iron "
                "on): the host decodes them with its bundled ROS 2 Humble types",
                self.paths[0], ", ".join(undefined),
            )

    def messages(self) -> Iterator[RawMessage]:
        """Every message once (or forever with ``loop``), paced by ``rate`` (0: no pacing)."""
        for info, log_ns, data, due in self._timed():
            delay = due - time.monotonic()
            if delay > 0:
                self._sleep(delay)
            yield RawMessage(
                robot=self.robot,
                topic=info.topic,
                msgtype=info.msgtype,
                data=data,
                definition=info.definition,
                log_ns=log_ns,
            )

    def runs(self) -> Iterator[tuple[TopicInfo, Sequence[bytes | memoryview], list[int]]]:
        """What :meth:`messages` yields, paced alike, as runs of one topic's messages that are
        due at once: (topic, payloads, log times). A replay keeping up yields each message as
        its time comes, one a run; one behind (or unpaced) gathers every message due, up to
        RUN_WINDOW messages, into a run per topic, each topic's messages in their order: the
        relay bundles them (schemas/wire.md).

        A rosbag2 whose every file is an indexed MCAP, or every file sqlite3, is read by a bulk
        reader (:meth:`bulk_files`): unpaced, in windows with no Python per message (at most
        about RUN_BYTES of payload a window; its runs in the order of their last messages);
        paced, its records one by one as any other bag's, in the order each topic first
        appears in the window."""
        files = self.bulk_files()
        if files is None or self.rate > 0:
            yield from self._gathered(self._timed(bulk=files is not None))
            return
        self.log_undefined()
        while True:
            for opened in files:
                for window in opened.windows(RUN_WINDOW, RUN_BYTES):
                    for run in window:
                        yield run.info, run.payloads(), run.log_ns.tolist()
            if not self.loop:
                return

    def bulk_files(self) -> list[McapFile] | list[Sqlite3File] | None:
        """Every storage file of the bag opened for a bulk reader, in the order :meth:`messages`
        reads them, each with the channels it yields as :meth:`messages` would: a rosbag2 whose
        files are all indexed MCAP (:mod:`robot_relay.sources.mcap`) or all sqlite3
        (:mod:`robot_relay.sources.sqlite`); None for any other bag, or when no topic is wanted
        (the caller then reads with rosbags). Opened with the bag, closed with it."""
        return self._bulk

    def _open_bulk(self) -> list[McapFile] | list[Sqlite3File] | None:
        # At open: a relay imports numpy and reads the summaries (0.1 s here) before a host is
        # there, not between the host's arrival and the first message.
        storages = self._storages() if self.connections else None
        if storages is None:
            return None
        from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

        if all(isinstance(storage, Sqlite3Reader) for storage, _ in storages):
            from robot_relay.sources.sqlite import Sqlite3File

            sqlite_files = [Sqlite3File(self.paths[0], storage, channels)
                            for storage, channels in storages]
            for sqlite_file in sqlite_files:  # a file reading ahead stops with the bag
                self._stack.callback(sqlite_file.close)
            return sqlite_files
        from robot_relay.sources.mcap_stream import StreamedMcap, StreamedMcapFile

        if all(isinstance(storage, StreamedMcap) for storage, _ in storages):
            streamed: list[McapFile] = [StreamedMcapFile(storage, channels)
                                        for storage, channels in storages]
            for opened in streamed:
                self._stack.callback(opened.close)
            return streamed
        mcap_files = self.mcap_storages()
        if mcap_files is None:
            return None
        from robot_relay.sources.mcap import McapFile, NotIndexedError

        files: list[McapFile] = []
        for path, channels in mcap_files:
            try:
                files.append(McapFile(path, channels))
            except NotIndexedError as why:
                log.debug("%s: %s; reading the bag with rosbags", path, why)
                for opened in files:
                    opened.close()
                return None
            self._stack.callback(files[-1].close)
        return files

    def _gathered(
        self, timed: Iterator[tuple[TopicInfo, int, bytes | memoryview, float]]
    ) -> Iterator[tuple[TopicInfo, list[bytes | memoryview], list[int]]]:
        """:meth:`runs` of messages read one by one (``timed``, :meth:`_timed`'s)."""
        gathered: dict[str, tuple[TopicInfo, list[bytes | memoryview], list[int]]] = {}
        count = 0
        for info, log_ns, data, due in timed:
            delay = due - time.monotonic()
            if gathered and (delay > 0 or count >= RUN_WINDOW):
                yield from gathered.values()
                gathered, count = {}, 0
            if delay > 0:
                self._sleep(delay)
            run = gathered.get(info.topic)
            if run is None:
                run = gathered[info.topic] = (info, [], [])
            run[1].append(data)
            run[2].append(log_ns)
            count += 1
        yield from gathered.values()

    def _timed(self, bulk: bool = False) -> Iterator[tuple[TopicInfo, int, bytes | memoryview, float]]:
        """Every message once (or forever with ``loop``): its topic, log time, CDR, and the
        ``time.monotonic()`` at which ``rate`` makes it due (-inf unpaced); the caller waits.
        Read through rosbags, or with ``bulk`` by the bulk reader (:meth:`bulk_files`)."""
        if not self.connections:
            return
        self.log_undefined()
        while True:
            started = time.monotonic()
            first_ns: int | None = None
            for info, log_ns, data in self._bulk_records() if bulk else self._records():
                if first_ns is None:
                    first_ns = log_ns
                due = started + (log_ns - first_ns) / 1e9 / self.rate if self.rate > 0 else -math.inf
                yield info, log_ns, data, due
            self._name_damage()
            if not self.loop:
                return

    def _records(self) -> Iterator[tuple[TopicInfo, int, bytes | memoryview]]:
        """The bag's messages through rosbags: topic, log time, CDR."""
        for connection, log_ns, raw in self._read():
            info = self._infos[connection.id]
            data = self._cdr(raw, info)
            if data is not None:
                yield info, log_ns, data

    def _bulk_records(self) -> Iterator[tuple[TopicInfo, int, bytes | memoryview]]:
        """:meth:`_records` by the bulk reader (an indexed MCAP rosbag2: CDR already)."""
        for opened in self._bulk or ():
            for records in opened.records(RUN_WINDOW):
                yield from records

    def _name_damage(self) -> None:
        """Say once per pass what of a damaged bag was lost (the rest was read)."""
        lost = []
        if isinstance(self._reader, _SalvagedBag):
            lost.append(self._reader.damage() or "no message (every chunk read)")
        if self._malformed:
            lost.append(f"{self._malformed} messages whose log time or payload is malformed")
        if lost:
            read = (
                f"{self._reader.refusal}; " if isinstance(self._reader, _SalvagedBag) else ""
            )
            log.warning(
                "bag %s is damaged (%sthe readable part was read); lost: %s",
                self.paths[0], read, "; ".join(lost),
            )

    def _read(self) -> Iterator[tuple[Any, int, bytes | memoryview]]:
        """The reader's messages; a read error in the middle of the bag (a corrupt sqlite3 row or
        chunk) ends it with a SourceError naming the file and what was read up to there."""
        count, last_ns = 0, None
        self._malformed = 0
        try:
            for connection, log_ns, raw in self._reader.messages(connections=self._asked):
                if not isinstance(log_ns, int) or not isinstance(raw, bytes | memoryview):
                    # A sqlite3 row whose timestamp or data is not what rosbag2 writes.
                    self._malformed += 1
                    continue
                count += 1
                last_ns = log_ns
                yield connection, log_ns, raw
        except Exception as err:  # rosbags' readers raise whatever their storage hits
            where = "at its start" if last_ns is None else f"after log time {last_ns} ns"
            msg = (
                f"bag {self.paths[0]} is damaged: reading stopped {where}, after {count} "
                f"messages ({type(err).__name__}: {err}); the rest of the bag is lost"
            )
            raise SourceError(msg) from err
