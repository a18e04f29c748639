"""CI's script (``.ci/run``): the README's test command as written, after ``.ci/install-viewers``
installed what the real viewers' tests need (a Chromium, Mesa's Vulkan drivers), quietly, once,
only what is missing, fetching package lists only when they lack a package (apt-get and apt-cache
replaced by stubs that log their calls; the Vulkan drivers' directory a temporary one)."""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.integration.test_readme_commands import REPO, quick_start_commands

INSTALL = REPO / ".ci" / "install-viewers"
BROWSER, VULKAN = "chromium-headless-shell", "mesa-vulkan-drivers"
LAVAPIPE = "lvp_icd.x86_64.json"
"""What mesa-vulkan-drivers puts in /usr/share/vulkan/icd.d for lavapipe."""
TOOLS = ("cat", "env", "mktemp", "rm")
"""What the script runs besides apt (and ``id``, a stub: root)."""
STUB = """#!/bin/bash
echo "${{0##*/}} $*" >> "{calls}"
{body}
"""


def install_call(*packages: str) -> str:
    return f"apt-get install -y -qq --no-install-recommends {' '.join(packages)}"


def test_ci_runs_the_readme_test_command_as_written() -> None:
    steps = (REPO / ".ci" / "run").read_text().strip().splitlines()
    assert steps[-2:] == [".ci/install-viewers", quick_start_commands()[1]]


@dataclass(frozen=True, slots=True)
class Machine:
    """A PATH of stubs: apt-cache knows the packages or not, apt-get installs them."""

    bin: Path
    calls: Path
    icds: Path
    """Where Vulkan drivers announce themselves (SWANKY_VULKAN_ICDS)."""

    def stub(self, name: str, body: str = "") -> None:
        path = self.bin / name
        path.write_text(STUB.format(calls=self.calls, body=body))
        path.chmod(0o755)

    def install(self) -> tuple[int, list[str], str]:
        """Exit code, apt calls (this run's), stderr."""
        self.calls.write_text("")
        env = {"PATH": str(self.bin), "HOME": os.environ.get("HOME", "/"),
               "SWANKY_VULKAN_ICDS": str(self.icds)}
        done = subprocess.run(["/bin/bash", str(INSTALL)], env=env, capture_output=True, text=True,
                              timeout=60, check=False)
        logged = [line for line in self.calls.read_text().splitlines() if not line.startswith("id ")]
        return done.returncode, logged, done.stderr


@pytest.fixture
def machine(tmp_path: Path) -> Machine:
    bin_dir, icds = tmp_path / "bin", tmp_path / "icd.d"
    bin_dir.mkdir()
    icds.mkdir()
    for tool in TOOLS:
        found = shutil.which(tool)
        assert found is not None
        (bin_dir / tool).symlink_to(found)
    stubs = Machine(bin_dir, tmp_path / "calls", icds)
    stubs.stub("id", "echo 0")
    return stubs


def with_apt(machine: Machine, lists_know_them: bool) -> None:
    """apt-get install makes the browser a command and puts lavapipe's file in place."""
    machine.stub("apt-cache", "" if lists_know_them else "exit 100")
    browser, lavapipe = machine.bin / BROWSER, machine.icds / LAVAPIPE
    machine.stub("apt-get", f'if [ "$1" = install ]; then\n'
                            f'  for p in "$@"; do\n'
                            f'    [ "$p" = {BROWSER} ] && printf "#!/bin/bash\\n" > "{browser}" &&\n'
                            f'      chmod +x "{browser}"\n'
                            f'    [ "$p" = {VULKAN} ] && echo {{}} > "{lavapipe}"\n'
                            f'  done\nfi\nexit 0')


def test_what_is_missing_is_installed_once_without_fetching_lists_that_have_it(machine: Machine) -> None:
    with_apt(machine, lists_know_them=True)
    assert machine.install() == (
        0, [f"apt-cache show {BROWSER} {VULKAN}", install_call(BROWSER, VULKAN)],
        f".ci/install-viewers: installed {BROWSER} {VULKAN} for the real viewers' tests\n",
    )
    assert machine.install() == (0, [], "")  # installed: nothing to do, nothing said


def test_only_the_missing_package_is_installed(machine: Machine) -> None:
    with_apt(machine, lists_know_them=True)
    (machine.icds / LAVAPIPE).write_text("{}")  # a machine with Mesa's Vulkan drivers
    code, calls, _ = machine.install()
    assert (code, calls) == (0, [f"apt-cache show {BROWSER}", install_call(BROWSER)])


def test_package_lists_are_fetched_when_they_lack_a_package(machine: Machine) -> None:
    with_apt(machine, lists_know_them=False)
    code, calls, _ = machine.install()
    assert (code, calls) == (0, [f"apt-cache show {BROWSER} {VULKAN}", "apt-get update -qq",
                                 install_call(BROWSER, VULKAN)])


def test_without_apt_it_says_which_viewer_tests_will_skip(machine: Machine) -> None:
    code, calls, stderr = machine.install()
    assert (code, calls) == (0, [])
    assert stderr.startswith(f".ci/install-viewers: no apt-get here, so no {BROWSER} {VULKAN}: the "
                             "tests of the viewers that need them will skip (Chromium: the web "
                             "viewer's screenshot; Vulkan: the native viewer's lag).")


def test_a_failed_install_fails_with_apt_output(machine: Machine) -> None:
    machine.stub("apt-cache")
    machine.stub("apt-get", 'echo "E: Unable to fetch some archives"; exit 100')
    code, calls, stderr = machine.install()
    assert (code, calls) == (1, [f"apt-cache show {BROWSER} {VULKAN}", install_call(BROWSER, VULKAN),
                                 "apt-get update -qq"])
    assert stderr.splitlines() == [
        "E: Unable to fetch some archives",
        f".ci/install-viewers: could not install {BROWSER} {VULKAN} (apt-get's output above)",
    ]
