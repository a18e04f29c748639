"""What runs on the simulated robot from tick to tick: the log lines of the loop follower
(waypoints reached, doorways passed) and each tick's sensor readings, computed only when a
message of that tick asks for them. It builds no map: that is the host's job."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from host_bridge.demo.robot import TICK_HZ, Pose2D, RobotState, nearest_leg
from host_bridge.demo.sensors import (
    CAMERA_FOCAL,
    CAMERA_HZ,
    SCAN_HZ,
    CameraView,
    render_camera,
    scan_ranges,
)
from host_bridge.demo.world import WAYPOINTS, distance_to_walls

DOOR_CLEARANCE = 0.6  # m; closer than this to a wall the driver logs a warning

# rcl_interfaces/msg/Log levels
LOG_INFO = 20
LOG_WARN = 30
LOGGER_NAME = "swanky_bot.driver"


@dataclass(frozen=True, slots=True)
class LogLine:
    level: int
    text: str
    function: str


class Step:
    """What the message builders see at one tick: the true ``state`` (what the sensors see) and
    the wheel ``odom``. Sensors are computed when a builder first asks (a run limited to some
    topics skips the camera), so builders ask only on their ticks."""

    def __init__(
        self, tick: int, stamp_ns: int, state: RobotState, odom: Pose2D, *, acceleration: float,
        log: LogLine | None,
    ) -> None:
        self.tick = tick
        self.stamp_ns = stamp_ns
        self.state = state
        self.odom = odom
        self.acceleration = acceleration  # dv/dt over the last tick, m/s^2
        self.log = log

    @cached_property
    def scan(self) -> NDArray[np.float32]:
        return scan_ranges(self.state)

    @cached_property
    def camera(self) -> CameraView:
        return render_camera(self.state)

    @property
    def step_ms(self) -> float:
        """The /instrumentation/timer series: a modelled cost of the step (control, plus each
        sensor due), not a measured one, so that the bag stays byte-for-byte deterministic."""
        sensors = ((SCAN_HZ, 0.9), (CAMERA_HZ, 2.6))  # (rate, ms when due)
        due = sum(ms for hz, ms in sensors if self.tick % (TICK_HZ // hz) == 0)
        return 0.8 + 0.1 * math.sin(0.7 * self.tick) + due


class Driver:
    """The memory one simulated robot needs between ticks: the leg it is on, whether it is in a
    doorway, log lines not yet published (one per tick, as a real /rosout would interleave
    them)."""

    def __init__(self) -> None:
        self.leg: int | None = None
        self.in_doorway = False
        self.previous_v = 0.0
        self.pending: deque[LogLine] = deque()

    def _events(self, state: RobotState) -> None:
        leg = nearest_leg(state.x, state.y)[0]
        if self.leg is None:
            self.pending.append(LogLine(
                LOG_INFO,
                f"driving the apartment loop from ({state.x:.2f}, {state.y:.2f}), next "
                f"waypoint {(leg + 1) % len(WAYPOINTS)} at {_waypoint_text(leg + 1)}",
                "start",
            ))
            self.pending.append(LogLine(
                LOG_WARN,
                "camera: no calibration file found, publishing the nominal intrinsics "
                f"(fx = fy = {CAMERA_FOCAL:g} px)",
                "start",
            ))
        elif leg != self.leg:
            self.pending.append(LogLine(
                LOG_INFO,
                f"waypoint {leg} reached at {_waypoint_text(leg)}, heading for waypoint "
                f"{(leg + 1) % len(WAYPOINTS)} at {_waypoint_text(leg + 1)}",
                "follow_loop",
            ))
        self.leg = leg
        clearance = float(distance_to_walls([(state.x, state.y)])[0])
        if clearance < DOOR_CLEARANCE and not self.in_doorway:
            self.pending.append(LogLine(
                LOG_WARN, f"passing a doorway: {clearance:.2f} m from the wall", "follow_loop"
            ))
        self.in_doorway = clearance < DOOR_CLEARANCE

    def step(self, tick: int, stamp_ns: int, state: RobotState, odom: Pose2D) -> Step:
        self._events(state)
        acceleration = (state.v - self.previous_v) * TICK_HZ
        self.previous_v = state.v
        log = self.pending.popleft() if self.pending else None
        return Step(tick, stamp_ns, state, odom, acceleration=acceleration, log=log)


def _waypoint_text(index: int) -> str:
    x, y = WAYPOINTS[index % len(WAYPOINTS)]
    return f"({x:.1f}, {y:.1f})"
