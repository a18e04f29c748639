"""What the robot does from tick to tick: its /rosout lines and the step timer."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from host_bridge.demo import messages, robot
from tests.host_bridge.demo.support import SHORT_S, Messages, log_stamp_ns


def test_rosout_reports_waypoints_and_doorways() -> None:
    store = messages.typestore()
    logs: list[Any] = [
        store.deserialize_cdr(m.data, m.msgtype) for m in messages.simulate(20.0, topics={"/rosout"})
    ]
    expected = [(20, "driving the apartment loop"), (30, "camera: no calibration"),
                (30, "passing a doorway"), (20, "waypoint 1 reached")]
    assert len(logs) == len(expected)
    for m, (level, start) in zip(logs, expected, strict=True):
        assert (m.level, m.msg[: len(start)]) == (level, start)
    assert logs[3].msg.startswith("waypoint 1 reached at (6.0, 1.7)")
    assert all(m.name == "swanky_bot.driver" for m in logs)
    # the doorway warning comes as the robot passes x = 4 at about 0.22 m/s
    seconds = [(log_stamp_ns(m) - messages.DEFAULT_START_NS) / 1e9 for m in logs]
    assert seconds[:2] == pytest.approx([0.0, 1.0 / robot.TICK_HZ])  # one line per tick
    assert 7.0 < seconds[2] < 8.5


def test_step_timer_is_a_positive_series(short: Messages) -> None:
    values = np.array([m.data for _, m in short[messages.STEP_TIMER_TOPIC]])
    assert len(values) == SHORT_S * robot.TICK_HZ
    assert np.all((values > 0.5) & (values < 8.0))
    # camera ticks cost more than plain control ticks
    assert values[::6].mean() > values[1::6].mean() + 2.0
