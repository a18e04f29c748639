"""``--save`` files end with Rerun's footer, so ``rerun rrd verify`` accepts them and
``RrdReader(path).store()`` opens them: a bag conversion's one file, and a live host's files,
split every ``--save-split`` seconds because Rerun holds a file's index in memory until it
closes (host_bridge/outputs/sink.py, :class:`~host_bridge.outputs.sink.SavedFile`)."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from host_bridge.cli import main as host_main
from host_bridge.core.contract import ColumnsItem, LogItem
from host_bridge.core.destinations import SinkOptions
from host_bridge.demo.bag import write_demo_bag
from host_bridge.outputs import sink as sink_module
from host_bridge.outputs.sink import FEW_ROWS, SPLIT_PROPERTY, RerunSink, split_path
from tests.integration.procs import free_port
from tests.rrd import entity_rows, verify

SPLIT_S = 1.0
STEPS = 35
STEP_S = 0.1
"""3.5 s of logging: a file a second, so the recording is split while both threads log."""
NS = 1_000_000_000


def items(step: int) -> Iterator[tuple[list[LogItem], dict[str, int]]]:
    """An image, a cloud and a plot value per step, at ros_time ``step`` s."""
    pixels = np.full((4, 6, 3), step, dtype=np.uint8)
    points = np.arange(9, dtype=np.float32).reshape(3, 3) + step
    yield ([LogItem("/r/camera", (rr.Image(pixels),)), LogItem("/r/cloud", (rr.Points3D(points),)),
            LogItem("/r/speed", (rr.Scalars(0.5 * step),))], {"ros_time": step * NS})


def log_steps(sink: RerunSink, entity: str) -> None:
    """STEPS rows of ``entity``, STEP_S apart (/r/speed with the camera and cloud of :func:`items`)."""
    for step in range(STEPS):
        if entity == "/r/speed":
            for entries, times in items(step):
                sink.log(entries, times)
        else:
            sink.log([LogItem(entity, (rr.Scalars(float(step)),))], {"ros_time": step * NS})
        time.sleep(STEP_S)


def rows_in(files: Sequence[Path], entity: str) -> list[dict[str, Any]]:
    return [row for path in files for row in entity_rows(path, entity).get(entity, [])]


def test_a_split_save_is_files_rerun_accepts_each_holding_what_it_needs(tmp_path: Path) -> None:
    out = tmp_path / "out.rrd"
    sink = RerunSink(SinkOptions(save=out, save_split_s=SPLIT_S))
    sink.log([LogItem("/r/robot_model", (rr.TextDocument("static"),), static=True)], {})
    sink.send_blueprint(rrb.Blueprint(rrb.Spatial3DView(origin="/r")))
    loggers = [threading.Thread(target=log_steps, args=(sink, entity)) for entity in ("/r/speed", "/r/odom")]
    for logger in loggers:
        logger.start()
    for logger in loggers:
        logger.join()
    sink.close()

    files = sorted(tmp_path.iterdir(), key=lambda path: int(path.stem.rsplit("_", 1)[1]))
    assert len(files) >= 3
    assert files == [split_path(out, i) for i in range(len(files))]  # out.rrd became out_0.rrd
    verify(*files)
    assert {RrdReader(path).recordings()[0].recording_id for path in files} == {sink.recording_id}
    for path in files:  # each opens alone with the model and the layout
        assert [row["TextDocument:text"] for row in entity_rows(path)["/r/robot_model"]] == [["static"]]
        assert RrdReader(path).blueprints()
    assert sum(1 for path in files if entity_rows(path, "/r/speed")) >= 3  # split mid-logging
    for entity in ("/r/speed", "/r/odom"):  # every row once, in whichever file
        rows = sorted(rows_in(files, entity), key=lambda row: row["ros_time"])
        assert [row["ros_time"] for row in rows] == [step * NS for step in range(STEPS)]
    assert [row["Image:buffer"][0][0] for row in sorted(rows_in(files, "/r/camera"),
                                                     key=lambda row: row["ros_time"])] == list(range(STEPS))


def test_a_file_is_split_after_its_first_data_not_while_the_host_waits(tmp_path: Path) -> None:
    """A host waiting for robots makes no empty files: a file's time starts with its data."""
    out = tmp_path / "out.rrd"
    sink = RerunSink(SinkOptions(save=out, save_split_s=0.3))
    time.sleep(1.5)  # five split periods without data
    assert sorted(tmp_path.iterdir()) == [out]
    for step in range(10):
        for entries, times in items(step):
            sink.log(entries, times)
        time.sleep(0.1)
    sink.close()
    files = sorted(tmp_path.iterdir(), key=lambda path: int(path.stem.rsplit("_", 1)[1]))
    assert len(files) >= 2  # 1 s of data in files of 0.3 s
    verify(*files)
    assert entity_rows(files[0], "/r/speed")  # the first file begins with the data
    assert sorted(row["ros_time"] for row in rows_in(files, "/r/speed")) == [step * NS for step in range(10)]


