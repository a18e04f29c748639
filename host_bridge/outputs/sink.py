"""The Rerun side: one recording stream, its sinks (viewer, gRPC address, .rrd file, web), and
the only place that calls ``log`` / ``send_columns``.

Nothing here may wait for a viewer without bound: a viewer that is missing, dies or stops
reading is found out (an HTTP/2 probe, flushes waited on in short steps, a bounded close) and
named, so the host neither hangs nor ignores Ctrl-C, and a ``--save`` file is still completed.
How far behind the viewers are is measured (viewer_lag.py); a viewer that falls behind is sent
less (thinning.py decides what, :meth:`RerunSink.saved_only`), one that stops taking data is
sent none but static data until it catches up (:data:`SUSPEND_S`): no thread waits for a viewer,
and a ``--save`` file beside it gets everything."""

from __future__ import annotations

import errno
import ipaddress
import logging
import os
import re
import shutil
import socket
import sys
import sysconfig
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import urlsplit

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from host_bridge.core.contract import ColumnsItem, LogEntry, LogItem, RowsColumn
from host_bridge.core.destinations import LOOPBACK, SinkOptions
from host_bridge.core.rerun_private import NativeStream, column_values, log_row, native, set_times
from host_bridge.errors import SinkError
from host_bridge.outputs.viewer_lag import BATCHER_TICK_S, LaggingViewer, ViewerLag

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
LIVE_FILE_FLUSH_S = 5.0
"""A live ``--save`` file is handed the rows Rerun's batcher holds every this long, as one chunk
per entity: fewer, larger chunks than a viewer's (Rerun's index of a file grows with their
number, :class:`SavedFile`; the demo robot made 200 a second at the batcher's default 0.2 s tick,
25 at 5 s). By a flush, not the tick alone: Rerun 0.41's tick fires only after that long without
any flush, so with images flushed by size every fraction of a second the rows of small topics
piled up in the batcher until the file closed (the demo's host grew by 130 MB in 2 minutes). A
host killed outright loses up to this much of its file."""
SUSPEND_S = 5.0
"""A viewer this far behind gets nothing but static data until it has caught up: it stopped
taking data (frozen, or its machine overloaded), and what it would be sent meanwhile would pile
up in this process (Rerun's client holds up to 100 MiB, then blocks whoever logs, which would
hold back the ``--save`` file and the other robots too)."""
FILE_COLUMN_CHUNKS = 2000
"""A live ``--save`` file ends sooner than its ``--save-split`` seconds once it was sent this many
runs of columns. Each is a chunk of its own (send_columns skips the batcher), and Rerun's index of
the file, which it holds in memory until the file ends, costs about 7 KB a chunk: a 10-minute demo
bag replayed at 10x into one file (1,027 runs for each of its 30 Hz topics, 21,362 chunks,
82 MB) grew the host by 158 MB (benchmarks/rss_replay.py). This many bounds it near 15 MB."""
FIRST_FILE_FLUSH_S = 0.5
"""A live file's first flush after its first data; each next one waits twice as long, up to
LIVE_FILE_FLUSH_S: the robots' latched topics (model, map, /tf_static), which arrive first, are
on disk within a second, for four more chunks per entity and file."""


SPLIT_PROPERTY = "split"
"""The recording property each file after the first of a split ``--save`` begins with: its
number (out_1.rrd: 1)."""


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

    @property
    def url(self) -> str:
        """The URL Rerun's gRPC sink connects to."""
        return f"rerun+{'https' if self.tls else 'http'}://{self.where}/proxy"


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
        cells = column_values(column)
        at = [0, len(cells)] if at is None else at
        if len(at) != count + 1:
            break
        spans.append((cells, at, column.component_descriptor()))
    else:
        return [{descriptor: cells.slice(at[row], at[row + 1] - at[row])
                 for cells, at, descriptor in spans} for row in range(count)]
    lists = [column.as_arrow_array() for column in columns]
    if any(len(c) != count or not pa.types.is_list(c.type) for c in lists):
        return None
    descriptors = [column.component_descriptor() for column in columns]
    return [{descriptor: c[row].values for c, descriptor in zip(lists, descriptors, strict=True)
             if c[row].is_valid} for row in range(count)]


