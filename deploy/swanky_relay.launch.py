"""ROS 2 launch file for the relay, for robots brought up with ``ros2 launch`` rather than systemd.

    ros2 launch deploy/swanky_relay.launch.py config:=/etc/swanky/relay.yaml

ROS's environment is already sourced wherever ``ros2 launch`` runs, so the relay is started as a
plain process (it is not a ROS package, so not a launch_ros Node), restarted if it dies.
"""

from __future__ import annotations

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument(
            "config", default_value="/etc/swanky/relay.yaml",
            description="relay configuration (deploy/relay.yaml is an example)",
        ),
        DeclareLaunchArgument(
            "relay", default_value="swanky-relay",
            description="the swanky-relay executable (e.g. /opt/swanky/venv/bin/swanky-relay)",
        ),
        ExecuteProcess(
            cmd=[LaunchConfiguration("relay"), "--config", LaunchConfiguration("config")],
            name="swanky_relay",
            output="screen",
            respawn=True,
            respawn_delay=5.0,
            sigterm_timeout="10",
        ),
    ])
