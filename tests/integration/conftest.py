"""The integration tests' own fixtures (tests/conftest.py has those all tests share)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from tests.integration.test_readme_commands import QuickStartRun

README_MODULE = "tests/integration/test_readme_commands.py"


@pytest.fixture(scope="session", autouse=True)
def readme_commands(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[QuickStartRun | None]:
    """The README's Quick start commands, started with the first integration test when the
    README's tests are selected: minutes of installing that the other tests need not wait for
    (test_readme_commands.py)."""
    selected = any(item.nodeid.startswith(README_MODULE) for item in request.session.items)
    if not selected or os.environ.get("SWANKY_README_TEST"):
        yield None
        return
    from tests.integration.test_readme_commands import QuickStartRun

    commands = QuickStartRun(tmp_path_factory.mktemp("readme"))
    yield commands
    commands.cancel()
