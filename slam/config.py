"""One typed configuration tree: defaults in code, YAML overrides, saved with every run.

Each component receives only its own section (``cfg.tracking``, ``cfg.mapping``, ...).
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import math
import numbers
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from slam.config_ranges import check_ranges
from slam.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class DatasetConfig:
    """How the sequence is read. ``calibration`` fields override the sequence's own (null = keep)."""

    path: str | None = None  # the sequence folder (recorded so a run folder can be re-evaluated)
    layout: str = "auto"  # auto | tum | 7scenes
    calibration: dict[str, float | None] = field(default_factory=dict)
    first_frame: int = 0  # the run starts at this frame of the sequence (a split recording)
    max_frames: int | None = None  # read at most this many frames
    stride: int = 1  # use every n-th frame
    # colour pixel-aligned with depth? null: as the sequence says (TUM: yes, 7-Scenes: no)
    color_registered: bool | None = None


@dataclass
class RansacConfig:
    """Feature RANSAC over 3D-3D ORB correspondences (minimal sets of 3 pairs)."""

    n_features: int = 1000  # ORB features a frame extracts (1000: ORB-SLAM's per-frame count)
    ratio: float = 0.8  # Lowe's ratio test for ORB matches (0.8: Lowe's value)
    iterations: int = 500  # hypotheses (500: 99.9% to draw 3 inliers at 20% inliers)
    inlier_threshold_m: float = 0.03  # 3-D distance of an inlier (the ICP checks' 3 cm)
    min_inliers: int = 15  # a pose fewer matches agree with is not a seed
    seed: int = 0  # the generator's seed: runs repeat


@dataclass
class IcpConfig:
    """Projective point-to-plane ICP, coarse to fine, and the checks of its result."""

    iterations: list[int] = field(
        default_factory=lambda: [6, 4, 2]
    )  # Gauss-Newton steps per level, coarse to fine
    # ... for a frame whose motion is large or unknown (it starts centimetres from the optimum)
    large_motion_iterations: list[int] = field(default_factory=lambda: [12, 8, 4])
    icp_depth_max_m: float = 2.5  # ICP uses depth to this range (Kinect noise grows as z^2) ...
    icp_near_fraction: float = 0.3  # ... when it holds this fraction of the valid pixels, else all
    max_correspondence_m: float = 0.03  # farther projective pairs are rejected (finest level)
    huber_delta_m: float = 0.05  # residuals past this weigh less (Huber)
    coarse_correspondence_factor: float = 2.0  # both grow by this factor per coarser level
    min_fitness: float = 0.1  # a result with fewer pixels paired than this fraction fails
    min_overlap: float = 0.3  # ... or with fewer within inlier_threshold_m of the model
    inlier_threshold_m: float = 0.03  # the distance of an overlapping pixel (m)
    max_step_translation_m: float = 0.3  # frame-to-frame ICP moving the guess more is rejected
    max_model_correction_m: float = 0.05  # frame-to-model ICP moving a trusted guess more ...
    max_model_correction_deg: float = 3.0  # ... or turning it more is distrusted
    same_start_translation_m: float = 0.005  # a model ICP starting this close to one tried ...
    same_start_rotation_deg: float = 0.3  # ... is skipped (the same result, for a ray-cast)


@dataclass
class MotionConfig:
    """The motion prediction and the checks of an estimate against it."""

    large_motion_translation_m: float = 0.06  # predicted motion above this: RANSAC seeds ICP
    large_motion_rotation_deg: float = 6.0  # ... or turning more than this
    hypotheses: bool = True  # large motion, poor overlap: identity, velocity, RANSAC guesses too
    hypothesis_overlap: float = 0.75  # ... unless the first estimate overlaps the model this well
    # a step departing from the prediction by more than max_acceleration_m_s2 * dt^2 (a hand's
    # acceleration: 11 mm at 30 Hz) is aligned again with colour joining depth
    max_acceleration_m_s2: float = 10.0
    # ... or by more than this many times the median of the last window's departures (the
    # recording's own pattern; 3: a 3-D Gaussian passes 3x its median with p ~ 1e-4; 0 = off)
    unusual_departure_factor: float = 3.0
    unusual_departure_window: int = 30  # frames in that pattern
    gap_factor: float = 2.5  # an interval this many times the usual one is a gap (no prediction)


