"""Frames handed to the API (issue 19): NaN, infinite or negative depth counts as no depth (it
raised Open3D's raw RuntimeError and left the Slam broken); a bad ``K`` is a clear error when a
Frame or the Slam gets it (fx=0, NaN cx, a 4x4 were accepted and every later frame was lost);
after any of these errors the Slam goes on."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

import slam
from slam.camera import check_intrinsics
from slam.config import config_from_dict
from slam.data.base import Calibration
from slam.errors import CalibrationError, FrameError
from slam.synthetic import SynthConfig, generate_sequence

FAST = {"tracking": {"downsample": 1}}


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """8 frames of the synthetic loop at 160x120."""
    half = SynthConfig.half_resolution()
    cfg = SynthConfig(
        frames=300, render_frames=8, seed=2, width=160, height=120,
        fx=half.fx / 2, fy=half.fy / 2, cx=(half.cx + 0.5) / 2 - 0.5, cy=(half.cy + 0.5) / 2 - 0.5,
    )  # fmt: skip
    seq = slam.open_sequence(generate_sequence(tmp_path_factory.mktemp("tiny") / "seq", cfg))
    return [seq[i] for i in range(len(seq))]


def damaged_depth(depth: np.ndarray, kind: str) -> np.ndarray:
    d = depth.copy()
    h, w = d.shape
    region = (slice(0, h // 2), slice(0, w // 3))
    d[region] = {"nan": np.nan, "inf": np.inf, "negative": -1.5}[kind]
    return d


@pytest.mark.parametrize("kind", ["nan", "inf", "negative"])
def test_first_frame_with_bad_depth_values_is_tracked(frames, kind, caplog):
    """Partly NaN, +inf or negative depth on the first frame: those pixels are no depth (a
    debug log says how many), the frame starts the map, the next frames track."""
    system = slam.Slam(config_from_dict(FAST))
    f0 = frames[0]
    bad = damaged_depth(f0.depth_m, kind)
    with caplog.at_level(logging.DEBUG, logger="slam.data.base"):
        r0 = system.step(dataclasses.replace(f0, depth_m=bad))
    assert r0.ok and r0.status.path == "init"
    assert np.isnan(bad).any() or np.isinf(bad).any() or (bad < 0).any()  # caller's copy kept
    assert any("depth values NaN, infinite or negative set to 0" in r.getMessage()
               for r in caplog.records)  # fmt: skip
    for f in frames[1:5]:
        assert system.step(f).ok
    res = system.finish()
    assert len(res.trajectory) == 5 and np.all(np.isfinite(res.trajectory.poses))


def test_depth_only_between_the_rows_open3d_samples(frames):
    # Open3D picks the blocks to fuse from every 4th pixel: depth only between those rows
    # raised its "No block is touched"; now such a frame fuses nothing (found by the fuzz test)
    system = slam.Slam(config_from_dict(FAST))
    depth = np.zeros_like(frames[0].depth_m)
    depth[-3:] = frames[0].depth_m[-3:]  # 480 pixels with depth: 2.5% of the frame
    r = system.step(dataclasses.replace(frames[0], depth_m=depth))
    assert r.status is not None


def test_depth_all_invalid_is_a_lost_frame(frames):
    system = slam.Slam(config_from_dict(FAST))
    r = system.step(dataclasses.replace(frames[0], depth_m=np.full_like(frames[0].depth_m, np.nan)))
    assert not r.ok and "no usable depth" in r.status.reason
    assert system.step(frames[1]).ok


K_GOOD = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])


@pytest.mark.parametrize(
    "K, match",
    [
        (np.diag([0.0, 100.0, 1.0]), r"focal lengths must be positive, got fx=0 fy=100"),
        (K_GOOD * [[1, 1, np.nan], [1, 1, 1], [1, 1, 1]], r"non-finite entries"),
        (np.eye(4), r"intrinsic matrix of shape \(4, 4\), expected 3x3"),
        (K_GOOD + [[0, 0, 500], [0, 0, 0], [0, 0, 0]], r"principal point \(cx=579.5, cy=59.5\) "
         r"lies outside the 160x120 image"),
        (K_GOOD + [[0, 0, 0], [0, 0, 0], [0.1, 0, 0]], r"no skew, last row \[0, 0, 1\]"),
        (K_GOOD + [[0, 2.0, 0], [0, 0, 0], [0, 0, 0]], r"no skew"),
        ("intrinsics", r"not a numeric 3x3 matrix"),
    ],
)  # fmt: skip
def test_bad_K_is_a_clear_error(frames, K, match):
    f = frames[0]
    with pytest.raises(CalibrationError, match=r"frame 0: K: .*" + match):
        slam.Frame(0, f.timestamp, f.color, f.depth_m, K)
    with pytest.raises(CalibrationError, match=match):
        check_intrinsics(K, 160, 120)


def test_bad_K_given_to_the_slam_leaves_it_usable(frames):
    """A frame whose K was replaced after it was made: Slam.step refuses it before changing
    anything; the same Slam then tracks the good frames (the first starts the map)."""
    system = slam.Slam(config_from_dict(FAST))
    bad = dataclasses.replace(frames[0])
    bad.K = np.eye(4)
    with pytest.raises(CalibrationError, match=r"frame 0: K: intrinsic matrix of shape \(4, 4\)"):
        system.step(bad)
    assert system.statuses == [] and system.clock.last_t is None
    results = [system.step(f) for f in frames[:4]]
    assert [r.ok for r in results] == [True] * 4 and results[0].status.path == "init"


@pytest.mark.parametrize(
    "change, match",
    [
        ({"depth_m": np.zeros(5, np.float32)}, r"depth_m must be an HxW array of metres"),
        ({"color": np.zeros((10, 10, 3), np.uint8)}, r"color must be None or an HxWx3 uint8"),
        ({"timestamp": float("nan")}, r"timestamp must be a finite number"),
    ],
)
def test_malformed_frame_is_a_clear_error(frames, change, match):
    f = frames[0]
    with pytest.raises(FrameError, match=r"frame 0: " + match):
        dataclasses.replace(f, **change)


def test_calibration_is_checked_like_K():
    with pytest.raises(CalibrationError, match=r"calibration values must be finite.*cx=nan"):
        Calibration(64, 48, 50.0, 50.0, float("nan"), 23.5)
    with pytest.raises(CalibrationError, match=r"principal point \(cx=640, cy=23.5\) lies outside"):
        Calibration(64, 48, 50.0, 50.0, 640.0, 23.5)