def _stream(recording_id: str | None, batcher: rr.ChunkBatcherConfig | None) -> rr.RecordingStream:
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id, batcher_config=batcher)
    # Swanky sets log_time itself (the bag's record time); the SDK's wall clock would clash.
    rr.set_log_time_enabled(False, recording=stream)
    rr.set_log_tick_enabled(False, recording=stream)
    return stream


def _numbered(path: Path) -> bool:
    """Whether a split ``--save path`` gets numbered files (not /dev/null, not a pipe)."""
    return not path.exists() or path.is_file()


def split_path(path: Path, index: int) -> Path:
    """File ``index`` of a split ``--save path``: out.rrd -> out_0.rrd, out_1.rrd, ... (the
    names ``ros2 bag record`` gives its splits)."""
    return path.with_name(f"{path.stem}_{index}{path.suffix}")


class SavedFile:
    """A ``--save`` file, written by a recording stream of its own and ended with Rerun's footer,
    the index of its chunks that ``rerun rrd verify`` checks and ``RrdReader(...).store()`` reads.

    Rerun builds that index in memory until the file closes: a row per chunk in a column per
    timeline and component of the whole recording (re_log_encoding's RrdManifestBuilder), about
    5 KB a chunk for the demo robot, whose host grew by 1 MB/s with it in 0.2 s batches (Rerun's
    default), 0.3 MB/s in 5 s ones (LIVE_FILE_FLUSH_S). So a live host's file is split every
    ``split_s`` seconds, as ``ros2 bag record --max-bag-duration`` does: out.rrd is closed
    with its footer and renamed out_0.rrd, the recording goes on in out_1.rrd, and so on. Each
    file holds the static data (robot model, /tf_static, video codecs) and the layout logged
    before it, so it opens alone; all share the recording id, so ``rerun out_*.rrd`` opens them
    as one recording. A path that is not a regular file (/dev/null, a pipe) gets each in turn.

    A stream of its own because starting the next file replaces the stream's sinks, and a
    viewer's would be reconnected (``--serve-web``'s server cannot be: its port is taken); and
    so closing the file waits for no viewer."""

    def __init__(
        self, path: Path, recording_id: str | None, batcher: rr.ChunkBatcherConfig | None,
        split_s: float | None = None,
    ) -> None:
        """Opens ``path``, which :meth:`check` has found fit."""
        self.path = path
        self._numbered = _numbered(path)
        self.stream = _stream(recording_id, batcher)
        self.stream.set_sinks(rr.FileSink(str(path)))
        self.files = 1
        self.column_chunks = 0
        """Runs of columns sent to this file (a chunk each in Rerun's index, not batched)."""
        self.first_data_at: float | None = None
        """When (monotonic) this file's first data was logged: a file's time starts with its data."""
        self._lock = threading.Lock()
        self._statics: dict[str, dict[rr.ComponentDescriptor, Any]] = {}
        self._layout: Callable[[rr.RecordingStream], None] | None = None
        self._closing = threading.Event()
        self._worker: threading.Thread | None = None
        if split_s is not None:
            self._worker = threading.Thread(
                target=self._flush_and_split, args=(split_s,), name="rrd-file", daemon=True)
            self._worker.start()

    @staticmethod
    def check(path: Path, split_s: float | None) -> None:
        """A SinkError if ``path`` cannot be written, or if a split recording there would mix
        its files with an earlier one's (checked before any viewer starts)."""
        if not path.parent.is_dir():
            msg = f"--save {path}: directory {path.parent} does not exist"
            raise SinkError(msg)
        if split_s is None:
            return
        if split_s <= 0:
            msg = f"--save-split {split_s:g}: the seconds between files must be more than 0"
            raise SinkError(msg)
        pattern = re.compile(re.escape(path.stem) + r"_\d+" + re.escape(path.suffix))
        earlier = sorted(p.name for p in path.parent.iterdir() if pattern.fullmatch(p.name))
        if earlier and _numbered(path):
            more = len(earlier) - 3
            shown = ", ".join(earlier[:3]) + (f" and {more} more" if more > 0 else "")
            msg = (
                f"--save {path}: {shown} of an earlier recording are there, and a recording "
                "longer than --save-split goes on in such files; move them away or save under "
                "another name"
            )
            raise SinkError(msg)

    def _name(self, index: int) -> Path:
        return split_path(self.path, index) if self._numbered else self.path

    def log_static(self, path: str, archetypes: Sequence[rr.AsComponents]) -> None:
        """Log static data, kept (the latest of each component) for the files that follow."""
        with self._lock:
            self.stream.log(path, *archetypes, static=True)
            if self._worker is not None:  # files follow
                kept = self._statics.setdefault(path, {})
                for archetype in archetypes:
                    kept.update((batch.component_descriptor(), batch)
                                for batch in archetype.as_component_batches())

    def send_layout(self, send: Callable[[rr.RecordingStream], None]) -> None:
        """``send(stream)`` sends the layout; it is sent again at the start of every next file."""
        with self._lock:
            send(self.stream)
            self._layout = send

    def _flush_and_split(self, split_s: float) -> None:
        """Hand the file what the batcher holds every LIVE_FILE_FLUSH_S (``split_s`` if shorter),
        FIRST_FILE_FLUSH_S after a file's first data, then twice as long each time; go on in the
        next file once this one has ``split_s`` seconds of data (its time starts with its first
        data: a host waiting for robots makes no empty files), or sooner once it was sent
        FILE_COLUMN_CHUNKS runs of columns."""
        splitting = True
        longest_flush_s = min(LIVE_FILE_FLUSH_S, split_s)
        flush_s = min(FIRST_FILE_FLUSH_S, longest_flush_s)
        flushed_at = time.monotonic()
        # Woken ten times per split period (and for the first flushes): a file ends within a
        # tenth of it, or half a second, of being due.
        while not self._closing.wait(min(split_s / 10, FIRST_FILE_FLUSH_S)):
            now, began = time.monotonic(), self.first_data_at
            due = began is not None and (
                now >= began + split_s or self.column_chunks >= FILE_COLUMN_CHUNKS)
            if not splitting or not due:
                if began is None:  # nothing to hand over: each file's first rows come soon
                    flush_s = min(FIRST_FILE_FLUSH_S, longest_flush_s)
                elif now >= flushed_at + flush_s:
                    self.stream.flush()
                    flushed_at = now
                    flush_s = min(2 * flush_s, longest_flush_s)
                continue
            try:
                self._next_file()
            except (OSError, RuntimeError) as err:
                log.error("--save: cannot split the recording (%s); it goes on in %s, unsplit",
                          err, self._name(self.files - 1))
                splitting = False
            flushed_at = time.monotonic()

    def _next_file(self) -> None:
        with self._lock:
            done, following = self._name(self.files - 1), self._name(self.files)
            # Rerun hands the current file what its batcher holds, ends it with the footer and
            # closes it before set_sinks returns.
            self.stream.set_sinks(rr.FileSink(str(following)))
            self.files += 1
            self.first_data_at = None
            self.column_chunks = 0
            if self.files == 2 and self._numbered:
                self.path.rename(done)
            # Every file holds data of its own, so Rerun ends it with its footer even when the
            # host stops before any other data comes (a file with nothing in it gets none).
            self.stream.send_property(SPLIT_PROPERTY, rr.AnyValues(file=self.files - 1))
            for path, batches in self._statics.items():
                self.stream.log(path, list(batches.values()), static=True)
            if self._layout is not None:
                self._layout(self.stream)
        log.info("saved %s; the recording goes on in %s", done, following)

    def flush(self) -> None:
        """Until the file has everything logged so far (in steps: signals are seen between)."""
        while True:
            try:
                self.stream.flush(timeout_sec=FLUSH_STEP_S)
                return
            except RuntimeError as err:
                if "timed out" not in str(err):
                    msg = f"--save {self._name(self.files - 1)}: {err}"
                    raise SinkError(msg) from err

    def close(self) -> None:
        """End the last file with its footer."""
        self._closing.set()
        if self._worker is not None:
            self._worker.join()
        self.stream.disconnect()
        if self.files > 1:
            log.info("saved %s to %s (%d files; `rerun %s` opens them as one recording)",
                     self._name(0).name, self._name(self.files - 1).name, self.files,
                     self.path.parent / f"{self.path.stem}_*{self.path.suffix}")


