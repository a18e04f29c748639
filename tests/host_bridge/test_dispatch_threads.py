"""One robot logged from two threads at once (its small topics and its heavy ones, see
inputs/queues.py): the frames the dispatcher places at the robot's root never overwrite a real
transform that was logged meanwhile."""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence

import rerun as rr

from host_bridge.core.contract import LogEntry, LogItem
from host_bridge.pipeline.dispatch import Dispatcher

TIMES = {"ros_time": 1_700_000_000_000_000_000}


class GatedSink:
    """Keeps what is logged to the robot's /tf_static entity of ``camera``; holds the thread
    logging ``/a/points`` until released."""

    def __init__(self) -> None:
        self.camera_parents: list[str] = []
        self.points_logging = threading.Event()
        self.release = threading.Event()

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        for entry in entries:
            assert isinstance(entry, LogItem)
            if entry.path == "/a/points":
                self.points_logging.set()
                self.release.wait(20)
            if entry.path == "/a/tf_static/camera":
                (transform,) = entry.archetypes
                assert isinstance(transform, rr.Transform3D)
                assert transform.parent_frame is not None
                self.camera_parents.extend(transform.parent_frame.as_arrow_array().to_pylist())

    def close(self) -> None:
        pass


def test_a_frame_placed_for_one_thread_never_lands_after_anothers_real_transform() -> None:
    sink = GatedSink()
    dispatcher = Dispatcher(sink)
    cloud = LogItem("/a/points", (rr.CoordinateFrame("a/camera"),))
    static_transform = LogItem(
        "/a/tf_static/camera",
        (rr.Transform3D(parent_frame="a/base_link", child_frame="a/camera", translation=[1, 2, 3]),),
        static=True,
    )
    # The heavy thread logs a cloud in frame a/camera, which nothing places yet: the
    # dispatcher places it at the robot's root, on the entity /tf_static uses for a/camera.
    heavy = threading.Thread(target=dispatcher.log, args=("a", [cloud], TIMES))
    heavy.start()
    assert sink.points_logging.wait(20)
    # Meanwhile the small thread logs /tf_static's real transform of a/camera.
    small = threading.Thread(target=dispatcher.log, args=("a", [static_transform], TIMES))
    small.start()
    small.join(0.5)  # it waits for the placement it comes after
    sink.release.set()
    heavy.join(20)
    small.join(20)
    assert sink.camera_parents == ["tf#/a", "a/base_link"]  # the real one last: it stands
    assert dispatcher.frames("a").unplaced() == ["base_link"]
