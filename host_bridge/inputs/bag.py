"""Offline input: a bag straight into the host pipeline, no Zenoh, in runs for batching.

It reuses the relay's raw bag source, so a bag converted here and one replayed through a relay
give the host the same RawMessages (same CDR, same definitions, same log times).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from host_bridge.errors import InputError
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource
from robot_relay.wire import RawMessage


def bag_runs(path: Path, robot: str, run_size: int = 2048) -> Iterator[list[RawMessage]]:
    """The bag's messages in log-time order, ``run_size`` at a time."""
    try:
        with BagSource(path, robot) as source:
            run: list[RawMessage] = []
            for raw in source.messages():
                run.append(raw)
                if len(run) >= run_size:
                    yield run
                    run = []
            if run:
                yield run
    except SourceError as err:
        raise InputError(str(err)) from err
