"""The host sees a bag's end when the bag input reaches it, not at its next look at the input
(issue 13: every conversion paid up to ``POLL_S`` there)."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path

import pytest

from host_bridge import app
from host_bridge.cli import main as host_main
from host_bridge.core.destinations import SinkOptions
from host_bridge.errors import InputError
from host_bridge.inputs.bag import BagInput
from host_bridge.inputs.base import Deliver, InputItem
from robot_relay.sources.bag import BagSource
from tests.integration.robot_bags import Entry, joint_state, write_bag
from tests.rrd import entity_rows

GENEROUS_S = 60.0
"""Bounds a wait that a loaded machine may stretch; the tests assert what happened, not when."""


class EndingInput:
    """An Input that ends when the test says so."""

    def __init__(self) -> None:
        self.over = threading.Event()
        self.last_activity = 0.0

    def start(self, deliver: Deliver) -> None:
        pass

    def ended(self) -> bool:
        return self.over.is_set()

    def close(self) -> None:
        pass


def waiting(source: EndingInput, stop: threading.Event, ended: threading.Event | None) -> threading.Thread:
    thread = threading.Thread(target=app.wait_for_end, args=(source, stop, None, None, ended))
    thread.start()
    return thread


def test_an_ended_input_wakes_the_wait_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    # An hour between looks: the wait can only return this soon because the event woke it.
    monkeypatch.setattr(app, "POLL_S", 3600.0)
    source, stop, ended = EndingInput(), threading.Event(), threading.Event()
    thread = waiting(source, stop, ended)
    source.over.set()
    ended.set()
    thread.join(GENEROUS_S)
    assert not thread.is_alive()
    assert not stop.is_set()


def test_a_stop_still_ends_the_wait_for_an_input_that_has_not_ended(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(app, "POLL_S", 0.01)
    source, stop, ended = EndingInput(), threading.Event(), threading.Event()
    thread = waiting(source, stop, ended)
    stop.set()
    thread.join(GENEROUS_S)
    assert not thread.is_alive()
    assert not source.ended()


def ten_joint_states(directory: Path) -> Path:
    return write_bag(directory, [
        Entry("/joint_states", "sensor_msgs/msg/JointState", i * 10**8, joint_state(i * 10**8, [i, -i]))
        for i in range(10)
    ])


def test_the_bag_input_finishes_after_delivering_every_message(tmp_path: Path) -> None:
    delivered: list[int] = []
    source = BagInput(ten_joint_states(tmp_path / "bag"), "robot")

    def deliver(items: Sequence[InputItem]) -> None:
        assert not source.finished.is_set()
        delivered.append(sum(len(item) if isinstance(item, Sequence) else 1 for item in items))

    source.start(deliver)
    assert source.finished.wait(GENEROUS_S)
    assert (sum(delivered), source.ended()) == (10, True)
    source.close()


def test_a_bag_that_cannot_be_read_finishes_too_and_says_why(tmp_path: Path) -> None:
    source = BagInput(tmp_path / "no_such_bag", "robot")
    source.start(lambda items: None)
    assert source.finished.wait(GENEROUS_S)
    with pytest.raises(InputError, match="no_such_bag"):
        source.ended()
    source.close()


def test_the_host_converting_a_bag_returns_when_the_bag_ends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # An hour between looks at the input: run() returns this soon only through the bag's event.
    monkeypatch.setattr(app, "POLL_S", 3600.0)
    out = tmp_path / "out.rrd"
    options = app.HostOptions(
        sink=SinkOptions(save=out), bag=ten_joint_states(tmp_path / "bag"), send_layout=False
    )
    outputs = app.Outputs()
    codes: list[int] = []
    thread = threading.Thread(
        target=lambda: codes.append(app.run(options, threading.Event(), lambda: False, outputs)),
        daemon=True,  # if the bag's end were missed, it would wait out the hour
    )
    thread.start()
    thread.join(GENEROUS_S)
    assert not thread.is_alive()
    assert outputs.close()
    assert codes == [0]
    left = "/robot/joint_states/wheel_left_joint/position"
    rows = entity_rows(out, left)[left]
    assert sorted(row["Scalars:scalars"][0] for row in rows) == [float(i) for i in range(10)]


def test_the_command_opens_its_bag_once_while_the_app_imports(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # cli.main opens the bag on a thread before importing the app (inputs/bag_opener.py); the
    # progress line's extent and the conversion both read that opening.
    opened: list[tuple[Path, str]] = []
    open_source = BagSource.open

    def counted(source: BagSource) -> BagSource:
        opened.append((source.paths[0], threading.current_thread().name))
        return open_source(source)

    monkeypatch.setattr(BagSource, "open", counted)
    out = tmp_path / "out.rrd"
    bag = ten_joint_states(tmp_path / "bag")
    assert host_main(["--bag", str(bag), "--save", str(out), "--no-blueprint"]) == 0
    assert opened == [(bag, "bag-open")]
    left = "/robot/joint_states/wheel_left_joint/position"
    rows = entity_rows(out, left)[left]
    assert sorted(row["Scalars:scalars"][0] for row in rows) == [float(i) for i in range(10)]
