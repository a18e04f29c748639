"""The viewer layout (a Rerun blueprint) built from the topics seen, and kept in step with them.

:func:`build_blueprint` is pure: robots and their topics (ROS type, entity path) in, a
``rerun.blueprint.Blueprint`` out. Per robot: one 3D view of everything under ``/<robot>`` (model,
scan, cloud, map, walls, trails, camera frustums), a 2D view per image topic, a map for GPS
fixes, time series grouped by kind, bar charts of custom types' long arrays, and a text log.
Where a type goes is its row's :class:`~host_bridge.table.registry.View` in the type table. Several
robots get one tab each, after a tab with every robot in one 3D view. The 3D views name no
target frame: the data does (host_bridge/core/frames.py logs the robot's ``map``, ``odom`` or model
root as the frame of ``/<robot>`` and keeps every frame of the robot connected to it), so a saved
blueprint still fits a robot whose frames differ.

:class:`BlueprintFollower` owns the "when": the dispatcher tells it of each new topic (and of a
topic whose type changed), and it rebuilds and re-sends the blueprint when the set of (robot,
topic, type) changed, at most once per interval, so a robot that joins later or a topic that
starts late gets its view.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import rerun.blueprint as rrb

from host_bridge.converters.camera import pinhole_path
from host_bridge.core.contract import STATS_ROOT, WARNINGS_PATH, ConvertContext
from host_bridge.errors import ConfigError
from host_bridge.table.registry import Registry, View, default_registry

TIMER_PREFIX = "/instrumentation/timer/"

# Time series, one view per group, in this order; timers (by topic) have their own.
SIGNALS = "Signals"
TIMERS = "Timers"
PLOT_GROUPS: dict[View, str] = {
    View.ODOMETRY: "Odometry", View.IMU: "IMU", View.BATTERY: "Battery", View.JOINTS: "Joints",
    View.SIGNALS: SIGNALS, View.CUSTOM: SIGNALS,
}
PLOT_ORDER = ("Odometry", "IMU", "Battery", "Joints", SIGNALS, TIMERS)
# Rerun's time series do not draw bar charts: the generic converter's long arrays (a custom
# scan, a histogram) get a bar chart view of every custom topic of the robot. It stays empty
# when none of them has such an array; the layout only knows types, not what they logged.
ARRAYS = "Arrays"


@dataclass(frozen=True, slots=True, order=True)
class TopicEntry:
    """One topic as the dispatcher tells of it."""

    robot: str
    topic: str
    msgtype: str
    entity_path: str


@dataclass(frozen=True, slots=True)
class _Placed:
    """A topic and the view kind its type's row gives it."""

    robot: str
    topic: str
    entity_path: str
    view: View


def _subtree(path: str) -> str:
    return f"+ {path.rstrip('/')}/**"


def _is_under(path: str, root: str) -> bool:
    return path == root or path.startswith(root.rstrip("/") + "/")


def _plot_group(entry: _Placed) -> str | None:
    if entry.topic.startswith(TIMER_PREFIX):
        return TIMERS
    return PLOT_GROUPS.get(entry.view)


def _plot_query(entry: _Placed) -> str:
    if entry.view is View.ODOMETRY:
        # Only the twist is scalar; the pose and its trail are for the 3D view.
        return _subtree(f"{entry.entity_path}/twist")
    return _subtree(entry.entity_path)


def _pinholes(topics: Iterable[_Placed]) -> set[str]:
    """Entity paths of the cameras' pinholes (logged by the CameraInfo converter)."""
    return {
        pinhole_path(ConvertContext(robot=t.robot, topic=t.topic, entity_path=t.entity_path, times={}))
        for t in topics
        if t.view is View.CAMERA
    }


def _flat_pictures(topics: Sequence[_Placed]) -> list[str]:
    """Images and their overlays under no pinhole: 2D content a 3D view cannot place (it shows
    "2D visualizers require a pinhole ancestor" for them), so 3D views leave them out."""
    pinholes = _pinholes(topics)
    return [
        t.entity_path for t in topics
        if t.view in (View.IMAGE, View.IMAGE_OVERLAY)
        and not any(_is_under(t.entity_path, p) for p in pinholes)
    ]


def _spatial_contents(included: Sequence[str], topics: Sequence[_Placed]) -> list[str]:
    return [*included, *(f"- {path.rstrip('/')}/**" for path in _flat_pictures(topics))]


