"""A bag opened on a thread of its own while ``swanky-host`` imports the app.

Opening a bag can take a good part of importing the app (0.3-0.4 s on a quiet machine, most of
it Rerun's SDK): rosbags reads every channel's QoS and a sqlite3 bag's tables, and a bag recorded
with ``--compression-mode file`` starts decompressing there (robot_relay/sources/mcap_stream.py:
its thread decompresses ahead of the reader while the app imports; zstd runs in C with the GIL
released), so with a second core the import and the opening overlap; a sqlite3 bag's rows start
to be fetched there too, by a process of their own (inputs/rows_ahead.py). This module imports
only the relay's bag source (rosbags and numpy load on the thread, inside ``BagSource.open``), so
the thread starts before the import.
"""

from __future__ import annotations

import threading
from pathlib import Path

from host_bridge.errors import InputError
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource

RUN_BYTES = 64 * 1024 * 1024
"""The most payload bytes a run holds (inputs/bag.py's runs, beside RUN_MESSAGES): a run of images
or clouds must not hold a whole bag."""


def open_bag(path: Path, robot: str) -> BagSource:
    """The bag opened (its index or metadata read, no message), or an InputError saying why not.
    A sqlite3 bag's first file starts fetching its rows at once, in a process of its own
    (inputs/rows_ahead.py), for runs of :data:`RUN_BYTES`."""
    try:
        source = BagSource(path, robot).open()
    except SourceError as err:
        raise InputError(str(err)) from err
    from host_bridge.inputs.rows_ahead import read_ahead  # numpy and rosbags: opening loaded them

    read_ahead(source, 0, RUN_BYTES)
    return source


class BagOpener:
    """:func:`open_bag` on a thread started at once; :meth:`take` waits for the bag."""

    def __init__(self, path: Path, robot: str) -> None:
        self.path = path
        self._opened: BagSource | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._open, args=(path, robot), name="bag-open", daemon=True
        )
        self._thread.start()

    def _open(self, path: Path, robot: str) -> None:
        try:
            self._opened = open_bag(path, robot)
        except BaseException as err:  # raised by take() on the app's thread
            self._error = err

    def take(self) -> BagSource:
        """The opened bag, from now on the caller's to close; what opening raised (InputError:
        the bag cannot be read), raised here."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        opened, self._opened = self._opened, None
        if opened is None:
            msg = f"bag {self.path} was taken already"
            raise RuntimeError(msg)
        return opened

    def close(self) -> None:
        """Close the bag unless :meth:`take` handed it on (the host ended before converting it:
        an error in its options, ``--print-config``)."""
        self._thread.join()
        if self._opened is not None:
            self._opened.close()
            self._opened = None
