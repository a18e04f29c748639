"""deploy/: the systemd unit, the ROS 2 launch file and the lab router config work as written.

deploy/relay.yaml is checked against the schema in tests/robot_relay/test_policy.py.
"""

from __future__ import annotations

import configparser
import os
import shlex
import shutil
import subprocess
import sys
import time
import types
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.integration.procs import free_port

pytestmark = pytest.mark.integration

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def unit() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(interpolation=None, strict=False)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(DEPLOY / "swanky-relay.service")
    return parser


def test_systemd_unit_starts_the_relay_after_the_network_inside_ros_environment(tmp_path: Path) -> None:
    service = unit()
    assert "network-online.target" in service["Unit"]["After"]
    assert "network-online.target" in service["Unit"]["Wants"]
    assert service["Service"]["Restart"] == "on-failure"
    assert service["Install"]["WantedBy"] == "multi-user.target"
    analyze = shutil.which("systemd-analyze")
    if analyze is not None:
        check = subprocess.run([analyze, "verify", str(DEPLOY / "swanky-relay.service")],
                               check=False, capture_output=True, text=True, timeout=60)
        assert (check.returncode, check.stderr) == (0, "")

    # Run ExecStart's command with a stand-in ROS setup script and relay: the relay must see
    # ROS's environment and get the config and the extra arguments.
    setup = tmp_path / "setup.bash"
    setup.write_text("export AMENT_PREFIX_PATH=/opt/ros/humble\nexport ROS_DOMAIN_ID=7\n")
    relay = tmp_path / "swanky-relay"
    relay.write_text('#!/bin/sh\necho "$AMENT_PREFIX_PATH $ROS_DOMAIN_ID $*"\n')
    relay.chmod(0o755)
    command = shlex.split(service["Service"]["ExecStart"])
    assert command[:2] == ["/bin/bash", "-c"]
    env = {"PATH": os.environ["PATH"], "ROS_SETUP": str(setup), "SWANKY_RELAY": str(relay),
           "SWANKY_CONFIG": "/etc/swanky/relay.yaml", "SWANKY_ARGS": "--robot tb3 -e tcp/10.0.0.1:7447"}
    out = subprocess.run(command, env=env, check=True, capture_output=True, text=True, timeout=30)
    assert out.stdout == (
        "/opt/ros/humble 7 --config /etc/swanky/relay.yaml --robot tb3 -e tcp/10.0.0.1:7447\n"
    )


class _Entity:
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args
        self.kwargs = kwargs


def test_launch_file_runs_the_relay_with_its_config(monkeypatch: pytest.MonkeyPatch) -> None:
    """ROS 2 launch is not installable here: stand-ins record what the file builds."""
    names = {"launch": ["LaunchDescription"], "launch.actions": ["DeclareLaunchArgument", "ExecuteProcess"],
             "launch.substitutions": ["LaunchConfiguration"]}
    for module_name, classes in names.items():
        module = types.ModuleType(module_name)
        for class_name in classes:
            setattr(module, class_name, type(class_name, (_Entity,), {}))
        monkeypatch.setitem(sys.modules, module_name, module)
    namespace: dict[str, Any] = {"__name__": "swanky_relay_launch"}
    exec(compile((DEPLOY / "swanky_relay.launch.py").read_text(), "swanky_relay.launch.py", "exec"),
         namespace)
    description = namespace["generate_launch_description"]()
    entities = description.args[0]
    arguments = {e.args[0]: e.kwargs["default_value"] for e in entities
                 if type(e).__name__ == "DeclareLaunchArgument"}
    assert arguments == {"config": "/etc/swanky/relay.yaml", "relay": "swanky-relay"}
    (process,) = [e for e in entities if type(e).__name__ == "ExecuteProcess"]
    cmd = process.kwargs["cmd"]
    assert [c.args[0] if type(c).__name__ == "LaunchConfiguration" else c for c in cmd] == [
        "relay", "--config", "config"
    ]
    assert process.kwargs["respawn"] is True


def test_router_config_routes_between_a_robot_and_a_host() -> None:
    config = zenoh.Config.from_file(str(DEPLOY / "zenoh-router.json5"))
    assert config.get_json("mode") == '"router"'
    assert config.get_json("listen/endpoints") == '["tcp/0.0.0.0:7447"]'
    # The same file, on a loopback port: a client robot and a client host talk through it.
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config.insert_json5("listen/endpoints", f'["{endpoint}"]')
    router = zenoh.open(config)
    clients = []
    try:
        for _ in range(2):
            client = zenoh.Config()
            client.insert_json5("mode", '"client"')
            client.insert_json5("connect/endpoints", f'["{endpoint}"]')
            clients.append(zenoh.open(client))
        robot, host = clients
        got: list[bytes] = []
        subscriber = host.declare_subscriber("swanky/tb3/data/**", lambda s: got.append(s.payload.to_bytes()))
        publisher = robot.declare_publisher("swanky/tb3/data/scan")
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            publisher.put(b"cdr")
            time.sleep(0.05)
        assert got[:1] == [b"cdr"]
        subscriber.undeclare()
        publisher.undeclare()
    finally:
        for client_session in clients:
            client_session.close()
        router.close()
