"""What a run produces (:class:`RunResult`), shared by the stepwise system and the runner."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from slam.records import RunMetrics
from slam.trajectory import Trajectory

if TYPE_CHECKING:
    import open3d as o3d

    from slam.config import SlamConfig
    from slam.loops.closer import LoopCloser
    from slam.mapping.submaps import SubmapMap
    from slam.records import TrackingStatus
    from slam.saved_map import Map


@dataclass
class RunResult:
    """What a run produces. ``trajectory`` is the final estimate, ``odometry`` the frontend-only
    one (identical until loop closure corrects poses); both hold the frames that have a pose in
    the main map component (lost frames have none). ``segments``: trajectories of map segments
    that were never joined to the main one (their frame is unrelated to it), by segment id.
    ``pose_graph``: the trajectory before bundle adjustment (the pose graph's keyframes)."""

    trajectory: Trajectory
    odometry: Trajectory
    mesh: o3d.geometry.TriangleMesh | None
    metrics: RunMetrics
    tracking: list[TrackingStatus] = field(default_factory=list)
    config: SlamConfig | None = None
    model: SubmapMap | None = None  # the submaps (odometry frame), for re-meshing and inspection
    loop_closer: LoopCloser | None = None  # keyframes, pose graph and loop records
    segments: dict[int, Trajectory] = field(default_factory=dict)
    pose_graph: Trajectory | None = None  # frames following the pose graph alone (before BA)
    map: Map | None = None  # the map to save (keyframes, TSDF) for later localisation runs

    @property
    def poses(self) -> np.ndarray:
        return self.trajectory.poses

    @property
    def timestamps(self) -> np.ndarray:
        return self.trajectory.timestamps
