"""A map that outlives its run: a finished run's keyframes and TSDF, saved in its run folder
(``RUN_DIR/map/``) and loaded by a later run that localises against it (``slam run SEQ --map
RUN_DIR``, :class:`slam.Slam` with ``map=``).

Layout (format ``slam-map``, version :data:`FORMAT_VERSION`):

- ``map.json``: the format and version, the camera the map was recorded with (intrinsics and
  image size, whether colour is registered), the mapping settings the TSDF was fused with, the
  volume's pose in the map's world frame and the weight its surfaces are rendered from, each
  keyframe's id, frame index, timestamp, final pose (the run's optimised one) and feature
  count, and each file's SHA-256;
- ``keyframes.npz``: the keyframes' ORB features (pixels, descriptors, 3-D points, levels),
  concatenated, and their tracking-resolution depth and intrinsics;
- ``volume.npz``: the TSDF's allocated blocks, compressed: block coordinates, TSDF and weight
  as float16 (the TSDF is a fraction of the truncation: 1e-3 of it is 0.04 mm at 4 cm), colour
  as float16.

Files are read with ``allow_pickle=False`` (a map folder is data, never code) and refused,
before any is used, when a digest differs (a damaged or edited map). ``map.json`` is written
last, each file atomically, so a map folder is whole or has no ``map.json``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam.config import LoopConfig, MappingConfig, SlamConfig, config_from_dict
from slam.errors import ConfigError, RunFolderError
from slam.files import file_digest, write_via_tmp
from slam.keyframe import FeatureSet, Keyframe
from slam.loops.place_recognition import KeyframeDatabase
from slam.mapping.tsdf import TSDFVolume
from slam.run_folder.layout import MAP_DIR, METRICS_FILE

__all__ = ["MAP_DIR", "Map", "MapError"]

log = logging.getLogger(__name__)

MANIFEST = "map.json"
FORMAT_NAME = "slam-map"
FORMAT_VERSION = 1
_KEYFRAMES = "keyframes.npz"
_VOLUME = "volume.npz"
#: the camera's intrinsics and size must agree to this (pixels) for a recording to use a map
CAMERA_TOLERANCE_PX = 0.5


class MapError(RunFolderError):
    """A saved map that cannot be used: missing, unfinished, damaged, of another format
    version, or recorded with another camera."""


@dataclass
class Map:
    """A finished run's map in its world frame: ``keyframes`` (final poses, ORB features,
    depth), the TSDF ``volume`` placed at ``T_world_volume``, rendered from surfaces fused with
    at least ``min_weight`` (None: the mapping config's threshold), the recording's camera
    (``K``, ``size`` = width, height) and whether its colour is registered to depth.
    ``source``: the run folder it was loaded from."""

    keyframes: list[Keyframe]
    volume: TSDFVolume
    T_world_volume: np.ndarray
    min_weight: float | None
    K: np.ndarray
    size: tuple[int, int]
    has_color: bool
    color_registered: bool
    source: Path | None = None

    # --- the camera
    def check_camera(self, K: np.ndarray, size: tuple[int, int], where: str) -> None:
        """Refuse a recording whose camera (``K``, ``size``) is not the map's: poses from
        another camera's intrinsics would be wrong by its focal lengths' ratio."""
        K = np.asarray(K, float)
        if tuple(size) != tuple(self.size) or np.abs(K - self.K).max() > CAMERA_TOLERANCE_PX:
            raise MapError(
                f"{where}: its camera (fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, "
                f"cy {K[1, 2]:.2f}, {size[0]}x{size[1]}) is not the map's (fx "
                f"{self.K[0, 0]:.2f}, fy {self.K[1, 1]:.2f}, cx {self.K[0, 2]:.2f}, cy "
                f"{self.K[1, 2]:.2f}, {self.size[0]}x{self.size[1]}; {self.source}): localise "
                "recordings of the camera that made the map, or give the right calibration"
            )

    def place_index(self, loop: LoopConfig) -> KeyframeDatabase:
        """The keyframes indexed for place recognition (the vocabulary learnt on them)."""
        db = KeyframeDatabase(loop.vocabulary_words, loop.vocabulary_keyframes)
        for kf in self.keyframes:
            db.observe(kf.features.descriptors)
        for kf in self.keyframes:
            db.add(kf.id, kf.features.descriptors)
        return db

    # --- files
    def save(self, folder: str | Path, config: SlamConfig) -> Path:
        """Write the map into ``folder`` (see the module docstring); ``config``: the run's
        (its mapping section says how the TSDF was fused). Returns the folder."""
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        (out / MANIFEST).unlink(missing_ok=True)
        digests = {
            _KEYFRAMES: _write_npz(out / _KEYFRAMES, _keyframe_arrays(self.keyframes)),
            _VOLUME: _write_npz(out / _VOLUME, _volume_arrays(self.volume)),
        }
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "camera": {"K": self.K.tolist(), "width": self.size[0], "height": self.size[1]},
            "has_color": self.has_color,
            "color_registered": self.color_registered,
            "mapping": config.to_dict()["mapping"],
            "T_world_volume": np.asarray(self.T_world_volume, float).tolist(),
            "min_weight": self.min_weight,
            "keyframes": [_keyframe_doc(kf) for kf in self.keyframes],
            "digests": digests,
        }
        data = (json.dumps(manifest, indent=1) + "\n").encode()
        write_via_tmp(out / MANIFEST, lambda f: f.write(data))
        return out

    @classmethod
    def load(cls, run_dir: str | Path) -> Map:
        """The map of a finished run folder (``RUN_DIR/map/``), checked whole before use."""
        run = Path(run_dir)
        folder = run / MAP_DIR
        if not run.is_dir():
            raise MapError(f"{run}: no such run folder (give the folder a `slam run` wrote)")
        if not (run / METRICS_FILE).is_file():
            raise MapError(
                f"{run}: the run has not finished (no {METRICS_FILE}: it is still running, or "
                "was interrupted); wait for it, or `slam run --resume` it"
            )
        if not (folder / MANIFEST).is_file():
            raise MapError(
                f"{run}: no map ({MAP_DIR}/{MANIFEST}); the run was made without one "
                "(output.save_map off, or an older version): run the recording again"
            )
        doc = _read_manifest(folder / MANIFEST)
        try:
            for name, digest in doc["digests"].items():
                if name not in (_KEYFRAMES, _VOLUME) or file_digest(folder / name) != digest:
                    raise MapError(
                        f"{folder / name}: damaged (its SHA-256 is not the one {MANIFEST} "
                        "recorded): run the recording again to make the map anew"
                    )
            mapping = config_from_dict({"mapping": doc["mapping"]}).mapping
            keyframes = _keyframes(_read_npz(folder / _KEYFRAMES), doc["keyframes"])
            volume = _volume(_read_npz(folder / _VOLUME), mapping, bool(doc["has_color"]))
            cam = doc["camera"]
            weight = doc["min_weight"]
            return cls(
                keyframes, volume, np.array(doc["T_world_volume"], float).reshape(4, 4),
                None if weight is None else float(weight), np.array(cam["K"], float).reshape(3, 3),
                (int(cam["width"]), int(cam["height"])), bool(doc["has_color"]),
                bool(doc["color_registered"]), run,
            )  # fmt: skip
        except (KeyError, TypeError, ValueError, IndexError, ConfigError, RuntimeError) as exc:
            raise MapError(
                f"{folder}: not a map this version can read ({type(exc).__name__}: {exc}); "
                "run the recording again to make the map anew"
            ) from exc


def _keyframe_doc(kf: Keyframe) -> dict[str, Any]:
    return {
        "id": kf.id, "index": kf.index, "timestamp": kf.timestamp, "segment": kf.segment,
        "T_world_cam": np.asarray(kf.T_world_cam, float).tolist(), "features": len(kf.features),
    }  # fmt: skip


def _keyframe_arrays(keyframes: list[Keyframe]) -> dict[str, np.ndarray]:
    feats = [kf.features for kf in keyframes]
    if not keyframes:
        return {}
    return {
        "pixels": np.concatenate([np.asarray(f.pixels, np.float64).reshape(-1, 2) for f in feats]),
        "descriptors": np.concatenate(
            [np.asarray(f.descriptors, np.uint8).reshape(-1, 32) for f in feats]
        ),
        "points_cam": np.concatenate(
            [np.asarray(f.points_cam, np.float64).reshape(-1, 3) for f in feats]
        ),
        "octave": np.concatenate([f.levels() for f in feats]),
        "depth_m": np.stack([np.asarray(kf.depth_m, np.float32) for kf in keyframes]),
        "K": np.stack([np.asarray(kf.K, np.float64) for kf in keyframes]),
    }


def _keyframes(arrays: dict[str, np.ndarray], docs: list[dict[str, Any]]) -> list[Keyframe]:
    out, start = [], 0
    for i, d in enumerate(docs):
        n = int(d["features"])
        sl = slice(start, start + n)
        start += n
        feats = FeatureSet(
            arrays["pixels"][sl], arrays["descriptors"][sl], arrays["points_cam"][sl],
            arrays["octave"][sl],
        )  # fmt: skip
        T = np.array(d["T_world_cam"], float).reshape(4, 4)
        out.append(
            Keyframe(
                int(d["index"]),
                float(d["timestamp"]),
                T,
                feats,
                arrays["depth_m"][i],
                arrays["K"][i],
                int(d["id"]),
                int(d["segment"]),
            )  # fmt: skip
        )
    if docs and start != len(arrays["pixels"]):
        raise ValueError(f"{start} features named, {len(arrays['pixels'])} stored")
    return out


def _volume_arrays(volume: TSDFVolume) -> dict[str, np.ndarray]:
    a = volume.to_arrays()
    out = {"keys": a["keys"], "n_integrated": a["n_integrated"]}
    for name in ("tsdf", "weight", "color"):
        if name in a:
            out[name] = np.clip(a[name], -65504, 65504).astype(np.float16)
    return out


def _volume(arrays: dict[str, np.ndarray], cfg: MappingConfig, has_color: bool) -> TSDFVolume:
    a = {k: (v.astype(np.float32) if v.dtype == np.float16 else v) for k, v in arrays.items()}
    return TSDFVolume.from_arrays(a, cfg, has_color and "color" in a)


# --- files: atomic writes (slam.files), pickle-free reads
def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """Write ``arrays`` compressed, atomically; returns the file's SHA-256."""
    write_via_tmp(path, lambda f: np.savez_compressed(f, **arrays))
    return file_digest(path)


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise MapError(f"{path}: unreadable ({exc}); run the recording again") from exc


def _read_manifest(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise MapError(f"{path}: unreadable ({exc}); run the recording again") from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise MapError(f"{path}: not a map ({FORMAT_NAME} format); give a run folder's map")
    if doc.get("version") != FORMAT_VERSION:
        raise MapError(
            f"{path}: a map of format version {doc.get('version')!r}; this version reads "
            f"{FORMAT_VERSION}: run the recording again with this version to make its map"
        )
    return doc
