"""Microsoft 7-Scenes layout: ``frame-XXXXXX.color.{png,jpg}``, ``.depth.png``, ``.pose.txt``.

Files may sit in one folder (the original ``seq-01/`` layout) or in split sub-folders
(``rgb/``, ``depth/``, ``pose/``). Depth is millimetres; 65535 marks no depth.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from slam.data.base import Frame, Sequence
from slam.data.calibration import SEVEN_SCENES_DEFAULT, apply_overrides, read_calibration_yaml
from slam.data.images import Undistorter, read_color, read_depth
from slam.errors import DatasetError
from slam.trajectory import Trajectory

log = logging.getLogger(__name__)

_DEPTH_RE = re.compile(r"frame-(\d+)\.depth\.png$")
FPS = 30.0


def find_depth_files(folder: Path) -> list[Path]:
    """Depth images of a 7-Scenes folder (directly in it or in a ``depth/`` sub-folder)."""
    for d in (folder, folder / "depth"):
        if d.is_dir():
            files = sorted(p for p in d.iterdir() if _DEPTH_RE.search(p.name))
            if files:
                return files
    return []


class SevenScenesSequence(Sequence):
    """A 7-Scenes sequence; timestamps are frame number / 30 s."""

    def __init__(self, path: str | Path, calibration_overrides: dict | None = None) -> None:
        self.path = Path(path)
        depth_files = find_depth_files(self.path)
        if not depth_files:
            raise DatasetError(
                f"{self.path}: no frame-XXXXXX.depth.png files here or in {self.path / 'depth'}"
            )
        self._ids = [_DEPTH_RE.search(p.name).group(1) for p in depth_files]  # type: ignore[union-attr]
        self._depth = depth_files
        self._color: list[Path] | None = []
        for p in depth_files:
            c = self._sibling(p, "color", ("png", "jpg"))
            if c is None:
                self._color = None
                log.info("%s: no colour image for %s, sequence is depth-only", self.path, p.name)
                break
            self._color.append(c)
        calib_yaml = self.path / "calibration.yaml"
        calib = read_calibration_yaml(calib_yaml) if calib_yaml.is_file() else SEVEN_SCENES_DEFAULT
        self.calibration_source = (
            "the folder's calibration.yaml" if calib_yaml.is_file() else "the 7-Scenes defaults"
        )
        self.calibration = apply_overrides(calib, calibration_overrides)
        c = self.calibration
        self._undistort = (
            Undistorter(c.K, c.distortion, c.width, c.height) if c.has_distortion else None
        )
        self._gt: Trajectory | None = None
        self._gt_loaded = False

    def _sibling(self, depth_path: Path, kind: str, exts: tuple[str, ...]) -> Path | None:
        stem = depth_path.name.replace(".depth.png", "")
        folders = [depth_path.parent, self.path, self.path / {"color": "rgb"}.get(kind, kind)]
        for folder in folders:
            for ext in exts:
                cand = folder / f"{stem}.{kind}.{ext}"
                if cand.is_file():
                    return cand
        return None

    @property
    def has_color(self) -> bool:
        return self._color is not None

    @property
    def color_registered(self) -> bool:
        """7-Scenes' colour and depth come from two uncalibrated cameras: not registered."""
        return False

    def __len__(self) -> int:
        return len(self._depth)

    def timestamp(self, index: int) -> float:
        return int(self._ids[index]) / FPS

    def _read(self, index: int) -> Frame:
        c = self.calibration
        depth = read_depth(
            self._depth[index], index, c.depth_scale, invalid_value=65535,
            size=(c.width, c.height),
        )  # fmt: skip
        color = read_color(self._color[index], index) if self._color is not None else None
        if color is not None:
            color = self._fit_color(color, depth, index)
        if self._undistort is not None and depth.shape == self._undistort.map_x.shape:
            depth = self._undistort.depth(depth)
            color = None if color is None else self._undistort.color(color)
        return Frame(index, self.timestamp(index), color, depth, self.calibration.K)

    @property
    def ground_truth(self) -> Trajectory | None:
        if not self._gt_loaded:
            self._gt_loaded = True
            stamps, poses = [], []
            for i, p in enumerate(self._depth):
                pose_file = self._sibling(p, "pose", ("txt",))
                if pose_file is None:
                    continue
                try:
                    T = np.loadtxt(pose_file).reshape(4, 4)
                except ValueError as exc:
                    log.warning("%s: unreadable pose file, skipped: %s", pose_file, exc)
                    continue
                if np.all(np.isfinite(T)):
                    stamps.append(self.timestamp(i))
                    poses.append(T)
            if poses:
                self._gt = Trajectory(np.array(stamps), np.stack(poses))
        return self._gt
