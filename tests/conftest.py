"""Shared fixtures: the real ROS data beside the repo (../shared/data), loopback Zenoh sessions."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from tests.integration.procs import free_port, open_loopback

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA} (clone ../shared beside the repo)")
    return SHARED_DATA


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """A host session listening on a free loopback port and a robot session connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    host = open_loopback("-l", endpoint)
    robot = open_loopback("-e", endpoint)
    yield host, robot
    robot.close()
    host.close()
