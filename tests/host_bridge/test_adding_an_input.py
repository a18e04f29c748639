"""CONTRIBUTING.md's "Adding an input", done once: a made-up input (a thermometer's log file,
``<seconds> <celsius>`` per line) written against host_bridge/inputs/base.py, opened where
``app.open_input`` opens the real ones, and run by the real command line into a ``--save`` file
that is read back."""

from __future__ import annotations

import threading
import time
from contextlib import ExitStack
from pathlib import Path

import pytest
from rosbags.typesys import Stores, get_typestore

from host_bridge import app, cli
from host_bridge.inputs.base import Deliver, Input, RobotEvent
from host_bridge.pipeline.dispatch import Dispatcher
from robot_relay.wire import RawMessage
from tests.rrd import entity_rows

FLOAT64 = "std_msgs/msg/Float64"
STORE = get_typestore(Stores.ROS2_HUMBLE)


class ThermometerLogInput:
    """Step 1: the four members of the Input protocol. Reads on a thread of its own and hands
    the dispatcher one run of RawMessages (CDR as ROS serialises it, the log time from the
    file), after saying the robot joined."""

    def __init__(self, path: Path, robot: str) -> None:
        self.path = path
        self.robot = robot
        self.last_activity = time.monotonic()
        self._thread: threading.Thread | None = None

    def start(self, deliver: Deliver) -> None:
        self._thread = threading.Thread(target=self._read, args=(deliver,), daemon=True)
        self._thread.start()

    def _read(self, deliver: Deliver) -> None:
        deliver([RobotEvent(self.robot, joined=True, source="thermometer log")])
        run = []
        for line in self.path.read_text(encoding="utf-8").splitlines():
            seconds, celsius = line.split()
            cdr = bytes(STORE.serialize_cdr(STORE.types[FLOAT64](data=float(celsius)), FLOAT64))
            run.append(RawMessage(self.robot, "/temperature", FLOAT64, cdr,
                                  log_ns=int(float(seconds) * 1e9)))
        self.last_activity = time.monotonic()
        deliver(run)

    def ended(self) -> bool:
        return self._thread is not None and not self._thread.is_alive()

    def close(self) -> None:
        if self._thread is not None:
            self._thread.join()


pytestmark = pytest.mark.usefixtures("keep_signal_handlers")  # main() installs its own


def test_a_new_input_runs_through_the_host_into_a_saved_recording(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    log_file = tmp_path / "thermometer.log"
    log_file.write_text("100.0 20.5\n100.5 21.0\n101.0 21.5\n", encoding="utf-8")

    def open_input(
        options: app.HostOptions, dispatcher: Dispatcher, *, demo: object,
        robot_files: object, stop: threading.Event, closing: ExitStack, bag_opener: object = None,
        layout: object = None,
    ) -> Input:
        """Step 3: built where app.open_input builds the others (its flag is step 2)."""
        source: Input = ThermometerLogInput(log_file, options.robot)
        closing.callback(source.close)
        return source

    monkeypatch.setattr(app, "open_input", open_input)
    out = tmp_path / "thermometer.rrd"
    code = cli.main(["--robot", "lab", "--save", str(out), "--no-blueprint", "--no-stats"])
    assert code == 0, capsys.readouterr().err
    rows = entity_rows(out)
    temperature = rows["/lab/temperature"]
    assert [row["Scalars:scalars"] for row in temperature] == [[20.5], [21.0], [21.5]]
    assert [row["log_time"] for row in temperature] == [100_000_000_000, 100_500_000_000,
                                                          101_000_000_000]
    assert [row["TextLog:text"] for row in rows["/_swanky/robots"]] == [
        ["robot lab joined (thermometer log)"]
    ]
    summary = capsys.readouterr().err.splitlines()
    assert summary[-2].split()[:8] == ["lab", "/temperature", FLOAT64, "3", "3", "0", "0", "0"]
