"""Per-frame and per-run records shared across the package (bottom layer: imports nothing of
``slam`` but errors). Written to the run folder by :mod:`slam.run_folder`."""

from __future__ import annotations

from dataclasses import asdict, dataclass


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
    model_rejected: bool = False
    keyframe: bool = False
    ms: float = 0.0

    def as_row(self) -> dict:
        return asdict(self)
