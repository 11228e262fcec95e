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
    iterations: list[int] = field(default_factory=lambda: [6, 4, 2])  # coarse ... fine
    depth_min_m: float = 0.2
    depth_max_m: float = 4.0
    max_correspondence_m: float = 0.07  # projective correspondences farther apart are rejected
    huber_delta_m: float = 0.05
    min_fitness: float = 0.1  # ICP check: fraction of pixels with an ICP correspondence
    min_overlap: float = 0.3  # ICP check: fraction of pixels within inlier_threshold of the model
    inlier_threshold_m: float = 0.03
    max_step_translation_m: float = 0.3  # frame-to-frame ICP moving the guess more is rejected
    max_model_correction_m: float = 0.05  # frame-to-model ICP moving the guess more is rejected
    max_model_correction_deg: float = 3.0
    large_motion_translation_m: float = 0.06  # predicted motion above this -> RANSAC seed
    large_motion_rotation_deg: float = 6.0
    relocalisation_keyframes: int = 5  # RANSAC tries this many recent keyframes when needed
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


@dataclass
class OutputConfig:
    save_mesh: bool = True
    save_tracking_log: bool = True


@dataclass
class SlamConfig:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
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


def load_config(path: str | Path | None) -> SlamConfig:
    """Default config, overridden by the YAML file at ``path`` when given."""
    if path is None:
        return SlamConfig()
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config: {exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {exc}") from exc
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
