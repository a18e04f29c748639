"""Shared fixtures: the real ROS data beside the repo (../shared/data), loopback Zenoh sessions."""

from __future__ import annotations

import os
from collections.abc import Generator, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
import zenoh

from robot_relay.session import close_session
from tests import reliability as reliability_table
from tests.integration.procs import free_port, open_loopback

if TYPE_CHECKING:
    from tests.integration.test_readme_commands import QuickStartRun

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
README_MODULE = "tests/integration/test_readme_commands.py"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA} (clone ../shared beside the repo)")
    return SHARED_DATA


@pytest.fixture(scope="session", autouse=True)
def readme_commands(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[QuickStartRun | None]:
    """The README's Quick start commands, started with the session when its tests are selected:
    minutes of installing that the other tests need not wait for (test_readme_commands.py)."""
    selected = any(item.nodeid.startswith(README_MODULE) for item in request.session.items)
    if not selected or os.environ.get("SWANKY_README_TEST"):
        yield None
        return
    from tests.integration.test_readme_commands import QuickStartRun

    commands = QuickStartRun(tmp_path_factory.mktemp("readme"))
    yield commands
    commands.cancel()


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """A host session listening on a free loopback port and a robot session connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    host = open_loopback("-l", endpoint)
    robot = open_loopback("-e", endpoint)
    yield host, robot
    close_session(robot)  # also frees its shared-memory pool
    close_session(host)


@pytest.fixture
def reliability(request: pytest.FixtureRequest) -> Iterator[reliability_table.Record]:
    """Records a row of docs/RELIABILITY.md (tests/reliability.py) if the test passes."""
    start = len(reliability_table.recorded)
    yield reliability_table.recorder(request.node.nodeid)
    report = getattr(request.node, "rep_call", None)
    if report is None or not report.passed:
        del reliability_table.recorded[start:]


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    if report.when == "call":
        item.rep_call = report  # type: ignore[attr-defined]
    return report


def pytest_sessionfinish(session: pytest.Session) -> None:
    if reliability_table.recorded:
        reliability_table.write_table(reliability_table.recorded)
