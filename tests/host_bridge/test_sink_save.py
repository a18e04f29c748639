"""``--save`` files: a live host writes no index footer (Rerun keeps the footer's index in memory
until the file closes, so a live host's RSS grew with it: benchmarks/rss_replay.py), a bag
conversion does; either way the file holds the same rows."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.cli import main as host_main
from host_bridge.contract import LogItem
from host_bridge.demo.bag import write_demo_bag
from host_bridge.destinations import SinkOptions
from host_bridge.sink import RerunSink
from tests.integration.procs import free_port
from tests.rrd import entity_rows

NO_FOOTER = "RRD file has no footer"


def items(step: int) -> Iterator[tuple[list[LogItem], dict[str, int]]]:
    """An image, a cloud and a plot value per step, at ros_time ``step`` s."""
    pixels = np.full((4, 6, 3), step, dtype=np.uint8)
    points = np.arange(9, dtype=np.float32).reshape(3, 3) + step
    yield ([LogItem("/r/camera", (rr.Image(pixels),)), LogItem("/r/cloud", (rr.Points3D(points),)),
            LogItem("/r/speed", (rr.Scalars(0.5 * step),))], {"ros_time": step * 1_000_000_000})


def saved(path: Path, *, index_footer: bool) -> Path:
    sink = RerunSink(SinkOptions(save=path), index_footer=index_footer)
    sink.log([LogItem("/r/robot_model", (rr.TextDocument("static"),), static=True)], {})
    for step in range(20):
        for entries, times in items(step):
            sink.log(entries, times)
    sink.close()
    return path


def read(path: Path) -> tuple[dict[str, list[dict[str, Any]]], list[str]]:
    """The file's rows per entity, and what Rerun's reader warned about."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = entity_rows(path)
    return rows, [str(warning.message) for warning in caught]


def test_a_save_without_the_index_footer_holds_the_same_rows(tmp_path: Path) -> None:
    with_footer, footer_warnings = read(saved(tmp_path / "footer.rrd", index_footer=True))
    without, warned = read(saved(tmp_path / "live.rrd", index_footer=False))
    assert not [w for w in footer_warnings if NO_FOOTER in w]
    assert [w for w in warned if NO_FOOTER in w]
    # Every entity but the recording's properties, whose start time is the wall clock's.
    del with_footer["/__properties"], without["/__properties"]
    assert without == with_footer
    assert [row["ros_time"] for row in without["/r/speed"]] == [s * 1_000_000_000 for s in range(20)]
    assert [row["Scalars:scalars"] for row in without["/r/speed"]] == [
        [0.5 * s] for s in range(20)]
    assert without["/r/robot_model"][0]["static"] is True


def test_a_bag_conversion_ends_with_the_footer_a_live_host_does_not(tmp_path: Path) -> None:
    bag = write_demo_bag(tmp_path / "demo", 2.0)
    assert host_main(["--bag", str(bag), "--save", str(tmp_path / "bag.rrd")]) == 0
    rows, warned = read(tmp_path / "bag.rrd")
    assert not [w for w in warned if NO_FOOTER in w]
    assert len(rows["/robot/scan"]) == 10  # the demo's 5 Hz lidar for 2 s
    live = tmp_path / "live.rrd"
    assert host_main(["-l", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting",
                      "--no-rmw-zenoh", "--save", str(live), "--duration", "1"]) == 0
    _, warned = read(live)
    assert [w for w in warned if NO_FOOTER in w]
