"""The README's Quick start as a new user runs it: its two commands, read from README.md and run
verbatim one after the other in a fresh copy of the repository (``../shared`` beside it), with
no venv activated, so a first command that cannot find its viewer or a test command that fails
in a clean install cannot come back unnoticed.

Where the demo needs a display this machine lacks, its verbatim run must fail with the
"no display" explanation (which shows the viewer beside the venv's Python was found); the
command's last step then runs again with ``--save demo.rrd --duration 10`` appended, the
headless form the README gives, and the .rrd is read back. The test command runs its pytest
on one small module, chosen through ``PYTEST_ADDOPTS`` so the command text stays as written;
the nested run skips this module, so it never recurses.

Both commands install from the package index (pip's configured mirror here): minutes, so the
copy and its venv are shared by both tests, as a user's clone is, and they run in the background
from the first integration test on (tests/integration/conftest.py) at a lower CPU priority: the
suite's other tests go on meanwhile, and these two only read what the commands did.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from host_bridge.demo.robot import WHEEL_RADIUS
from host_bridge.outputs.sink import VIEWER_PORT
from tests.rrd import entity_rows
from tests.viewer_port import default_viewer_port

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
NESTED = "SWANKY_README_TEST"
"""Set for the nested test run: this module must not run itself again."""
NESTED_TESTS = "tests/host_bridge/test_sink_spawn.py"
HEADLESS = "--save demo.rrd --duration 10"
INSTALL_TIMEOUT_S = 1500

if os.environ.get(NESTED):
    pytest.skip("the README test command runs inside this test", allow_module_level=True)


def quick_start_commands() -> tuple[str, str]:
    """The ``sh`` blocks of the README's Quick start: the demo command, the test command."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("\n## Quick start\n", 1)[1].split("\n## ", 1)[0]
    demo, tests = re.findall(r"```sh\n(.*?)\n```", section, re.DOTALL)
    return demo, tests


def fresh_copy(destination: Path) -> Path:
    """The repository's files as a clone has them (tracked and new, not ignored: no .venv), in
    a git repository of its own."""
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=REPO, capture_output=True, check=True,
    ).stdout.decode().split("\0")
    copy = destination / "swanky"
    for name in filter(None, listed):
        source = REPO / name
        if source.is_file():  # not deleted in the work tree
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, copy / name)
    subprocess.run(["git", "init", "-q"], cwd=copy, check=True)  # a clone's tools read .gitignore
    shared = REPO.parent / "shared"
    if shared.is_dir():
        (destination / "shared").symlink_to(shared)
    return copy


def user_environment() -> dict[str, str]:
    """This environment as a shell without any venv activated: no venv bin/ on PATH."""
    env = {key: value for key, value in os.environ.items()
           if key not in ("VIRTUAL_ENV", "PYTHONHOME", "PYTHONPATH", "PYTEST_ADDOPTS")
           and not key.startswith("PYTEST_")}
    env["PATH"] = os.pathsep.join(
        entry for entry in env.get("PATH", "").split(os.pathsep)
        if entry and not (Path(entry).parent / "pyvenv.cfg").exists()
    )
    return env


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def viewer_port_taken() -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", VIEWER_PORT)) == 0


@dataclass(frozen=True)
class QuickStart:
    copy: Path
    demo_verbatim: subprocess.CompletedProcess[str] | None
    """None where the demo command could not run verbatim here (see ``demo``)."""
    demo: subprocess.CompletedProcess[str]
    tests: subprocess.CompletedProcess[str]


NICENESS = 10
"""The commands' CPU priority below the suite's: they take the cores the other tests leave."""


