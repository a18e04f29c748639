"""Simulated runs shared by the demo tests, decoded once per test session's package."""

from __future__ import annotations

import io

import pytest
import yourdfpy

from host_bridge.demo import messages, robot
from tests.host_bridge.demo.support import LAP_S, SHORT_S, Messages, decode_run

LAP_TOPICS = ("/tf_static", "/tf", "/odom", messages.GROUND_TRUTH_POSE_TOPIC, "/joint_states", "/scan")


@pytest.fixture(scope="package")
def lap() -> Messages:
    """A full lap of the motion topics, deserialised: topic -> [(log_ns, message)]."""
    return decode_run(duration_s=LAP_S, topics=LAP_TOPICS)


@pytest.fixture(scope="package")
def short() -> Messages:
    """Every topic over a few seconds."""
    return decode_run(duration_s=SHORT_S)


@pytest.fixture(scope="package")
def urdf() -> yourdfpy.URDF:
    """The published robot model, read by an independent URDF parser."""
    return yourdfpy.URDF.load(io.StringIO(robot.robot_description()), load_meshes=False)
