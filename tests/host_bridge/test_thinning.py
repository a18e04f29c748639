"""What a viewer that falls behind is sent (host_bridge/pipeline/thinning.py): Pace's arithmetic, and
heavy runs routed to the viewer (a real ``rerun`` binary saving what it receives), to the
``--save`` file only, or nowhere."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from host_bridge.core.destinations import SinkOptions
from host_bridge.outputs.sink import RerunSink
from host_bridge.outputs.stats import HELD_S
from host_bridge.outputs.viewer_lag import LONGEST_PERIOD_S, SHORTEST_PERIOD_S
from host_bridge.pipeline import thinning
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.pipeline.thinning import FIRST_INTERVAL_S, Pace, ViewerThinning
from robot_relay.wire import RawMessage
from tests.integration.procs import saving_viewer
from tests.rrd import entity_rows

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
ROBOT = "r"
IMAGE, IMAGE_TOPIC = "sensor_msgs/msg/Image", "/camera/image_raw"
STRING, STRING_TOPIC = "std_msgs/msg/String", "/status"
SENT_AT = (0.0, 0.3, 0.6, 1.0, 1.3)
"""When each image comes, in seconds; with a 1 s interval the viewer gets those at 0 and 1."""
INTERVAL_S = 1.0


def test_pace_backs_off_once_a_second_while_behind_and_recovers_to_every_message() -> None:
    pace = Pace()
    assert (pace.interval, pace.period) == (0.0, SHORTEST_PERIOD_S)
    intervals = []
    for tick in range(28):  # 7 s behind, a look every 0.25 s
        pace.update(tick * 0.25, round_trip=2.0, answers=0.0)
        intervals.append(pace.interval)
    assert intervals[::4] == [0.25, 0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    assert intervals[1:4] == [0.25] * 3  # once a second at most
    assert pace.period == SHORTEST_PERIOD_S  # the viewer answered at once: the host is slow
    ended = [pace.update(7 + tick * 0.25, round_trip=0.1, answers=0.1) for tick in range(40)]
    assert ended.count(True) == 1
    assert pace.interval == 0.0
    # 4 s down to 1/30 s at x0.85 a look: 30 looks, 7.5 s.
    assert ended.index(True) == 29
    # Between the two thresholds nothing changes.
    pace.update(20.0, round_trip=0.4, answers=0.4)
    assert (pace.interval, pace.period) == (0.0, SHORTEST_PERIOD_S)


def test_pace_batches_longer_only_for_viewers_slow_to_answer() -> None:
    pace = Pace()
    for second in range(5):
        pace.update(float(second), round_trip=2.0, answers=1.5)
    assert pace.period == LONGEST_PERIOD_S
    for tick in range(12):
        pace.update(5 + tick * 0.25, round_trip=0.3, answers=0.1)  # answers quick, flush not
    assert pace.period == SHORTEST_PERIOD_S
    assert pace.interval == 4.0  # the round trip is still over CAUGHT_UP_S: no recovery


class Lag:
    """A ViewerLag whose round trip sits between the thresholds: Pace leaves it alone, and the
    test sets the interval."""

    names = "the test's viewer"
    round_trip = 0.4
    answers = 0.4
    period = SHORTEST_PERIOD_S
    seconds = 0.6


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def image_cdr(index: int) -> bytes:
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=10 + index, nanosec=0),
                                      frame_id="camera")
    image = T[IMAGE](header=header, height=2, width=2, encoding="mono8", is_bigendian=0, step=2,
                     data=np.full(4, index, np.uint8))
    return bytes(STORE.serialize_cdr(image, IMAGE))


def string_cdr(index: int) -> bytes:
    return bytes(STORE.serialize_cdr(T[STRING](data=f"status {index}"), STRING))


def run_thinned(
    sink: RerunSink, clock: Clock, lag_path: str = thinning.LAG_PATH,
) -> tuple[Dispatcher, ViewerThinning]:
    """Images at SENT_AT with the interval at INTERVAL_S, each with a small message beside it."""
    dispatcher = Dispatcher(sink)
    thinner = ViewerThinning(dispatcher, sink, Lag(), clock=clock, path=lag_path)  # type: ignore[arg-type]
    dispatcher.offload = thinner
    thinner.pace.interval = INTERVAL_S
    for index, at in enumerate(SENT_AT):
        clock.now = at
        ns = 10**18 + index * 10**8
        dispatcher.dispatch([RawMessage(ROBOT, IMAGE_TOPIC, IMAGE, image_cdr(index), receive_ns=ns)])
        dispatcher.dispatch([RawMessage(ROBOT, STRING_TOPIC, STRING, string_cdr(index), receive_ns=ns)])
    return dispatcher, thinner


def temporal(path: Path, entity: str) -> list[dict[str, Any]]:
    return [row for row in entity_rows(path, entity).get(entity, []) if not row["static"]]


def image_fills(path: Path) -> list[int]:
    """Which image each row is (image i is filled with i)."""
    return [row["Image:buffer"][0][0] for row in temporal(path, f"/{ROBOT}{IMAGE_TOPIC}")]


def statuses(path: Path) -> list[str]:
    return [row["TextLog:text"][0] for row in temporal(path, f"/{ROBOT}{STRING_TOPIC}")]


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_thinned_images_go_to_the_file_only_and_small_topics_everywhere(
    tmp_path: Path, caplog: pytest.LogCaptureFixture,
) -> None:
    received, saved = tmp_path / "viewer.rrd", tmp_path / "saved.rrd"
    with saving_viewer(received) as (url, _):
        sink = RerunSink(SinkOptions(connect=url, save=saved), keep_up=True)
        with caplog.at_level(logging.INFO, logger="swanky.host"):
            dispatcher, thinner = run_thinned(sink, Clock())
            thinner.close()
        counters = dispatcher.counters[(ROBOT, IMAGE_TOPIC)]
        sink.close()
    assert image_fills(saved) == [0, 1, 2, 3, 4]
    assert image_fills(received) == [0, 3]
    assert statuses(saved) == statuses(received) == [f"status {i}" for i in range(5)]
    assert (counters.received, counters.converted) == (5, 5)
    assert thinner.thinned() == {(ROBOT, IMAGE_TOPIC): 3}
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warned[0] == (
        f"[{ROBOT}] {IMAGE_TOPIC}: the Rerun viewer the test's viewer is 0.6 s behind: it gets the "
        "newest message of this topic at most every 1 s (1 Hz) until it catches up; the --save file "
        f"gets every one (each time: /_stats/{ROBOT}{IMAGE_TOPIC}/viewer_thinned)")
    assert warned[1] == (
        "heavy messages not sent to the Rerun viewer because it fell behind (the --save file has "
        f"them all):\n[{ROBOT}] {IMAGE_TOPIC}: 3")
    assert len(warned) == 2  # the topic is named once


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_without_a_file_a_thinned_image_is_not_converted(tmp_path: Path) -> None:
    received = tmp_path / "viewer.rrd"
    with saving_viewer(received) as (url, _):
        sink = RerunSink(SinkOptions(connect=url), keep_up=True)
        dispatcher, thinner = run_thinned(sink, Clock())
        thinner.close()
        sink.close()
    assert image_fills(received) == [0, 3]
    assert statuses(received) == [f"status {i}" for i in range(5)]
    counters = dispatcher.counters[(ROBOT, IMAGE_TOPIC)]
    assert (counters.received, counters.converted) == (5, 2)


@pytest.mark.parametrize(("host_name", "lag_path"), [
    (None, "/_stats/host/viewer_lag_ms"),
    ("east", "/_stats/host/east/viewer_lag_ms"),  # one of two hosts sharing a viewer
])
def test_the_lag_and_the_thinned_count_are_logged_into_the_file_up_to_the_stop(
    tmp_path: Path, host_name: str | None, lag_path: str,
) -> None:
    saved = tmp_path / "saved.rrd"
    sink = RerunSink(SinkOptions(save=saved))
    _, thinner = run_thinned(sink, Clock(), thinning.lag_path(host_name))
    thinner.close()
    sink.close()
    rows = entity_rows(saved)
    assert [path for path in rows if "viewer_lag_ms" in path] == [lag_path]
    assert [row["Scalars:scalars"][0] for row in rows[lag_path]][-1] == pytest.approx(600.0)
    counts = rows[f"/_stats/{ROBOT}{IMAGE_TOPIC}/viewer_thinned"]
    assert sum(row["Scalars:scalars"][0] for row in counts) == 3


def test_stats_are_held_only_while_the_viewer_is_behind(tmp_path: Path) -> None:
    sink = RerunSink(SinkOptions(save=tmp_path / "saved.rrd"))
    thinner = ViewerThinning(Dispatcher(sink), sink, Lag(), clock=Clock())  # type: ignore[arg-type]
    assert thinner.stats_hold_s() == 0.0
    thinner.pace.update(0.0, round_trip=0.6, answers=0.1)  # behind, the viewer quick to answer
    assert (thinner.pace.interval, thinner.pace.period) == (FIRST_INTERVAL_S, SHORTEST_PERIOD_S)
    assert thinner.stats_hold_s() == HELD_S
    thinner.pace.interval = 0.0
    thinner.pace.period = LONGEST_PERIOD_S  # batched longer: the viewer is slow to answer
    assert thinner.stats_hold_s() == HELD_S
    thinner.pace.period = SHORTEST_PERIOD_S  # caught up
    assert thinner.stats_hold_s() == 0.0
    thinner.close()
    sink.close()
