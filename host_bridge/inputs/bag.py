"""Offline input: a bag straight into the host pipeline, no Zenoh, in runs for batching.

It reuses the relay's raw bag source, so a bag converted here and one replayed through a relay
give the host the same RawMessages (same CDR, same definitions, same log times). A rosbag2 in
MCAP storage is read in bulk by :mod:`host_bridge.inputs.mcap` instead (the same RawMessages in
the same order, payloads sliced out of whole chunks); a file it does not take is read by the
source.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from host_bridge.errors import InputError
from host_bridge.inputs.base import Deliver
from host_bridge.inputs.mcap import McapFile, NotIndexedError
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource
from robot_relay.wire import RawMessage

log = logging.getLogger("swanky.host")


def bag_runs(path: Path, robot: str, run_size: int = 2048) -> Iterator[list[RawMessage]]:
    """The bag's messages in log-time order, ``run_size`` at a time."""
    try:
        with BagSource(path, robot) as source:
            run: list[RawMessage] = []
            for batch in bag_batches(source, run_size):
                at = 0
                while at < len(batch):
                    taken = run_size - len(run)
                    run.extend(batch[at : at + taken])
                    at += taken
                    if len(run) == run_size:
                        yield run
                        run = []
            if run:
                yield run
    except SourceError as err:
        raise InputError(str(err)) from err


def bag_batches(source: BagSource, size: int) -> Iterator[list[RawMessage]]:
    """What ``source.messages()`` yields, at most ``size`` a list; read in bulk
    (:mod:`host_bridge.inputs.mcap`) where every file of the bag is an indexed MCAP."""
    storages = source.mcap_storages() if source.connections else None
    files: list[McapFile] = []
    try:
        for path, channels in storages or ():
            files.append(McapFile(path, channels))
    except NotIndexedError as why:
        log.debug("%s: %s; reading the bag with rosbags", path, why)
        for opened in files:
            opened.close()
        storages = None
    if storages is None:
        messages = source.messages()
        while batch := list(itertools.islice(messages, size)):
            yield batch
        return
    source.log_undefined()
    for opened in files:
        try:
            yield from opened.batches(source.robot, size)
        finally:
            opened.close()


class BagInput:
    """The :class:`~host_bridge.inputs.base.Input` of ``--bag``: the bag's runs, read and
    delivered on a thread of its own until its end or :meth:`close` (after the current run)."""

    def __init__(self, path: Path, robot: str) -> None:
        self.path = path
        self.robot = robot
        self.last_activity = time.monotonic()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def start(self, deliver: Deliver) -> None:
        self._thread = threading.Thread(
            target=self._read, args=(deliver,), name="bag-input", daemon=True
        )
        self._thread.start()

    def _read(self, deliver: Deliver) -> None:
        try:
            for run in bag_runs(self.path, self.robot):
                self.last_activity = time.monotonic()
                deliver(run)
                if self._closing.is_set():
                    return
        except BaseException as err:  # raised on the app's thread by ended()
            self._error = err

    def ended(self) -> bool:
        if self._error is not None:
            raise self._error
        return self._thread is not None and not self._thread.is_alive()

    def close(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join()
