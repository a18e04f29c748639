"""Bags of the kinds users bring, written here byte for byte as their recorder writes them.

* :func:`write_humble_sqlite3_bag`: what ``ros2 bag record`` on Humble writes by default, a
  sqlite3 bag without message definitions: rosbag2 0.15's schema 3 (tables ``schema``,
  ``metadata``, ``topics``, ``messages``; no ``message_definitions``) and metadata.yaml version 5.
  rosbags' Writer only writes versions 8/9, always with definitions, so this one is made with
  Humble's own table layout (rosbag2 humble ``sqlite_storage.cpp`` ``initialize()``).
* :func:`humble_qos`: the QoS text rosbag2 writes into both metadata.yaml and the storage.
* Service event definitions as rosbag2 Iron+ stores them (``SRV:`` block, ``---``, then the
  dependencies, rosbag2 ``LocalMessageDefinitionSource::get_full_text``).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

SEPARATOR = "=" * 80 + "\n"
INFINITE = {"sec": 2147483647, "nsec": 4294967295}


def humble_qos(reliability: int = 1, durability: int = 2, depth: int = 10,
               deadline: dict[str, int] | None = None) -> str:
    """rosbag2's offered_qos_profiles text of one publisher (enums as rmw numbers: reliability
    1 reliable 2 best effort, durability 1 transient local 2 volatile)."""
    profile = {
        "history": 1, "depth": depth, "reliability": reliability, "durability": durability,
        "deadline": dict(deadline or INFINITE), "lifespan": dict(INFINITE), "liveliness": 1,
        "liveliness_lease_duration": dict(INFINITE), "avoid_ros_namespace_conventions": False,
    }
    return yaml.safe_dump([profile], sort_keys=False).strip()


@dataclass(frozen=True, slots=True)
class Recorded:
    """One topic of a bag: its messages as (log time ns, CDR bytes)."""

    topic: str
    msgtype: str
    messages: Sequence[tuple[int, bytes]]
    qos: str = humble_qos()


def write_humble_sqlite3_bag(path: Path, topics: Sequence[Recorded]) -> Path:
    path.mkdir(parents=True)
    db_name = f"{path.name}_0.db3"
    db = sqlite3.connect(path / db_name)
    db.executescript("""
        CREATE TABLE schema(schema_version INTEGER PRIMARY KEY,ros_distro TEXT NOT NULL);
        CREATE TABLE metadata(id INTEGER PRIMARY KEY,metadata_version INTEGER NOT NULL,
                              metadata TEXT NOT NULL);
        CREATE TABLE topics(id INTEGER PRIMARY KEY,name TEXT NOT NULL,type TEXT NOT NULL,
                            serialization_format TEXT NOT NULL,offered_qos_profiles TEXT NOT NULL);
        CREATE TABLE messages(id INTEGER PRIMARY KEY,topic_id INTEGER NOT NULL,
                              timestamp INTEGER NOT NULL, data BLOB NOT NULL);
        CREATE INDEX timestamp_idx ON messages (timestamp ASC);
        INSERT INTO schema (schema_version, ros_distro) VALUES (3, 'humble');
    """)
    stamps: list[int] = []
    for topic_id, recorded in enumerate(topics, start=1):
        db.execute(
            "INSERT INTO topics (id, name, type, serialization_format, offered_qos_profiles) "
            "VALUES (?, ?, ?, 'cdr', ?)",
            (topic_id, recorded.topic, recorded.msgtype, recorded.qos),
        )
        for log_ns, data in recorded.messages:
            db.execute("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                       (topic_id, log_ns, data))
            stamps.append(log_ns)
    start = min(stamps)
    duration = max(stamps) - start
    info = {
        "version": 5,
        "storage_identifier": "sqlite3",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": len(stamps),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": r.topic, "type": r.msgtype, "serialization_format": "cdr",
                    "offered_qos_profiles": r.qos,
                },
                "message_count": len(r.messages),
            }
            for r in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [db_name],
        "files": [{
            "path": db_name,
            "starting_time": {"nanoseconds_since_epoch": start},
            "duration": {"nanoseconds": duration},
            "message_count": len(stamps),
        }],
    }
    text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)
    db.execute("INSERT INTO metadata (metadata_version, metadata) VALUES (5, ?)", (text,))
    db.commit()
    db.close()
    (path / "metadata.yaml").write_text(text)
    return path


def service_definition(service: str, srv_text: str, dependencies: dict[str, str]) -> str:
    """rosbag2's definition of ``<service>_Event``: the .srv text, then each .msg it uses."""
    text = f"{SEPARATOR}SRV: {service}\n{srv_text}"
    for name, msg_text in dependencies.items():
        text += f"\n{SEPARATOR}MSG: {name}\n{msg_text}"
    return text
