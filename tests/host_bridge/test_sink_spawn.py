"""A viewer that dies right after spawning (a headless machine) is a clear error, not a hang."""

from __future__ import annotations

import socket
from typing import Any

import pytest
import rerun as rr

from host_bridge import sink
from host_bridge.errors import SinkError


def test_viewer_that_never_listens_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket() as sock:  # a port where nothing listens
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    spawned: list[dict[str, Any]] = []
    monkeypatch.setattr(sink, "VIEWER_PORT", port)
    monkeypatch.setattr("shutil.which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr(rr, "spawn", lambda **kwargs: spawned.append(kwargs))
    with pytest.raises(SinkError, match=r"exited without listening.*--save FILE\.rrd or --serve-web"):
        sink.RerunSink(sink.SinkOptions(spawn=True))
    assert len(spawned) == 1
