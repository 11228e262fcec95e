"""Per-frame and per-run records shared across the package (bottom layer: imports nothing of
``slam`` but errors). Written to the run folder by :mod:`slam.run_folder`."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np


@dataclass
class TrackingStatus:
    """Per-frame tracking record (written to ``tracking.csv``; summarised in ``metrics.json``).

    ``path``: ``init`` (first frame of a map segment), ``icp`` (ICP from the motion
    prediction), ``ransac+icp`` (ICP seeded by RANSAC), ``reloc`` (relocalised against a
    keyframe after tracking was lost), ``lost`` (no pose: no usable depth, or no estimate
    passed the checks; the frame is neither fused nor written to the trajectory). ``reason``
    says why a frame is lost; ``gap``: the frame follows a gap (skipped frames, a timestamp
    jump), so its pose had to be verified.
    """

    index: int
    path: str
    ok: bool
    timestamp: float = 0.0
    reason: str = ""
    gap: bool = False
    segment: int = 0
    icp_fitness: float = 0.0
    icp_rmse_m: float = 0.0
    ransac_inliers: int = 0
    ransac_matches: int = 0
    overlap: float = 0.0
    f2f_fitness: float = 0.0
    # how blind the geometry was: the weakest over the strongest standard deviation of the
    # model ICP's pose (rotations as motion at the scene's depth; large: a direction that
    # depth alone hardly constrains, see slam.frontend.weighted_icp.constraint)
    constraint_ratio: float = 0.0
    # colour joined depth in the estimate kept (depth was blind, or broke a motion check)
    photometric: bool = False
    model_rejected: bool = False
    # the motion check the estimate on depth alone broke ("acceleration": past what a hand
    # can do; "unusual": past this recording's own pattern), "" when it broke none or was
    # not checked (slam.frontend.colour_stages.check_motion)
    motion_check: str = ""
    keyframe: bool = False
    ms: float = 0.0

    def as_row(self) -> dict:
        return asdict(self)


@dataclass
class LoopRecord:
    """One verified revisit candidate (a line of ``loops.json``): keyframe ``query_kf`` (the new
    one) against ``match_kf``, the verification's outcome and ``T_match_query``, the query
    camera's pose in the match camera (4x4 array), as the verifier measured it."""

    query_kf: int
    match_kf: int
    query_frame: int
    match_frame: int
    query_timestamp: float
    match_timestamp: float
    score: float
    accepted: bool
    reason: str
    matches: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    icp_fitness: float = 0.0
    overlap: float = 0.0
    T_match_query: np.ndarray = field(default_factory=lambda: np.eye(4))

    def as_json(self) -> dict[str, Any]:
        """The ``loops.json`` entry (numbers rounded as written: 4 decimals, the transform 9)."""
        d = asdict(self)
        for k in ("score", "inlier_ratio", "icp_fitness", "overlap"):
            d[k] = round(float(d[k]), 4)
        d["T_match_query"] = np.round(np.asarray(self.T_match_query), 9).tolist()
        return d

    @staticmethod
    def from_json(d: dict[str, Any]) -> LoopRecord:
        names = {f.name for f in fields(LoopRecord)}
        rec = LoopRecord(**{k: v for k, v in d.items() if k in names})
        rec.T_match_query = np.asarray(rec.T_match_query, float)
        return rec


@dataclass
class FrameLog:
    """The frames that have a pose, in order: index, timestamp, odometry pose, tracking run (a
    run ends where tracking was lost) and map segment."""

    index: list[int] = field(default_factory=list)
    timestamp: list[float] = field(default_factory=list)
    pose: list[np.ndarray] = field(default_factory=list)
    run: list[int] = field(default_factory=list)
    segment: list[int] = field(default_factory=list)

    def append(self, index: int, t: float, T: np.ndarray, run: int, segment: int) -> None:
        self.index.append(index)
        self.timestamp.append(t)
        self.pose.append(T)
        self.run.append(run)
        self.segment.append(segment)

    def __len__(self) -> int:
        return len(self.index)

    def state_dict(self) -> dict[str, list]:
        return {f.name: list(getattr(self, f.name)) for f in fields(self)}

    @staticmethod
    def from_state_dict(d: dict[str, list]) -> FrameLog:
        return FrameLog(**{f.name: list(d[f.name]) for f in fields(FrameLog)})


#: ``metrics.json`` keys present only when they apply (absent rather than null)
_OPTIONAL = frozenset(
    {
        "resumed_at_frame",
        "map",
        "frames_localised",
        "frames_not_localised",
        "first_localised_frame",
        "ate_rmse_map_frame_m",
        "map_frame_error",
        "extended_map",
        "map_extension",
        "read_ms_per_frame",
        "calibration_source",
        "ate_rmse_m",
        "ate_rmse_odometry_m",
        "ate_rmse_pose_graph_m",
        "rpe_trans_rmse_m",
        "rpe_rot_rmse_deg",
        "matched_poses",
        "drift_percent",
        "evaluation_error",
        "slam_version",
        "git_commit",
        "git_dirty",
    }
)


