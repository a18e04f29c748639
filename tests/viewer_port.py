"""Rerun's default viewer port (9876) is one per machine: the tests that must use it (the
README's demo command as a user runs it) take it in turn, across the two pytest workers, the
README's background commands and the test run nested in them, which run on the same machine."""

from __future__ import annotations

import fcntl
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

LOCK = Path(tempfile.gettempdir()) / "swanky-tests-default-viewer-port.lock"


@contextmanager
def default_viewer_port() -> Iterator[None]:
    """Held while this process may open or connect to the default viewer port."""
    with LOCK.open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield  # the lock goes with the file's closing
