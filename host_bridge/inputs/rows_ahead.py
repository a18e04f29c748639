"""A sqlite3 bag's rows fetched by a process of their own, ahead of the host converting them.

Fetching the rows is what a sqlite3 bag costs beyond an MCAP one (apsw makes a tuple a row), and
no thread of the host can take it off the conversion's way: apsw lets the GIL go for every row it
steps, so a fetching thread waited for the GIL once a row while the converting thread held it.
``swanky-host --bag`` starts ``python -m robot_relay.sources.sqlite_rows`` (a process importing
apsw, not numpy) as soon as the bag is open, on the thread that opens it before the app's import
(inputs/bag_opener.py), and the next file's while a file converts; that process packs the rows in
batches and writes them to a pipe ahead of the host, which reads the same batches
(:class:`~robot_relay.sources.sqlite.Sqlite3File` fetches payloads of 64 KiB and more from the
file itself, uncopied). The relay never starts a process: it reads its bags' rows itself.

The small-message file of ``benchmarks/bag_conversion.py`` (470,000 rows, alternated with the tree
before): 1.72-1.98 s -> 1.36-1.49 s, the same messages in an MCAP 1.35 s.
"""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from robot_relay.errors import SourceError
from robot_relay.sources import sqlite_rows
from robot_relay.sources.bag import BagSource
from robot_relay.sources.sqlite import Sqlite3File
from robot_relay.sources.sqlite_rows import BATCH, END, FRAME, Packed, RowsError

log = logging.getLogger("swanky.host")

PIPE_BYTES = 1024 * 1024
"""The pipe from the reading process, as large as Linux lets a process make it unasked
(/proc/sys/fs/pipe-max-size): a read call per MB, not per 64 KB."""


def read_ahead(source: BagSource, index: int, payload_bytes: int) -> None:
    """Bulk file ``index`` of the opened ``source`` (none past the last) has its rows fetched
    ahead, for windows of about ``payload_bytes``, if it is a sqlite3 file; an MCAP's reading is
    decompression in C already. Where no process can be started, the file fetches its rows itself."""
    files = source.bulk_files() or []
    if index >= len(files) or not isinstance(opened := files[index], Sqlite3File):
        return
    try:
        opened.read_from(RowsAhead(opened.bag, opened.path, tuple(opened.channels), payload_bytes))
    except OSError as err:
        log.debug("bag %s: fetching the rows of %s in this process (%s)", opened.bag, opened.path, err)


def _widen(pipe: io.RawIOBase) -> None:
    """The pipe made :data:`PIPE_BYTES` long where the platform can (Linux); elsewhere it only
    takes more reads."""
    try:
        import fcntl  # not on Windows

        fcntl.fcntl(pipe.fileno(), fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (ImportError, AttributeError, OSError):
        pass


class RowsAhead:
    """The rows of the sqlite3 file at ``path`` (of ``bag``), of storage connections
    ``channels``, fetched by ``python -m robot_relay.sources.sqlite_rows`` and read back from its
    frames (:class:`~robot_relay.sources.sqlite.PackedRows`)."""

    def __init__(self, bag: Path, path: Path, channels: Sequence[int], payload_bytes: int) -> None:
        self._bag = bag
        self._path = path
        self.malformed = 0
        self._read = 0
        package_root = Path(sqlite_rows.__file__).resolve().parents[2]
        python_path = os.pathsep.join(filter(None, (str(package_root), os.environ.get("PYTHONPATH"))))
        if not sys.executable:  # an embedded interpreter: nothing to run the reader with
            msg = "no Python executable to run the reader with"
            raise OSError(msg)
        self._process = subprocess.Popen(
            [sys.executable, "-m", sqlite_rows.__name__, str(path), str(payload_bytes),
             *map(str, channels)],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, bufsize=0,
            env={**os.environ, "PYTHONPATH": python_path},
            # Out of the terminal's process group: Ctrl-C is the host's to handle (it ends this
            # process when it closes the bag); the reader printed a KeyboardInterrupt otherwise.
            start_new_session=True,
        )
        self._out: io.RawIOBase = self._process.stdout  # type: ignore[assignment]
        _widen(self._out)

    def batches(self) -> Iterator[Packed]:
        """The batches the process fetched; a read error it reports as a RowsError, its end
        before the last frame as a SourceError naming the bag."""
        while True:
            kind, count, self.malformed, last_ns, length = FRAME.unpack(self._take(FRAME.size))
            if kind == END:
                return
            if kind != BATCH:
                cause = self._take(length).decode(errors="replace")
                raise RowsError(cause, count, None if last_ns < 0 else last_ns)
            columns = memoryview(self._take(32 * count))
            step = 8 * count
            channels, log_ns, sizes, row_ids = (columns[start:start + step]
                                                for start in range(0, 4 * step, step))
            yield Packed(channels, log_ns, sizes, row_ids, memoryview(self._take(length)))
            self._read += count

    def _take(self, size: int) -> bytearray:
        buffer = bytearray(size)
        view = memoryview(buffer)
        got = 0
        while got < size:
            read = self._out.readinto(view[got:])
            if not read:
                msg = (f"bag {self._bag}: the process reading {self._path} ended (exit code "
                       f"{self._process.wait()}) after {self._read} messages; the rest of the bag "
                       "is lost")
                raise SourceError(msg)
            got += read
        return buffer

    def close(self) -> None:
        """End the process (at once, if it is still reading) and wait for it."""
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait()
        self._out.close()
