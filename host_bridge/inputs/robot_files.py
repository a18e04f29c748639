"""Meshes from the robot: asks a relay's file server (robot_relay/files.py, schemas/wire.md) for
the ``package://`` files the PC does not have, and keeps what it got.

It is the :data:`host_bridge.core.resources.RobotFetch` of a live host. The session is attached once
the host has opened it. Fetches run on the host's converting thread, so each is bounded by
``timeout``, and a robot that let one run out is not asked again for ``quiet`` seconds: a dead
relay costs one timeout per model, not one per mesh. A reply over ``max_bytes`` (the relay's own
limit, 64 MiB) is refused and not kept: a relay that is not Swanky's, or a hostile one, cannot
fill the host's cache.
"""

from __future__ import annotations

import threading
import time

import zenoh

from host_bridge.core.resources import PACKAGE_SCHEME, split_package_uri
from host_bridge.errors import ConvertError
from robot_relay.files import DEFAULT_MAX_BYTES
from robot_relay.wire import files_key

FETCH_TIMEOUT_S = 5.0
QUIET_AFTER_TIMEOUT_S = 30.0


class RobotFiles:
    """``fetch(robot, uri)``: the bytes of ``package://`` ``uri`` from ``robot``'s relay, cached
    in memory per (robot, uri) for the host's lifetime (a URDF re-sent on reconnect is free)."""

    def __init__(
        self,
        timeout: float = FETCH_TIMEOUT_S,
        quiet: float = QUIET_AFTER_TIMEOUT_S,
        max_bytes: int = DEFAULT_MAX_BYTES,
    ) -> None:
        self._timeout = timeout
        self._quiet = quiet
        self._max_bytes = max_bytes
        self._session: zenoh.Session | None = None
        self._cache: dict[tuple[str, str], bytes] = {}
        self._timed_out: dict[str, float] = {}
        self._lock = threading.Lock()

    def attach(self, session: zenoh.Session) -> None:
        self._session = session

    def detach(self) -> None:
        self._session = None

    def fetch(self, robot: str, uri: str) -> bytes:
        with self._lock:
            cached = self._cache.get((robot, uri))
        if cached is not None:
            return cached
        data = self._ask(robot, uri)
        with self._lock:
            self._cache[(robot, uri)] = data
        return data

    def _ask(self, robot: str, uri: str) -> bytes:
        session = self._session
        if session is None or not uri.startswith(PACKAGE_SCHEME):
            msg = f"robot {robot} cannot be asked for {uri} (no live session)"
            raise ConvertError(msg)
        since = self._timed_out.get(robot)
        if since is not None and time.monotonic() - since < self._quiet:
            msg = f"robot {robot} did not answer a file request just before; not asked for {uri}"
            raise ConvertError(msg)
        package, relpath = split_package_uri(uri)
        try:
            replies = list(session.get(files_key(robot, package, relpath), timeout=self._timeout))
        except zenoh.ZError as err:
            # Not a valid key (empty path chunks, '*'): the relay could not serve it either.
            msg = f"robot {robot} cannot be asked for {uri}: {err}"
            raise ConvertError(msg) from err
        for reply in replies:
            if reply.ok is not None:
                self._timed_out.pop(robot, None)
                size = len(reply.ok.payload)
                if size > self._max_bytes:
                    msg = (
                        f"robot {robot} sent {size} bytes for {uri}, over the limit of "
                        f"{self._max_bytes} bytes a relay serves; not kept"
                    )
                    raise ConvertError(msg)
                data: bytes = reply.ok.payload.to_bytes()
                return data
        for reply in replies:
            if reply.err is not None:
                msg = f"robot {robot} refused {uri} ({reply.err.payload.to_string()})"
                raise ConvertError(msg)
        self._timed_out[robot] = time.monotonic()
        msg = (
            f"no file server of robot {robot} answered for {uri} (waited up to "
            f"{self._timeout:g} s); is its swanky-relay running and recent enough to serve files?"
        )
        raise ConvertError(msg)
