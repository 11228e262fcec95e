"""Damaged copies of a TUM-layout sequence, for robustness tests and benchmarks.

Real recordings have gaps, jumps, blank and corrupt frames. :func:`damage_sequence` writes a copy
of a sequence with such defects made on purpose, and with ground truth for the frames it keeps,
so the pipeline's behaviour on them can be measured against the clean run::

    from slam.synthetic.damage import Damage, damage_sequence
    damage_sequence("data/room", "data/room-blackout", Damage(blackout=range(100, 115)))
    damage_sequence("data/room", "data/room-teleport",
                    Damage(frames=[*range(250), *range(50, 300)], retime=True))

Unchanged images are symbolic links to the source's (no copy); modified ones are written.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from slam.data.loader import open_sequence
from slam.data.tum import TumSequence
from slam.errors import DatasetError
from slam.trajectory import Trajectory, atomic_write_text, write_tum

log = logging.getLogger(__name__)

#: How a corrupt image is made: ``truncate`` (first half of the file), ``random`` (random
#: bytes), ``empty`` (zero bytes), ``wrong_size`` (a valid image at half the width and height),
#: ``missing`` (listed but absent). Prefix ``color:`` to damage the colour image instead of depth.
CORRUPT_MODES = ("truncate", "random", "empty", "wrong_size", "missing")


@dataclass
class Damage:
    """What to do to a sequence. Frame numbers in ``blackout`` and ``corrupt`` are positions in
    the damaged sequence (after ``frames`` has been applied).

    ``frames``: source frame numbers in their new order (repeats and jumps allowed; None = all).
    ``retime``: give the damaged frames evenly spaced timestamps (the source's median interval)
    instead of their own, so a jump in ``frames`` shows no time gap (a teleported camera).
    ``blackout``: frames whose depth is all zero and colour all black (a covered lens).
    ``corrupt``: frame -> mode (:data:`CORRUPT_MODES`, e.g. ``"truncate"`` or ``"color:random"``).
    ``depth_scale_factor``: multiplies the calibration's depth_scale (a wrong calibration).
    ``seed``: for random bytes.
    """

    frames: list[int] | None = None
    retime: bool = False
    blackout: Iterable[int] = ()
    corrupt: dict[int, str] = field(default_factory=dict)
    depth_scale_factor: float = 1.0
    seed: int = 0


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.is_symlink() or dst.exists():
        dst.unlink()
    os.symlink(src.resolve(), dst)


def _corrupt(src: Path, dst: Path, mode: str, rng: np.random.Generator) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.is_symlink() or dst.exists():
        dst.unlink()
    data = src.read_bytes()
    if mode == "truncate":
        dst.write_bytes(data[: len(data) // 2])
    elif mode == "random":
        dst.write_bytes(rng.integers(0, 256, max(len(data), 64), dtype=np.uint8).tobytes())
    elif mode == "empty":
        dst.write_bytes(b"")
    elif mode == "wrong_size":
        img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=0)
        if not cv2.imwrite(str(dst.with_suffix(src.suffix)), small):
            raise DatasetError(f"{dst}: cv2.imwrite failed")
    elif mode != "missing":
        raise ValueError(f"unknown corrupt mode {mode!r}; expected one of {CORRUPT_MODES}")


def damage_sequence(src: str | Path, dst: str | Path, damage: Damage) -> Path:
    """Write a damaged copy of the TUM-layout sequence ``src`` into ``dst`` (replaced if it
    exists): ``rgb.txt``/``depth.txt`` with one line per frame (both at the frame's timestamp),
    images (links or damaged files), ``calibration.yaml`` and ``groundtruth.txt`` at the new
    timestamps (the source's ground truth at each frame's source timestamp)."""
    seq = open_sequence(src)
    if not isinstance(seq, TumSequence):
        raise DatasetError(f"{src}: damage_sequence needs a TUM-layout sequence")
    dst = Path(dst)
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    order = list(range(len(seq))) if damage.frames is None else [int(i) for i in damage.frames]
    src_stamps = seq.timestamps()
    if damage.retime:
        dt = float(np.median(np.diff(src_stamps))) if len(src_stamps) > 1 else 1 / 30
        stamps = src_stamps[order[0]] + dt * np.arange(len(order))
    else:
        stamps = src_stamps[order]
    if np.any(np.diff(stamps) <= 0):
        raise DatasetError("damaged frame order goes back in time: use retime=True")
    blackout = set(damage.blackout)
    rng = np.random.default_rng(damage.seed)
    calib = seq.calibration
    rgb_lines, depth_lines = [], []
    for k, i in enumerate(order):
        rgb_src, depth_src = seq.files(i)
        name = f"{k:06d}"
        depth_dst = dst / "depth" / f"{name}{depth_src.suffix}"
        rgb_dst = None if rgb_src is None else dst / "rgb" / f"{name}{rgb_src.suffix}"
        mode = damage.corrupt.get(k)
        target, _, how = (mode or "").rpartition(":")
        target = target or "depth"
        if k in blackout:
            h, w = calib.height, calib.width
            depth_dst.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(depth_dst.with_suffix(".png")), np.zeros((h, w), np.uint16))
            depth_dst = depth_dst.with_suffix(".png")
            if rgb_dst is not None:
                rgb_dst = rgb_dst.with_suffix(".png")
                rgb_dst.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(rgb_dst), np.zeros((h, w, 3), np.uint8))
        else:
            for kind, s, d in (("depth", depth_src, depth_dst), ("color", rgb_src, rgb_dst)):
                if s is None or d is None:
                    continue
                if mode and target == kind:
                    _corrupt(s, d, how, rng)
                else:
                    _link(s, d)
        t = f"{stamps[k]:.6f}"
        depth_lines.append(f"{t} {depth_dst.relative_to(dst)}\n")
        if rgb_dst is not None:
            rgb_lines.append(f"{t} {rgb_dst.relative_to(dst)}\n")
    header = f"# damaged copy of {Path(src).resolve()} (slam.synthetic.damage)\n"
    atomic_write_text(dst / "depth.txt", header + "".join(depth_lines))
    if rgb_lines:
        atomic_write_text(dst / "rgb.txt", header + "".join(rgb_lines))
    scale = calib.depth_scale * damage.depth_scale_factor
    values = {**calib.to_dict(), "depth_scale": scale}
    atomic_write_text(
        dst / "calibration.yaml", "".join(f"{k}: {v!r}\n" for k, v in values.items())
    )
    gt = seq.ground_truth
    if gt is not None and len(gt):
        at = {round(float(t), 6): T for t, T in zip(gt.timestamps, gt.poses)}
        rows = [
            (stamps[k], at[round(float(src_stamps[i]), 6)])
            for k, i in enumerate(order)
            if round(float(src_stamps[i]), 6) in at
        ]
        if rows:
            write_tum(
                dst / "groundtruth.txt",
                Trajectory(np.array([r[0] for r in rows]), np.stack([r[1] for r in rows])),
            )
    log.info("wrote a damaged copy of %s (%d frames) to %s", src, len(order), dst)
    return dst
