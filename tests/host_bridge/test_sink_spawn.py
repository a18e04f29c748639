"""Spawning the viewer: the ``rerun`` beside the running Python is found without an activated
venv, and a viewer that dies at once is a clear error saying why (no display, or a display it
cannot use), not a hang."""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import sysconfig
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr

from host_bridge.core.contract import LogItem
from host_bridge.core.destinations import SinkOptions
from host_bridge.errors import SinkError
from host_bridge.outputs import sink
from tests.integration.procs import headless_viewer
from tests.rrd import entity_rows
from tests.viewer_port import default_viewer_port


def test_viewer_beside_the_interpreter_is_found_without_path(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))  # what `.venv/bin/swanky-host` sees, unactivated
    beside = Path(sysconfig.get_path("scripts")) / "rerun"
    assert beside.is_file(), f"rerun-sdk installs its viewer as {beside}"
    assert sink.viewer_executable() == str(beside)


def test_viewer_on_path_is_the_last_resort(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    elsewhere = tmp_path / "rerun"
    elsewhere.write_text("#!/bin/sh\n", encoding="utf-8")
    elsewhere.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(sysconfig, "get_path", lambda *args: str(tmp_path / "empty"))
    monkeypatch.setattr(sys, "executable", str(tmp_path / "empty" / "python"))
    assert sink.viewer_executable() == str(elsewhere)


def _port_nobody_listens_on() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.mark.parametrize(
    ("display", "reason"),
    [
        ({}, "no display: DISPLAY and WAYLAND_DISPLAY are unset"),
        ({"DISPLAY": ":99"}, "DISPLAY=:99 is set but the viewer could not open a window there"),
        ({"WAYLAND_DISPLAY": "wayland-0"}, "WAYLAND_DISPLAY=wayland-0 is set but the viewer could not"),
    ],
)
def test_viewer_that_never_listens_is_named(
    monkeypatch: pytest.MonkeyPatch, display: dict[str, str], reason: str
) -> None:
    port = _port_nobody_listens_on()
    spawned: list[dict[str, Any]] = []
    monkeypatch.setattr(sink, "VIEWER_PORT", port)
    monkeypatch.setattr(sys, "platform", "linux")
    for name in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(name, raising=False)
    for name, value in display.items():
        monkeypatch.setenv(name, value)
    monkeypatch.setattr(rr, "spawn", lambda **kwargs: spawned.append(kwargs))
    with pytest.raises(SinkError) as caught:
        sink.RerunSink(SinkOptions(spawn=True))
    viewer = sink.viewer_executable()
    assert str(caught.value).startswith(
        f"cannot spawn the Rerun viewer {viewer}: it exited without listening on port {port} ({reason}"
    )
    assert str(caught.value).endswith("on a machine without a screen use --save FILE.rrd or --serve-web")
    assert [(call["port"], call["executable_path"]) for call in spawned] == [(port, viewer)]


def test_no_viewer_anywhere_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sink, "viewer_executable", lambda: None)
    with pytest.raises(SinkError) as caught:
        sink.RerunSink(SinkOptions(spawn=True))
    assert str(caught.value) == (
        f"cannot spawn the Rerun viewer: no 'rerun' executable beside {sys.executable} or on "
        "PATH; install rerun-sdk (pip install \".[host]\") or use --save FILE.rrd, --serve-web "
        "or --rerun-addr URL"
    )


def test_readme_demo_command_without_venv_on_path_finds_the_viewer(tmp_path: Path) -> None:
    """The README's ``.venv/bin/swanky-host --demo``, venv not activated, on a machine with no
    display: the real viewer is spawned (found beside the interpreter) and its failure named."""
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        pytest.skip("this machine has a display: the viewer would open")
    host = Path(sysconfig.get_path("scripts")) / "swanky-host"
    env = {"PATH": "/usr/bin:/bin", "HOME": os.environ.get("HOME", str(tmp_path))}
    with default_viewer_port():
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", sink.VIEWER_PORT)) == 0:
                pytest.skip(f"port {sink.VIEWER_PORT} is taken: rr.spawn would reuse what listens there")
        done = subprocess.run(
            [str(host), "--demo", "--duration", "5"], cwd=tmp_path, env=env, capture_output=True,
            text=True, timeout=120, check=False,
        )
    last = done.stderr.strip().splitlines()[-1]
    assert (done.returncode, last) == (2, (
        f"swanky-host: error: cannot spawn the Rerun viewer {host.parent / 'rerun'}: it exited "
        f"without listening on port {sink.VIEWER_PORT} (no display: DISPLAY and WAYLAND_DISPLAY "
        "are unset); on a machine without a screen use --save FILE.rrd or --serve-web"
    ))
    assert "Traceback" not in done.stderr


def test_closing_the_spawned_viewer_is_no_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Closing the viewer's window, then Ctrl-C: how a user ends the README's demo."""
    with headless_viewer() as (_, port, viewer):
        monkeypatch.setattr(sink, "VIEWER_PORT", port)
        monkeypatch.setattr(rr, "spawn", lambda **kwargs: None)  # it is already there
        rerun_sink = sink.RerunSink(SinkOptions(spawn=True, save=tmp_path / "out.rrd"))
        points = [LogItem(f"/p{i}", (rr.Points3D(np.full((50, 3), i, np.float32)),)) for i in range(20)]
        rerun_sink.log(points[:10], {"ros_time": 1})
        rerun_sink.flush()
        viewer.kill()
        viewer.wait(timeout=10)
        rerun_sink.log(points[10:], {"ros_time": 2})
        with caplog.at_level(logging.INFO, logger="swanky.host"):
            rerun_sink.close()  # no SinkError
    rows = entity_rows(tmp_path / "out.rrd")
    assert sorted(path for path in rows if path.startswith("/p")) == sorted(f"/p{i}" for i in range(20))
    assert caplog.messages in ([], ["the Rerun viewer was closed; not waiting for it"])
