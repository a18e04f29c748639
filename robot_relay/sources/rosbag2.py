"""rosbags' rosbag2 ``Reader``, as BagSource opens rosbag2 bags, with two changes for the bulk
readers: a directory's sqlite3 files are opened without counting their rows
(:class:`~robot_relay.sources.sqlite.UncountedSqlite3Reader`), and the one MCAP file of a bag
recorded with ``--compression-mode file`` is not decompressed at open but streamed
(:class:`~robot_relay.sources.mcap_stream.StreamedMcap`). Any other bag, and one of those the
streaming reader does not take, opens as rosbags opens it.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from contextlib import ExitStack
from pathlib import Path, PurePath
from types import MappingProxyType
from typing import Any

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinition,
    MessageDefinitionFormat,
)
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.metadata import ReaderMetadata, parse_qos
from rosbags.rosbag2.reader import DirectoryReader
from ruamel.yaml import YAML

from robot_relay.sources.mcap_stream import NotStreamableError, StreamedMcap
from robot_relay.sources.sqlite import UncountedSqlite3Reader

log = logging.getLogger("swanky.relay")


class _Rosbag2Directory(DirectoryReader):
    STORAGE_PLUGINS: Mapping[str, Any] = MappingProxyType(
        {**DirectoryReader.STORAGE_PLUGINS, "sqlite3": UncountedSqlite3Reader})

    def open(self) -> None:
        if len(list(Path(str(self.path)).glob("*.mcap.zstd"))) == 1:
            try:
                self._open_streamed()
            except NotStreamableError as why:
                log.debug("%s: %s; rosbags decompresses it whole", self.path, why)
            else:
                return
        super().open()

    def _open_streamed(self) -> None:
        """Open a bag whose metadata.yaml names one zstd'ed MCAP file as rosbags 0.11's
        ``DirectoryReader.open`` does (pinned in pyproject.toml: the same connections, ids and
        metadata), but with that file as a :class:`StreamedMcap`; NotStreamableError (before
        anything is kept) for any other bag, or metadata rosbags would refuse (it says why)."""
        directory = Path(str(self.path))
        try:
            info = YAML(typ="safe").load((directory / "metadata.yaml").read_text())[
                "rosbag2_bagfile_information"]
            (name,) = info["relative_file_paths"]
            path = directory / PurePath(name).name
            compressed = (info.get("compression_mode") or "").lower() == "file" and (
                info.get("compression_format") == "zstd")
            if not (compressed and info["storage_identifier"] == "mcap" and info["version"] <= 9
                    and path.name.endswith(".mcap.zstd") and path.exists()):
                msg = "not one zstd'ed MCAP file"
                raise NotStreamableError(msg)
            connections = [
                Connection(
                    id=index + 1,
                    topic=topic["topic_metadata"]["name"],
                    msgtype=topic["topic_metadata"]["type"],
                    msgdef=MessageDefinition(MessageDefinitionFormat.NONE, ""),
                    digest=topic["topic_metadata"].get("type_description_hash", ""),
                    msgcount=topic["message_count"],
                    ext=ConnectionExtRosbag2(
                        serialization_format=topic["topic_metadata"]["serialization_format"],
                        offered_qos_profiles=parse_qos(
                            topic["topic_metadata"].get("offered_qos_profiles", [])),
                    ),
                    owner=self,
                )
                for index, topic in enumerate(info["topics_with_message_count"])
            ]
            if any(topic["topic_metadata"]["serialization_format"] != "cdr"
                   for topic in info["topics_with_message_count"]):
                msg = "a topic not serialised as CDR"
                raise NotStreamableError(msg)
            duration = info["duration"]["nanoseconds"]
            start_time = info["starting_time"]["nanoseconds_since_epoch"]
            count = info["message_count"]
        except NotStreamableError:
            raise
        except Exception as err:  # what rosbags' own open says better: it opens the bag
            raise NotStreamableError(f"metadata.yaml: {type(err).__name__}: {err}") from err
        storage = StreamedMcap(path, {c.topic for c in connections})
        storage.open()
        self.stack = ExitStack()
        self.stack.callback(storage.close)
        self.storages = [storage]
        self.metadata = ReaderMetadata(
            duration=duration + 1 if count else 0,
            start_time=start_time if count else 2**63 - 1,
            end_time=start_time + duration + 1 if count else 0,
            message_count=count,
            compression_format="zstd",
            compression_mode="file",
            ros_distro=info.get("ros_distro"),
            custom=info.get("custom_data"),
        )
        self.files = info.get("files", [])[:]
        definitions = {stored.msgtype: stored.msgdef for stored in reversed(storage.connections)
                       if stored.msgdef.format != MessageDefinitionFormat.NONE}
        self.connections = [
            connection._replace(msgdef=definitions.get(connection.msgtype, connection.msgdef))
            for connection in connections
        ]


class Rosbag2Reader(Reader):
    """rosbags' rosbag2 ``Reader``, its directories opened as the module docstring says; a bare
    .db3 or .mcap file (whose counts are the bag's) as rosbags opens it."""

    STORAGE_PLUGINS: Mapping[str, Any] = MappingProxyType(
        {**Reader.STORAGE_PLUGINS, "dir": _Rosbag2Directory})

