"""The Rerun side: one recording stream, its sinks (viewer, gRPC address, .rrd file, web), and
the only place that calls ``log`` / ``send_columns``.

Nothing here may wait for a viewer without bound: a viewer that is missing, dies or stops
reading is found out (an HTTP/2 probe, flushes waited on in short steps, a bounded close) and
named, so the host neither hangs nor ignores Ctrl-C, and a ``--save`` file is still completed.
A viewer slower than the data holds the host's robot workers back (:class:`_ViewerPacer`), so
the host's memory stays bounded and their queues drop, and count, what it cannot take."""

from __future__ import annotations

import errno
import ipaddress
import logging
import os
import shutil
import socket
import sys
import sysconfig
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import urlsplit

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
import rerun_bindings

from host_bridge.contract import ColumnsItem, LogEntry, LogItem, RowsColumn
from host_bridge.destinations import LOOPBACK, SinkOptions
from host_bridge.errors import SinkError

log = logging.getLogger("swanky.host")

APPLICATION_ID = "swanky"

ALL_INTERFACES = ("0.0.0.0", "::")
VIEWER_PORT = 9876
"""Where ``--spawn`` starts the viewer (Rerun's default), and a ``--serve-web`` gRPC default."""
WEB_PORT = 9090
"""``rr.serve_web_viewer``'s default HTTP port."""
REDAP_DEFAULT_PORT = 51234
"""The port Rerun's own URL parser (re_uri) assumes for a viewer URL that names none."""
VIEWER_SCHEMES = ("rerun", "rerun+http", "rerun+https")
PROBE_TIMEOUT_S = 2.0
H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
"""What an HTTP/2 client sends first: the magic line and an empty SETTINGS frame (RFC 9113)."""
H2_FRAME_HEADER = 9
H2_FRAME_TYPE = 3
H2_SETTINGS = 4
DISCONNECT_TIMEOUT_S = 6.0
"""Longer than Rerun's own 5 s wait for a viewer it is still connecting to at shutdown."""
FEW_ROWS = 4
"""ColumnsItems of up to this many rows are logged row by row (cheaper than send_columns)."""
FLUSH_STEP_S = 1.0
"""Flushes wait in steps this long, so Python sees signals and a dead viewer in between."""
EAGER_FLUSH_BYTES = 256 * 1024
"""Rerun's batcher holds logged rows until they add up to 2 MiB (two 640x480 images) or 200 ms
pass; at this size instead, each image or cloud of a bag goes on to the file's encoder as it is
logged, and the encoder works while the host converts rather than after. ``swanky-host --bag``
of benchmarks/bag_conversion.py's files, 4 and 3 alternated runs: large (300 images, 100 clouds,
597 MB) 1.41-1.66 s at 2 MiB, 1.17-1.33 s at this; small (470k messages, mostly send_columns,
whose chunks skip the batcher) 1.04-1.08 s and 0.95-1.04 s."""
PACE_PERIOD_S = 0.2
"""How often the gRPC viewers are asked whether they have taken everything logged so far."""
PACE_BEHIND_S = 0.5
"""A viewer that has not taken what was logged within this long is behind: logging waits."""


class Sink(Protocol):
    """Where converted entries go: what the dispatcher and the ``/_stats`` tap write to.
    :class:`RerunSink` is the host's; a second recording or a test's list would do as well."""

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        """Log ``entries`` (LogItems at ``times`` unless they carry their own, ColumnsItems
        with their time columns, static items once)."""

    def close(self) -> None:
        """Deliver everything logged (a file is then complete); a SinkError names what missed
        some."""


@dataclass(frozen=True, slots=True)
class ViewerAddress:
    """A viewer this host sends to as a gRPC client: ``name`` is what the user gave (or knows)."""

    name: str
    host: str
    port: int
    tls: bool = False
    spawned: bool = False
    """The viewer --spawn opened: closing its window is how a user ends looking, not an error."""

    @property
    def where(self) -> str:
        return f"{self.host}:{self.port}"


