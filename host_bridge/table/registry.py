"""The type table: one record per ROS type holding all the host knows about it: its converter,
where the layout shows it, the options record its converter reads (what a config file may set
for it), the lane the dispatcher converts it in, and how the relay forwards it.

One :class:`Row` per type, written out in :func:`default_registry` with the full type name, so a
new type is one converter module and one line there (CONTRIBUTING.md). Nothing registers itself
on import and a type registered twice is an error. The contract converters follow is
:mod:`host_bridge.core.contract`; the configuration (:mod:`host_bridge.table.config`) takes each type's
option names, converter choices and defaults from its row. The relay keeps its own copy of the
traffic column, ``robot_relay.policy.TRAFFIC`` (the robot has no host code), and
``tests/host_bridge/test_registry.py`` checks it against the rows.

The table names each converter by its module and attribute (:class:`Lazy`), imported when a
topic of its type first needs it: the command line imports this module and must start fast, and
a bag converts with only its own types' converter modules imported (the others' cost 6% of
``swanky-host --bag`` of nav2_turtlebot.mcap, sampled with py-spy).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import Enum
from fnmatch import fnmatchcase
from importlib import import_module
from typing import Any

from host_bridge.core.contract import Converter, LogEntry, Run, combine
from host_bridge.core.options import NoOptions
from host_bridge.errors import RegistryError
from robot_relay.policy import DEFAULT_TRAFFIC, TrafficClass

CATCH_ALL = "*"
_GLOB_CHARS = frozenset("*?[")


class View(Enum):
    """Where Swanky's layout (:mod:`host_bridge.outputs.blueprint`) shows a type's topics, besides the
    robot's 3D view, which holds everything under ``/<robot>``."""

    SPATIAL = "the 3D view only (scans, clouds, maps, markers, poses, the robot model)"
    CAMERA = "the 3D view; its pinhole roots the 2D views of the images beside it"
    IMAGE = "a 2D view of its own, in its camera's pinhole when it has one"
    IMAGE_OVERLAY = "drawn on the images of its camera namespace"
    MAP = "the map view (GPS fixes)"
    LOG = "the text log"
    ODOMETRY = "the Odometry plots (the twist; the pose is for the 3D view)"
    IMU = "the IMU plots"
    BATTERY = "the Battery plots"
    JOINTS = "the Joints plots"
    SIGNALS = "the Signals plots"
    CUSTOM = "the generic converter's: Signals plots, and bar charts of its long arrays"


class Lane(Enum):
    """Where the host converts a type's messages (:mod:`host_bridge.inputs.queues`: each robot
    has a thread for its small topics and one for its heavy ones) and whether a newer message may
    take an older one's place when the host falls behind."""

    SMALL = "the robot's thread, every message in order (scans, IMU, TF: small and frequent)"
    HEAVY = (
        "the robot's heavy thread (a live host's converter process, offload.py), latest-only when "
        "behind: big messages of which only the newest matters (a frame, a cloud, a whole map)"
    )
    PATCH = (
        "the heavy thread, in order with the heavy messages it changes in place (a grid's "
        "updates), never replaced"
    )


@dataclass(frozen=True, slots=True)
class Lazy:
    """A converter named by its module under ``host_bridge.converters`` and its attribute there,
    imported on first use; :meth:`Registry.get` hands out the converter itself (the dispatcher
    asks whether it is a ``PerMessage``). Callable as the converter, for ``combine``."""

    module: str
    name: str

    def load(self) -> Converter:
        converter: Converter = getattr(import_module(f"host_bridge.converters.{self.module}"), self.name)
        return converter

    def __call__(self, run: Run) -> list[LogEntry]:
        return self.load()(run)


def loaded(converter: Converter) -> Converter:
    """``converter``, imported if the table names it lazily."""
    return converter.load() if isinstance(converter, Lazy) else converter


def is_robot_description(topic: str) -> bool:
    """``/robot_description`` or a namespaced one (``/tb1/robot_description``): std_msgs/String
    there is a robot model (the description converter's row), plain text everywhere else."""
    return topic.rstrip("/").split("/")[-1] == "robot_description"


