"""TUM RGB-D layout: ``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt`` and ``calibration.yaml``."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from slam.data.base import Calibration, Frame, Sequence
from slam.data.calibration import (
    KEYS,
    apply_overrides,
    from_overrides,
    missing_overrides,
    read_calibration_yaml,
    tum_default_for,
    with_tum_distortion,
)
from slam.data.images import Undistorter, read_color, read_depth
from slam.errors import CalibrationError, DatasetError, TrajectoryError
from slam.trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)


#: A list where at least this fraction of the entries name a file an earlier entry already
#: named is refused: the repeated images make a stationary camera (no motion, no lost frame).
DUPLICATE_ERROR_FRACTION = 0.5
_SEPARATOR = re.compile(r"[\s,]+")


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a TUM ``timestamp filename`` list (``#`` comments). Returns sorted stamps and names.

    The file name is everything after the timestamp and its separator (white space or a comma),
    so names with spaces survive; a UTF-8 byte-order mark is ignored. Entries naming a file an
    earlier entry names: a warning naming them, or a :class:`DatasetError` when they are at least
    half of the list (:data:`DUPLICATE_ERROR_FRACTION`)."""
    if not path.is_file():
        raise DatasetError(f"{path}: list file not found (TUM layout needs rgb.txt and depth.txt)")
    stamps: list[float] = []
    names: list[str] = []
    linenos: list[int] = []
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read the list: {exc}") from exc
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = _SEPARATOR.split(line, maxsplit=1)
        if len(parts) < 2 or not parts[1].strip():
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename', got {line!r}")
        try:
            stamps.append(float(parts[0]))
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: bad timestamp {parts[0]!r}") from exc
        if not np.isfinite(stamps[-1]):
            raise DatasetError(f"{path}:{lineno}: bad timestamp {parts[0]!r}")
        names.append(parts[1].strip())
        linenos.append(lineno)
    if not stamps:
        raise DatasetError(f"{path}: no entries")
    seen: dict[float, int] = {}
    for lineno, t in zip(linenos, stamps):
        if t in seen:
            raise DatasetError(
                f"{path}: lines {seen[t]} and {lineno} have the same timestamp {t:.6f}; each "
                "image needs its own time: remove or correct the duplicate line"
            )
        seen[t] = lineno
    _check_duplicate_names(path, names, linenos, text.splitlines())
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps)[order], [names[i] for i in order]


def _check_duplicate_names(
    path: Path, names: list[str], linenos: list[int], lines: list[str]
) -> None:
    """Entries naming a file that an earlier entry names: each image shows one moment, so a
    repeated one makes the camera stand still. Most entries repeated: a :class:`DatasetError`;
    a few: a warning naming them."""
    first: dict[str, int] = {}
    repeats: dict[str, list[int]] = {}
    for name, lineno in zip(names, linenos):
        if name in first:
            repeats.setdefault(name, []).append(lineno)
        else:
            first[name] = lineno
    if not repeats:
        return
    n_repeated = sum(len(v) for v in repeats.values())
    worst = max(repeats, key=lambda n: len(repeats[n]))
    example = repeats[worst][0]
    if n_repeated >= DUPLICATE_ERROR_FRACTION * len(names):
        raise DatasetError(
            f"{path}: {n_repeated} of its {len(names)} entries name an image an earlier entry "
            f"already names ({len(repeats)} file(s) repeated; {worst!r} is named "
            f"{len(repeats[worst]) + 1} times, first on line {first[worst]}, again e.g. on "
            f"line {example}: {lines[example - 1].strip()!r}); each entry must name its own "
            "image (a repeated image makes the camera stand still): regenerate the list"
        )
    shown = ", ".join(
        f"{n!r} (lines {first[n]}, {', '.join(map(str, repeats[n]))})" for n in list(repeats)[:5]
    )
    more = f" and {len(repeats) - 5} more" if len(repeats) > 5 else ""
    log.warning(
        "%s: %d of its %d entries name an image an earlier entry already names: %s%s; those "
        "frames repeat an earlier image (the camera seems to stand still there)",
        path,
        n_repeated,
        len(names),
        shown,
        more,
    )