def _probe(viewer: ViewerAddress) -> str | None:
    """None if a Rerun viewer answers at the address, else why not. Over plain HTTP a viewer's
    gRPC server answers the HTTP/2 preface with its SETTINGS at once; a port where something
    else listens (the web viewer's page, say) or a frozen viewer does not."""
    try:
        sock = socket.create_connection((viewer.host, viewer.port), timeout=PROBE_TIMEOUT_S)
    except socket.gaierror as err:
        return f"cannot resolve {viewer.host!r} ({err.strerror})"
    except TimeoutError:
        return f"no answer within {PROBE_TIMEOUT_S:.0f} s"
    except OSError as err:
        return str(err.strerror or err)
    with sock:
        if viewer.tls:  # no TLS handshake here: Rerun's own client reports certificate trouble
            return None
        try:
            sock.sendall(H2_PREFACE)
            answer = sock.recv(H2_FRAME_HEADER)
        except OSError:
            answer = b""
    if len(answer) > H2_FRAME_TYPE and answer[H2_FRAME_TYPE] == H2_SETTINGS:
        return None
    return "something listens there but does not answer as a Rerun viewer (gRPC)"


def viewer_address(url: str) -> ViewerAddress:
    """The host and port of a ``--rerun-addr`` URL, or a SinkError saying what a good one is."""
    example = f"e.g. rerun+http://{LOOPBACK}:{VIEWER_PORT}/proxy"
    parts = urlsplit(url)
    if parts.scheme not in VIEWER_SCHEMES or not parts.hostname or parts.path != "/proxy":
        msg = f"--rerun-addr {url}: not a Rerun viewer URL ({example})"
        raise SinkError(msg)
    try:
        port = parts.port or REDAP_DEFAULT_PORT
    except ValueError as err:
        msg = f"--rerun-addr {url}: bad port ({err}; {example})"
        raise SinkError(msg) from err
    return ViewerAddress(url, parts.hostname, port, tls=parts.scheme != "rerun+http")


def viewer_executable() -> str | None:
    """The ``rerun`` viewer of the rerun-sdk this Python imports: beside the interpreter's
    scripts first (a venv's ``bin/``, also when the venv is not activated; ``pip install
    --user``'s ``~/.local/bin``), so viewer and SDK versions match; else the first on PATH."""
    directories = [
        sysconfig.get_path("scripts"),
        str(Path(sys.executable).parent),
        sysconfig.get_path("scripts", sysconfig.get_preferred_scheme("user")),
    ]
    for directory in directories:
        found = shutil.which("rerun", path=directory)
        if found is not None:
            return found
    return shutil.which("rerun")


def _why_no_window() -> str:
    """Why a spawned viewer died at once, as far as the environment tells."""
    if sys.platform in ("darwin", "win32"):
        return "it could not open a window; see its error above"
    shown = [f"{name}={os.environ[name]}" for name in ("WAYLAND_DISPLAY", "DISPLAY") if os.environ.get(name)]
    if not shown:
        return "no display: DISPLAY and WAYLAND_DISPLAY are unset"
    return f"{' and '.join(shown)} is set but the viewer could not open a window there; see its error above"


def _check_port_free(host: str, port: int, flag: str) -> None:
    """A SinkError naming ``flag`` if ``port`` cannot be listened on at ``host`` (Rerun's own
    servers would only log the failure and drop everything sent to them)."""
    try:
        family = socket.AF_INET6 if ipaddress.ip_address(host).version == 6 else socket.AF_INET
    except ValueError as err:
        msg = f"--web-bind {host!r}: not an IP address (e.g. 127.0.0.1, 0.0.0.0, ::)"
        raise SinkError(msg) from err
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        # As Rerun's servers do, so a port left in TIME_WAIT by a previous run counts as free.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as err:
            if err.errno == errno.EADDRINUSE:
                msg = f"--serve-web: port {port} is in use by another program; choose another with {flag} N"
            else:
                msg = f"--serve-web: cannot listen on {host}:{port} ({err.strerror}); check --web-bind"
            raise SinkError(msg) from err


def _never() -> bool:
    return False


