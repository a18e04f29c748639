"""The Rerun side: one recording stream, its sinks (viewer, gRPC address, .rrd file, web), and
the only place that calls ``log`` / ``send_columns``."""

from __future__ import annotations

import shutil
import socket
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from host_bridge.errors import SinkError
from host_bridge.registry import ColumnsItem, LogEntry, LogItem

APPLICATION_ID = "swanky"


@dataclass(frozen=True, slots=True)
class SinkOptions:
    """Where the recording goes; several at once are allowed (e.g. a viewer and a file)."""

    spawn: bool = False
    connect: str | None = None
    save: Path | None = None
    serve_web: bool = False
    web_port: int | None = None
    grpc_port: int | None = None
    recording_id: str | None = None

    @property
    def any(self) -> bool:
        return self.spawn or self.connect is not None or self.save is not None or self.serve_web


VIEWER_PORT = 9876
"""Where ``rr.spawn`` starts the viewer and ``rr.GrpcSink()`` sends by default."""


def _listening(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(2.0)
        return sock.connect_ex(("127.0.0.1", port)) == 0


class RerunSink:
    """Logs converter output with the message's timelines."""

    def __init__(self, options: SinkOptions) -> None:
        self.recording = rr.RecordingStream(APPLICATION_ID, recording_id=options.recording_id)
        # Swanky sets log_time itself (the bag's record time); the SDK's wall clock would clash.
        rr.set_log_time_enabled(False, recording=self.recording)
        rr.set_log_tick_enabled(False, recording=self.recording)
        self.web_url: str | None = None
        self._open(options)
        # Rerun's time context is per thread (the dispatcher and the slow-converter worker).
        self._local = threading.local()

    def _open(self, options: SinkOptions) -> None:
        sinks: list[rr.sinks.LogSinkLike] = []
        if options.save is not None:
            if not options.save.parent.is_dir():
                msg = f"--save {options.save}: directory {options.save.parent} does not exist"
                raise SinkError(msg)
            sinks.append(rr.FileSink(str(options.save)))
        if options.spawn:
            if shutil.which("rerun") is None:
                msg = "cannot spawn the Rerun viewer: no 'rerun' executable on PATH"
                raise SinkError(msg)
            try:
                rr.spawn(connect=False, recording=self.recording)
            except Exception as err:
                msg = (
                    f"cannot spawn the Rerun viewer ({err}); on a headless machine use "
                    "--save FILE.rrd or --serve-web"
                )
                raise SinkError(msg) from err
            if not _listening(VIEWER_PORT):
                # rr.spawn only warns when the viewer dies at once (no display): without this
                # check every later flush would wait forever for it.
                msg = (
                    f"cannot spawn the Rerun viewer: it exited without listening on port "
                    f"{VIEWER_PORT} (no display?); on a headless machine use --save FILE.rrd or "
                    "--serve-web"
                )
                raise SinkError(msg)
            sinks.append(rr.GrpcSink())
        if options.connect is not None:
            sinks.append(rr.GrpcSink(options.connect))
        if options.serve_web:
            sinks.append(rr.GrpcServerSink(port=options.grpc_port or 9876))
        self.recording.set_sinks(*sinks)
        if options.serve_web:
            grpc_url = f"rerun+http://127.0.0.1:{options.grpc_port or 9876}/proxy"
            rr.serve_web_viewer(web_port=options.web_port, open_browser=False, connect_to=grpc_url)
            self.web_url = f"http://127.0.0.1:{options.web_port or 9090}/?url={grpc_url}"

    def _set_times(self, times: Mapping[str, int]) -> None:
        if times == getattr(self._local, "times", None):
            return
        self.recording.reset_time()
        for name, ns in times.items():
            self.recording.set_time(name, timestamp=np.datetime64(ns, "ns"))
        self._local.times = times

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        for entry in entries:
            if isinstance(entry, ColumnsItem):
                indexes = [
                    rr.TimeColumn(name, timestamp=values.astype("datetime64[ns]"))
                    for name, values in entry.times.items()
                ]
                self.recording.send_columns(entry.path, indexes=indexes, columns=entry.columns)
            elif isinstance(entry, LogItem):
                if entry.static:
                    self.recording.log(entry.path, *entry.archetypes, static=True)
                else:
                    self._set_times(times if entry.times is None else entry.times)
                    self.recording.log(entry.path, *entry.archetypes)

    def send_blueprint(self, blueprint: rrb.Blueprint) -> None:
        """Make ``blueprint`` the viewer's layout (and its default); a saved .rrd keeps it too."""
        self.recording.send_blueprint(blueprint, make_active=True, make_default=True)

    def send_blueprint_file(self, path: Path) -> None:
        """Send a saved .rbl as is: its blueprint store and activation travel with the data."""
        rr.log_file_from_path(path, recording=self.recording)

    def flush(self) -> None:
        self.recording.flush()

    def close(self) -> None:
        """Flush everything and close the sinks, so a saved .rrd is complete."""
        self.recording.flush()
        self.recording.disconnect()
