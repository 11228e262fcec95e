"""Inputs checked before any work, each error saying what is wrong and how to fix it."""

import cv2
import numpy as np
import pytest

import slam
from slam.data.checks import check_sequence, suggest_depth_scale
from slam.errors import CalibrationError, DatasetError, FrameSizeError
from tests.data.test_tum import _write_seq


def _seq(tmp_path, n=6, **kw):
    return _write_seq(tmp_path / "s", [i / 30 for i in range(n)], [i / 30 for i in range(n)], **kw)


def test_duplicate_timestamps_name_the_lines(tmp_path):
    root = _seq(tmp_path)
    lines = (root / "depth.txt").read_text().splitlines()
    lines[3] = lines[2].split()[0] + " " + lines[3].split()[1]  # line 4 repeats line 3's time
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"depth.txt: lines 3 and 4 have the same timestamp"):
        slam.open_sequence(root)


def test_sequence_path_that_is_a_file(tmp_path):
    f = tmp_path / "rgb.txt"
    f.write_text("")
    with pytest.raises(DatasetError, match="is a file, not a sequence folder"):
        slam.open_sequence(f)


def test_depth_size_against_calibration(tmp_path):
    root = _seq(tmp_path)
    cv2.imwrite(str(root / "depth/3.png"), np.full((24, 32), 5000, np.uint16))
    seq = slam.open_sequence(root)
    with pytest.raises(FrameSizeError, match="frame 3: depth image is 32x24 but the calibration says 64x48"):
        seq[3]
    check_sequence(seq, list(range(len(seq))))  # a later frame: skipped by the run, not fatal
    cv2.imwrite(str(root / "depth/0.png"), np.full((24, 32), 5000, np.uint16))
    with pytest.raises(CalibrationError, match="frame 0: depth image is 32x24 .* calibration.yaml"):
        check_sequence(slam.open_sequence(root), list(range(len(seq))))


@pytest.mark.parametrize("factor, expected", [(1000.0, 5000), (1 / 1000, 5000), (0.2, 1000)])
def test_wrong_depth_scale_names_the_one_that_fits(tmp_path, factor, expected):
    root = _seq(tmp_path)  # depth values ~5000: 1 m at the TUM scale 5000
    calib = (root / "calibration.yaml").read_text()
    (root / "calibration.yaml").write_text(
        calib.replace("depth_scale: 5000.0", f"depth_scale: {5000.0 * factor}")
    )
    seq = slam.open_sequence(root)
    if factor == 0.2:  # scale 1000: 5 m median, plausible: no error
        check_sequence(seq, list(range(len(seq))))
        return
    with pytest.raises(CalibrationError, match=rf"depth_scale is likely wrong. depth_scale {expected} would give 1.00 m"):
        check_sequence(seq, list(range(len(seq))))


def test_suggested_scales():
    assert suggest_depth_scale(2.0 * 5000) == 5000
    assert suggest_depth_scale(2.0 * 1000) == 1000
    assert suggest_depth_scale(2.0) == 1.0
    assert suggest_depth_scale(3e9) == 2e9  # nothing common fits: the one giving 1.5 m


def test_first_frames_without_depth_do_not_stop_the_check(tmp_path):
    root = _seq(tmp_path)
    for i in range(6):
        cv2.imwrite(str(root / f"depth/{i}.png"), np.zeros((48, 64), np.uint16))
    check_sequence(slam.open_sequence(root), list(range(6)))


def test_truncated_jpeg_is_unreadable(tmp_path):
    """OpenCV decodes the first part of a truncated JPEG and greys the rest: that is an
    unreadable frame, not a frame to track."""
    from slam.data.images import read_color
    from slam.errors import FrameReadError

    ok, buf = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8))
    (tmp_path / "a.jpg").write_bytes(buf.tobytes())
    assert read_color(tmp_path / "a.jpg", 0).shape == (48, 64, 3)
    (tmp_path / "b.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    with pytest.raises(FrameReadError, match="frame 7: colour image .*b.jpg is a truncated JPEG"):
        read_color(tmp_path / "b.jpg", 7)
