"""The pose graph: keyframe poses tied by scan matches, loop closures among them, optimised by
GTSAM's ISAM2 over SE(2) ``BetweenFactorPose2``s (a loop closure goes through a Huber kernel,
so one wrong closure bends the trajectory less than the many right ones).

ISAM2 rather than a batch optimiser: a closure re-solves only the part of the graph it touches.
Batch Levenberg-Marquardt took 0.2-0.7 s per closure on a 3,000-keyframe chain with 30 closures
here, ISAM2 42 ms (1.26 s for all 30), and a long log closes hundreds of loops. Keyframes wait
in ``_new`` until the next closure, the only time their optimised poses are read.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from host_bridge.slam.pose import Pose2, pose2

# Standard deviations (x m, y m, yaw rad) of the constraints.
FIRST = np.array([1e-3, 1e-3, 1e-4])
MATCHED = np.array([0.02, 0.02, np.radians(0.5)])
ODOMETRY = np.array([0.1, 0.1, np.radians(3.0)])
CLOSURE = np.array([0.05, 0.05, np.radians(1.0)])
HUBER_K = 1.345
EXTRA_ITERATIONS = 2
"""ISAM2 relinearises once per update: a loop closure gets this many more to settle."""


class PoseGraph:
    """Keyframes are numbered in the order they are added, from 0."""

    def __init__(self) -> None:
        import gtsam  # [slam]: only a host that maps loads it

        self._gtsam = gtsam
        params = gtsam.ISAM2Params()
        # QR: Cholesky called a long chain with a closure "indeterminate" (a 3,000-keyframe
        # corridor here); QR solved it, 42 ms a closure.
        params.setFactorization("QR")
        self._isam = gtsam.ISAM2(params)
        self._new = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._count = 0
        self.closures = 0

    def _noise(self, sigmas: npt.NDArray[np.float64], robust: bool = False) -> Any:
        gtsam = self._gtsam
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))
        if robust:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), noise)
        return noise

    def add(self, pose: Pose2, relative: Pose2 | None = None, matched: bool = True) -> int:
        """Add a keyframe at ``pose``, tied to the previous one by ``relative`` (its pose seen
        from the previous keyframe; trusted as a scan match or, less, as odometry)."""
        gtsam = self._gtsam
        key = self._count
        self._values.insert(key, gtsam.Pose2(*pose))
        if key == 0:
            self._new.add(gtsam.PriorFactorPose2(key, gtsam.Pose2(*pose), self._noise(FIRST)))
        else:
            assert relative is not None
            sigmas = MATCHED if matched else ODOMETRY
            self._new.add(gtsam.BetweenFactorPose2(key - 1, key, gtsam.Pose2(*relative),
                                                   self._noise(sigmas)))
        self._count += 1
        return key

    def close_loop(self, older: int, newer: int, relative: Pose2) -> None:
        """``newer`` was seen from ``older`` at ``relative`` by matching it against the map there."""
        gtsam = self._gtsam
        self._new.add(gtsam.BetweenFactorPose2(older, newer, gtsam.Pose2(*relative),
                                               self._noise(CLOSURE, robust=True)))
        self.closures += 1

    def optimize(self) -> list[Pose2]:
        """Every keyframe's pose after optimisation, in key order."""
        gtsam = self._gtsam
        self._isam.update(self._new, self._values)
        for _ in range(EXTRA_ITERATIONS):
            self._isam.update()
        self._new = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        result = self._isam.calculateEstimate()
        poses = []
        for key in range(self._count):
            found = result.atPose2(key)
            poses.append(pose2(found.x(), found.y(), found.theta()))
        return poses
