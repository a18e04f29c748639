"""CI's script (``.ci/run``): the README's test command as written, after ``.ci/install-browser``
installed the browser the web viewer's test needs, quietly, once, and fetching package lists
only when they lack the package (apt-get and apt-cache replaced by stubs that log their calls)."""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.integration.test_readme_commands import REPO, quick_start_commands

INSTALL = REPO / ".ci" / "install-browser"
PACKAGE = "chromium-headless-shell"
INSTALL_CALL = f"apt-get install -y -qq --no-install-recommends {PACKAGE}"
TOOLS = ("cat", "env", "mktemp", "rm")
"""What the script runs besides apt (and ``id``, a stub: root)."""
STUB = """#!/bin/bash
echo "${{0##*/}} $*" >> "{calls}"
{body}
"""


def test_ci_runs_the_readme_test_command_as_written() -> None:
    steps = (REPO / ".ci" / "run").read_text().strip().splitlines()
    assert steps[-2:] == [".ci/install-browser", quick_start_commands()[1]]


@dataclass(frozen=True, slots=True)
class Machine:
    """A PATH of stubs: apt-cache knows the package or not, apt-get installs a browser."""

    bin: Path
    calls: Path

    def stub(self, name: str, body: str = "") -> None:
        path = self.bin / name
        path.write_text(STUB.format(calls=self.calls, body=body))
        path.chmod(0o755)

    def install_browser(self) -> tuple[int, list[str], str]:
        """Exit code, apt calls (this run's), stderr."""
        self.calls.write_text("")
        env = {"PATH": str(self.bin), "HOME": os.environ.get("HOME", "/")}
        done = subprocess.run(["/bin/bash", str(INSTALL)], env=env, capture_output=True, text=True,
                              timeout=60, check=False)
        logged = [line for line in self.calls.read_text().splitlines() if not line.startswith("id ")]
        return done.returncode, logged, done.stderr


@pytest.fixture
def machine(tmp_path: Path) -> Machine:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in TOOLS:
        found = shutil.which(tool)
        assert found is not None
        (bin_dir / tool).symlink_to(found)
    stubs = Machine(bin_dir, tmp_path / "calls")
    stubs.stub("id", "echo 0")
    return stubs


def with_apt(machine: Machine, lists_know_it: bool) -> None:
    machine.stub("apt-cache", "" if lists_know_it else "exit 100")
    browser = machine.bin / PACKAGE
    machine.stub("apt-get", f'[ "$1" = install ] && printf "#!/bin/bash\\n" > "{browser}" '
                            f'&& chmod +x "{browser}"; exit 0')


def test_the_browser_is_installed_once_without_fetching_lists_that_have_it(machine: Machine) -> None:
    with_apt(machine, lists_know_it=True)
    assert machine.install_browser() == (
        0, [f"apt-cache show {PACKAGE}", INSTALL_CALL],
        f".ci/install-browser: installed {PACKAGE} for the web viewer's screenshot test\n",
    )
    assert machine.install_browser() == (0, [], "")  # installed: nothing to do, nothing said


def test_package_lists_are_fetched_when_they_lack_the_browser(machine: Machine) -> None:
    with_apt(machine, lists_know_it=False)
    code, calls, _ = machine.install_browser()
    assert (code, calls) == (0, [f"apt-cache show {PACKAGE}", "apt-get update -qq", INSTALL_CALL])


def test_without_apt_it_says_the_screenshot_test_will_skip(machine: Machine) -> None:
    code, calls, stderr = machine.install_browser()
    assert (code, calls) == (0, [])
    assert stderr.startswith(".ci/install-browser: no apt-get here, so no Chromium: the web "
                             "viewer's screenshot test will skip.")


def test_a_failed_install_fails_with_apt_output(machine: Machine) -> None:
    machine.stub("apt-cache")
    machine.stub("apt-get", 'echo "E: Unable to fetch some archives"; exit 100')
    code, calls, stderr = machine.install_browser()
    assert (code, calls) == (1, [f"apt-cache show {PACKAGE}", INSTALL_CALL, "apt-get update -qq"])
    assert stderr.splitlines() == [
        "E: Unable to fetch some archives",
        f".ci/install-browser: could not install {PACKAGE} (apt-get's output above)",
    ]
