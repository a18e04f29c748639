"""Offline conversion: the progress line (pure rendering, pacing) and the end-of-run summary."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from host_bridge.core.destinations import SinkOptions
from host_bridge.inputs.bag import BagExtent, BagInput
from host_bridge.outputs.progress import LOG_PERIOD_S, Progress, render_progress
from host_bridge.outputs.sink import RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from robot_relay.sources.bag import BagSource
from robot_relay.wire import RawMessage

EXTENT = BagExtent(messages=8197, topics=4, start_ns=10**18, end_ns=10**18 + 97_400_000_000)


def test_render_progress() -> None:
    line = render_progress(EXTENT, 3700, 3, 10**18 + 43_800_000_000, 2.0)
    assert line == " 45% 3,700/8,197 msgs  3/4 topics  bag 43.8/97.4 s  1,850 msg/s"
    assert render_progress(EXTENT, 0, 0, None, 0.0) == (
        "  0% 0/8,197 msgs  0/4 topics  bag 0.0/97.4 s  - msg/s"
    )
    empty = BagExtent(0, 0, 0, 0)
    assert render_progress(empty, 0, 0, None, 1.0).startswith("100% 0/0 msgs")


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def raw(topic: str, log_ns: int) -> RawMessage:
    return RawMessage("r", topic, "std_msgs/msg/String", b"", log_ns=log_ns)


def test_progress_without_a_terminal_writes_a_plain_line_per_period() -> None:
    stream = io.StringIO()
    clock = FakeClock()
    progress = Progress(BagExtent(4, 2, 0, 4_000_000_000), stream, clock)
    assert not progress.tty
    clock.now = 1.0
    progress([raw("/a", 1_000_000_000)])
    assert stream.getvalue() == ""  # less than LOG_PERIOD_S since the start
    clock.now = LOG_PERIOD_S + 0.1
    progress([raw("/a", 2_000_000_000), raw("/b", 2_500_000_000)])
    clock.now = LOG_PERIOD_S + 0.2
    progress([raw("/b", 3_000_000_000)])
    progress.finish()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(" 75% 3/4 msgs  2/2 topics  bag 2.5/4.0 s")
    assert lines[1].startswith("100% 4/4 msgs  2/2 topics  bag 3.0/4.0 s")
    assert "\r" not in stream.getvalue()


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_on_a_terminal_redraws_at_most_four_times_a_second() -> None:
    stream = FakeTty()
    clock = FakeClock()
    progress = Progress(BagExtent(100, 1, 0, 1), stream, clock)
    for i in range(100):
        clock.now = i * 0.01  # 100 runs within one second
        progress([raw("/a", 0)])
    progress.finish()
    redraws = stream.getvalue().count("\r\x1b[K")
    assert redraws == 4  # at 0.25, 0.5, 0.75 s, and the final one
    assert stream.getvalue().endswith("100% 100/100 msgs  1/1 topics  bag 0.0/0.0 s  101 msg/s\n")


def test_summary_of_a_real_bag(
    shared_data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bag = shared_data / "tf_nav2_sim_evo" / "tf_example"
    openings: list[Path] = []
    opening = BagSource.open

    def counted(source: BagSource) -> BagSource:
        openings.append(source.paths[0])
        return opening(source)

    monkeypatch.setattr(BagSource, "open", counted)
    bag_input = BagInput(bag, "robot")
    extent = bag_input.extent()
    assert extent == BagExtent(518, 2, extent.start_ns, extent.start_ns + extent.duration_ns, {
        "/tf_static": "tf2_msgs/msg/TFMessage", "/tf": "tf2_msgs/msg/TFMessage"})
    assert round(extent.duration_ns / 1e9, 1) == 51.7
    stream = io.StringIO()
    progress = Progress(extent, stream)
    dispatcher = Dispatcher(RerunSink(SinkOptions(save=tmp_path / "out.rrd")), taps=[progress])
    bag_input.start(dispatcher.take)
    assert bag_input.finished.wait(60)
    bag_input.close()
    assert bag_input.ended()
    assert openings == [bag]  # the extent and the messages from one opening of the bag
    progress.finish()
    dispatcher.close()
    dispatcher.sink.close()
    assert stream.getvalue().startswith("100% 518/518 msgs  2/2 topics  bag 51.7/51.7 s")
    lines = dispatcher.summary().splitlines()
    assert lines[0].split() == ["robot", "topic", "type", "received", "converted", "dropped",
                                "warnings", "gaps", "ms/msg"]
    rows = [line.split() for line in lines[1:]]
    assert [r[:8] for r in rows] == [
        ["robot", "/tf", "tf2_msgs/msg/TFMessage", "517", "517", "0", "0", "0"],
        ["robot", "/tf_static", "tf2_msgs/msg/TFMessage", "1", "1", "0", "0", "0"],
        ["total", "2", "topics", "518", "518", "0", "0", "0"],
    ]
    assert all(float(r[-1]) > 0 for r in rows)
