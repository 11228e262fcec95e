"""One typed configuration tree: defaults in code, YAML overrides, saved with every run.

Each component receives only its own section (``cfg.tracking``, ``cfg.mapping``, ...).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from slam.errors import ConfigError


@dataclass
class DatasetConfig:
    """How the sequence is read. ``calibration`` fields override the sequence's own (null = keep)."""

    path: str | None = None  # the sequence folder (recorded so a run folder can be re-evaluated)
    layout: str = "auto"  # auto | tum | 7scenes
    calibration: dict[str, float | None] = field(default_factory=dict)
    max_frames: int | None = None  # read at most this many frames
    stride: int = 1  # use every n-th frame
    # colour pixel-aligned with depth? null: as the sequence says (TUM: yes, 7-Scenes: no)
    color_registered: bool | None = None


@dataclass
class RansacConfig:
    """Feature RANSAC over 3D-3D ORB correspondences (minimal sets of 3 pairs)."""

    n_features: int = 1000
    ratio: float = 0.8  # Lowe's ratio test for ORB matches
    iterations: int = 500
    inlier_threshold_m: float = 0.03
    min_inliers: int = 15
    seed: int = 0


@dataclass
class TrackingConfig:
    """Frame-to-model projective point-to-plane ICP with RANSAC seeding/rescue."""

    frame_to_frame: bool = True  # initialise model ICP by ICP against the previous frame
    downsample: int = 2  # ICP and model ray-casting run at 1/downsample resolution
    # edge-preserving (bilateral) smoothing of the depth used for tracking, as in KinectFusion;
    # fusion keeps the raw depth. Range sigma (0 = off) and spatial sigma in full-res pixels
    bilateral_sigma_m: float = 0.03
    bilateral_sigma_px: float = 4.5
    iterations: list[int] = field(default_factory=lambda: [6, 4, 2])  # coarse ... fine
    depth_min_m: float = 0.2
    depth_max_m: float = 4.0
    max_correspondence_m: float = 0.07  # projective correspondences farther apart are rejected
    huber_delta_m: float = 0.05
    coarse_correspondence_factor: float = 2.0  # both grow by this factor per coarser level
    min_fitness: float = 0.1  # ICP check: fraction of pixels with an ICP correspondence
    min_overlap: float = 0.3  # ICP check: fraction of pixels within inlier_threshold of the model
    inlier_threshold_m: float = 0.03
    max_step_translation_m: float = 0.3  # frame-to-frame ICP moving the guess more is rejected
    max_model_correction_m: float = 0.05  # frame-to-model ICP moving the guess more is rejected
    max_model_correction_deg: float = 3.0
    large_motion_translation_m: float = 0.06  # predicted motion above this -> RANSAC seed
    large_motion_rotation_deg: float = 6.0
    hypotheses: bool = True  # large motion, poor overlap: also try identity/velocity/RANSAC guesses
    hypothesis_overlap: float = 0.75  # ... unless the first estimate already overlaps this well
    relocalisation_keyframes: int = 5  # RANSAC tries this many recent keyframes when needed
    # colour in tracking (only where colour is registered to depth, see dataset.color_registered):
    # weight of the photometric term of a joint photometric + geometric frame-to-model alignment
    # against the model's ray-cast colour (slam.frontend.photometric); 0 = depth only. Off: at
    # 1.0 it measured no better on tum-fr1-xyz and worse on the demo and the cabinet, ~2x slower
    photometric_weight: float = 0.0
    photometric_frame_to_frame: bool = False  # ... the frame-to-frame alignment joint too
    keyframe_translation_m: float = 0.15
    keyframe_rotation_deg: float = 12.0
    ransac: RansacConfig = field(default_factory=RansacConfig)


@dataclass
class MappingConfig:
    """TSDF fusion (Open3D VoxelBlockGrid) and meshing."""

    voxel_size_m: float = 0.01
    trunc_voxels: float = 4.0  # truncation distance = trunc_voxels * voxel_size
    block_resolution: int = 8  # voxels per block side; 8 hugs the surface band tighter than 16
    block_count: int = 20000  # initial hash-map capacity in blocks (grows when needed)
    depth_max_m: float = 3.5
    integrate_color: bool = True
    raycast_weight_threshold: float = 3.0
    mesh_weight_threshold: float = 3.0
    # submaps: each fused in the frame of its anchor keyframe, re-fused under corrected anchors
    submap_keyframes: int = 10  # a new submap every this many keyframes (0: a single map)
    submap_min_frames: int = 60  # ... and at least this many frames
    submap_overlap_frames: int = 3  # frames fused into both the old and the new submap
    submap_seed_views: int = 3  # a new submap starts with the old one seen from its last views
    reintegration_stride: int = 10  # re-fuse a submap from every n-th of its frames' viewpoints
    reintegration_downsample: int = 2  # those views are ray-cast at 1/n resolution
    spill_submaps: bool = True  # finished submaps wait on disk (temporary folder), not in memory


