"""/_stats from RawMessages with known times, sizes and sequence gaps: exact numbers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from host_bridge.core.columns import PackedPayloads
from host_bridge.core.contract import TIMELINE_LOG, TIMELINE_RECEIVE, ColumnsItem, RowsColumn
from host_bridge.core.counters import SHORT_RUN, TopicCounters, sequence_gap, sequence_gaps
from host_bridge.core.destinations import SinkOptions
from host_bridge.core.rerun_private import column_values
from host_bridge.inputs.base import MessageRun
from host_bridge.inputs.clocks import ClockEstimate
from host_bridge.outputs.sink import RerunSink
from host_bridge.outputs.stats import (
    HostDrops,
    QuietZeros,
    RelayRates,
    StatsTap,
    StatsTracker,
    TopicStats,
    clock_items,
    topic_stats_items,
)
from robot_relay.wire import RawMessage, RelayReport
from tests.rrd import entity_rows

S = 1_000_000_000
MS = 1_000_000
T0 = 1_700_000_000 * S  # a whole second


def live(topic: str, at: int, sequence: int, size: int = 100, robot: str = "tb3") -> RawMessage:
    return RawMessage(robot, topic, "std_msgs/msg/String", b"\0" * size, receive_ns=at,
                      log_ns=at - 5 * MS, sequence=sequence)


def test_rate_bandwidth_drops_latency_per_second() -> None:
    tracker = StatsTracker()
    closed: list[TopicStats] = []
    # Second 0: /scan at 10 Hz, sequences 0..9 except 3 and 4 (lost), 1000 bytes, 20 ms late.
    for seq in (0, 1, 2, 5, 6, 7, 8, 9):
        at = T0 + seq * 100 * MS
        closed += tracker.observe(live("/scan", at, seq, 1000), host_ns=at + 20 * MS)
    # /odom: two messages, 50 and 70 ms late.
    closed += tracker.observe(live("/odom", T0 + 10 * MS, 0), host_ns=T0 + 60 * MS)
    closed += tracker.observe(live("/odom", T0 + 20 * MS, 1), host_ns=T0 + 90 * MS)
    assert closed == []  # the second has not ended yet
    # Second 1 starts: closes second 0 for both topics.
    closed = tracker.observe(live("/scan", T0 + S, 10, 1000), host_ns=T0 + S + 20 * MS)
    by_topic = {s.topic: s for s in closed}
    scan = by_topic["/scan"]
    assert (scan.robot, scan.timeline, scan.end_ns) == ("tb3", TIMELINE_RECEIVE, T0 + S)
    assert scan.rate_hz == 8.0
    assert scan.bandwidth_kbps == 8 * 1000 * 8 / 1000
    assert scan.drops == 2
    assert scan.latency_ms == 20.0
    assert scan.convert_ms is None
    odom = by_topic["/odom"]
    assert (odom.rate_hz, odom.drops, odom.latency_ms) == (2.0, 0, 60.0)
    assert odom.bandwidth_kbps == 2 * 100 * 8 / 1000


def test_silence_gives_zero_rate_and_a_long_one_is_skipped() -> None:
    tracker = StatsTracker()
    tracker.observe(live("/scan", T0, 0), T0)
    closed = tracker.observe(live("/scan", T0 + 3 * S + 1, 1), T0 + 3 * S + 1)
    assert [(s.end_ns, s.rate_hz) for s in closed] == [
        (T0 + S, 1.0), (T0 + 2 * S, 0.0), (T0 + 3 * S, 0.0)
    ]
    closed = tracker.observe(live("/scan", T0 + 3600 * S, 2), T0 + 3600 * S)
    # An hour of silence: one empty period, not 3600.
    assert [(s.end_ns, s.rate_hz) for s in closed] == [(T0 + 4 * S, 1.0), (T0 + 5 * S, 0.0)]
    closed = tracker.observe(live("/scan", T0 + 3601 * S, 3), T0 + 3601 * S)
    assert [(s.end_ns, s.rate_hz, s.drops) for s in closed] == [(T0 + 3601 * S, 1.0, 0)]


def test_robots_have_their_own_clocks_and_a_bag_uses_log_time() -> None:
    tracker = StatsTracker()
    bag = RawMessage("bag", "/tf", "tf2_msgs/msg/TFMessage", b"1234", log_ns=5 * S + 1)
    assert tracker.observe(bag, 0) == []
    assert tracker.observe(live("/scan", T0, 0), T0) == []  # another robot: nothing closes
    closed = tracker.observe(RawMessage("bag", "/tf", "x", b"", log_ns=6 * S), 0)
    assert [(s.robot, s.timeline, s.end_ns, s.rate_hz, s.latency_ms) for s in closed] == [
        ("bag", TIMELINE_LOG, 6 * S, 1.0, None)
    ]
    assert tracker.observe(RawMessage("bag", "/x", "x", b""), 0) == []  # no time: not counted


def test_sequence_wrap_and_relay_restart_are_not_drops() -> None:
    tracker = StatsTracker()
    for i, seq in enumerate((0xFFFFFFFE, 0xFFFFFFFF, 0, 1, 0, 1, 3)):
        tracker.observe(live("/scan", T0 + i * MS, seq), T0)
    (scan,) = tracker.observe(live("/scan", T0 + S, 4), T0 + S)
    assert scan.drops == 1  # only 2 is missing


def test_host_drops_are_counted_apart_from_the_links_and_flushed_at_stop() -> None:
    # What the host's queue had dropped per topic when it handed over each batch.
    dropped: dict[str, int] = {}
    tracker = StatsTracker(host_dropped=lambda robot: dict(dropped) if robot == "tb3" else {})
    # Batch 1: /scan 0-4 were dropped before the first one the tap sees (no gap to show them).
    dropped["/scan"] = 5
    assert tracker.observe_batch([live("/scan", T0, 5), live("/scan", T0 + 100 * MS, 6)], T0) == []
    # Batch 2: 7 and 8 dropped by the host, 9 lost on the link; /odom's only message dropped.
    dropped.update({"/scan": 7, "/odom": 1})
    assert tracker.observe_batch([live("/scan", T0 + 500 * MS, 10)], T0) == []
    # Batch 3 opens the next second: the first closes.
    closed = tracker.observe_batch([live("/scan", T0 + S, 11)], T0 + S)
    assert [(s.topic, s.rate_hz, s.drops, s.host_drops) for s in closed] == [
        ("/scan", 3.0, 1, 7),
        ("/odom", 0.0, 0, 1),  # nothing reached the pipeline, yet its drops show
    ]
    paths = [i.path for i in topic_stats_items(closed)]
    assert [p for p in paths if p.startswith("/_stats/tb3/odom/")] == [
        "/_stats/tb3/odom/rate_hz", "/_stats/tb3/odom/bandwidth_kbps", "/_stats/tb3/odom/drops",
        "/_stats/tb3/odom/host_drops",
    ]
    # /scan 12 and 13 dropped after the last closed period: logged when the host stops, once.
    dropped["/scan"] = 9
    assert tracker.host_drops_at_stop() == [
        HostDrops("tb3", "/scan", TIMELINE_RECEIVE, T0 + 2 * S, 2)
    ]
    assert tracker.host_drops_at_stop() == []


def test_without_a_host_queue_there_is_no_host_drops_series() -> None:
    tracker = StatsTracker()  # a bag: no queue between the input and the pipeline
    tracker.observe_batch([live("/scan", T0, 0), live("/scan", T0 + MS, 3)], T0)
    (scan,) = tracker.observe_batch([live("/scan", T0 + S, 4)], T0 + S)
    assert (scan.drops, scan.host_drops) == (2, None)
    assert [i.path for i in topic_stats_items([scan]) if "drops" in i.path] == [
        "/_stats/tb3/scan/drops"
    ]
    assert tracker.host_drops_at_stop() == []


def test_convert_time_from_the_dispatcher_counters() -> None:
    counters = {("tb3", "/scan"): TopicCounters("x", converted=0, convert_seconds=0.0)}

    def totals(robot: str, topic: str) -> tuple[int, float]:
        c = counters.get((robot, topic))
        return (0, 0.0) if c is None else (c.converted, c.convert_seconds)

    tracker = StatsTracker(convert_totals=totals)
    tracker.observe(live("/scan", T0, 0), T0)
    counters["tb3", "/scan"] = TopicCounters("x", converted=4, convert_seconds=0.010)
    (scan,) = tracker.observe(live("/scan", T0 + S, 1), T0 + S)
    assert scan.convert_ms == pytest.approx(2.5)
    assert scan.convert_seconds == pytest.approx(0.010)
    items = {i.path: i for i in topic_stats_items([scan])}
    assert sorted(items) == [
        "/_stats/tb3/host/convert_load_percent", "/_stats/tb3/scan/bandwidth_kbps",
        "/_stats/tb3/scan/convert_ms", "/_stats/tb3/scan/drops", "/_stats/tb3/scan/latency_ms",
        "/_stats/tb3/scan/rate_hz",
    ]
    load = items["/_stats/tb3/host/convert_load_percent"]
    assert row_value(load) == pytest.approx(1.0)
    assert {name: values.tolist() for name, values in load.times.items()} == {TIMELINE_RECEIVE: [T0 + S]}
    assert row_value(items["/_stats/tb3/scan/convert_ms"]) == pytest.approx(2.5)


def row_value(item: ColumnsItem) -> float:
    """The value of a one-row Scalars item (a slice of the batch its period's rows share)."""
    (column,) = item.columns
    assert isinstance(column, RowsColumn)
    first, end = column.row_offsets.tolist()
    assert end == first + 1
    return float(column_values(column)[first].as_py())


def test_relay_rates_between_reports() -> None:
    rates = RelayRates()
    first = rates.items(RelayReport("tb3", T0, 12.5, messages=100, payload_bytes=10_000))
    assert [i.path for i in first] == ["/_stats/tb3/relay/cpu_percent"]
    second = rates.items(RelayReport("tb3", T0 + 2 * S, 30.0, messages=300, payload_bytes=260_000))
    values = {i.path: i.archetypes[0].scalars.as_arrow_array().to_pylist()  # type: ignore[attr-defined]
              for i in second}
    assert values == {
        "/_stats/tb3/relay/cpu_percent": [30.0],
        "/_stats/tb3/relay/sent_hz": [100.0],
        "/_stats/tb3/relay/sent_kbps": [1000.0],
    }


def test_a_relay_clocks_offset_and_uncertainty_in_milliseconds_at_the_pcs_time() -> None:
    items = clock_items("tb3", ClockEstimate(7_500_123_456, 412_000, T0 + 3 * S))
    assert [(i.path, i.archetypes[0].scalars.as_arrow_array().to_pylist(),  # type: ignore[attr-defined]
             i.times) for i in items] == [
        ("/_stats/tb3/clock/offset_ms", [7500.123456], {TIMELINE_RECEIVE: T0 + 3 * S}),
        ("/_stats/tb3/clock/uncertainty_ms", [0.412], {TIMELINE_RECEIVE: T0 + 3 * S}),
    ]


def test_stats_tap_logs_scalars_into_rerun(tmp_path: Path) -> None:
    out = tmp_path / "stats.rrd"
    sink = RerunSink(SinkOptions(save=out))
    clock = iter([T0 + 950 * MS, T0 + S + 450 * MS, T0 + 2 * S + 30 * MS])
    tap = StatsTap(sink, {}, clock=lambda: next(clock))
    tap([live("/scan", T0 + i * 100 * MS, i) for i in range(10)])
    tap([live("/scan", T0 + S + i * 100 * MS, 10 + 2 * i) for i in range(5)])
    tap([live("/scan", T0 + 2 * S, 20)])
    sink.close()
    rows = entity_rows(out)

    def series(name: str) -> list[tuple[int, Any]]:
        return [(r[TIMELINE_RECEIVE], r["Scalars:scalars"][0]) for r in rows[f"/_stats/tb3/scan/{name}"]]

    assert series("rate_hz") == [(T0 + S, 10.0), (T0 + 2 * S, 5.0)]
    assert series("drops") == [(T0 + S, 0.0), (T0 + 2 * S, 4.0)]
    # The host clock is read once per run (as it is taken from the input queue).
    assert series("latency_ms") == [(T0 + S, pytest.approx(950 - 450)),
                                    (T0 + 2 * S, pytest.approx(450 - 200))]


class LogCalls:
    """A stand-in sink: each ``log`` call's (entity path, receive time) pairs."""

    def __init__(self) -> None:
        self.calls: list[list[tuple[str, int]]] = []

    def log(self, items: list[Any], times: dict[str, int]) -> None:
        self.calls.append([(item.path, int(np.asarray(item.times[TIMELINE_RECEIVE]).flat[0]))
                           for item in items])


def test_rows_held_for_a_slow_viewer_are_logged_together_in_order() -> None:
    """While the viewers take data in slowly (thinning.py), a host's /_stats rows of several
    seconds are logged at once (one chunk per series, not one per second); none is lost."""
    sink, hold_s = LogCalls(), [5.0]
    seconds = iter(range(20))
    tap = StatsTap(sink, {}, clock=lambda: T0 + next(seconds) * S + 950 * MS,  # type: ignore[arg-type]
                   hold_s=lambda: hold_s[0])
    for second in range(8):  # second k's batch closes second k - 1
        tap([live("/scan", T0 + second * S + i * 100 * MS, 10 * second + i) for i in range(10)])
    rate = "/_stats/tb3/scan/rate_hz"
    calls = [[at for path, at in call if path == rate] for call in sink.calls]
    assert calls == [[T0 + k * S for k in range(1, 7)]]  # held from second 1's row to 6's
    hold_s[0] = 0.0  # the viewer caught up: each row as it comes
    tap([live("/scan", T0 + 8 * S, 80)])
    tap.close()  # logs the last quiet zero of the drops (QuietZeros), no rate row
    calls = [[at for path, at in call if path == rate] for call in sink.calls]
    assert calls == [[T0 + k * S for k in range(1, 7)], [T0 + 7 * S, T0 + 8 * S], []]


def test_a_drop_count_is_logged_where_it_changes_and_every_ten_periods_else() -> None:
    quiet = QuietZeros(every=10, period_ns=S)
    drops = [0] * 12 + [3, 0, 2, 2] + [0] * 14
    logged = [row for n, count in enumerate(drops)
              for row in quiet.rows("/d", TIMELINE_RECEIVE, T0 + (n + 1) * S, float(count))]
    assert logged == [
        (T0 + S, 0.0),  # the first period
        (T0 + 11 * S, 0.0),  # ten periods on
        (T0 + 12 * S, 0.0), (T0 + 13 * S, 3.0),  # the run begins after period 12 ...
        (T0 + 14 * S, 0.0), (T0 + 15 * S, 2.0), (T0 + 16 * S, 2.0),
        (T0 + 17 * S, 0.0),  # ... and ends at 17
        (T0 + 27 * S, 0.0),
    ]
    assert quiet.skipped() == [("/d", TIMELINE_RECEIVE, T0 + 30 * S)]  # logged when the host stops


def test_stats_tap_logs_each_drop_count_where_it_changes_and_the_last_zero_at_stop(
    tmp_path: Path,
) -> None:
    out = tmp_path / "stats.rrd"
    sink = RerunSink(SinkOptions(save=out))
    clock = iter(T0 + n * S for n in range(100))
    tap = StatsTap(sink, {}, clock=lambda: next(clock))
    sequence = 0
    for second in range(25):
        sequence += 2 if second == 15 else 1  # one /scan message lost in second 15
        tap([live("/scan", T0 + second * S + 500 * MS, sequence)])
    tap.close()
    sink.close()
    rows = entity_rows(out)

    def series(name: str) -> list[tuple[int, Any]]:
        return [(r[TIMELINE_RECEIVE], r["Scalars:scalars"][0]) for r in rows[f"/_stats/tb3/scan/{name}"]]

    assert len(series("rate_hz")) == 24  # the 25th second is still open
    assert series("drops") == [
        (T0 + S, 0.0), (T0 + 11 * S, 0.0), (T0 + 15 * S, 0.0), (T0 + 16 * S, 1.0),
        (T0 + 17 * S, 0.0), (T0 + 24 * S, 0.0),  # the last closed period, at stop
    ]


def as_run(messages: list[RawMessage]) -> MessageRun:
    """``messages`` (one topic) as the run a relay's bundles bring: arrays, payloads packed."""
    first = messages[0]
    return MessageRun(
        first.robot, first.topic, first.msgtype, None,
        PackedPayloads.of([m.data for m in messages]),
        log_ns=np.array([m.log_ns for m in messages], np.int64),
        receive_ns=np.array([m.receive_ns for m in messages], np.int64),
        sequence=np.array([m.sequence for m in messages], np.int64),
    )


@pytest.mark.parametrize("seed", range(20))
def test_a_run_counts_as_its_messages_one_by_one(seed: int) -> None:
    """Random runs over period ends, with sequence gaps, wraps and host drops: the closed
    periods are the same whether the batch is a run or its messages."""
    rng = np.random.default_rng(seed)
    dropped = {"/imu": 0}
    by_message = StatsTracker(host_dropped=lambda robot: dict(dropped))
    by_run = StatsTracker(host_dropped=lambda robot: dict(dropped))
    at, sequence = T0, int(rng.choice([0, 0xFFFFFFF0]))
    closed: tuple[list[TopicStats], list[TopicStats]] = ([], [])
    for _ in range(30):
        messages = []
        for _ in range(int(rng.integers(1, 40))):
            at += int(rng.integers(0, 300)) * MS
            sequence = (sequence + 1 + int(rng.choice([0, 0, 0, 1, 3]))) & 0xFFFFFFFF
            messages.append(live("/imu", at, sequence, size=int(rng.integers(10, 500))))
        dropped["/imu"] += int(rng.choice([0, 0, 1, 2]))
        host_ns = at + int(rng.integers(0, 50)) * MS
        closed[0].extend(by_message.observe_batch(messages, host_ns))
        closed[1].extend(by_run.observe_batch(as_run(messages), host_ns))
    assert len(closed[0]) > 5
    assert closed[0] == closed[1]


def test_sequence_gaps_of_a_run_sum_the_gaps_between_its_messages() -> None:
    numbers = [5, 6, 9, 0xFFFFFFFF, 0, 2]
    gaps = sum(sequence_gap(last, n) for last, n in zip([3, *numbers], numbers, strict=False))
    assert sequence_gaps(3, np.array(numbers, np.int64)) == gaps == 1 + 2 + 0 + 0 + 1
    assert sequence_gaps(None, np.array(numbers, np.int64)) == 2 + 0 + 0 + 1  # nothing before
    assert sequence_gaps(7, np.array([], np.int64)) == 0
    # A run as long as SHORT_RUN or longer is summed with numpy: the same sums.
    longer = numbers + [n * 3 for n in range(1, SHORT_RUN)]
    gaps = sum(sequence_gap(last, n) for last, n in zip([3, *longer], longer, strict=False))
    assert sequence_gaps(3, np.array(longer, np.int64)) == gaps == 1 + 2 + 0 + 0 + 1 + 0 + 14 * 2
