"""One typed configuration tree: defaults in code, YAML overrides, saved with every run.

Each component receives only its own section (``cfg.tracking``, ``cfg.mapping``, ...).
"""

from __future__ import annotations

import dataclasses
import difflib
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
    # ... for a frame whose motion is large or unknown (fast, after a gap, the first step: a
    # RANSAC seed or a far guess), which starts centimetres from the optimum and needs more
    # Gauss-Newton steps to converge: on the cabinet's 0.66 s steps [6, 4, 2] stopped short
    # (0.020-0.042 m between runs of one tree); twice, three and four times the steps give
    # the same 0.017 m (docs/archive/journal.md). Same number of levels as iterations
    large_motion_iterations: list[int] = field(default_factory=lambda: [12, 8, 4])
    depth_min_m: float = 0.2
    depth_max_m: float = 4.0
    # ICP uses depth up to this range (a Kinect's depth noise grows as z^2 and is structured
    # beyond ~2.5 m) when it holds at least icp_near_fraction of the frame's valid pixels, else
    # all depth up to depth_max_m (far scenes)
    icp_depth_max_m: float = 2.5
    icp_near_fraction: float = 0.3
    # the depth sensor's axial noise, sigma(z) = depth_noise_sigma0_m + depth_noise_quadratic *
    # (z - 0.4 m)^2 (m; Nguyen, Izadi, Lovell 2012, Kinect v1): weighs depth's information
    depth_noise_sigma0_m: float = 0.0012
    depth_noise_quadratic: float = 0.0019
    # projective correspondences farther apart are rejected (at the finest level; 3 cm is the
    # inlier distance of the checks too). Against 7 cm: tum-fr1-xyz odometry 0.0157 -> 0.0143 m,
    # cabinet 0.0625 -> 0.0254 m, 7-Scenes 0.0536 -> 0.0532 m, the synthetic loops unchanged
    max_correspondence_m: float = 0.03
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
    # a step departing from the constant-velocity prediction by more than a hand-held camera
    # can accelerate in the frame interval (max_acceleration_m_s2 * dt^2: 11 mm at 30 Hz) is
    # not taken from depth alone: the frame is aligned again with colour joining depth at this
    # photometric weight (where colour is registered; 0 = off). Depth slides along a wall
    # filling the view or a corridor; texture does not
    max_acceleration_m_s2: float = 10.0
    motion_check_photometric_weight: float = 1.0
    # nor a frame whose departure from the prediction, as an acceleration (departure / dt^2),
    # is more than this many times the median of the last unusual_departure_window frames'
    # (0 = off; the recording's own motion pattern, from every estimate kept, aligned with
    # colour or not: a smooth pan accelerates far less than a hand-held camera can, and slides
    # below max_acceleration_m_s2 stand out against it; 3: a 3-D Gaussian's departures pass
    # 3x their median with probability ~1e-4). Such a step is scored by the images on the way
    # to the prediction first (a few ms), aligned again with colour only where they do not
    # prefer depth's end, and colour's estimate kept only where it returns towards the
    # prediction (on tum-fr1-xyz colour moved such steps away). On the scene matrix (session
    # 37, with colour-aligned frames in the pattern): the halls' worst steps up to 6x smaller
    # and their runs closer (hall-x1-s0's odometry range over 6 runs 9.4 -> 0.7 mm), the
    # desks' odometry 1.3-4.6x better, the walls' worst steps up to 2x smaller, the real rows
    # level, no row worse beyond its spread; tracking + fusion 0.91 (fr1) and 0.97 (demo) of
    # the baseline, but synthetic desks 0.5-0.75x the check off (it aligns again with
    # colour on ~40% of their frames). docs/archive/journal.md
    unusual_departure_factor: float = 3.0
    unusual_departure_window: int = 30
    # geometry is blind when the frame's own depth constrains the pose this many times worse
    # along its weakest direction than along its strongest (standard deviations, rotations as
    # motion at the scene's depth; slam.frontend.weighted_icp.depth_constraint, on the ICP
    # pyramid's level 1: 160 x 120 for VGA): then the 2.5 m near cut is dropped when all depth
    # is not blind. Within a joint alignment (colour with depth), depth is left out of the
    # directions its point-to-plane information constrains this many times worse than its
    # best: there colour decides alone (exact depth weighs a few edge pixels ~100x over colour
    # and slid a fast corridor 0.29 m; slam.frontend.weighted_icp.without_blind_directions).
    # Measured on every frame (the range tracking uses): real fr1 <= 15, 7-Scenes <= 23, the
    # cabinet (a large box) <= 30; synthetic rooms and desks <= 20; a wall filling the view up
    # to 160, corridors 48-95, the hall 30-58
    degenerate_ratio: float = 40.0
    # colour joins depth in every alignment of a frame (at motion_check_photometric_weight,
    # where colour is registered) whose ICP depth has a ratio above degenerate_ratio, or above
    # photometric_ratio while the predicted motion is not fast and no gap precedes the frame
    # (the photometric term's basin is a few pixels; the first step's motion is unknown, and
    # its RANSAC seed brings colour within reach): depth against the model slides along its
    # weak direction by the model's own sub-millimetre bias times about the ratio (wall rows:
    # 11 mm a frame at ratios 22-27; benchmarks/self_render_bias.py)
    photometric_ratio: float = 20.0
    # every tracked frame's pose (where colour is registered) is refined against the previous
    # frame's image: depth's estimate a prior with its point-to-plane information, colour's
    # photometric cost at this weight times what colour has earned on the recording (its
    # disagreement with depth where depth is surest, over depth's own: 1 on synthetic
    # sequences, ~1/400 on tum-fr1-xyz; slam.frontend.colour_step), in
    # colour_step_iterations Gauss-Newton steps. Where depth is weak (a wall filling the view,
    # a corridor) colour holds the frame. 0 = off. Colour's term on the colour_step_textured
    # fraction of the pixels whose intensity changes fastest (1: all; its information is the
    # image gradient), depth's information on every colour_step_geometry_stride-th row and
    # column (1 or 2): 0.125 and 2 cost a fifth of all pixels (docs/archive/journal.md)
    colour_step_weight: float = 0.0
    colour_step_iterations: int = 2
    colour_step_textured: float = 0.125
    colour_step_geometry_stride: int = 4
    # the colour a frame is aligned to against the model: "keyframe", the last keyframes'
    # images, each warped into the model's view by the model's depth and averaged, or "model",
    # the TSDF's own ray-cast colour. A TSDF's colour is smeared (aligned from the true pose to
    # a model of its 10 previous frames, a fast corridor's frame lands 1.8 mm off with the
    # model's colour, 0.2-0.4 mm with its own image: benchmarks/model_colour_bias.py). One
    # keyframe's image carries that keyframe's error along the blind direction (a fast corridor
    # and two halls drifted 25-70% more with 1 than with the model's colour); the mean of
    # photometric_keyframes of them averages it: on the scene matrix with 5, fast walls and
    # corridors 0.008-0.009 -> 0.003-0.006 m, fast halls 0.016 -> 0.010-0.013 (median), no row
    # worse beyond its spread (docs/archive/journal.md)
    photometric_reference: str = "keyframe"
    photometric_keyframes: int = 5
    keyframe_translation_m: float = 0.15
    keyframe_rotation_deg: float = 12.0
    # robustness: a frame with less usable depth than this fraction of its pixels is lost
    min_depth_fraction: float = 0.02
    # an interval this many times the usual one (or a skipped frame) is a gap: the motion
    # prediction is not trusted and the pose must be verified by ORB matches
    gap_factor: float = 2.5
    # ... verified when this many ORB matches agree with the pose (or the depth overlap with the
    # model reaches hypothesis_overlap); a fixed pose, unlike a RANSAC search, rarely gathers
    # agreeing matches by chance, so this is below ransac.min_inliers
    verify_min_matches: int = 8
    # ... or when its overlap with the model is at least this fraction of the recent frames'
    verify_overlap_ratio: float = 0.9
    # a frame whose overlap with the model falls below this fraction of the recent frames'
    # (median of the last 10) is verified the same way (clean runs: >= 0.70; a jump: 0.47)
    suspect_overlap_ratio: float = 0.6
    # a lost frame may look at what the model does not render yet: surfaces fused fewer
    # times than mapping.raycast_weight_threshold (a fast pan brings them into view faster
    # than frames fuse them). When relocalisation finds no keyframe either, the frame is
    # tracked again as after a gap (ORB matches must support the pose) against the model
    # rendered down to this weight (1: every surface seen once; 0: off). Only then: as
    # tracking's model everywhere, weight 1 or 2 made fast walls slide more (single-frame
    # surfaces at the view's edge, where the weak direction is held), and relocalisation
    # (depth against a keyframe's depth) places a frame better; last, a hall panned at
    # 135 deg/s lost 0 frames instead of 12 (docs/archive/journal.md)
    rescue_min_weight: float = 1.0
    # while lost, every frame is relocalised against the map's keyframes (at most this many
    # candidates a frame); after this many lost frames with usable depth a new map segment starts
    relocalisation_candidates: int = 5
    new_segment_after_lost: int = 10
    # a model-ICP start within this distance and angle of one this frame already tried is
    # skipped: it would converge to the same estimate again, at the cost of a ray-cast
    same_start_translation_m: float = 0.005
    same_start_rotation_deg: float = 0.3
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
    # depth-only ray-casts (frame-to-model ICP without colour) refined by a Newton step on the
    # trilinear TSDF: the ray-caster's voxel-pattern error (about 3 mm median at 1 cm voxels)
    # falls to 0.3 mm, for a second ray-cast and a numpy gather a render. Opt-in: the real
    # sequences and desks track better (cabinet 0.026 -> 0.018 m), some walls, halls and fast
    # rooms worse, and tracking + fusion runs at 0.69x the fps (docs/archive/journal.md)
    raycast_refine: bool = False
    mesh_weight_threshold: float = 3.0
    # submaps: each fused in the frame of its anchor keyframe, re-fused under corrected anchors
    submap_keyframes: int = 10  # a new submap every this many keyframes (0: a single map)
    submap_min_frames: int = 60  # ... and at least this many frames
    # frames fused into both the old and the new submap; tracking stays on the old one meanwhile
    submap_overlap_frames: int = 8
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
    # where colour is registered, ICP's pose must keep this fraction of RANSAC's inliers within
    # feature_agreement_scatter times their RMS residual at RANSAC's pose (depth and features
    # agree); where they do not, ICP slid along what depth cannot see
    min_feature_agreement: float = 0.5
    feature_agreement_scatter: float = 3.0
    # ICP between two keyframes' depth images (verification, relocalisation): correspondences
    # farther apart are rejected, residuals past huber_delta weigh less (keyframes are farther
    # apart than consecutive frames, so wider than tracking's)
    icp_max_correspondence_m: float = 0.07
    icp_huber_delta_m: float = 0.05
    # the loop's relative pose must agree with the current estimate within a tolerance that
    # grows with the path travelled between the two keyframes (odometry drift is bounded)
    consistency_m: float = 0.2
    consistency_per_m: float = 0.1
    consistency_deg: float = 10.0
    consistency_deg_per_m: float = 5.0
    # two map segments are joined when this many verified revisits agree on their transform
    join_verifications: int = 2