def test_a_host_stopped_right_after_a_split_ends_its_last_file_with_the_footer(tmp_path: Path) -> None:
    """The file begun by a split holds data of its own (the split property) even when nothing
    is logged into it: Rerun writes no footer into a file with nothing in it."""
    out = tmp_path / "out.rrd"
    sink = RerunSink(SinkOptions(save=out, save_split_s=0.3))
    for entries, times in items(0):
        sink.log(entries, times)
    deadline = time.monotonic() + 30
    while not split_path(out, 1).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    sink.close()  # nothing logged since the split
    files = [split_path(out, 0), split_path(out, 1)]
    assert sorted(tmp_path.iterdir()) == files
    verify(*files)
    assert [row["ros_time"] for row in rows_in(files, "/r/speed")] == [0]
    assert "/r/speed" not in entity_rows(files[1])
    property_path = f"/__properties/{SPLIT_PROPERTY}"
    assert entity_rows(files[1], property_path) == {property_path: [{"file": [1], "static": True}]}


def test_a_file_sent_many_runs_of_columns_ends_before_its_seconds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each run of columns is a chunk of Rerun's index of the file, held in memory until the
    file ends: a fast replay's file ends after FILE_COLUMN_CHUNKS of them, not only by time."""
    monkeypatch.setattr(sink_module, "FILE_COLUMN_CHUNKS", 5)
    out = tmp_path / "out.rrd"
    sink = RerunSink(SinkOptions(save=out, save_split_s=600.0))
    rows = FEW_ROWS + 1  # more rows than are logged row by row
    runs = 0
    while not split_path(out, 2).exists() and runs < 300:  # the file's thread looks every 0.5 s
        stamps = (runs * rows + np.arange(rows, dtype=np.int64)) * NS
        sink.log([ColumnsItem("/r/speed", rr.Scalars.columns(scalars=stamps / NS), {"ros_time": stamps})],
                 {})
        runs += 1
        time.sleep(0.1)
    sink.close()
    files = sorted(tmp_path.iterdir(), key=lambda path: int(path.stem.rsplit("_", 1)[1]))
    assert len(files) == 3, f"{runs} runs of columns in 30 s"  # the seconds never ran out
    verify(*files)
    for path in files[:2]:  # 5 runs, or more when the look came late
        assert len(entity_rows(path, "/r/speed")["/r/speed"]) >= 5 * rows
    saved = sorted(row["ros_time"] for row in rows_in(files, "/r/speed"))
    assert saved == [step * NS for step in range(runs * rows)]


def test_a_split_save_to_dev_null_writes_each_file_there(tmp_path: Path) -> None:
    """A path that is not a regular file is never renamed: the files go there in turn."""
    sink = RerunSink(SinkOptions(save=Path(os.devnull), save_split_s=0.2))
    for step in range(8):
        for entries, times in items(step):
            sink.log(entries, times)
        time.sleep(0.1)
    sink.close()
    assert Path(os.devnull).is_char_device()
    assert not split_path(Path(os.devnull), 0).exists()


def test_a_bag_conversion_and_a_live_host_end_their_files_with_the_footer(tmp_path: Path) -> None:
    bag = write_demo_bag(tmp_path / "demo", 2.0)
    assert host_main(["--bag", str(bag), "--save", str(tmp_path / "bag.rrd")]) == 0
    live = tmp_path / "live.rrd"
    assert host_main(["-l", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting",
                      "--no-rmw-zenoh", "--save", str(live), "--duration", "1"]) == 0
    verify(tmp_path / "bag.rrd", live)
    assert len(entity_rows(tmp_path / "bag.rrd")["/robot/scan"]) == 10  # the demo's 5 Hz lidar for 2 s
    assert sorted(path.name for path in tmp_path.glob("*.rrd")) == ["bag.rrd", "live.rrd"]  # no split


@pytest.mark.parametrize(("flags", "error"), [
    (["--save-split", "0"], "--save-split 0: the seconds between files must be more than 0"),
    ([], "--save {out}: out_0.rrd of an earlier recording are there, and a recording longer than "
         "--save-split goes on in such files; move them away or save under another name"),
])
def test_a_split_save_that_cannot_be_is_one_error_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], error: str,
) -> None:
    out = tmp_path / "out.rrd"
    split_path(out, 0).write_bytes(b"an earlier recording")
    assert host_main(["-l", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting",
                      "--save", str(out), "--duration", "1", *flags]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"swanky-host: error: {error.format(out=out)}"
    assert not out.exists()
    assert split_path(out, 0).read_bytes() == b"an earlier recording"