@dataclass
class RunMetrics:
    """A run's numbers: the fields are the ``metrics.json`` keys, in the order written (each one
    is described in docs/usage.md, "metrics.json keys"). Read like the JSON object it becomes
    (``m["ate_rmse_m"]``, ``m.get(...)``, ``"ate_rmse_m" in m``); keys that do not apply (no
    ground truth, no resume) are absent. :meth:`as_json` is the object written."""

    frames: int = 0
    frames_tracked: int = 0
    frames_in_trajectory: int = 0
    frames_skipped: int = 0
    skipped: list[dict[str, Any]] = field(default_factory=list)
    lost_frames: list[int] = field(default_factory=list)
    relocalisations: int = 0
    relocalisation_frames: list[int] = field(default_factory=list)
    map_segments: list[dict[str, Any]] = field(default_factory=list)
    segment_joins: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    fps: float | None = None
    fps_tracking_fusion: float = 0.0
    real_time_factor: float | None = None  # recording duration over run time (>= 1: real time)
    stage_ms_per_frame: dict[str, float] = field(default_factory=dict)
    stage_ms_total: dict[str, float] = field(default_factory=dict)
    tracking_failures: int = 0
    tracking_paths: dict[str, int] = field(default_factory=dict)
    colour_frames: int = 0  # tracked frames whose pose colour constrained with depth
    keyframes: int = 0
    submaps: int = 0
    loops_accepted: int = 0
    loops_rejected: int = 0
    loop_detection_ms: float = 0.0
    optimisation_ms: float = 0.0
    optimisations: int = 0
    ba: dict[str, Any] = field(default_factory=dict)
    icp_fitness_mean: float = 0.0
    icp_rmse_mean_m: float = 0.0
    mesh_vertices: int = 0
    map_blocks: int = 0
    # set by the runner (slam.run), not by the stepwise system
    sequence: str | None = None
    checkpoints: int = 0
    checkpoint_ms: float = 0.0
    workers: int = 1  # worker processes that tracked the sequence (slam run --workers)
    resumed_at_frame: int | None = None
    peak_rss_mb: float | None = None
    read_ms_per_frame: float | None = None  # the reader thread's time per frame read
    # images of the recording left out because they have no partner (TUM: rgb/depth pairs)
    unpaired_images: dict[str, int] = field(default_factory=dict)
    calibration_source: str | None = None  # where the sequence's calibration came from
    # a localisation run (slam run --map): the map's run folder, the frames placed in it, the
    # frames never placed (no pose made up for them), the first frame placed (sequence index)
    map: str | None = None
    frames_localised: int | None = None
    frames_not_localised: int | None = None
    first_localised_frame: int | None = None
    # a run that extended a saved map (slam run --map --extend): that map's run folder, and how
    # the new recording joined it (slam.merge.MergeReport)
    extended_map: str | None = None
    map_extension: dict[str, Any] | None = None
    # set when the run folder is written (slam.run_folder.save_run): the software that ran
    slam_version: str | None = None
    git_commit: str | None = None  # null when not run from a git checkout
    git_dirty: bool | None = None  # the checkout had uncommitted changes to tracked files
    # with ground truth (slam.pipeline.evaluate_against_ground_truth)
    ate_rmse_m: float | None = None
    ate_rmse_odometry_m: float | None = None
    ate_rmse_pose_graph_m: float | None = None
    rpe_trans_rmse_m: float | None = None
    rpe_rot_rmse_deg: float | None = None
    matched_poses: int | None = None
    drift_percent: float | None = None
    evaluation_error: str | None = None
    # a localisation run with ground truth: the error in the map's world frame, the map run's
    # alignment to its ground truth applied and none of its own (a map frame 20 cm off shows)
    ate_rmse_map_frame_m: float | None = None
    map_frame_error: str | None = None  # why that could not be measured

    def __post_init__(self) -> None:
        # given at construction: the optional keys with a value
        self.__dict__["_given"] = {k for k in _OPTIONAL if getattr(self, k) is not None}

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _OPTIONAL:  # an optional key is written once it is given, even as null
            self.__dict__.setdefault("_given", set()).add(name)
        object.__setattr__(self, name, value)

    def as_json(self) -> dict[str, Any]:
        """The ``metrics.json`` object: every field, less the optional ones never given."""
        given = self.__dict__.get("_given", set())
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name not in _OPTIONAL or f.name in given
        }

    def update(self, values: dict[str, Any]) -> None:
        """Set fields from a dict of ``metrics.json`` keys (unknown keys are an error)."""
        for k, v in values.items():
            if k not in _FIELDS:
                raise KeyError(f"{k!r} is not a field of slam.records.RunMetrics")
            setattr(self, k, v)

    # read access as the JSON object
    def __getitem__(self, key: str) -> Any:
        d = self.as_json()
        return d[key]

    def get(self, key: str, default: Any = None) -> Any:
        return self.as_json().get(key, default)

    def __contains__(self, key: object) -> bool:
        return key in self.as_json()

    def __iter__(self):  # noqa: ANN204 - as a dict's keys
        return iter(self.as_json())

    def __len__(self) -> int:
        return len(self.as_json())

    def keys(self):  # noqa: ANN201 - as dict.keys()
        return self.as_json().keys()

    def items(self):  # noqa: ANN201
        return self.as_json().items()

    def __setitem__(self, key: str, value: Any) -> None:
        self.update({key: value})


_FIELDS = frozenset(f.name for f in fields(RunMetrics))