@dataclass
class ColourConfig:
    """When and how colour joins depth (where colour is registered)."""

    motion_check_photometric_weight: float = 1.0  # colour's weight in those alignments (0 = off)
    # depth is blind when its weakest direction is this many times worse constrained than its
    # strongest (standard deviations): colour joins every alignment, depth leaves that direction
    degenerate_ratio: float = 40.0
    photometric_ratio: float = 20.0  # ... joins (not fast, no gap) above this ratio too
    # the colour a frame aligns to against the model: "keyframe" (the last keyframes' images
    # warped by the model's depth, averaged) or "model" (the TSDF's own, smeared colour)
    photometric_reference: str = "keyframe"
    photometric_keyframes: int = 5  # keyframes averaged (one carries its own error)


@dataclass
class RecoveryConfig:
    """Verification after a gap or a jump, relocalisation and map segments."""

    verify_min_matches: int = 8  # a pose is verified when this many ORB matches agree ...
    verify_overlap_ratio: float = 0.9  # ... or it overlaps this fraction of the recent frames'
    suspect_overlap_ratio: float = 0.6  # overlap below this fraction of recent: verify (a jump)
    relocalisation_keyframes: int = 5  # recent keyframes RANSAC tries when the motion is large
    relocalisation_candidates: int = 5  # keyframes a lost frame is registered against
    rescue_min_weight: float = 1.0  # a lost frame's last try: the model rendered to this weight
    new_segment_after_lost: int = 10  # lost frames with usable depth before a new map segment