def spawn_viewer(stream: rr.RecordingStream | None = None) -> ViewerAddress:
    """Start Rerun's viewer on :data:`VIEWER_PORT` (``--spawn``; one for all of ``--workers``),
    and check it listens; SinkError saying why not."""
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
            port=VIEWER_PORT, connect=False, recording=stream, executable_path=executable
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
    return viewer


class RerunSink:
    """Logs converter output with the message's timelines, into one recording stream for the
    viewers (``--spawn``, ``--rerun-addr``, ``--serve-web``) and one for a ``--save`` file
    (:class:`SavedFile`); each entry goes to both."""

    def __init__(
        self, options: SinkOptions, give_up: Callable[[], bool] = _never, *,
        eager_batches: bool = False, keep_up: bool = False,
    ) -> None:
        """``give_up()`` true: stop waiting for a slow viewer (the user asked the host to stop).

        ``eager_batches``: hand every row batch of :data:`EAGER_FLUSH_BYTES` or more to Rerun's
        encoder at once (a bag conversion, where the encoder otherwise finishes long after the
        host has logged everything).

        ``keep_up`` (live robots): measure how far behind the viewers are (:attr:`viewer_lag`),
        and send a viewer more than SUSPEND_S behind no data but static data until it caught up.
        Without it (a bag) a slow viewer is waited for: Rerun's client holds up to 100 MiB, then
        ``log`` blocks until the viewer takes more, and the bag is read no faster."""
        self._give_up = give_up
        self._batcher = rr.ChunkBatcherConfig(flush_num_bytes=EAGER_FLUSH_BYTES) if eager_batches else None
        # Kept up with, the viewers get rows batched by ViewerLag's flushes.
        self._viewers_batcher = rr.ChunkBatcherConfig(flush_tick=BATCHER_TICK_S) if keep_up else self._batcher
        self.web_url: str | None = None
        self.web_note: str | None = None
        self._viewers: list[ViewerAddress] = []
        self._viewer_urls: list[str] = []
        self._own_destination = options.save is not None or options.serve_web
        self.abandoned = False
        self._viewing, self._file = self._open(options)
        saving = None if self._file is None else self._file.stream
        self.streams = tuple(stream for stream in (self._viewing, saving) if stream is not None)
        self._natives = [native(stream) for stream in self.streams]
        self._saved_streams = () if saving is None else (saving,)
        self._saved_natives = [native(stream) for stream in self._saved_streams]
        self.viewer_lag = self._measure_lag(options) if keep_up else None
        self._suspended_at: float | None = None
        self._suspending = threading.Lock()
        # Rerun's time context is per thread (the dispatcher and the slow-converter worker), and
        # so is saved_only().
        self._local = threading.local()

    def _open(self, options: SinkOptions) -> tuple[rr.RecordingStream | None, SavedFile | None]:
        """The viewers' stream and the file, each if asked for. Every destination is checked
        before any is opened: nothing is written when one is wrong."""
        if options.save is not None:
            SavedFile.check(options.save, options.save_split_s)
        recording_id = options.recording_id
        viewing = None
        if options.connect is not None or options.spawn or options.serve_web:
            viewing = _stream(recording_id, self._viewers_batcher)
            recording_id = str(viewing.get_recording_id())
            sinks: list[rr.sinks.LogSinkLike] = []
            if options.connect is not None:
                sinks.append(self._connect(options.connect))
            if options.spawn:
                sinks.append(self._spawn(viewing))
            if options.serve_web:
                sinks.append(self._serve_grpc(options))
            viewing.set_sinks(*sinks)
            if options.serve_web:
                self._serve_web(options)
        if options.save is None:
            return viewing, None
        # A live file's rows in longer batches than a viewer's: fewer chunks for its footer.
        batcher = (rr.ChunkBatcherConfig(flush_tick=LIVE_FILE_FLUSH_S)
                   if options.save_split_s is not None else self._batcher)
        return viewing, SavedFile(options.save, recording_id, batcher, options.save_split_s)

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

    def _spawn(self, stream: rr.RecordingStream) -> rr.GrpcSink:
        viewer = spawn_viewer(stream)
        self._viewers.append(viewer)
        self._viewer_urls.append(viewer.url)
        return rr.GrpcSink(viewer.url)

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

    def _measure_lag(self, options: SinkOptions) -> ViewerLag | None:
        """How far behind the viewers are, when there are any (viewer_lag.py)."""
        if self._viewing is None:
            return None
        viewers = [LaggingViewer(viewer.name, url)
                   for viewer, url in zip(self._viewers, self._viewer_urls, strict=True)]
        if options.serve_web:
            viewers.append(LaggingViewer("the --serve-web server", None))
        return ViewerLag(self._viewing, viewers)

    @contextmanager
    def saved_only(self) -> Iterator[None]:
        """What this thread logs meanwhile goes to the ``--save`` file only, but static data
        (a viewer must never miss it): a heavy message the viewers are not sent
        (thinning.py)."""
        self._local.saved_only = True
        try:
            yield
        finally:
            self._local.saved_only = False

    def _destinations(self) -> tuple[Sequence[rr.RecordingStream], Sequence[NativeStream]]:
        """The streams (and their native handles) temporal data goes to now: the file's, and
        the viewers' unless this thread is in :meth:`saved_only` or they stopped taking data."""
        if getattr(self._local, "saved_only", False) or self._viewers_suspended():
            return self._saved_streams, self._saved_natives
        return self.streams, self._natives

    def _viewers_suspended(self) -> bool:
        """Whether the viewers are more than SUSPEND_S behind, or were and have not caught up
        since; each start and end is told once."""
        lag = self.viewer_lag
        if lag is None:
            return False
        seconds = lag.seconds
        if (seconds > SUSPEND_S) == (self._suspended_at is not None):
            return self._suspended_at is not None
        with self._suspending:
            if seconds > SUSPEND_S and self._suspended_at is None:
                self._suspended_at = time.monotonic()
                log.warning(
                    "the Rerun viewer %s is %.0f s behind: it gets no data but static data until it "
                    "has caught up%s", lag.names, seconds,
                    "" if self._file is None else " (the --save file gets everything)")
            elif seconds <= SUSPEND_S and self._suspended_at is not None:
                log.info("the Rerun viewer %s caught up: it was sent nothing for %.1f s",
                         lag.names, time.monotonic() - self._suspended_at)
                self._suspended_at = None
            return self._suspended_at is not None

    def shared_viewer(self) -> str | None:
        """The URL of the one destination, when it is a gRPC viewer, where another process can
        log into this recording (offload.py); None when a destination is this process's own
        (a --save file, the --serve-web server) or there are several."""
        if self._own_destination or len(self._viewer_urls) != 1:
            return None
        return self._viewer_urls[0]

    @property
    def saving(self) -> bool:
        """Whether a ``--save`` file gets what is logged."""
        return self._file is not None

    @property
    def recording_id(self) -> str:
        return str(self.streams[0].get_recording_id())

    def _set_times(self, times: Mapping[str, int]) -> None:
        if times == getattr(self._local, "times", None):
            return
        for handle in self._natives:
            set_times(handle, times)
        self._local.times = times

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        streams, natives = self._destinations()
        for entry in entries:
            if isinstance(entry, ColumnsItem):
                columns = list(entry.columns)
                if self._log_rows(natives, entry.path, columns, entry.times):
                    continue
                indexes = [
                    rr.TimeColumn(name, timestamp=values.astype(np.int64, copy=False).view("datetime64[ns]"))
                    for name, values in entry.times.items()
                ]
                for stream in streams:
                    stream.send_columns(entry.path, indexes=indexes, columns=columns)
                if self._file is not None and self._file.stream in streams:
                    self._file.column_chunks += 1  # approximate: the threads' += may race
            elif isinstance(entry, LogItem):
                if entry.static:
                    self._log_static(entry.path, entry.archetypes)
                else:
                    self._set_times(times if entry.times is None else entry.times)
                    for stream in streams:
                        stream.log(entry.path, *entry.archetypes)
        if self._file is not None and self._file.first_data_at is None:
            # After the entries: the file splits no sooner than split_s after they are in it.
            self._file.first_data_at = time.monotonic()

    def _log_static(self, path: str, archetypes: Sequence[rr.AsComponents]) -> None:
        if self._viewing is not None:
            self._viewing.log(path, *archetypes, static=True)
        if self._file is not None:
            self._file.log_static(path, archetypes)

    def _log_rows(
        self, natives: Sequence[NativeStream], path: str, columns: Sequence[Any],
        times: Mapping[str, npt.NDArray[np.int64]],
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
        for row, components in enumerate(rows):
            self._set_times({name: int(values[row]) for name, values in times.items()})
            for handle in natives:
                log_row(handle, path, components)
        return True

    def send_blueprint(self, blueprint: rrb.Blueprint) -> None:
        """Make ``blueprint`` the viewer's layout (and its default); a saved .rrd keeps it too."""
        self._send_layout(
            lambda stream: stream.send_blueprint(blueprint, make_active=True, make_default=True))

    def send_blueprint_file(self, path: Path) -> None:
        """Send a saved .rbl as is: its blueprint store and activation travel with the data."""
        self._send_layout(lambda stream: rr.log_file_from_path(path, recording=stream))

    def _send_layout(self, send: Callable[[rr.RecordingStream], None]) -> None:
        if self._viewing is not None:
            send(self._viewing)
        if self._file is not None:
            self._file.send_layout(send)

    def flush(self) -> None:
        """Wait until every sink has everything logged so far, the file first. A viewer that is
        slow to read is waited for (until ``give_up()``); one that went away is not: SinkError
        names it. Without a viewer (the web viewer's server alone) a flush waits only for this
        PC: giving up would not stop it, and the user would be told a complete file was not."""
        if self._file is not None:
            self._file.flush()
        if self._viewing is None:
            return
        while True:
            try:
                self._viewing.flush(timeout_sec=FLUSH_STEP_S)
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
                if self._viewers and self._give_up():
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
        """Flush and close the sinks, the file first: a saved .rrd is complete even when a
        viewer is gone or stopped answering (SinkError then names it, after the file is closed).

        A viewer that stopped answering (frozen, or its network gone without a word) holds
        Rerun's disconnect for ever; after ``DISCONNECT_TIMEOUT_S`` it is left behind and
        ``abandoned`` set: the process must then end with ``os._exit``, as Rerun's exit handler
        would wait for it too."""
        problem: SinkError | None = None
        if self.viewer_lag is not None:
            self.viewer_lag.stop()
        try:
            self.flush()
        except SinkError as err:
            problem = err
        if self._file is not None:
            self._file.close()
        if self._viewing is not None:
            closing = threading.Thread(target=self._viewing.disconnect, name="rerun-close", daemon=True)
            closing.start()
            closing.join(DISCONNECT_TIMEOUT_S)
            if closing.is_alive():
                self.abandoned = True
                stuck = "; ".join(viewer.name for viewer in self._viewers) or "the --serve-web server"
                msg = f"gave up closing {stuck} after {DISCONNECT_TIMEOUT_S:.0f} s: it stopped answering"
                raise SinkError(msg) from problem
        if problem is not None:
            raise problem
