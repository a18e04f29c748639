"""Offline conversion (swanky-host --bag) of every bag format gives the same transforms."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from host_bridge.cli import main as host_main
from tests.rrd import entity_rows


def convert(bag: Path, out: Path, *extra: str) -> dict[str, list[dict[str, Any]]]:
    assert host_main(["--bag", str(bag), "--save", str(out), "--strict", *extra]) == 0
    return entity_rows(out)


def transforms(rows: list[dict[str, Any]]) -> list[tuple[Any, ...]]:
    return [
        (
            row.get("ros_time"),
            row["Transform3D:parent_frame"][0],
            row["Transform3D:child_frame"][0],
            tuple(round(v, 6) for v in row["Transform3D:translation"][0]),
            tuple(round(v, 6) for v in row["Transform3D:quaternion"][0]),
        )
        for row in rows
    ]


def to_mcap(src: Path, dst: Path) -> Path:
    """Rewrite a rosbag2 as MCAP with rosbags' writer, copying the raw CDR unchanged."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    with AnyReader([src], default_typestore=store) as reader, Writer(
        dst, version=9, storage_plugin=StoragePlugin.MCAP
    ) as writer:
        out = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store)
               for c in reader.connections}
        for connection, timestamp, raw in reader.messages():
            writer.write(out[connection.id], timestamp, raw)
    return dst


def test_sqlite3_mcap_and_ros1_give_the_same_transforms(shared_data: Path, tmp_path: Path) -> None:
    evo = shared_data / "tf_nav2_sim_evo"
    sqlite = convert(evo / "tf_example", tmp_path / "sqlite.rrd")
    mcap = convert(to_mcap(evo / "tf_example", tmp_path / "mcap"), tmp_path / "mcap.rrd")
    ros1 = convert(evo / "tf_example.bag", tmp_path / "ros1.rrd")
    dynamic = transforms(sqlite["/robot/tf"])
    assert len(dynamic) == 517
    assert dynamic[0][1:3] == ("robot/odom", "robot/base_footprint")
    assert transforms(mcap["/robot/tf"]) == dynamic
    assert transforms(ros1["/robot/tf"]) == dynamic
    static = transforms(sqlite["/robot/tf_static/base_link"])
    assert static[0][1:3] == ("robot/base_footprint", "robot/base_link")
    assert transforms(ros1["/robot/tf_static/base_link"]) == static
    assert transforms(mcap["/robot/tf_static/base_link"]) == static


def test_transforms_match_rerun_own_mcap_importer(shared_data: Path, tmp_path: Path) -> None:
    """Cross-check with an independent decoder: `rerun mcap convert` (Rerun's Rust importer)."""
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if rerun is None:
        pytest.skip("rerun CLI not on PATH")
    bag = shared_data / "tf_nav2_sim_evo" / "nav2_turtlebot.mcap"
    theirs_path = tmp_path / "rerun.rrd"
    subprocess.run([rerun, "mcap", "convert", str(bag), "-o", str(theirs_path)], check=True,
                   capture_output=True, timeout=120)
    theirs = entity_rows(theirs_path, "/tf")["/tf"]
    ours = convert(bag, tmp_path / "ours.rrd", "--robot", "tb4")["/tb4/tf"]

    def key(row: dict[str, Any], prefix: str) -> tuple[Any, ...]:
        return (
            prefix + row["Transform3D:parent_frame"][0],
            prefix + row["Transform3D:child_frame"][0],
            tuple(round(v, 5) for v in row["Transform3D:translation"][0]),
        )

    their_rows = [r for r in theirs if "Transform3D:child_frame" in r]
    assert len(their_rows) == len(ours) == 7284
    assert sorted(key(r, "tb4/") for r in their_rows) == sorted(key(r, "") for r in ours)


def test_split_bag_without_leading_slashes_and_zero_stamps(shared_data: Path, tmp_path: Path) -> None:
    rows = convert(shared_data / "rosbag2_format_fixtures" / "mcap_wbag", tmp_path / "w.rrd")
    texts = [r for path, rs in rows.items() if path.startswith("/robot/AAA") for r in rs]
    assert texts, sorted(rows)
    total = sum(len(rs) for path, rs in rows.items() if path.startswith("/robot/"))
    assert total == 6074