def _image_views(topics: Sequence[_Placed]) -> list[rrb.View]:
    """A 2D view per image topic, rooted at its camera's pinhole when it has one, so overlays
    of the same camera and the 3D scene's projection land on the picture."""
    pinholes = _pinholes(topics)
    views: list[rrb.View] = []
    for image in (t for t in topics if t.view is View.IMAGE):
        cameras = [p for p in pinholes if _is_under(image.entity_path, p)]
        origin = max(cameras, key=len) if cameras else image.entity_path
        overlays = [
            t.entity_path for t in topics
            if t.view is View.IMAGE_OVERLAY and _is_under(t.entity_path, origin)
        ]
        views.append(rrb.Spatial2DView(
            name=image.topic, origin=origin,
            contents=[_subtree(image.entity_path), *(_subtree(p) for p in overlays)],
            # The image plane, i.e. the pinhole's child frame. Left unset, a view takes the
            # origin's CoordinateFrame: the camera's 3D optical frame, where no 2D content is.
            spatial_information=rrb.SpatialInformation(target_frame=f"tf#{origin}"),
        ))
    return views


def _plot_views(robot: str, topics: Sequence[_Placed], stats: bool) -> list[rrb.View]:
    groups: dict[str, list[str]] = {}
    for entry in topics:
        group = _plot_group(entry)
        if group is not None:
            groups.setdefault(group, []).append(_plot_query(entry))
    views: list[rrb.View] = [
        rrb.TimeSeriesView(name=group, origin=f"/{robot}", contents=groups[group])
        for group in PLOT_ORDER
        if group in groups
    ]
    arrays = [_subtree(t.entity_path) for t in topics if t.view is View.CUSTOM]
    if arrays:
        views.append(rrb.BarChartView(name=ARRAYS, origin=f"/{robot}", contents=arrays))
    if stats:
        views.append(rrb.TimeSeriesView(name="Stats", origin=f"{STATS_ROOT}/{robot}"))
        # How far behind the viewer showing this is (thinning.py), beside each robot's stats.
        views.append(rrb.TimeSeriesView(name="Viewer lag", origin=f"{STATS_ROOT}/host"))
    return views


def _log_view(topics: Sequence[_Placed]) -> rrb.View:
    queries = [_subtree(t.entity_path) for t in topics if t.view is View.LOG]
    return rrb.TextLogView(name="Log", origin="/", contents=[*queries, _subtree(WARNINGS_PATH)])


def _gps_view(name: str, topics: Iterable[_Placed]) -> rrb.View | None:
    fixes = [_subtree(t.entity_path) for t in topics if t.view is View.MAP]
    return rrb.MapView(name=name, origin="/", contents=fixes) if fixes else None


def robot_layout(robot: str, topics: Sequence[_Placed], *, stats: bool = False) -> rrb.Container:
    """3D view on the left; cameras and map, plots (as tabs) and the log on the right."""
    right: list[rrb.Container | rrb.View] = []
    pictures: list[rrb.View] = _image_views(topics)
    gps = _gps_view("GPS", topics)
    if gps is not None:
        pictures.append(gps)
    if pictures:
        right.append(rrb.Grid(*pictures) if len(pictures) > 1 else pictures[0])
    plots = _plot_views(robot, topics, stats)
    if plots:
        right.append(rrb.Tabs(*plots))
    right.append(_log_view(topics))
    return rrb.Horizontal(
        rrb.Spatial3DView(
            name=f"{robot} 3D", origin=f"/{robot}", contents=_spatial_contents(["$origin/**"], topics)
        ),
        rrb.Vertical(*right),
        column_shares=[3, 2],
        name=robot,
    )


def build_blueprint(
    topics: Iterable[TopicEntry], *, registry: Registry | None = None, stats: bool = False
) -> rrb.Blueprint:
    """The layout for these topics, placed by their rows in ``registry`` (default: Swanky's
    table); ``stats`` adds each robot's ``/_stats/<robot>`` plots."""
    table = registry or default_registry()
    by_robot: dict[str, list[_Placed]] = {}
    for entry in sorted(set(topics)):
        view = table.row(entry.msgtype, entry.topic).view
        placed = _Placed(entry.robot, entry.topic, entry.entity_path, view)
        by_robot.setdefault(entry.robot, []).append(placed)
    layouts = [robot_layout(robot, entries, stats=stats) for robot, entries in by_robot.items()]
    if len(layouts) == 1:
        return rrb.Blueprint(layouts[0])
    every = [t for entries in by_robot.values() for t in entries]
    shared: list[rrb.View] = [rrb.Spatial3DView(
        name="All robots 3D", origin="/",
        contents=_spatial_contents([_subtree(f"/{robot}") for robot in by_robot], every),
    )]
    gps = _gps_view("All robots GPS", every)
    if gps is not None:
        shared.append(gps)
    overview = rrb.Horizontal(*shared, name="All robots")
    return rrb.Blueprint(rrb.Tabs(overview, *layouts, active_tab=0))


