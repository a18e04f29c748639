"""Shared fixtures: the real ROS data beside the repo (../shared/data), loopback Zenoh sessions."""

from __future__ import annotations

import os
import signal
from collections.abc import Generator, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest
import zenoh

from robot_relay.session import close_session
from tests import reliability as reliability_table
from tests.integration.procs import free_port, open_loopback, stop_signals_back

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
INTEGRATION = "tests/integration/"
NICEST = 19
"""The unit tests' worker's priority (nice): the lowest."""


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA} (clone ../shared beside the repo)")
    return SHARED_DATA


@pytest.fixture
def keep_signal_handlers() -> Iterator[None]:
    """For tests that call a command's main(), which installs its own SIGINT/SIGTERM handlers:
    pytest's come back afterwards."""
    saved = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    yield
    for signum, handler in saved.items():
        signal.signal(signum, handler)


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


def pytest_configure(config: pytest.Config) -> None:
    """Ctrl-C and Ctrl-\\ back for the processes the tests start. A suite started as a background
    job of a non-interactive shell (``.ci/run &``) inherits SIGINT and SIGQUIT ignored (POSIX), and
    every process it starts would too: a Rerun viewer, which installs no SIGINT handler of its own,
    then ignored the SIGINT that tells it to finish its saved file (twice, 2026-11-29). Python
    handlers are reset to the default in the processes started; an ignored signal is not."""
    stop_signals_back()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    if report.when == "call":
        item.rep_call = report  # type: ignore[attr-defined]
    return report


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """pytest-xdist's two workers (``-n 2``, pyproject.toml) get two work units: the integration
    tests, run in order in one, never two at once (they measure processes on a 2-core machine),
    and every other test in the other. By path, as xdist's own loadfile scheduler groups by file
    (its xdist_group marks no longer group under pytest 9: they rename a node id pytest 9 no
    longer reads)."""
    from xdist.scheduler import LoadScopeScheduling

    class TwoUnits(LoadScopeScheduling):  # type: ignore[misc]  # xdist is untyped
        def _split_scope(self, nodeid: str) -> str:
            return "integration" if nodeid.startswith(INTEGRATION) else "unit"

    return TwoUnits(config, log)


@pytest.fixture(autouse=True)
def unit_tests_yield(request: pytest.FixtureRequest) -> None:
    """The worker that runs the unit tests gives way to the integration tests' processes: at
    the lowest priority it takes only the CPU they leave idle while they wait (a link cut, a
    frozen viewer), so it does not slow what they measure."""
    if (os.environ.get("PYTEST_XDIST_WORKER") and not request.node.nodeid.startswith(INTEGRATION)
            and os.getpriority(os.PRIO_PROCESS, 0) < NICEST):
        os.setpriority(os.PRIO_PROCESS, 0, NICEST)



def pytest_sessionfinish(session: pytest.Session) -> None:
    """The reliability table is written once, by the process that ran the tests or, with
    workers, by the controller from the rows they send it."""
    workeroutput: dict[str, Any] | None = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:
        workeroutput["reliability"] = [asdict(trial) for trial in reliability_table.recorded]
    elif reliability_table.recorded:
        reliability_table.write_table(reliability_table.recorded)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: object) -> None:
    """A worker's rows of the reliability table, for the controller to write (xdist's hook)."""
    rows = getattr(node, "workeroutput", {}).get("reliability", [])
    reliability_table.recorded.extend(reliability_table.Trial(**row) for row in rows)
