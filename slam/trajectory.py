"""Trajectories: timestamps plus camera-to-world poses, and strict TUM file I/O.

TUM format: one pose per line, ``timestamp tx ty tz qx qy qz qw``, ``#`` starts a comment.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.errors import TrajectoryError
from slam.geometry import pose_to_tum, tum_to_pose

log = logging.getLogger(__name__)


@dataclass
class Trajectory:
    """Timestamps (N,) in seconds and poses ``T_world_cam`` (N, 4, 4)."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=float).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=float).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise TrajectoryError(
                f"trajectory has {len(self.timestamps)} timestamps but {len(self.poses)} poses"
            )

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def path_length(self) -> float:
        """Total distance travelled, metres."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())


def read_tum(path: str | Path, skip_non_finite: bool = False) -> Trajectory:
    """Read a TUM trajectory file. Raises :class:`TrajectoryError` naming the line on bad input;
    with ``skip_non_finite`` (ground truth: a motion-capture dropout is written as NaN) rows
    with a non-finite value are left out, with a warning saying how many."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"{path}: trajectory file not found")
    try:
        with path.open(encoding="utf-8-sig") as f:  # a byte-order mark is not part of line 1
            return parse_tum(f, str(path), skip_non_finite)
    except UnicodeDecodeError as exc:
        raise TrajectoryError(f"{path}: not UTF-8 text: {exc}") from exc
    except OSError as exc:
        raise TrajectoryError(f"{path}: cannot read: {exc}") from exc


def parse_tum(
    lines: Iterable[str], source: str = "<text>", skip_non_finite: bool = False
) -> Trajectory:
    """Parse TUM-format lines (``source`` names them in errors), as :func:`read_tum` does."""
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    skipped: list[int] = []
    for lineno, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise TrajectoryError(
                f"{source}:{lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', "
                f"got {len(parts)}: {line[:80]!r}"
            )
        try:
            values = np.array([float(p) for p in parts])
        except ValueError as exc:
            raise TrajectoryError(f"{source}:{lineno}: not a number: {line[:80]!r}") from exc
        if not np.all(np.isfinite(values)):
            if skip_non_finite and np.isfinite(values[0]):
                skipped.append(lineno)
                continue
            raise TrajectoryError(f"{source}:{lineno}: non-finite value: {line[:80]!r}")
        if np.linalg.norm(values[4:8]) < 1e-9:
            raise TrajectoryError(f"{source}:{lineno}: zero quaternion")
        stamps.append(values[0])
        poses.append(tum_to_pose(values[1:]))
    if skipped:
        log.warning(
            "%s: %d rows with non-finite values left out (lines %s)",
            source, len(skipped), ", ".join(map(str, skipped[:5])) + (", ..." if len(skipped) > 5 else ""),
        )  # fmt: skip
    if not stamps:
        raise TrajectoryError(f"{source}: no poses in file")
    return Trajectory(np.array(stamps), np.stack(poses))


def as_written(traj: Trajectory) -> Trajectory:
    """The trajectory exactly as :func:`read_tum` reads it back after :func:`write_tum` (rounded
    to the file's precision), so numbers computed from it equal those computed from the file."""
    return parse_tum(format_tum(traj).splitlines(), "<as written>")


def format_tum(traj: Trajectory) -> str:
    """TUM text of a trajectory, full precision (timestamps 6 decimals, poses 9)."""
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, metres)"]
    for t, T in zip(traj.timestamps, traj.poses):
        v = pose_to_tum(T)
        lines.append(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in v))
    return "\n".join(lines) + "\n"


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write a trajectory in TUM format, atomically (temp file + rename)."""
    atomic_write_text(path, format_tum(traj))


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write text to ``path`` through a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; results are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