@dataclass
class BackendConfig:
    """GTSAM keyframe pose graph: odometry edges, robust loop edges, Levenberg-Marquardt."""

    # edge information = per-correspondence J^T J of the registration (its shape) / sigma^2
    odometry_sigma_m: float = 0.003  # floor of an odometry edge's sigma
    odometry_drift_per_m: float = 0.03  # odometry edge sigma grows with the motion it spans
    # the odometry edge's information (its shape) is measured on the two keyframes' depth
    # with correspondences closer than this
    odometry_information_threshold_m: float = 0.03
    loop_sigma_m: float = 0.02
    loop_kernel: str = "cauchy"  # cauchy | huber | none
    loop_kernel_width: float = 2.0  # in standard deviations of the loop edge
    loop_prune_sigma: float = 5.0  # a loop still this far off after optimisation is removed
    max_iterations: int = 100


@dataclass
class BAConfig:
    """Bundle adjustment of keyframe poses and ORB landmarks (slam.backend.bundle_adjustment):
    landmark tracks built as keyframes arrive, merged across accepted loops, and optimised
    jointly with the keyframe poses (reprojection + depth per observation, Huber-robust)."""

    enabled: bool = True
    after_loops: bool = True  # a global BA after an accepted loop ...
    loop_interval_keyframes: int = 10  # ... when this many keyframes came since the last BA
    at_finish: bool = True  # and once at the end of the run
    # track building: each new keyframe is matched (guided by the relative pose) against the
    # previous match_window keyframes and up to match_nearby other keyframes of the same map
    # whose poses lie within nearby_distance_m / nearby_angle_deg of it
    match_window: int = 4
    match_nearby: int = 4
    nearby_distance_m: float = 0.6
    nearby_angle_deg: float = 35.0
    match_radius_px: float = 10.0  # around the pixel the relative pose predicts
    max_hamming: int = 64  # ORB descriptor distance (of 256 bits) for a match
    match_ratio: float = 0.85  # best over second-best distance among the candidates in reach
    depth_tolerance: float = 0.05  # the predicted depth must agree within 2 cm + this fraction
    # the factor graph: pixel noise of an ORB keypoint of pyramid level 0 (x 1.2 per level),
    # the sensor's depth noise at 1 m (grows with depth^2, as a structured-light sensor's
    # disparity noise), Huber threshold in pixels. A keypoint's depth is read at its pixel;
    # where depth changes fast around it (corners, depth edges) the pixel's error (keypoint
    # localisation, colour-depth calibration and capture-time offset) reads another ray's
    # depth: its depth noise adds slope (m/px) x depth_misregistration_px (x 1.2 per level),
    # in quadrature (0: off). One noise for every keypoint had to be 5x the sensor's for fr1's
    # corners (keyframe ATE 12.1 mm at 0.004, 10.2 mm at 0.02) and then let BA slide along a
    # textured wall (synthetic wall-x1-s1: final 0.0188 m against odometry 0.0081 m; with the
    # slope: 0.0059 m; fr1 unchanged; docs/archive/journal.md)
    pixel_sigma_px: float = 1.0
    depth_sigma_m: float = 0.004
    depth_misregistration_px: float = 2.0
    huber_px: float = 2.5
    # an observation whose whitened residual stays above this chi^2 (3 dof, 95%: 7.815) after
    # the optimisation is an outlier: removed, and the problem optimised again without it
    outlier_chi2: float = 7.815
    max_iterations: int = 5  # Levenberg-Marquardt, before and again after removing outliers
    # a landmark joins the problem with at most this many observations, evenly spaced along its
    # track (0: all): long tracks make the reduced camera system dense (time, memory)
    max_observations_per_landmark: int = 20
    # the pose graph's depth-registration edges (odometry, loops) stay in the problem, their
    # information scaled by a weight that starts at this factor (0: pure BA, keyframes held by
    # landmarks only). Where tracks are short (a keyframe's landmarks seen by 2-3 keyframes)
    # sparse features alone drift more than dense ICP odometry. How accurate the edges are
    # against the landmarks differs by orders of magnitude between sequences (at the true
    # poses, exact synthetic depth: 0.005 of the variance assumed at 100, tum-fr1-xyz 46x);
    # the weight is fixed (estimating it from the residuals: docs/decisions.md)
    pose_graph_weight: float = 100.0
    # an adjustment with fewer inlier observations than this per keyframe is not used (the
    # pose graph stands): too few landmarks to beat the depth odometry (tum-fr3-cabinet-kf58,
    # 46 per keyframe: 57 -> 66 mm; the sequences above: 130-215)
    min_observations_per_keyframe: int = 100
    # colour not registered to depth (separate cameras, e.g. 7-Scenes): the depth read at a
    # colour keypoint belongs to a neighbouring ray, so the depth term is weakened to this
    # (see slam.backend.bundle_adjustment)
    unregistered_depth_sigma_m: float = 0.06


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
