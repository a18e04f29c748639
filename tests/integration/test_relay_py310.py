"""The robot side installs and runs on Python 3.10 with only the [relay] extra."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("numpy", "rerun", "cv2", "host_bridge", "rosbags", "trimesh", "yourdfpy")


def python310() -> str:
    candidates = [shutil.which("python3.10"),
                  *map(str, Path.home().glob(".pyenv/versions/3.10*/bin/python3.10"))]
    for candidate in filter(None, candidates):
        if subprocess.run([candidate, "--version"], check=False, capture_output=True).returncode == 0:
            return candidate
    pytest.skip("no Python 3.10 interpreter on this machine")


def test_relay_installs_and_imports_on_python_310_without_host_dependencies(tmp_path: Path) -> None:
    env = tmp_path / "venv"
    subprocess.run([python310(), "-m", "venv", str(env)], check=True, timeout=120)
    python = env / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "-q", f"{REPO}[relay]"], check=True,
                   timeout=600, capture_output=True)
    probe = (
        "import sys, robot_relay.cli, robot_relay.relay, robot_relay.files, "
        "robot_relay.sources.ros2\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r}))\n"
        "print(sys.version_info[:2])"
    )
    out = subprocess.run([str(python), "-c", probe], check=True, capture_output=True, text=True,
                         timeout=60).stdout.splitlines()
    assert out == ["[]", "(3, 10)"]
    live = subprocess.run([str(env / "bin" / "swanky-relay"), "--robot", "pi"],
                          check=False, capture_output=True, text=True, timeout=60)
    assert live.returncode == 2
    assert "rclpy is not importable" in live.stderr
