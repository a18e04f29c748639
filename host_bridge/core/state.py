"""What converters keep between messages: per robot, named fields all its topics share (its
model's kinematics, its grids); per topic, the topic's options and one record per converter
that keeps something, found by class. The records the robot's fields hold (:class:`RobotModel`,
:class:`Grid`) are defined here, below the converters that make them, so the layers import one
way.

Named fields and classes rather than string-keyed dicts: a misspelt key was a bug mypy could not
see (markers read ``"resolve_uri"`` while the host set ``"resolver"``, so no ``package://``
marker mesh ever loaded on a real host).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.core.options import GridDrawingOptions, Options, options_from
from host_bridge.core.resources import ResourceResolver
from host_bridge.errors import ConvertError

State = TypeVar("State")
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class MimicModel:
    joint: str
    multiplier: float
    offset: float


@dataclass(frozen=True, slots=True)
class JointModel:
    """One URDF joint: origin pose (parent link -> joint frame), unit axis, mimic rule."""

    name: str
    type: str
    parent: str
    child: str
    translation: FloatArray
    rotation: FloatArray
    quaternion: FloatArray
    axis: FloatArray
    mimic: MimicModel | None = None


@dataclass(frozen=True, slots=True)
class RobotModel:
    """The kinematics of one URDF, enough to turn joint values into link transforms."""

    name: str
    joints: Mapping[str, JointModel]
    mimic_order: tuple[str, ...]
    # The link no joint moves: the frame the model hangs from (None for a URDF without links).
    root: str | None = None


@dataclass(frozen=True, slots=True)
class Grid:
    """One occupancy grid as the converters need it; ``cells`` is read-only, row 0 at the origin.

    ``options`` are the grid topic's own, so an update (whose topic has its own options)
    renders the patched grid the way the grid topic asked for; a map's hold its walls' too
    (:class:`~host_bridge.core.options.GridOptions`), a costmap's do not.
    """

    topic: str
    entity_path: str
    frame: str | None
    cells: npt.NDArray[np.int8]
    resolution: float
    translation: npt.NDArray[np.float64]
    quaternion: npt.NDArray[np.float64]
    options: GridDrawingOptions


@dataclass(slots=True)
class RobotState:
    """Shared by every topic of one robot; the dispatcher makes one per robot.

    Converters of one robot run on its thread; the wall worker reads ``grids`` and writes
    ``wall_digests`` on its own, so a Grid is replaced by a new one, never changed in place.
    """

    # Finds the files a model or marker names: --package-path, ROS paths, this robot's relay.
    resolver: ResourceResolver = field(default_factory=ResourceResolver.from_env)
    # The kinematics of the robot's model (/robot_description or --urdf); joint states move it.
    model: RobotModel | None = None
    # The --urdf file drawn for the robot: its /robot_description is then not drawn.
    model_file: Path | None = None
    # Frames /tf or /tf_static drive (ROS ids): joint states leave them to TF.
    tf_children: set[str] = field(default_factory=set)
    # The robot's /tf_static entity once a /tf_static message showed it.
    static_tf_root: str | None = None
    # The last grid of each grid topic, which its update topic patches.
    grids: dict[str, Grid] = field(default_factory=dict)
    # Hash of what each wall entity shows, so an unchanged map is not meshed again.
    wall_digests: dict[str, bytes] = field(default_factory=dict)


def static_transform_path(robot: str, robot_state: RobotState, child_frame_id: str) -> str:
    """The one static entity holding the relation into ``child_frame_id``.

    Rerun wants each frame relation on a single entity. A URDF's fixed joints are usually also
    on /tf_static (robot_state_publisher), so the model logs them here too and whichever of the
    two arrives last holds the value. The root is the robot's /tf_static entity (configurable),
    ``/<robot>/tf_static`` until a /tf_static message shows it.
    """
    root = robot_state.static_tf_root or f"/{robot}/tf_static"
    return f"{root}/{rr.escape_entity_path_part(child_frame_id.strip('/'))}"


class TopicState:
    """One topic of one robot: its option values (from the host configuration, made a typed
    record on first use) and the state records of its converters, one per class, made on first
    use. Two converters of one topic (JointState: kinematics and plots) keep separate records."""

    __slots__ = ("_options", "_records", "_values")

    def __init__(self, options: Mapping[str, Any] | None = None) -> None:
        self._values: Mapping[str, Any] = dict(options or {})
        self._options: dict[type[Any], Any] = {}
        self._records: dict[type[Any], Any] = {}

    @property
    def values(self) -> Mapping[str, Any]:
        """The option values as the host configuration gave them."""
        return self._values

    def options(self, kind: type[Options], topic: str) -> Options:
        found = self._options.get(kind)
        if found is None:
            try:
                found = self._options[kind] = options_from(kind, self._values)
            except ValueError as err:
                raise ConvertError(f"{topic}: {err}") from None
        return cast(Options, found)

    def state(self, kind: type[State]) -> State:
        found = self._records.get(kind)
        if found is None:
            found = self._records[kind] = kind()
        return cast(State, found)