@dataclass(frozen=True, slots=True)
class Row:
    """One line of the table.

    ``msgtype`` is a full type name, or a glob for a family of types (``*/srv/*_Event``), tried
    after the exact names in table order; ``*`` is the catch-all. ``topics`` limits the row to
    the topics it accepts, tried before the type's other row (std_msgs/String on
    /robot_description is a robot model, elsewhere text). ``options``: the record the
    converters read with ``ctx.options`` (:mod:`host_bridge.core.options`), which is what a config
    file may set for the type. ``converter``: see :mod:`host_bridge.core.contract`. ``lane``: see
    :class:`Lane`. ``slow``: a second converter too slow for the receive path (wall meshes of a
    map), run after ``converter`` in a worker that keeps only the newest message. ``traffic``:
    the relay's share of the link for the type (its own table, ``robot_relay.policy.TRAFFIC``,
    must agree). ``converter`` and ``slow`` may be :class:`Lazy`: :meth:`Registry.get` and
    :func:`loaded` give the converter itself.
    """

    msgtype: str
    converter: Converter
    view: View
    options: type[Any] = NoOptions
    lane: Lane = Lane.SMALL
    slow: Converter | None = None
    traffic: TrafficClass = DEFAULT_TRAFFIC
    topics: Callable[[str], bool] | None = None

    @property
    def is_family(self) -> bool:
        return not _GLOB_CHARS.isdisjoint(self.msgtype)


class Registry:
    """The table, looked up by full ROS type name (``sensor_msgs/msg/LaserScan``) and topic."""

    def __init__(self, rows: Iterable[Row]) -> None:
        self._rows = tuple(rows)
        self._exact: dict[str, Row] = {}
        self._routed: list[Row] = []
        self._converters: dict[tuple[str, str], Converter] = {}
        self._families: list[Row] = []
        seen: set[tuple[str, Callable[[str], bool] | None]] = set()
        for row in self._rows:
            if (row.msgtype, row.topics) in seen:
                msg = f"type {row.msgtype!r} is registered twice; each type has exactly one row"
                raise RegistryError(msg)
            seen.add((row.msgtype, row.topics))
            if row.slow is not None and (row.is_family or row.topics is not None):
                msg = f"{row.msgtype!r}: a slow converter is run per type, not per topic or family"
                raise RegistryError(msg)
            if row.topics is not None:
                self._routed.append(row)
            elif row.is_family:
                if self._families and self._families[-1].msgtype == CATCH_ALL:
                    msg = f"{row.msgtype!r} comes after the {CATCH_ALL!r} row and is never reached"
                    raise RegistryError(msg)
                self._families.append(row)
            else:
                self._exact[row.msgtype] = row
        if not self._families or self._families[-1].msgtype != CATCH_ALL:
            msg = f"the table needs a {CATCH_ALL!r} row last: the converter of every other type"
            raise RegistryError(msg)
        for routed in self._routed:
            if routed.options is not self.row(routed.msgtype).options:
                msg = f"{routed.msgtype!r}: all rows of a type take one options record (set per type)"
                raise RegistryError(msg)

    def row(self, msgtype: str, topic: str = "") -> Row:
        for row in self._routed:
            if fnmatchcase(msgtype, row.msgtype) and row.topics is not None and row.topics(topic):
                return row
        exact = self._exact.get(msgtype)
        if exact is not None:
            return exact
        return next(row for row in self._families if fnmatchcase(msgtype, row.msgtype))

    def get(self, msgtype: str, topic: str = "") -> Converter:
        """The converter of ``msgtype`` on ``topic``, imported; found once per (type, topic):
        the dispatcher asks for every run, a live message alone."""
        converter = self._converters.get((msgtype, topic))
        if converter is None:
            converter = self._converters[(msgtype, topic)] = loaded(self.row(msgtype, topic).converter)
        return converter

    def rows(self) -> tuple[Row, ...]:
        """Every row in table order (a test walks them all)."""
        return self._rows

    def types(self) -> list[str]:
        """The type names the table spells out (no globs)."""
        return sorted({row.msgtype for row in self._rows if not row.is_family})

    def slow_converters(self) -> dict[str, Converter]:
        """Each type's slow converter, imported on its first call (the SlowLane's worker calls
        it; a bag with no map imports no wall finder)."""
        return {t: row.slow for t, row in self._exact.items() if row.slow is not None}


