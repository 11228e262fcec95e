"""The range of every configuration key: :meth:`slam.config.SlamConfig.validate` raises a
:class:`ConfigError` naming the first key out of its range, with the value seen and what it
must be. One function per section; each check is ``(holds, key, value, requirement)``."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from slam.data.layouts import LAYOUT_NAMES, layout_names_text
from slam.errors import ConfigError

if TYPE_CHECKING:
    from slam.config import (
        BackendConfig,
        BAConfig,
        DatasetConfig,
        LoopConfig,
        MappingConfig,
        SlamConfig,
        TrackingConfig,
    )

#: The largest TSDF block edge, ``mapping.voxel_size_m`` x ``mapping.block_resolution`` (0.02 m
#: voxels with the default 8^3 blocks). Open3D's ray-cast (0.20) bounds its rays by projecting
#: every block into 16x16-pixel fragments of a coarse range map, kept in a buffer sized
#: ~1/voxel_size: when a frame needs more fragments than that buffer holds, the blocks that
#: spill over are counted but not written, and if one of them spans several fragments (a large
#: block, or one near the camera) the range map is built from uninitialised memory: a
#: segmentation fault, a hang or silent corruption. Measured on tum-fr1-xyz,
#: tum-fr3-cabinet-kf58 and 7scenes-300 (40 frames each, the fragment count of every ray-cast
#: replayed): uninitialised fragments from 0.03 m voxels up in two of the three sequences, none at
#: 0.01 and 0.02 m; crashes at 0.1 m (cabinet, every run), 0.15 (7-Scenes), 0.2-0.5 m (fr1).
MAX_BLOCK_SIZE_M = 0.16
_VOXEL_LIMIT = (
    "larger blocks make Open3D's ray-cast read uninitialised memory: segmentation faults from "
    "0.1 m voxels"
)

#: Counts a user could mean. A frame's Gauss-Newton iterations per pyramid level (defaults 2-12:
#: each costs a few milliseconds, so 100 is seconds a frame), RANSAC hypotheses (defaults
#: 500-1000; their arrays grow with the count: 1e9 took 24 GB) and the back end's solver
#: iterations (defaults 5-100). Larger values never end in practice and, inside a frame, cannot
#: be stopped by a signal.
MAX_GN_ITERATIONS = 100
MAX_RANSAC_ITERATIONS = 100_000
MAX_SOLVER_ITERATIONS = 10_000

Check = tuple[bool, str, Any, str]


def _dataset(d: DatasetConfig) -> list[Check]:
    return [  # fmt: skip
        (d.layout in LAYOUT_NAMES, "dataset.layout", d.layout, layout_names_text()),
        (d.first_frame >= 0, "dataset.first_frame", d.first_frame, ">= 0"),
        (d.max_frames is None or d.max_frames >= 1, "dataset.max_frames", d.max_frames, ">= 1 (or null for all)"),
        (d.stride >= 1, "dataset.stride", d.stride, ">= 1"),
    ]


def _tracking(t: TrackingConfig) -> list[Check]:
    return [  # fmt: skip
        (t.downsample in (1, 2, 4), "tracking.downsample", t.downsample, "1, 2 or 4"),
        (len(t.icp.iterations) >= 1, "tracking.icp.iterations", t.icp.iterations, "a non-empty list (iterations per pyramid level, coarse to fine)"),
        (all(0 <= i <= MAX_GN_ITERATIONS for i in t.icp.iterations) and sum(t.icp.iterations) > 0, "tracking.icp.iterations", t.icp.iterations, f"counts in [0, {MAX_GN_ITERATIONS}], not all 0"),
        (len(t.icp.large_motion_iterations) == len(t.icp.iterations), "tracking.icp.large_motion_iterations", t.icp.large_motion_iterations, f"one count per level of tracking.icp.iterations ({len(t.icp.iterations)} levels)"),
        (all(0 <= i <= MAX_GN_ITERATIONS for i in t.icp.large_motion_iterations) and sum(t.icp.large_motion_iterations) > 0, "tracking.icp.large_motion_iterations", t.icp.large_motion_iterations, f"counts in [0, {MAX_GN_ITERATIONS}], not all 0"),
        (t.depth_min_m >= 0, "tracking.depth_min_m", t.depth_min_m, ">= 0"),
        (t.depth_max_m > t.depth_min_m, "tracking.depth_max_m", t.depth_max_m, f"> tracking.depth_min_m ({t.depth_min_m})"),
        (t.icp.icp_depth_max_m > t.depth_min_m, "tracking.icp.icp_depth_max_m", t.icp.icp_depth_max_m, f"> tracking.depth_min_m ({t.depth_min_m})"),
        (0 <= t.icp.icp_near_fraction <= 1, "tracking.icp.icp_near_fraction", t.icp.icp_near_fraction, "in [0, 1]"),
        (t.depth_noise_sigma0_m > 0, "tracking.depth_noise_sigma0_m", t.depth_noise_sigma0_m, "> 0"),
        (t.motion.max_acceleration_m_s2 > 0, "tracking.motion.max_acceleration_m_s2", t.motion.max_acceleration_m_s2, "> 0"),
        (t.colour.motion_check_photometric_weight >= 0, "tracking.colour.motion_check_photometric_weight", t.colour.motion_check_photometric_weight, ">= 0"),
        (t.colour.degenerate_ratio >= 1, "tracking.colour.degenerate_ratio", t.colour.degenerate_ratio, ">= 1"),
        (t.colour.photometric_ratio >= 1, "tracking.colour.photometric_ratio", t.colour.photometric_ratio, ">= 1"),
        (t.colour.photometric_reference in ("keyframe", "model"), "tracking.colour.photometric_reference", t.colour.photometric_reference, '"keyframe" or "model"'),
        (t.colour.photometric_keyframes >= 1, "tracking.colour.photometric_keyframes", t.colour.photometric_keyframes, "at least 1"),
        (t.depth_noise_quadratic >= 0, "tracking.depth_noise_quadratic", t.depth_noise_quadratic, ">= 0"),
        (t.icp.max_correspondence_m > 0, "tracking.icp.max_correspondence_m", t.icp.max_correspondence_m, "> 0"),
        (t.icp.huber_delta_m > 0, "tracking.icp.huber_delta_m", t.icp.huber_delta_m, "> 0"),
        (t.icp.coarse_correspondence_factor >= 1, "tracking.icp.coarse_correspondence_factor", t.icp.coarse_correspondence_factor, ">= 1"),
        (0 <= t.icp.min_fitness <= 1, "tracking.icp.min_fitness", t.icp.min_fitness, "in [0, 1]"),
        (0 <= t.icp.min_overlap <= 1, "tracking.icp.min_overlap", t.icp.min_overlap, "in [0, 1]"),
        (t.recovery.rescue_min_weight >= 0, "tracking.recovery.rescue_min_weight", t.recovery.rescue_min_weight, ">= 0"),
        (0 <= t.motion.hypothesis_overlap <= 1, "tracking.motion.hypothesis_overlap", t.motion.hypothesis_overlap, "in [0, 1]"),
        (t.icp.inlier_threshold_m > 0, "tracking.icp.inlier_threshold_m", t.icp.inlier_threshold_m, "> 0"),
        (t.keyframe_translation_m > 0, "tracking.keyframe_translation_m", t.keyframe_translation_m, "> 0"),
        (t.keyframe_rotation_deg > 0, "tracking.keyframe_rotation_deg", t.keyframe_rotation_deg, "> 0"),
        (0 <= t.min_depth_fraction < 1, "tracking.min_depth_fraction", t.min_depth_fraction, "in [0, 1)"),
        (t.motion.gap_factor > 1, "tracking.motion.gap_factor", t.motion.gap_factor, "> 1"),
        (t.recovery.verify_min_matches >= 3, "tracking.recovery.verify_min_matches", t.recovery.verify_min_matches, ">= 3"),
        (0 < t.recovery.verify_overlap_ratio <= 1, "tracking.recovery.verify_overlap_ratio", t.recovery.verify_overlap_ratio, "in (0, 1]"),
        (0 <= t.recovery.suspect_overlap_ratio <= 1, "tracking.recovery.suspect_overlap_ratio", t.recovery.suspect_overlap_ratio, "in [0, 1]"),
        (t.recovery.relocalisation_candidates >= 1, "tracking.recovery.relocalisation_candidates", t.recovery.relocalisation_candidates, ">= 1"),
        (t.recovery.new_segment_after_lost >= 1, "tracking.recovery.new_segment_after_lost", t.recovery.new_segment_after_lost, ">= 1"),
        (t.ransac.n_features >= 10, "tracking.ransac.n_features", t.ransac.n_features, ">= 10"),
        (0 < t.ransac.ratio <= 1, "tracking.ransac.ratio", t.ransac.ratio, "in (0, 1]"),
        (1 <= t.ransac.iterations <= MAX_RANSAC_ITERATIONS, "tracking.ransac.iterations", t.ransac.iterations, f"in [1, {MAX_RANSAC_ITERATIONS}]"),
        (t.ransac.inlier_threshold_m > 0, "tracking.ransac.inlier_threshold_m", t.ransac.inlier_threshold_m, "> 0"),
        (t.ransac.min_inliers >= 3, "tracking.ransac.min_inliers", t.ransac.min_inliers, ">= 3"),
    ]


def _mapping(m: MappingConfig) -> list[Check]:
    return [  # fmt: skip
        (m.block_resolution in (4, 8, 16), "mapping.block_resolution", m.block_resolution, "4, 8 or 16"),
        (0 < m.voxel_size_m <= MAX_BLOCK_SIZE_M / m.block_resolution, "mapping.voxel_size_m", m.voxel_size_m,
         f"in (0, {MAX_BLOCK_SIZE_M / m.block_resolution:g}] metres with mapping.block_resolution {m.block_resolution} "
         f"(e.g. 0.01; a block, voxel_size_m x block_resolution, of at most {MAX_BLOCK_SIZE_M:g} m: {_VOXEL_LIMIT})"),
        (m.trunc_voxels > 0, "mapping.trunc_voxels", m.trunc_voxels, "> 0"),
        (m.block_count >= 1, "mapping.block_count", m.block_count, ">= 1"),
        (m.depth_max_m > 0, "mapping.depth_max_m", m.depth_max_m, "> 0"),
        (m.raycast_weight_threshold >= 0, "mapping.raycast_weight_threshold", m.raycast_weight_threshold, ">= 0"),
        (m.mesh_weight_threshold >= 0, "mapping.mesh_weight_threshold", m.mesh_weight_threshold, ">= 0"),
        (m.submap_keyframes >= 0, "mapping.submap_keyframes", m.submap_keyframes, ">= 0 (0: a single map)"),
        (m.submap_min_frames >= 0, "mapping.submap_min_frames", m.submap_min_frames, ">= 0"),
        (m.submap_overlap_frames >= 0, "mapping.submap_overlap_frames", m.submap_overlap_frames, ">= 0"),
        (m.submap_seed_views >= 0, "mapping.submap_seed_views", m.submap_seed_views, ">= 0"),
        (m.reintegration_stride >= 1, "mapping.reintegration_stride", m.reintegration_stride, ">= 1"),
        (m.reintegration_downsample in (1, 2, 4), "mapping.reintegration_downsample", m.reintegration_downsample, "1, 2 or 4"),
    ]


def _loop(lp: LoopConfig) -> list[Check]:
    return [  # fmt: skip
        (lp.vocabulary_words >= 2, "loop.vocabulary_words", lp.vocabulary_words, ">= 2"),
        (lp.vocabulary_keyframes >= 1, "loop.vocabulary_keyframes", lp.vocabulary_keyframes, ">= 1"),
        (lp.exclude_recent_keyframes >= 0, "loop.exclude_recent_keyframes", lp.exclude_recent_keyframes, ">= 0"),
        (lp.max_candidates >= 1, "loop.max_candidates", lp.max_candidates, ">= 1"),
        (0 < lp.ratio <= 1, "loop.ratio", lp.ratio, "in (0, 1]"),
        (1 <= lp.ransac_iterations <= MAX_RANSAC_ITERATIONS, "loop.ransac_iterations", lp.ransac_iterations, f"in [1, {MAX_RANSAC_ITERATIONS}]"),
        (lp.ransac_threshold_m > 0, "loop.ransac_threshold_m", lp.ransac_threshold_m, "> 0"),
        (lp.min_inliers >= 3, "loop.min_inliers", lp.min_inliers, ">= 3"),
        (0 <= lp.min_overlap <= 1, "loop.min_overlap", lp.min_overlap, "in [0, 1]"),
        (0 <= lp.min_feature_agreement <= 1, "loop.min_feature_agreement", lp.min_feature_agreement, "in [0, 1]"),
        (lp.feature_agreement_scatter > 0, "loop.feature_agreement_scatter", lp.feature_agreement_scatter, "> 0"),
        (lp.join_verifications >= 1, "loop.join_verifications", lp.join_verifications, ">= 1"),
    ]


def _backend(b: BackendConfig) -> list[Check]:
    return [  # fmt: skip
        (b.odometry_sigma_m > 0, "backend.odometry_sigma_m", b.odometry_sigma_m, "> 0"),
        (b.loop_sigma_m > 0, "backend.loop_sigma_m", b.loop_sigma_m, "> 0"),
        (b.loop_kernel in ("cauchy", "huber", "none"), "backend.loop_kernel", b.loop_kernel, "cauchy, huber or none"),
        (b.loop_kernel_width > 0, "backend.loop_kernel_width", b.loop_kernel_width, "> 0"),
        (b.loop_prune_sigma > 0, "backend.loop_prune_sigma", b.loop_prune_sigma, "> 0"),
        (1 <= b.max_iterations <= MAX_SOLVER_ITERATIONS, "backend.max_iterations", b.max_iterations, f"in [1, {MAX_SOLVER_ITERATIONS}]"),
    ]


def _ba(ba: BAConfig) -> list[Check]:
    return [  # fmt: skip
        (ba.loop_interval_keyframes >= 0, "ba.loop_interval_keyframes", ba.loop_interval_keyframes, ">= 0"),
        (ba.match_window >= 1, "ba.match_window", ba.match_window, ">= 1"),
        (ba.match_nearby >= 0, "ba.match_nearby", ba.match_nearby, ">= 0"),
        (ba.nearby_distance_m >= 0, "ba.nearby_distance_m", ba.nearby_distance_m, ">= 0"),
        (0 <= ba.nearby_angle_deg <= 180, "ba.nearby_angle_deg", ba.nearby_angle_deg, "in [0, 180]"),
        (ba.match_radius_px > 0, "ba.match_radius_px", ba.match_radius_px, "> 0"),
        (0 < ba.max_hamming <= 256, "ba.max_hamming", ba.max_hamming, "in (0, 256]"),
        (0 < ba.match_ratio <= 1, "ba.match_ratio", ba.match_ratio, "in (0, 1]"),
        (ba.depth_tolerance >= 0, "ba.depth_tolerance", ba.depth_tolerance, ">= 0"),
        (ba.pixel_sigma_px > 0, "ba.pixel_sigma_px", ba.pixel_sigma_px, "> 0"),
        (ba.depth_sigma_m > 0, "ba.depth_sigma_m", ba.depth_sigma_m, "> 0"),
        (ba.depth_misregistration_px >= 0, "ba.depth_misregistration_px", ba.depth_misregistration_px, ">= 0"),
        (ba.huber_px > 0, "ba.huber_px", ba.huber_px, "> 0"),
        (ba.outlier_chi2 > 0, "ba.outlier_chi2", ba.outlier_chi2, "> 0"),
        (1 <= ba.max_iterations <= MAX_SOLVER_ITERATIONS, "ba.max_iterations", ba.max_iterations, f"in [1, {MAX_SOLVER_ITERATIONS}]"),
        (ba.max_observations_per_landmark == 0 or ba.max_observations_per_landmark >= 2, "ba.max_observations_per_landmark", ba.max_observations_per_landmark, ">= 2 (or 0 for all)"),
        (ba.pose_graph_weight >= 0, "ba.pose_graph_weight", ba.pose_graph_weight, ">= 0"),
        (ba.min_observations_per_keyframe >= 0, "ba.min_observations_per_keyframe", ba.min_observations_per_keyframe, ">= 0"),
        (ba.unregistered_depth_sigma_m > 0, "ba.unregistered_depth_sigma_m", ba.unregistered_depth_sigma_m, "> 0"),
    ]


def check_ranges(cfg: SlamConfig) -> None:
    """Raise :class:`ConfigError` naming the first key whose value is out of its range."""
    checks = (
        _dataset(cfg.dataset) + _tracking(cfg.tracking) + _mapping(cfg.mapping)
        + _loop(cfg.loop) + _backend(cfg.backend) + _ba(cfg.ba)
    )  # fmt: skip
    for ok, key, value, requirement in checks:
        if not ok:
            raise ConfigError(f"config key '{key}' must be {requirement}, got {value!r}")
