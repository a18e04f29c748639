"""A fleet beyond one host: three relays and two hosts meet at a Zenoh router on loopback; each
host takes its subset of robots with ``--robots`` and sees exactly those, and lays out every
robot of the recording they share (host_bridge/outputs/shared_layout.py)."""

from __future__ import annotations

import re
import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from tests.integration.procs import command, free_port, running
from tests.integration.router import router_command, wait_for_port
from tests.rrd import entity_rows, saved_views

pytestmark = pytest.mark.integration


def robot_roots(rows: dict[str, list[dict[str, Any]]]) -> set[str]:
    """Entity roots that are robots (Swanky's own /_swanky, /_stats and Rerun's /__properties
    start with '_')."""
    return {path.split("/")[1] for path in rows if not path.startswith("/_")}


def fixes(bag: Path) -> list[tuple[int, list[float]]]:
    """(header stamp ns, [lat, lon]) of every NavSatFix, from rosbags' own deserialiser."""
    out = []
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for connection, _, data in reader.messages():
            msg: Any = reader.deserialize(data, connection.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            out.append((stamp, [round(msg.latitude, 9), round(msg.longitude, 9)]))
    return out


def logged_fixes(rows: list[dict[str, Any]]) -> list[tuple[int, list[float]]]:
    return [(r["ros_time"], [round(v, 9) for v in r["GeoPoints:positions"][0]]) for r in rows]


def recording_id(rrd: Path) -> str:
    """The recording (store) id of an .rrd, as Rerun's own CLI reads it."""
    rerun = Path(sys.executable).parent / "rerun"
    text = subprocess.run([str(rerun), "rrd", "print", str(rrd)], capture_output=True, text=True,
                          timeout=60, check=True).stdout
    match = re.search(r'StoreId\(\s*Recording,\s*"[^"]*",\s*"([^"]*)"', text)
    assert match is not None, text[:500]
    return match.group(1)


def test_two_hosts_split_three_relays_through_a_router(shared_data: Path, tmp_path: Path) -> None:
    # 151 GPS fixes over 15 s: cheap to convert, so the test measures routing, not converters.
    bag = shared_data / "gps_fix_rviz_satellite" / "sample.bag"
    port = free_port()
    zenoh_args = ("-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting")
    saved = {"east-$*": tmp_path / "east.rrd", "west-c": tmp_path / "west.rrd"}
    with ExitStack() as stack:
        stack.enter_context(running(router_command(port)))
        wait_for_port(port)
        hosts = [
            stack.enter_context(running(command(
                "host_bridge.cli", *zenoh_args, "--robots", robots, "--save", str(out),
                "--until-idle", "5", "--duration", "120", "--recording-id", "fleet-test",
            )))
            for robots, out in saved.items()
        ]
        relays = [
            stack.enter_context(running(command(
                "robot_relay.cli", "--robot", robot, "--bag", str(bag), "--rate", "5",
                *zenoh_args, "--wait-for-host", "60",
            )))
            for robot in ("east-a", "east-b", "west-c")
        ]
        for proc in relays + hosts:
            assert proc.wait(timeout=120) == 0, proc.stderr.read() if proc.stderr else ""
    expected = fixes(bag)
    assert len(expected) == 151
    east = entity_rows(saved["east-$*"])
    west = entity_rows(saved["west-c"])
    assert robot_roots(east) == {"east-a", "east-b"}
    assert robot_roots(west) == {"west-c"}
    for rows, robot in ((east, "east-a"), (east, "east-b"), (west, "west-c")):
        assert logged_fixes(rows[f"/{robot}/gps/fix"]) == expected, robot
    # Same recording id: a viewer both hosts send to shows one fleet, not two recordings.
    assert {recording_id(path) for path in saved.values()} == {"fleet-test"}
    # One layout whichever host sent it last: each lays out the other's robots too.
    for path in saved.values():
        assert {view["name"] for view in saved_views(path) if view.get("class") == "3D"} == {
            "All robots 3D", "east-a 3D", "east-b 3D", "west-c 3D"}, path.name
    assert {r["TextLog:text"][0] for r in west["/_swanky/robots"]} == {
        "robot west-c joined (swanky relay)", "robot west-c left (swanky relay)"
    }