@dataclass
class LoopConfig:
    """Revisit detection (bag of binary words over keyframe ORB) and geometric verification."""

    enabled: bool = True
    vocabulary_words: int = 1000  # words of the online vocabulary (k-majority on ORB)
    vocabulary_keyframes: int = 10  # keyframes whose descriptors train the vocabulary
    exclude_recent_keyframes: int = 8  # the most recent keyframes are not revisit candidates
    max_candidates: int = 3  # best-scoring candidates verified per keyframe
    min_score: float = 0.05  # bag-of-words similarity (sum of min of L1-normalised tf-idf)
    ratio: float = 0.8  # Lowe's ratio for descriptor matches between the two keyframes
    ransac_iterations: int = 1000
    ransac_threshold_m: float = 0.03
    min_inliers: int = 25
    min_inlier_ratio: float = 0.2  # RANSAC inliers / descriptor matches
    min_icp_fitness: float = 0.3
    min_overlap: float = 0.5  # fraction of pixels within overlap_threshold after ICP
    overlap_threshold_m: float = 0.03
    max_icp_correction_m: float = 0.15  # ICP moving the RANSAC pose more is a failure
    max_icp_correction_deg: float = 10.0
    # the loop's relative pose must agree with the current estimate within a tolerance that
    # grows with the path travelled between the two keyframes (odometry drift is bounded)
    consistency_m: float = 0.2
    consistency_per_m: float = 0.1
    consistency_deg: float = 10.0
    consistency_deg_per_m: float = 5.0


@dataclass
class BackendConfig:
    """GTSAM keyframe pose graph: odometry edges, robust loop edges, Levenberg-Marquardt."""

    # edge information = per-correspondence J^T J of the registration (its shape) / sigma^2
    odometry_sigma_m: float = 0.003  # floor of an odometry edge's sigma
    odometry_drift_per_m: float = 0.03  # odometry edge sigma grows with the motion it spans
    loop_sigma_m: float = 0.02
    loop_kernel: str = "cauchy"  # cauchy | huber | none
    loop_kernel_width: float = 2.0  # in standard deviations of the loop edge
    loop_prune_sigma: float = 5.0  # a loop still this far off after optimisation is removed
    max_iterations: int = 100


@dataclass
class OutputConfig:
    save_mesh: bool = True
    save_tracking_log: bool = True


@dataclass
class SlamConfig:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


def _build(cls: type, data: Any, where: str) -> Any:
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ConfigError(f"config section '{where}' must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {unknown} in section '{where or 'root'}'; "
            f"valid keys: {sorted(names)}"
        )
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, f"{where}.{name}" if where else name)
    return cls(**kwargs)


def _coerce(tp: Any, value: Any, where: str) -> Any:
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, where)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(inner[0], value, where)
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"config key '{where}' must be a list, got {value!r}")
        return [_coerce(args[0], v, where) for v in value]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"config key '{where}' must be a mapping, got {value!r}")
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{where}' must be true/false, got {value!r}")
        return value
    if tp in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{where}' must be a number, got {value!r}")
        if tp is int and float(value) != int(value):
            raise ConfigError(f"config key '{where}' must be an integer, got {value!r}")
        return tp(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config key '{where}' must be a string, got {value!r}")
        return value
    return value


def config_from_dict(data: dict[str, Any] | None) -> SlamConfig:
    """Defaults overridden by ``data`` (nested mapping); unknown keys are errors."""
    return _build(SlamConfig, data or {}, "")


def read_yaml(path: str | Path, what: str = "config") -> Any:
    """Parse a YAML file; an unreadable file or invalid YAML is a :class:`ConfigError`."""
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {exc}") from exc


def load_config(path: str | Path | None) -> SlamConfig:
    """Default config, overridden by the YAML file at ``path`` when given."""
    if path is None:
        return SlamConfig()
    path = Path(path)
    data = read_yaml(path)
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