class BlueprintFollower:
    """Re-sends the layout when the topics change, at most once per ``interval`` seconds.

    The first topic of a burst starts a timer; everything that arrives before it fires goes into
    one blueprint. :meth:`close` sends what is still pending (a saved .rrd gets the final layout).
    """

    def __init__(
        self,
        send: Callable[[rrb.Blueprint], None],
        *,
        interval: float = 1.0,
        stats: bool = False,
        registry: Registry | None = None,
    ) -> None:
        self._send = send
        self._interval = interval
        self._stats = stats
        self._registry = registry or default_registry()
        # Each topic as its latest type (a topic whose type changed is laid out as the new one).
        self._topics: dict[tuple[str, str], TopicEntry] = {}
        self._peers: dict[str, frozenset[TopicEntry]] = {}
        """Other hosts' topics, by host (shared_layout.py): they are laid out too."""
        self.on_own_topics: Callable[[frozenset[TopicEntry]], None] | None = None
        """Told this host's topics each time they changed (shared_layout.py shares them)."""
        self._told: frozenset[TopicEntry] = frozenset()
        self._sent: frozenset[TopicEntry] = frozenset()
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._closed = False

    def topic_seen(self, robot: str, topic: str, msgtype: str, entity_path: str) -> None:
        entry = TopicEntry(robot, topic, msgtype, entity_path)
        with self._lock:
            if self._topics.get((robot, topic)) == entry or self._closed:
                return
            self._topics[(robot, topic)] = entry
            self._start_timer()

    def peer_topics(self, peer: str, topics: frozenset[TopicEntry]) -> None:
        """Another host's topics (all of them: they replace what it said before)."""
        with self._lock:
            if self._peers.get(peer) == topics or self._closed:
                return
            self._peers[peer] = topics
            self._start_timer()

    def _start_timer(self) -> None:
        if self._timer is None:
            self._timer = threading.Timer(self._interval, self._fire)
            self._timer.daemon = True
            self._timer.start()

    def _fire(self) -> None:
        with self._lock:
            self._timer = None
            self._send_if_changed()

    def _send_if_changed(self) -> None:
        own = frozenset(self._topics.values())
        if own != self._told and self.on_own_topics is not None:
            self.on_own_topics(own)
            self._told = own
        topics = own.union(*self._peers.values())
        if topics == self._sent:
            return
        self._send(build_blueprint(topics, registry=self._registry, stats=self._stats))
        self._sent = topics

    def close(self) -> None:
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            self._closed = True
            self._send_if_changed()


def check_blueprint_file(path: Path, application_id: str) -> Path:
    """``path`` if it is a Rerun blueprint (.rbl) for ``application_id``, else a ConfigError
    naming the file and what is wrong with it."""
    from rerun.chunk import RrdReader

    if path.suffix != ".rbl":
        msg = f"--blueprint {path}: not an .rbl file (the Rerun viewer's menu saves one)"
        raise ConfigError(msg)
    if not path.is_file():
        msg = f"--blueprint {path}: no such file"
        raise ConfigError(msg)
    try:
        stores = RrdReader(path).blueprints()
    except (RuntimeError, ValueError) as err:
        msg = f"--blueprint {path}: not a Rerun blueprint file ({err})"
        raise ConfigError(msg) from err
    if not stores:
        msg = f"--blueprint {path}: the file holds no blueprint (is it a recording?)"
        raise ConfigError(msg)
    others = sorted({s.application_id for s in stores} - {application_id})
    if others:
        msg = (
            f"--blueprint {path}: the blueprint is for application {others[0]!r}, Swanky's "
            f"recordings are {application_id!r}; save it from a Swanky recording in the viewer"
        )
        raise ConfigError(msg)
    return path