class QuickStartRun:
    """The Quick start's commands run one after the other on a thread, in a fresh copy under
    ``directory``; :meth:`result` waits for them, :meth:`cancel` kills the one running."""

    def __init__(self, directory: Path) -> None:
        self._directory = directory
        self._proc: subprocess.Popen[str] | None = None
        self._cancelled = False
        self._lock = threading.Lock()
        self._outcome: QuickStart | BaseException | None = None
        self._thread = threading.Thread(target=self._run_all, name="readme-commands", daemon=True)
        self._thread.start()

    def _run(self, command: str, copy: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
        with self._lock:
            if self._cancelled:
                msg = "the test session ended first"
                raise RuntimeError(msg)
            self._proc = subprocess.Popen(
                ["nice", "-n", str(NICENESS), "sh", "-c", command], cwd=copy, env=env,
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
            )
        out, err = self._proc.communicate(timeout=INSTALL_TIMEOUT_S)
        return subprocess.CompletedProcess(command, self._proc.returncode, out, err)

    def _run_all(self) -> None:
        try:
            demo_command, test_command = quick_start_commands()
            copy = fresh_copy(self._directory)
            env = user_environment()
            verbatim = None
            with default_viewer_port():  # the verbatim demo spawns a viewer there
                if has_display() or viewer_port_taken():
                    # A viewer would open (or rr.spawn would reuse the one listening): no verbatim run.
                    demo = self._run(f"{demo_command} {HEADLESS}", copy, env)
                else:
                    verbatim = self._run(demo_command, copy, env)
            if verbatim is not None:
                last_step = demo_command.rsplit("&&", 1)[1].strip()
                demo = self._run(f"{last_step} {HEADLESS}", copy, env)
            tests = self._run(test_command, copy, {**env, NESTED: "1", "PYTEST_ADDOPTS": NESTED_TESTS})
            self._outcome = QuickStart(copy, verbatim, demo, tests)
        except BaseException as err:  # handed to the tests, which fail with it
            self._outcome = err

    def result(self) -> QuickStart:
        self._thread.join()
        if isinstance(self._outcome, BaseException):
            raise self._outcome
        assert self._outcome is not None
        return self._outcome

    def cancel(self) -> None:
        with self._lock:
            self._cancelled = True
            if self._proc is not None and self._proc.poll() is None:
                os.killpg(self._proc.pid, signal.SIGKILL)
        self._thread.join(timeout=30)


@pytest.fixture(scope="module")
def quick_start(readme_commands: QuickStartRun | None) -> QuickStart:
    assert readme_commands is not None  # started for this module by tests/conftest.py
    return readme_commands.result()


def test_readme_demo_command(quick_start: QuickStart) -> None:
    copy = quick_start.copy
    if quick_start.demo_verbatim is not None:
        last = quick_start.demo_verbatim.stderr.strip().splitlines()[-1]
        assert (quick_start.demo_verbatim.returncode, last) == (2, (
            f"swanky-host: error: cannot spawn the Rerun viewer {copy}/.venv/bin/rerun: it exited "
            f"without listening on port {VIEWER_PORT} (no display: DISPLAY and WAYLAND_DISPLAY are "
            "unset); on a machine without a screen use --save FILE.rrd or --serve-web"
        )), quick_start.demo_verbatim.stderr[-3000:]
    assert quick_start.demo.returncode == 0, quick_start.demo.stderr[-3000:]
    assert "Traceback" not in quick_start.demo.stderr
    rows = entity_rows(copy / "demo.rrd")
    scans = [row["Points3D:positions"] for row in rows["/sim/scan"] if row.get("Points3D:positions")]
    assert len(scans) >= 10, len(scans)  # 5 Hz for 10 s, less start-up
    assert min(len(points) for points in scans) > 100
    assert all(np.all(np.isfinite(np.asarray(points))) for points in scans)
    links = {path.split("/")[3] for path in rows if path.startswith("/sim/robot_model/")}
    assert links >= {"base_link", "wheel_left_link", "wheel_right_link", "base_scan"}
    wheels = rows["/sim/robot_model/wheel_left_link/visual_0"]
    assert [wheel["Cylinders3D:radii"] for wheel in wheels] == [[pytest.approx(WHEEL_RADIUS)]] * len(wheels)
    assert wheels


def test_readme_test_command(quick_start: QuickStart) -> None:
    tests = quick_start.tests
    out = tests.stdout
    assert tests.returncode == 0, f"stdout:\n{out[-5000:]}\nstderr:\n{tests.stderr[-3000:]}"
    assert "All checks passed!" in out  # ruff
    assert re.search(r"^Success: no issues found in \d+ source files$", out, re.MULTILINE), out
    summary = re.search(r"^(\d+) passed(?:, (\d+) skipped)? in ", out, re.MULTILINE)
    assert summary is not None, out[-3000:]
    assert int(summary[1]) >= 1