def default_registry() -> Registry:
    """Swanky's table. Every type spelt out; see :class:`Row`, :class:`View` and :class:`Lane`
    for the columns."""
    from host_bridge.core.options import (
        CostmapUpdateOptions,
        GenericOptions,
        GridDrawingOptions,
        GridOptions,
        GridUpdateOptions,
        ImageOptions,
        ImuOptions,
        LaserScanOptions,
        NavSatFixOptions,
        PathOptions,
        PointCloudOptions,
        PoseArrayOptions,
        PoseCovarianceOptions,
        PoseOptions,
        TfOptions,
    )
    from robot_relay.policy import BULK, FRAMES, SCANS, SENSOR, VIDEO

    return Registry([
        Row("tf2_msgs/msg/TFMessage", Lazy("tf", "SPEC"), View.SPATIAL, options=TfOptions, traffic=FRAMES),
        Row("sensor_msgs/msg/LaserScan", Lazy("laser", "SPEC"), View.SPATIAL, options=LaserScanOptions,
            traffic=SCANS),
        Row("sensor_msgs/msg/PointCloud2", Lazy("pointcloud", "SPEC"), View.SPATIAL,
            options=PointCloudOptions, lane=Lane.HEAVY, traffic=BULK),
        Row("nav_msgs/msg/Odometry", Lazy("odometry", "SPEC"), View.ODOMETRY, options=PoseOptions),
        Row("sensor_msgs/msg/Imu", Lazy("imu", "IMU"), View.IMU, options=ImuOptions, traffic=SENSOR),
        Row("sensor_msgs/msg/MagneticField", Lazy("imu", "MAGNETIC_FIELD"), View.IMU, traffic=SENSOR),
        Row("sensor_msgs/msg/NavSatFix", Lazy("geo", "SPEC"), View.MAP, options=NavSatFixOptions),
        Row("sensor_msgs/msg/Range", Lazy("proximity", "SPEC"), View.SIGNALS, traffic=SENSOR),
        # Cameras. CompressedImage is not heavy: its format may name a video codec, and a lost
        # video frame spoils the picture until the next keyframe.
        Row("sensor_msgs/msg/Image", Lazy("images", "IMAGE"), View.IMAGE, options=ImageOptions,
            lane=Lane.HEAVY, traffic=BULK),
        Row("sensor_msgs/msg/CompressedImage", Lazy("images", "COMPRESSED_IMAGE"), View.IMAGE,
            options=ImageOptions, traffic=BULK),
        Row("foxglove_msgs/msg/CompressedVideo", Lazy("video", "SPEC"), View.IMAGE, traffic=VIDEO),
        Row("sensor_msgs/msg/CameraInfo", Lazy("camera", "SPEC"), View.CAMERA, traffic=SENSOR),
        Row("vision_msgs/msg/Detection2D", Lazy("vision", "DETECTION_2D"), View.IMAGE_OVERLAY),
        Row("vision_msgs/msg/Detection2DArray", Lazy("vision", "DETECTION_2D_ARRAY"), View.IMAGE_OVERLAY),
        Row("vision_msgs/msg/Detection3D", Lazy("vision", "DETECTION_3D"), View.SPATIAL),
        Row("vision_msgs/msg/Detection3DArray", Lazy("vision", "DETECTION_3D_ARRAY"), View.SPATIAL),
        # Maps: a grid is drawn at once, its walls come from the slow worker.
        Row("nav_msgs/msg/OccupancyGrid", Lazy("occupancy", "GRID"), View.SPATIAL, options=GridOptions,
            lane=Lane.HEAVY, slow=Lazy("walls", "GRID_WALLS")),
        Row("map_msgs/msg/OccupancyGridUpdate", Lazy("occupancy", "GRID_UPDATE"), View.SPATIAL,
            options=GridUpdateOptions, lane=Lane.PATCH, slow=Lazy("walls", "UPDATE_WALLS")),
        Row("nav2_msgs/msg/Costmap", Lazy("occupancy", "COSTMAP"), View.SPATIAL, options=GridDrawingOptions,
            lane=Lane.HEAVY),
        Row("nav2_msgs/msg/CostmapUpdate", Lazy("occupancy", "COSTMAP_UPDATE"), View.SPATIAL,
            options=CostmapUpdateOptions, lane=Lane.PATCH),
        Row("nav_msgs/msg/GridCells", Lazy("nav", "GRID_CELLS"), View.SPATIAL),
        Row("nav_msgs/msg/Path", Lazy("nav", "PATH"), View.SPATIAL, options=PathOptions),
        Row("geometry_msgs/msg/PoseStamped", Lazy("geometry", "POSE_STAMPED"), View.SPATIAL,
            options=PoseOptions),
        Row("geometry_msgs/msg/PoseWithCovarianceStamped", Lazy("geometry", "POSE_WITH_COVARIANCE"),
            View.SPATIAL, options=PoseCovarianceOptions),
        Row("geometry_msgs/msg/PoseArray", Lazy("geometry", "POSE_ARRAY"), View.SPATIAL,
            options=PoseArrayOptions),
        Row("geometry_msgs/msg/PointStamped", Lazy("geometry", "POINT"), View.SPATIAL),
        Row("geometry_msgs/msg/PolygonStamped", Lazy("geometry", "POLYGON"), View.SPATIAL),
        Row("geometry_msgs/msg/TwistStamped", Lazy("geometry", "TWIST"), View.SIGNALS),
        Row("geometry_msgs/msg/WrenchStamped", Lazy("geometry", "WRENCH"), View.SIGNALS),
        Row("geometry_msgs/msg/Vector3Stamped", Lazy("geometry", "VECTOR3"), View.SIGNALS),
        Row("visualization_msgs/msg/Marker", Lazy("markers", "MARKER"), View.SPATIAL),
        Row("visualization_msgs/msg/MarkerArray", Lazy("markers", "MARKER_ARRAY"), View.SPATIAL),
        # The robot: its model moves with the joints, which are also plotted.
        Row("std_msgs/msg/String", Lazy("urdf.description", "SPEC"), View.SPATIAL,
            topics=is_robot_description),
        Row("sensor_msgs/msg/JointState",
            combine(Lazy("joints", "JOINT_STATE"), Lazy("scalars", "JOINT_STATE")), View.JOINTS),
        Row("trajectory_msgs/msg/JointTrajectory", Lazy("joints", "JOINT_TRAJECTORY"), View.SPATIAL),
        Row("sensor_msgs/msg/BatteryState", Lazy("scalars", "BATTERY"), View.BATTERY),
        Row("sensor_msgs/msg/Temperature", Lazy("scalars", "TEMPERATURE"), View.SIGNALS),
        Row("sensor_msgs/msg/FluidPressure", Lazy("scalars", "FLUID_PRESSURE"), View.SIGNALS),
        Row("sensor_msgs/msg/Illuminance", Lazy("scalars", "ILLUMINANCE"), View.SIGNALS),
        Row("sensor_msgs/msg/RelativeHumidity", Lazy("scalars", "RELATIVE_HUMIDITY"), View.SIGNALS),
        # Text.
        Row("rcl_interfaces/msg/Log", Lazy("logs", "ROS2_LOG"), View.LOG),
        Row("rosgraph_msgs/msg/Log", Lazy("logs", "ROS1_LOG"), View.LOG),
        Row("std_msgs/msg/String", Lazy("logs", "STRING"), View.LOG),
        Row("diagnostic_msgs/msg/DiagnosticArray", Lazy("diagnostics", "SPEC"), View.LOG),
        Row("*/srv/*_Event", Lazy("services", "SPEC"), View.LOG),  # /<service>/_service_event
        # Plain numbers.
        Row("std_msgs/msg/Bool", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Byte", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Char", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Int8", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/UInt8", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Int16", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/UInt16", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Int32", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/UInt32", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Int64", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/UInt64", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Float32", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/Float64", Lazy("scalars", "NUMBER"), View.SIGNALS),
        Row("std_msgs/msg/ByteMultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/Int8MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/UInt8MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/Int16MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/UInt16MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/Int32MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/UInt32MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/Int64MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/UInt64MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/Float32MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("std_msgs/msg/Float64MultiArray", Lazy("scalars", "NUMBER_ARRAY"), View.SIGNALS),
        Row("builtin_interfaces/msg/Time", Lazy("scalars", "SECONDS"), View.SIGNALS),
        Row("builtin_interfaces/msg/Duration", Lazy("scalars", "SECONDS"), View.SIGNALS),
        # Every other type, custom ones included.
        Row(CATCH_ALL, Lazy("generic", "SPEC"), View.CUSTOM, options=GenericOptions),
    ])