def associate(a: np.ndarray, b: np.ndarray, max_diff: float = 0.02) -> list[tuple[int, int]]:
    """One-to-one nearest-timestamp association (TUM ``associate.py`` semantics).

    Candidate pairs closer than ``max_diff`` are taken greedily by increasing time difference,
    each index used at most once. Returns index pairs sorted by ``a``.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if len(a) == 0 or len(b) == 0:
        return []
    # candidates: for each a, the b neighbours around its insertion point (sorted b); widen a few
    # positions so greedy one-to-one choice still sees alternatives.
    pos = np.searchsorted(b, a)
    ia_list, ib_list = [], []
    for off in (-2, -1, 0, 1):
        ib = pos + off
        ok = (ib >= 0) & (ib < len(b))
        ia_list.append(np.nonzero(ok)[0])
        ib_list.append(ib[ok])
    ia = np.concatenate(ia_list)
    ib = np.concatenate(ib_list)
    diff = np.abs(a[ia] - b[ib])
    keep = diff < max_diff
    ia, ib, diff = ia[keep], ib[keep], diff[keep]
    order = np.lexsort((ib, ia, diff))
    used_a = np.zeros(len(a), bool)
    used_b = np.zeros(len(b), bool)
    pairs = []
    for k in order:  # loop over candidate pairs (a few per frame), not pixels
        i, j = ia[k], ib[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            pairs.append((int(i), int(j)))
    pairs.sort()
    return pairs


def interpolate_poses(traj: Trajectory, stamps: np.ndarray, max_gap: float = 0.1) -> Trajectory:
    """Poses of ``traj`` at ``stamps``: linear/slerp between neighbours at most ``max_gap`` apart.

    Stamps outside the trajectory's range or inside a larger gap are dropped.
    """
    t = traj.timestamps
    if len(t) < 2:
        keep = np.isin(stamps, t)
        return Trajectory(stamps[keep], traj.poses[np.searchsorted(t, stamps[keep])])
    idx = np.searchsorted(t, stamps, side="right") - 1
    idx = np.clip(idx, 0, len(t) - 2)
    t0, t1 = t[idx], t[idx + 1]
    near = np.minimum(np.abs(stamps - t0), np.abs(stamps - t1)) < 1e-4  # a sample at the stamp
    inside = (stamps >= t[0] - 1e-9) & (stamps <= t[-1] + 1e-9) & ((t1 - t0 <= max_gap) | near)
    s = stamps[inside]
    i0 = idx[inside]
    alpha = np.clip((s - t[i0]) / np.maximum(t[i0 + 1] - t[i0], 1e-12), 0.0, 1.0)
    rot = Rotation.from_matrix(traj.poses[:, :3, :3])
    slerp = Slerp(t, rot)
    poses = np.tile(np.eye(4), (len(s), 1, 1))
    poses[:, :3, :3] = slerp(np.clip(s, t[0], t[-1])).as_matrix()
    p = traj.positions
    poses[:, :3, 3] = p[i0] * (1 - alpha)[:, None] + p[i0 + 1] * alpha[:, None]
    return Trajectory(s, poses)


class TumSequence(Sequence):
    """A sequence in TUM RGB-D layout.

    Frames are the one-to-one nearest-timestamp pairs of ``rgb.txt`` and ``depth.txt`` (within
    ``max_dt`` seconds); a frame's timestamp is its depth image's: the pose is estimated from the
    depth (ICP against the model), so that is the moment it belongs to (TUM fr1's colour and
    depth are up to 17 ms apart; stamped at the colour's time the final ATE on ``tum-fr1-xyz``
    reads ~10% worse); the colour's offset is the frame's ``color_dt_s``. Without ``rgb.txt``
    the sequence is depth-only. Calibration:
    ``calibration.yaml`` in the folder, else the TUM defaults when the folder name says
    freiburg1/2/3, else a :class:`CalibrationError`; ``calibration_overrides`` (from config/CLI)
    replace single fields.
    """

    def __init__(
        self,
        path: str | Path,
        calibration_overrides: dict | None = None,
        max_dt: float = 0.02,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: sequence folder not found")
        depth_stamps, depth_names = read_file_list(self.path / "depth.txt")
        rgb_list = self.path / "rgb.txt"
        if rgb_list.is_file():
            rgb_stamps, rgb_names = read_file_list(rgb_list)
            pairs = associate(rgb_stamps, depth_stamps, max_dt)
            if not pairs:
                raise DatasetError(
                    f"{self.path}: no rgb/depth pair within {max_dt} s: rgb.txt spans "
                    f"[{rgb_stamps[0]:.3f}, {rgb_stamps[-1]:.3f}], depth.txt spans "
                    f"[{depth_stamps[0]:.3f}, {depth_stamps[-1]:.3f}]"
                )
            self._stamps = np.array([depth_stamps[j] for _, j in pairs])
            self._color_dt = np.array([rgb_stamps[i] - depth_stamps[j] for i, j in pairs])
            self._rgb: list[str] | None = [rgb_names[i] for i, _ in pairs]
            self._depth = [depth_names[j] for _, j in pairs]
            self._unpaired = {
                "rgb": len(rgb_stamps) - len(pairs), "depth": len(depth_stamps) - len(pairs)
            }  # fmt: skip
            if self._unpaired["depth"]:
                log.warning(
                    "%s: %d of %d depth images have no colour image within %g s: they are not "
                    "frames of the run (the run reports them as unpaired_images)",
                    self.path, self._unpaired["depth"], len(depth_stamps), max_dt,
                )  # fmt: skip
            if self._unpaired["rgb"]:
                log.info("%s: %d rgb images without a depth match were dropped", self.path,
                         self._unpaired["rgb"])  # fmt: skip
        else:
            self._unpaired = {}
            self._stamps = depth_stamps
            self._color_dt = np.zeros(len(depth_stamps))
            self._rgb = None
            self._depth = depth_names
        self.calibration = apply_overrides(
            with_tum_distortion(self._find_calibration(calibration_overrides)),
            calibration_overrides,
        )
        c = self.calibration
        self._undistort = (
            Undistorter(c.K, c.distortion, c.width, c.height) if c.has_distortion else None
        )
        self._gt: Trajectory | None = None
        self._gt_loaded = False
        self._check_first_files()

    def _find_calibration(self, overrides: dict | None) -> Calibration:
        yaml_path = self.path / "calibration.yaml"
        if yaml_path.is_file():
            self.calibration_source = "the folder's calibration.yaml"
            return read_calibration_yaml(yaml_path)
        default = tum_default_for(self.path)
        if default is not None:
            self.calibration_source = "the TUM defaults for the folder's name"
            log.info("%s: no calibration.yaml, using TUM defaults by folder name", self.path)
            return default
        from_config = from_overrides(overrides)
        if from_config is not None:
            self.calibration_source = "the config's dataset.calibration"
            log.info("%s: no calibration.yaml, using the config's dataset.calibration", self.path)
            return from_config
        missing = missing_overrides(overrides)
        hint = (
            f" (it gives {len(KEYS) - len(missing)} of them; missing: {', '.join(missing)})"
            if len(missing) < len(KEYS)
            else ""
        )
        raise CalibrationError(
            f"{self.path}: no calibration.yaml and the folder name does not say freiburg1/2/3; "
            "add calibration.yaml (width, height, fx, fy, cx, cy, depth_scale) or give all seven "
            f"in the config section 'dataset.calibration'{hint}, e.g. a YAML file for --config: "
            "'dataset: {calibration: {width: 640, height: 480, fx: 525.0, fy: 525.0, cx: 319.5, "
            "cy: 239.5, depth_scale: 5000}}'"
        )

    def _check_first_files(self) -> None:
        missing = [
            n for n in self._depth[:1] + (self._rgb or [])[:1] if not (self.path / n).is_file()
        ]
        if missing:
            name = missing[0]
            first = name.split()[0]
            hint = (
                f" (a file name is everything after the timestamp; {first!r} exists: remove "
                "the extra columns from the list)"
                if first != name and (self.path / first).is_file()
                else ""
            )
            raise DatasetError(f"{self.path}: image listed but not found: {name!r}{hint}")

    @property
    def has_color(self) -> bool:
        return self._rgb is not None

    @property
    def unpaired_images(self) -> dict[str, int]:
        return dict(self._unpaired)

    @property
    def color_registered(self) -> bool:
        """TUM RGB-D's depth is registered to colour; a 7-Scenes recording converted to this
        layout (its ``pose/frame-XXXXXX.pose.txt`` files kept) is not."""
        pose = self.path / "pose"
        seven_scenes = pose.is_dir() and next(pose.glob("frame-*.pose.txt"), None) is not None
        return self.has_color and not seven_scenes

    def __len__(self) -> int:
        return len(self._stamps)

    def timestamp(self, index: int) -> float:
        return float(self._stamps[index])

    def timestamps(self) -> np.ndarray:
        return self._stamps.copy()

    def files(self, index: int) -> tuple[Path | None, Path]:
        """(colour image or None for depth-only, depth image) of frame ``index``."""
        rgb = None if self._rgb is None else self.path / self._rgb[index]
        return rgb, self.path / self._depth[index]

    def _read(self, index: int) -> Frame:
        c = self.calibration
        depth = read_depth(
            self.path / self._depth[index], index, c.depth_scale, size=(c.width, c.height)
        )
        color = None
        if self._rgb is not None:
            color = self._fit_color(read_color(self.path / self._rgb[index], index), depth, index)
        if self._undistort is not None and depth.shape == self._undistort.map_x.shape:
            depth = self._undistort.depth(depth)
            color = None if color is None else self._undistort.color(color)
        # when the colour image was taken after the depth image: as stamped, plus the camera's
        # calibrated colour delay
        color_dt = float(self._color_dt[index])
        if color is not None:
            color_dt += c.colour_delay_s or 0.0
        return Frame(index, float(self._stamps[index]), color, depth, c.K, color_dt)

    @property
    def ground_truth(self) -> Trajectory | None:
        """``groundtruth.txt`` interpolated at the frame timestamps (frames it covers)."""
        if not self._gt_loaded:
            self._gt_loaded = True
            gt_path = self.path / "groundtruth.txt"
            if gt_path.is_file():
                try:
                    self._gt = interpolate_poses(read_tum(gt_path, skip_non_finite=True), self._stamps)
                except TrajectoryError as exc:
                    log.warning(
                        "%s: ground truth unreadable, evaluation disabled: %s", gt_path, exc
                    )
        return self._gt
