"""The relay's own stats report: CPU from os.times() deltas, and its JSON on the wire."""

from __future__ import annotations

import json

import pytest

from robot_relay.errors import WireError
from robot_relay.stats import CpuMeter, process_cpu_seconds
from robot_relay.wire import RelayReport, stats_key


def test_cpu_meter_is_cpu_time_over_wall_time() -> None:
    clock = iter([10.0, 12.0, 12.0, 13.0])
    cpu = iter([1.0, 1.5, 1.5, 3.0])
    meter = CpuMeter(cpu_seconds=lambda: next(cpu), clock=lambda: next(clock))
    assert meter.percent() == 25.0  # 0.5 s of CPU in 2 s
    assert meter.percent() == 0.0  # no time passed
    assert meter.percent() == 150.0  # two threads busy: more than one core


def test_cpu_meter_on_this_process_sees_work() -> None:
    meter = CpuMeter()
    started = process_cpu_seconds()
    while process_cpu_seconds() - started < 0.2:
        sum(range(10_000))
    assert meter.percent() > 5.0


def test_report_round_trips_and_rejects_other_versions() -> None:
    report = RelayReport("tb3", 1_700_000_000_000_000_000, 12.34, messages=5, payload_bytes=999)
    key = stats_key("tb3")
    assert key == "swanky/tb3/stats"
    assert RelayReport.from_json(report.to_json(), key) == report
    with pytest.raises(WireError, match=r"swanky/tb3/stats.*version 2"):
        RelayReport.from_json(report.to_json().replace('"version": 1', '"version": 2'), key)
    with pytest.raises(WireError, match="not valid"):
        RelayReport.from_json("{}", key)


def test_report_carries_drops_per_topic_and_reads_reports_without_them() -> None:
    report = RelayReport("tb3", 5, 1.0, messages=9, payload_bytes=90, drops={"/odom": 3})
    key = stats_key("tb3")
    assert json.loads(report.to_json())["drops"] == {"/odom": 3}
    assert RelayReport.from_json(report.to_json(), key) == report
    older = json.dumps({"version": 1, "robot": "tb3", "time_ns": 5, "cpu_percent": 1.0,
                        "messages": 9, "bytes": 90})
    assert RelayReport.from_json(older, key).drops == {}


def test_host_logs_the_drops_since_the_previous_report() -> None:
    from host_bridge.outputs.stats import RelayRates

    rates = RelayRates()

    def drops(report: RelayReport) -> dict[str, list[float]]:
        return {item.path: item.archetypes[0].scalars.as_arrow_array().to_pylist()  # type: ignore[attr-defined]
                for item in rates.items(report) if item.path.endswith("/ros_drops")}

    assert drops(RelayReport("tb3", 1_000, 1.0, 10, 100, {"/odom": 2})) == {
        "/_stats/tb3/odom/ros_drops": [2.0]
    }
    assert drops(RelayReport("tb3", 2_000, 1.0, 20, 200, {"/odom": 2, "/scan": 5})) == {
        "/_stats/tb3/odom/ros_drops": [0.0], "/_stats/tb3/scan/ros_drops": [5.0]
    }
    # The relay restarted: its counts began again; nothing negative is logged.
    assert drops(RelayReport("tb3", 3_000, 1.0, 1, 10, {"/odom": 1})) == {}