class _ViewerPacer:
    """Back-pressure from the gRPC viewers (--rerun-addr, --spawn).

    Rerun's gRPC client buffers whatever it has not sent, without limit (rerun-sdk 0.41 has no
    memory limit for it): logging 5.7 MB/s to a frozen viewer grew the host by exactly that
    rate (112 -> 266 MB in 27 s). A flush returns once the client has sent everything logged
    before it, and what it can send is bounded by the connection's HTTP/2 window and socket
    buffers (a frozen viewer stopped it after ~3 MB). So a thread flushes every
    PACE_PERIOD_S; while a flush is not done within PACE_BEHIND_S, :meth:`wait` holds whoever
    logs (the robots' workers), whose bounded queues then keep the newest heavy messages and
    count what they drop. A healthy viewer takes a flush in a few ms: nothing waits. A viewer
    that went away (its flush fails at once) is not waited for: :meth:`RerunSink.close` names
    it."""

    def __init__(self, recording: rr.RecordingStream, names: str) -> None:
        self._recording = recording
        self._names = names
        self.caught_up = threading.Event()
        self.caught_up.set()
        self.times_behind = 0
        self._behind_since: float | None = None
        self._seconds_behind = 0.0
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rerun-pacer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stopping.wait(PACE_PERIOD_S):
            if self._flushed(PACE_BEHIND_S):
                continue
            self.caught_up.clear()
            self._behind_since = time.monotonic()
            if not self.times_behind:
                log.warning(
                    "the Rerun viewer %s takes the data slower than it comes: logging waits for it "
                    "(live robots' queues keep their newest messages and count the drops)",
                    self._names,
                )
            self.times_behind += 1
            while not self._stopping.is_set() and not self._flushed(FLUSH_STEP_S):
                pass
            self._seconds_behind += time.monotonic() - self._behind_since
            self._behind_since = None
            self.caught_up.set()

    def _flushed(self, timeout_s: float) -> bool:
        """False if the viewers had not taken everything logged within ``timeout_s``."""
        try:
            self._recording.flush(timeout_sec=timeout_s)
        except RuntimeError as err:
            if "timed out" in str(err):  # Rerun's words for a viewer that is only slow
                return False
            self._stopping.set()  # gone: waiting for it would only lose the other sinks' data
        return True

    def wait(self, give_up: Callable[[], bool]) -> None:
        """Until the viewers have caught up, or ``give_up()``."""
        while not self.caught_up.wait(FLUSH_STEP_S):
            if give_up():
                return

    def stop(self) -> None:
        """Stop pacing. Not waiting for the thread's flush step: the close that follows waits
        for the viewers anyway, and the host must not be held longer for a slow one."""
        self._stopping.set()
        self.caught_up.set()
        if self.times_behind:
            since = self._behind_since
            seconds = self._seconds_behind + (0.0 if since is None else time.monotonic() - since)
            log.info(
                "the Rerun viewer %s fell behind %d time%s, %.1f s in all", self._names,
                self.times_behind, "" if self.times_behind == 1 else "s", seconds,
            )


_Row = dict[rr.ComponentDescriptor, pa.Array]


def _rows(columns: Sequence[Any], count: int) -> list[_Row] | None:
    """Each of the ``count`` rows of ``columns`` as its components' cells (a null row leaves
    its component out); None for a column whose rows are not known. A lean column's rows are
    slices of its cells at its offsets, and any ComponentColumn's one row is its whole batch:
    an Arrow list array per column and a list scalar per row cost more than logging a live
    message's row."""
    spans = []
    for column in columns:
        if isinstance(column, RowsColumn):
            at: list[int] | None = column.row_offsets.tolist()
        elif isinstance(column, rr.ComponentColumn) and count == 1:
            at = None
        else:
            break
        cells = column.component_batch.as_arrow_array()
        at = [0, len(cells)] if at is None else at
        if len(at) != count + 1:
            break
        spans.append((cells, at, column.descriptor))
    else:
        return [{descriptor: cells.slice(at[row], at[row + 1] - at[row])
                 for cells, at, descriptor in spans} for row in range(count)]
    lists = [column.as_arrow_array() for column in columns]
    if any(len(c) != count or not pa.types.is_list(c.type) for c in lists):
        return None
    descriptors = [column.component_descriptor() for column in columns]
    return [{descriptor: c[row].values for c, descriptor in zip(lists, descriptors, strict=True)
             if c[row].is_valid} for row in range(count)]