@dataclass
class TrackingConfig:
    """Frame-to-model tracking: the depth it uses, then its sub-sections (ICP, motion checks,
    colour, recovery, RANSAC)."""

    frame_to_frame: bool = True  # model ICP starts from ICP against the previous frame
    downsample: int = 2  # ICP and ray-casting run at 1/downsample resolution (320x240 for VGA)
    bilateral_sigma_m: float = 0.03  # bilateral smoothing of tracking depth: range sigma (0 = off)
    bilateral_sigma_px: float = 4.5  # ... and spatial sigma in full-resolution pixels
    depth_min_m: float = 0.2  # depth outside [min, max] is not used (a Kinect's range)
    depth_max_m: float = 4.0
    # the sensor's axial noise sigma(z) = sigma0 + quadratic * (z - 0.4 m)^2 (Kinect v1, Nguyen
    # et al. 2012): weighs depth's information against colour's
    depth_noise_sigma0_m: float = 0.0012
    depth_noise_quadratic: float = 0.0019
    keyframe_translation_m: float = 0.15  # a new keyframe after this much motion ...
    keyframe_rotation_deg: float = 12.0  # ... or this much turn
    min_depth_fraction: float = 0.02  # a frame with less usable depth is lost
    icp: IcpConfig = field(default_factory=IcpConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    colour: ColourConfig = field(default_factory=ColourConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)


@dataclass
class MappingConfig:
    """TSDF fusion (Open3D VoxelBlockGrid) and meshing."""

    voxel_size_m: float = 0.01  # TSDF voxel side (1 cm: a room in ~1 GB at Kinect range)
    trunc_voxels: float = 4.0  # truncation distance in voxels (covers Kinect noise to ~3 m)
    block_resolution: int = 8  # voxels per block side (8 hugs the surface band tighter than 16)
    block_count: int = 20000  # initial hash-map capacity in blocks (grows when needed)
    depth_max_m: float = 3.5  # depth fused up to this range (noise grows as z^2 beyond)
    integrate_color: bool = True  # fuse colour too (coloured mesh, colour ray-casts)
    raycast_weight_threshold: float = 3.0  # tracking's model: surfaces fused at least this often
    mesh_weight_threshold: float = 3.0  # the mesh: surfaces fused at least this often
    submap_keyframes: int = 10  # a new submap every this many keyframes (0: a single map)
    submap_min_frames: int = 60  # ... and at least this many frames
    submap_overlap_frames: int = 8  # frames fused into both the old and the new submap
    submap_seed_views: int = 3  # a new submap starts with the old one seen from its last views
    reintegration_stride: int = 10  # re-fuse a submap from every n-th of its frames' viewpoints
    reintegration_downsample: int = 2  # those views are ray-cast at 1/n resolution
    spill_submaps: bool = True  # finished submaps wait on disk, not in memory


@dataclass
class LoopConfig:
    """Revisit detection (bag of binary words over keyframe ORB) and geometric verification."""

    enabled: bool = True  # detect revisits and close loops
    vocabulary_words: int = 1000  # words of the online vocabulary (k-majority on ORB)
    vocabulary_keyframes: int = 10  # keyframes whose descriptors train the vocabulary
    exclude_recent_keyframes: int = 8  # the most recent keyframes are not revisit candidates
    max_candidates: int = 3  # best-scoring candidates verified per keyframe
    min_score: float = 0.05  # bag-of-words similarity (sum of min of L1-normalised tf-idf)
    ratio: float = 0.8  # Lowe's ratio for descriptor matches between the two keyframes
    ransac_iterations: int = 1000  # RANSAC hypotheses between the two keyframes' 3-D features
    ransac_threshold_m: float = 0.03  # a RANSAC inlier's 3-D distance
    min_inliers: int = 25  # fewer RANSAC inliers: not a loop
    min_inlier_ratio: float = 0.2  # RANSAC inliers / descriptor matches
    min_icp_fitness: float = 0.3  # ICP's fraction of paired pixels after RANSAC's pose
    min_overlap: float = 0.5  # fraction of pixels within overlap_threshold_m after ICP
    overlap_threshold_m: float = 0.03  # the distance of an overlapping pixel
    max_icp_correction_m: float = 0.15  # ICP moving the RANSAC pose more is a failure
    max_icp_correction_deg: float = 10.0  # ... or turning it more
    # ICP's pose must keep this fraction of RANSAC's inliers (where colour is registered):
    # where it does not, ICP slid along what depth cannot see
    min_feature_agreement: float = 0.5
    feature_agreement_scatter: float = 3.0  # ... within this many times their RMS residual
    icp_max_correspondence_m: float = 0.07  # keyframe-to-keyframe ICP: wider than tracking's
    icp_huber_delta_m: float = 0.05  # ... and its Huber threshold
    # the loop must agree with the current estimate within a tolerance growing with the path
    # between the two keyframes (odometry drift is bounded): base and per metre travelled
    consistency_m: float = 0.2
    consistency_per_m: float = 0.1
    consistency_deg: float = 10.0
    consistency_deg_per_m: float = 5.0
    join_verifications: int = 2  # verified revisits that must agree to join two map segments


@dataclass
class BackendConfig:
    """GTSAM keyframe pose graph: odometry edges, robust loop edges, Levenberg-Marquardt."""

    odometry_sigma_m: float = 0.003  # floor of an odometry edge's sigma (its shape: ICP's J^T J)
    odometry_drift_per_m: float = 0.03  # ... which grows with the motion the edge spans
    odometry_information_threshold_m: float = 0.03  # that shape's correspondences: this close
    loop_sigma_m: float = 0.02  # a loop edge's sigma
    loop_kernel: str = "cauchy"  # robust kernel of loop edges: cauchy | huber | none
    loop_kernel_width: float = 2.0  # in standard deviations of the loop edge
    loop_prune_sigma: float = 5.0  # a loop still this far off after optimisation is removed
    max_iterations: int = 100  # Levenberg-Marquardt iterations


@dataclass
class BAConfig:
    """Bundle adjustment of keyframe poses and ORB landmarks (slam.backend.bundle_adjustment):
    landmark tracks built as keyframes arrive, merged across accepted loops, and optimised
    jointly with the keyframe poses (reprojection + depth per observation, Huber-robust)."""

    enabled: bool = True  # bundle-adjust keyframes and landmarks
    after_loops: bool = True  # a global BA after an accepted loop ...
    loop_interval_keyframes: int = 10  # ... when this many keyframes came since the last BA
    at_finish: bool = True  # and once at the end of the run
    match_window: int = 4  # a new keyframe is matched against this many previous ones ...
    match_nearby: int = 4  # ... and up to this many others of the map lying near it:
    nearby_distance_m: float = 0.6  # within this distance ...
    nearby_angle_deg: float = 35.0  # ... and this angle
    match_radius_px: float = 10.0  # around the pixel the relative pose predicts
    max_hamming: int = 64  # ORB descriptor distance (of 256 bits) for a match
    match_ratio: float = 0.85  # best over second-best distance among the candidates in reach
    depth_tolerance: float = 0.05  # the predicted depth must agree within 2 cm + this fraction
    pixel_sigma_px: float = 1.0  # pixel noise of a level-0 ORB keypoint (x 1.2 per level)
    depth_sigma_m: float = 0.004  # the sensor's depth noise at 1 m (grows with depth^2)
    # pixel error read as depth where depth changes fast around a keypoint (corners, edges):
    # its depth noise adds slope (m/px) x this, in quadrature (0: off)
    depth_misregistration_px: float = 2.0
    huber_px: float = 2.5  # Huber threshold of the reprojection term
    outlier_chi2: float = 7.815  # an observation above this chi^2 (3 dof, 95%) is removed
    max_iterations: int = 5  # Levenberg-Marquardt, before and again after removing outliers
    max_observations_per_landmark: int = 20  # evenly spaced along a track (0: all; density)
    pose_graph_weight: float = 100.0  # the depth edges stay in BA at this weight (0: pure BA)
    min_observations_per_keyframe: int = 100  # fewer: BA is not used (the pose graph stands)
    # the depth term where colour is not registered to depth (7-Scenes): another ray's depth
    unregistered_depth_sigma_m: float = 0.06


@dataclass
class OutputConfig:
    """What the run folder gets besides the trajectories and metrics."""

    save_mesh: bool = True  # mesh.ply
    save_tracking_log: bool = True  # tracking.csv
    # map/: keyframes and the TSDF under the final poses, for `slam run --map` (about 1/3 of
    # the run folder's size at float16 TSDF, uint8 colour, compressed)
    save_map: bool = True


@dataclass
class SlamConfig:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    ba: BAConfig = field(default_factory=BAConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def validate(self) -> SlamConfig:
        """Raise :class:`ConfigError` naming the first key whose value is out of range: a
        number that is not finite (NaN, infinite) anywhere in the tree, then the range of each
        key."""
        for key, value in _non_finite(self):
            raise ConfigError(f"config key '{key}' must be a finite number, got {value!r}")
        check_ranges(self)
        return self

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


def _non_finite(obj: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted key, value) of every number in a config tree that is NaN or infinite: float
    fields, the items of lists, the values of mappings (``dataset.calibration``)."""
    out: list[tuple[str, Any]] = []

    def bad(v: Any) -> bool:
        return isinstance(v, numbers.Real) and not isinstance(v, bool) and not math.isfinite(v)

    for f in dataclasses.fields(obj):
        value, key = getattr(obj, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out += _non_finite(value, f"{key}.")
        elif isinstance(value, list | tuple):
            out += [(key, value) for v in value if bad(v)][:1]
        elif isinstance(value, dict):
            out += [(f"{key}.{k}", v) for k, v in value.items() if bad(v)]
        elif bad(value):
            out.append((key, value))
    return out


def _build(cls: type, data: Any, where: str) -> Any:
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ConfigError(f"config section '{where}' must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    data = _moved_into_sections(cls, data, where)
    data = _without_retired(data, where)
    unknown = sorted(set(data) - names)
    if unknown:
        hints = []
        for key in unknown:
            close = difflib.get_close_matches(str(key), sorted(names), n=1, cutoff=0.6)
            elsewhere = _sections_with(str(key))
            if close:
                hints.append(f"did you mean '{close[0]}' for '{key}'?")
            elif elsewhere:
                hints.append(f"'{key}' belongs in section {' or '.join(elsewhere)}")
        raise ConfigError(
            f"unknown config key(s) {unknown} in section '{where or 'root'}'"
            + (f"; {'; '.join(hints)}" if hints else "")
            + f"; valid keys: {sorted(names)}"
        )
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, f"{where}.{name}" if where else name)
    return cls(**kwargs)


#: the sub-sections ``tracking`` got in 2026-11: their keys were read from ``tracking`` itself
#: before (``ransac`` was a sub-section already)
_TRACKING_SUBSECTIONS = ("icp", "motion", "colour", "recovery")


def _moved_into_sections(cls: type, data: dict[str, Any], where: str) -> dict[str, Any]:
    """A ``tracking`` section written before its sub-sections: each key that now lives in one
    is moved there, with a warning (``tracking.iterations`` is ``tracking.icp.iterations``)."""
    if cls is not TrackingConfig:
        return data
    hints = typing.get_type_hints(cls)
    home = {f.name: sub for sub in _TRACKING_SUBSECTIONS for f in dataclasses.fields(hints[sub])}
    out = dict(data)
    for key in [k for k in data if k in home]:
        sub = out.get(home[key]) or {}
        if not isinstance(sub, dict) or key in sub:
            continue  # left for the section's own error (given in both places: unknown)
        out[home[key]] = {**sub, key: out.pop(key)}
        log.warning(
            "config key '%s.%s' is now '%s.%s.%s': read as that (update the file)",
            where, key, where, home[key], key,
        )  # fmt: skip
    return out


#: keys that no longer exist, and why: read from an older file, they are dropped with a warning
_RETIRED = {
    "mapping.raycast_refine": "tracking against the trilinear surface lost on the scene matrix "
    "(docs/decisions.md)",
    **{
        f"tracking.colour.colour_step_{key}": "the colour step was removed: real rows no better, "
        "the whole run slower (docs/decisions.md)"
        for key in ("weight", "iterations", "textured", "geometry_stride")
    },
}


def _without_retired(data: dict[str, Any], where: str) -> dict[str, Any]:
    out = dict(data)
    for key in [k for k in data if f"{where}.{k}" in _RETIRED]:
        out.pop(key)
        log.warning("config key '%s.%s' is ignored: %s", where, key, _RETIRED[f"{where}.{key}"])
    return out


def _sections_with(key: str) -> list[str]:
    """Config sections (dotted paths) that have a field called ``key``."""
    out = []

    def walk(cls: type, prefix: str) -> None:
        for f in dataclasses.fields(cls):
            tp = typing.get_type_hints(cls)[f.name]
            if dataclasses.is_dataclass(tp):
                walk(tp, f"{prefix}{f.name}.")
            elif f.name == key and prefix:
                out.append(f"'{prefix[:-1]}'")

    walk(SlamConfig, "")
    return out


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
        if tp is int and (not math.isfinite(value) or float(value) != int(value)):
            raise ConfigError(f"config key '{where}' must be an integer, got {value!r}")
        return tp(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config key '{where}' must be a string, got {value!r}")
        return value
    return value


def config_from_dict(data: dict[str, Any] | None) -> SlamConfig:
    """Defaults overridden by ``data`` (nested mapping); unknown keys and out-of-range values
    are errors."""
    return _build(SlamConfig, data or {}, "").validate()


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
