"""Fixtures shared by the integration tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from tests.integration.procs import free_port, open_loopback


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """A host session listening on a free loopback port and a robot session connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    host = open_loopback("-l", endpoint)
    robot = open_loopback("-e", endpoint)
    yield host, robot
    robot.close()
    host.close()