class RerunSink:
    """Logs converter output with the message's timelines."""

    def __init__(
        self, options: SinkOptions, give_up: Callable[[], bool] = _never, *, index_footer: bool = True,
        eager_batches: bool = False,
    ) -> None:
        """``give_up()`` true: stop waiting for a slow viewer (the user asked the host to stop).

        ``index_footer``: end a ``--save`` file with Rerun's index of its chunks (the viewer
        then opens it lazily). Rerun keeps that index in memory until the file closes, growing
        with every chunk: a live host's RSS grew 317 -> 445 MB over a 4-minute demo replayed at
        10x with it, and stayed flat without (benchmarks/rss_replay.py). So only a recording
        that ends (a bag) gets one; ``rerun rrd optimize`` adds one to any other.

        ``eager_batches``: hand every row batch of :data:`EAGER_FLUSH_BYTES` or more to Rerun's
        encoder at once (a bag conversion, where the encoder otherwise finishes long after the
        host has logged everything)."""
        self._give_up = give_up
        self._index_footer = index_footer
        self.recording = rr.RecordingStream(
            APPLICATION_ID, recording_id=options.recording_id,
            batcher_config=rr.ChunkBatcherConfig(flush_num_bytes=EAGER_FLUSH_BYTES) if eager_batches
            else None,
        )
        # Swanky sets log_time itself (the bag's record time); the SDK's wall clock would clash.
        rr.set_log_time_enabled(False, recording=self.recording)
        rr.set_log_tick_enabled(False, recording=self.recording)
        self.web_url: str | None = None
        self.web_note: str | None = None
        self._viewers: list[ViewerAddress] = []
        self._viewer_urls: list[str] = []
        self._own_destination = options.save is not None or options.serve_web
        self._save = options.save
        self.abandoned = False
        self._open(options)
        self._pacer = (
            _ViewerPacer(self.recording, "; ".join(viewer.name for viewer in self._viewers))
            if self._viewers else None
        )
        # Rerun's time context is per thread (the dispatcher and the slow-converter worker).
        self._local = threading.local()

    def _open(self, options: SinkOptions) -> None:
        sinks: list[rr.sinks.LogSinkLike] = []
        if options.save is not None:
            if not options.save.parent.is_dir():
                msg = f"--save {options.save}: directory {options.save.parent} does not exist"
                raise SinkError(msg)
            sinks.append(rr.FileSink(str(options.save), write_footer=self._index_footer))
        if options.connect is not None:
            sinks.append(self._connect(options.connect))
        if options.spawn:
            sinks.append(self._spawn())
        if options.serve_web:
            sinks.append(self._serve_grpc(options))
        self.recording.set_sinks(*sinks)
        if options.serve_web:
            self._serve_web(options)

    def _connect(self, url: str) -> rr.GrpcSink:
        address = viewer_address(url)
        problem = _probe(address)
        if problem is not None:
            msg = (
                f"--rerun-addr {url}: no Rerun viewer at {address.where}: {problem}; start one "
                f"(`rerun` listens on port {VIEWER_PORT}) or use --spawn, --save FILE.rrd or "
                "--serve-web"
            )
            raise SinkError(msg)
        try:
            sink = rr.GrpcSink(url)
        except RuntimeError as err:  # a URL Rerun reads differently from urlsplit
            msg = f"--rerun-addr {url}: {err}"
            raise SinkError(msg) from err
        self._viewers.append(address)
        self._viewer_urls.append(url)
        return sink

    def _spawn(self) -> rr.GrpcSink:
        executable = viewer_executable()
        if executable is None:
            msg = (
                f"cannot spawn the Rerun viewer: no 'rerun' executable beside {sys.executable} "
                "or on PATH; install rerun-sdk (pip install \".[host]\") or use --save FILE.rrd, "
                "--serve-web or --rerun-addr URL"
            )
            raise SinkError(msg)
        try:
            rr.spawn(
                port=VIEWER_PORT, connect=False, recording=self.recording, executable_path=executable
            )
        except Exception as err:
            msg = (
                f"cannot spawn the Rerun viewer {executable} ({err}); on a machine without a "
                "screen use --save FILE.rrd or --serve-web"
            )
            raise SinkError(msg) from err
        viewer = ViewerAddress(
            f"rerun+http://{LOOPBACK}:{VIEWER_PORT}/proxy (the spawned viewer)", LOOPBACK,
            VIEWER_PORT, spawned=True,
        )
        if _probe(viewer) is not None:
            # rr.spawn only warns when the viewer dies at once: without this check every later
            # flush would wait for it.
            msg = (
                f"cannot spawn the Rerun viewer {executable}: it exited without listening on "
                f"port {VIEWER_PORT} ({_why_no_window()}); on a machine without a screen use "
                "--save FILE.rrd or --serve-web"
            )
            raise SinkError(msg)
        self._viewers.append(viewer)
        self._viewer_urls.append(f"rerun+http://{LOOPBACK}:{VIEWER_PORT}/proxy")
        return rr.GrpcSink(self._viewer_urls[-1])

    def _serve_grpc(self, options: SinkOptions) -> rr.GrpcServerSink:
        port = options.grpc_port or VIEWER_PORT
        _check_port_free(options.web_bind, port, "--grpc-port")
        # Rerun's page server always listens on every interface.
        _check_port_free(ALL_INTERFACES[0], options.web_port or WEB_PORT, "--web-port")
        return rr.GrpcServerSink(bind_ip=options.web_bind, port=port)

    def _serve_web(self, options: SinkOptions) -> None:
        grpc_port = options.grpc_port or VIEWER_PORT
        web_port = options.web_port or WEB_PORT
        host = LOOPBACK if options.web_bind in ALL_INTERFACES else options.web_bind
        grpc_url = f"rerun+http://{host}:{grpc_port}/proxy"
        try:
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc_url)
        except RuntimeError as err:  # the port was taken since it was checked
            msg = (
                f"--serve-web: cannot serve the web viewer on port {web_port} ({err}); choose "
                "another with --web-port N"
            )
            raise SinkError(msg) from err
        self.web_url = f"http://{host}:{web_port}/?url={grpc_url}"
        # Rerun serves the viewer page (code only, no data) on every interface, whatever we ask.
        if options.web_bind in ALL_INTERFACES:
            self.web_note = (
                f"the recording (port {grpc_port}) and the viewer page (port {web_port}) are open "
                "to every network interface (--web-bind); from another machine use this PC's "
                f"address instead of {host}"
            )
        else:
            self.web_note = (
                f"the recording is served on {options.web_bind}:{grpc_port} only (--web-bind "
                f"0.0.0.0 opens it to the network); Rerun serves the viewer page (code, no data) "
                f"on port {web_port} of every interface"
            )

    def shared_viewer(self) -> str | None:
        """The URL of the one destination, when it is a gRPC viewer, where another process can
        log into this recording (offload.py); None when a destination is this process's own
        (a --save file, the --serve-web server) or there are several."""
        if self._own_destination or len(self._viewer_urls) != 1:
            return None
        return self._viewer_urls[0]

    @property
    def recording_id(self) -> str:
        return str(self.recording.get_recording_id())

    def _set_times(self, times: Mapping[str, int]) -> None:
        if times == getattr(self._local, "times", None):
            return
        native = self.recording.to_native()
        rerun_bindings.reset_time(native)
        for name, ns in times.items():
            rerun_bindings.set_time_timestamp_nanos_since_epoch(name, ns, native)
        self._local.times = times

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        if self._pacer is not None and not self._pacer.caught_up.is_set():
            self._pacer.wait(self._give_up)
        for entry in entries:
            if isinstance(entry, ColumnsItem):
                columns = list(entry.columns)
                if self._log_rows(entry.path, columns, entry.times):
                    continue
                indexes = [
                    rr.TimeColumn(name, timestamp=values.astype(np.int64, copy=False).view("datetime64[ns]"))
                    for name, values in entry.times.items()
                ]
                self.recording.send_columns(entry.path, indexes=indexes, columns=columns)
            elif isinstance(entry, LogItem):
                if entry.static:
                    self.recording.log(entry.path, *entry.archetypes, static=True)
                else:
                    self._set_times(times if entry.times is None else entry.times)
                    self.recording.log(entry.path, *entry.archetypes)

    def _log_rows(
        self, path: str, columns: Sequence[Any], times: Mapping[str, npt.NDArray[np.int64]]
    ) -> bool:
        """Log the columns of up to FEW_ROWS rows row by row (a ``log`` each: the same rows in
        the recording); False for more. A live run is often one message, and a ``send_columns``
        of one row costs about twice a ``log``."""
        counts = {len(values) for values in times.values()}
        if len(counts) != 1 or not 0 < (count := counts.pop()) <= FEW_ROWS:
            return False
        rows = _rows(columns, count)
        if rows is None:
            return False
        # Rerun's binding itself: rr.log wraps, checks and unwraps the cells again, a tenth to a
        # sixth of a live Imu's or TF's conversion and logging (Imu 515 -> 445-478 us, TF 450 -> 383).
        native = self.recording.to_native()
        for row, components in enumerate(rows):
            self._set_times({name: int(values[row]) for name, values in times.items()})
            rerun_bindings.log_arrow_msg(path, components=components, static_=False, recording=native)
        return True

    def send_blueprint(self, blueprint: rrb.Blueprint) -> None:
        """Make ``blueprint`` the viewer's layout (and its default); a saved .rrd keeps it too."""
        self.recording.send_blueprint(blueprint, make_active=True, make_default=True)

    def send_blueprint_file(self, path: Path) -> None:
        """Send a saved .rbl as is: its blueprint store and activation travel with the data."""
        rr.log_file_from_path(path, recording=self.recording)

    def flush(self) -> None:
        """Wait until every sink has everything logged so far. A viewer that is slow to read is
        waited for (until ``give_up()``); one that went away is not: SinkError names it."""
        while True:
            try:
                self.recording.flush(timeout_sec=FLUSH_STEP_S)
                return
            except RuntimeError as err:
                lost = self._lost_viewers(err)
                if lost and all(viewer.spawned for viewer, _ in lost):
                    log.info("the Rerun viewer was closed; not waiting for it")
                    return
                if lost:
                    named = "; ".join(
                        f"{viewer.name} ({viewer.where}: {problem})" for viewer, problem in lost
                    )
                    msg = f"lost the Rerun viewer at {named}: what it had not received yet is not shown"
                    raise SinkError(msg) from err
                if self._give_up():
                    msg = f"stopped before every sink had everything ({err})"
                    raise SinkError(msg) from err

    def _lost_viewers(self, err: RuntimeError) -> list[tuple[ViewerAddress, str]]:
        """The viewers, with why, that a failed flush step means are gone, not just slow."""
        probed = [(viewer, _probe(viewer)) for viewer in self._viewers]
        lost = [(viewer, problem) for viewer, problem in probed if problem is not None]
        # Rerun's words when its client gave up ("unable to connect", "connection severed"),
        # e.g. something else took the port after the viewer died.
        if not lost and "connect" in str(err):
            lost = [(viewer, str(err)) for viewer in self._viewers]
        return lost

    def close(self) -> None:
        """Flush and close the sinks, so a saved .rrd is complete even when a viewer is gone
        (SinkError then names it, after the file is closed).

        A viewer that stopped answering (frozen, or its network gone without a word) holds
        Rerun's disconnect for ever; after ``DISCONNECT_TIMEOUT_S`` it is left behind and
        ``abandoned`` set: the process must then end with ``os._exit``, as Rerun's exit handler
        would wait for it too."""
        problem: SinkError | None = None
        if self._pacer is not None:
            self._pacer.stop()
        try:
            self.flush()
        except SinkError as err:
            problem = err
        closing = threading.Thread(target=self.recording.disconnect, name="rerun-close", daemon=True)
        closing.start()
        closing.join(DISCONNECT_TIMEOUT_S)
        if closing.is_alive():
            self.abandoned = True
            stuck = "; ".join(viewer.name for viewer in self._viewers) or "a Rerun sink"
            saved = "" if self._save is None else (
                f"; {self._save} lacks its index footer (`rerun rrd optimize` adds one)"
            )
            msg = f"gave up closing {stuck} after {DISCONNECT_TIMEOUT_S:.0f} s: it stopped answering{saved}"
            raise SinkError(msg) from problem
        if problem is not None:
            raise problem
