import cv2
import numpy as np

from slam.data import SevenScenesSequence, open_sequence
from tests.conftest import shared_sequence


def test_seven_scenes_single_folder(tmp_path):
    root = tmp_path / "seq-01"
    root.mkdir()
    for i in range(3):
        d = np.full((480, 640), 1500, np.uint16)  # the default 7-Scenes calibration size
        d[0, 0] = 65535
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), d)
        cv2.imwrite(str(root / f"frame-{i:06d}.color.png"), np.zeros((480, 640, 3), np.uint8))
        T = np.eye(4)
        T[0, 3] = i
        np.savetxt(root / f"frame-{i:06d}.pose.txt", T)
    seq = open_sequence(root)
    assert isinstance(seq, SevenScenesSequence) and len(seq) == 3
    f = seq[1]
    assert f.depth_m[0, 0] == 0.0  # 65535 = no depth
    assert abs(f.depth_m[1, 1] - 1.5) < 1e-6
    assert abs(f.timestamp - 1 / 30) < 1e-9
    np.testing.assert_allclose(seq.ground_truth.positions[:, 0], [0, 1, 2])
    assert seq.calibration.fx == 585.0
    assert not seq.color_registered  # two cameras: bundle adjustment weakens its depth term


def test_seven_scenes_split_folders_real():
    path = shared_sequence("7scenes-300")
    seq = SevenScenesSequence(path)
    assert len(seq) == 300
    gt_tum = open_sequence(path).ground_truth
    assert np.abs(seq.ground_truth.positions - gt_tum.positions).max() < 1e-3
    f = seq[150]
    assert f.color.shape == (480, 640, 3) and f.depth_m.dtype == np.float32
