import cv2
import numpy as np
import pytest

from slam.data import open_sequence
from slam.data.tum import associate, interpolate_poses
from slam.errors import CalibrationError, DatasetError, FrameReadError
from slam.trajectory import Trajectory


def _write_seq(root, rgb_stamps, depth_stamps, calib=True, gt=None, size=(64, 48)):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = ["# rgb"], ["# depth"]
    w, h = size
    for i, t in enumerate(rgb_stamps):
        cv2.imwrite(str(root / f"rgb/{i}.png"), np.full((h, w, 3), i, np.uint8))
        rgb_lines.append(f"{t:.6f} rgb/{i}.png")
    for i, t in enumerate(depth_stamps):
        cv2.imwrite(str(root / f"depth/{i}.png"), np.full((h, w), 5000 + i, np.uint16))
        depth_lines.append(f"{t:.6f} depth/{i}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if calib:
        (root / "calibration.yaml").write_text(
            "width: 64\nheight: 48\nfx: 50.0\nfy: 50.0\ncx: 31.5\ncy: 23.5\ndepth_scale: 5000.0\n"
        )
    if gt is not None:
        (root / "groundtruth.txt").write_text(gt)
    return root


def test_association_with_offset_timestamps(tmp_path):
    rgb = [0.000, 0.033, 0.066, 0.100, 0.133]
    depth = [0.012, 0.045, 0.078, 0.300, 0.145]  # offset by 12 ms; 0.300 has no partner
    seq = open_sequence(_write_seq(tmp_path / "s", rgb, depth))
    assert len(seq) == 4
    # a frame is stamped with its depth image's time: the pose is estimated from the depth
    np.testing.assert_allclose(seq.timestamps(), [0.012, 0.045, 0.078, 0.145])
    f = seq[3]
    assert f.depth_m[0, 0] == pytest.approx((5000 + 4) / 5000.0)  # depth file 4 (0.145)
    assert f.color[0, 0, 0] == 4
    # ... and says when its colour was taken (tracking moves the colour camera by it)
    assert [seq[i].color_dt_s for i in range(4)] == pytest.approx([-0.012] * 3 + [-0.012])
    # the depth image without a partner is counted (it is not a frame of the run)
    assert seq.unpaired_images == {"rgb": 1, "depth": 1}


def test_associate_is_one_to_one():
    a = np.array([0.0, 0.01, 0.02])
    b = np.array([0.011])
    assert associate(a, b, 0.02) == [(1, 0)]
    assert associate(np.array([0.0]), np.array([0.5]), 0.02) == []


def test_ground_truth_interpolated_at_frames(tmp_path):
    gt = "# gt\n0.0 0 0 0 0 0 0 1\n0.05 1 0 0 0 0 0 1\n0.10 2 0 0 0 0 0 1\n"
    seq = open_sequence(_write_seq(tmp_path / "s", [0.02, 0.07], [0.02, 0.07], gt=gt))
    g = seq.ground_truth
    np.testing.assert_allclose(g.positions[:, 0], [0.4, 1.4], atol=1e-9)


def test_interpolate_drops_outside_and_gaps():
    traj = Trajectory(np.array([0.0, 1.0, 1.01]), np.tile(np.eye(4), (3, 1, 1)))
    out = interpolate_poses(traj, np.array([-1.0, 0.5, 1.005, 2.0]), max_gap=0.1)
    np.testing.assert_allclose(out.timestamps, [1.005])


def test_missing_calibration_is_a_clear_error(tmp_path):
    root = _write_seq(tmp_path / "unknown_cam", [0.0], [0.0], calib=False)
    with pytest.raises(CalibrationError, match="calibration.yaml"):
        open_sequence(root)


def test_calibration_from_config_alone(tmp_path):
    """No calibration.yaml, no freiburg in the name: the config's dataset.calibration, when it
    gives all seven keys, is the calibration (the error message says to do exactly that)."""
    root = _write_seq(tmp_path / "unknown_cam", [0.0], [0.0], calib=False)
    calib = {"width": 64, "height": 48, "fx": 50.0, "fy": 51.0, "cx": 31.5, "cy": 23.5}
    with pytest.raises(CalibrationError, match=r"gives 6 of them; missing: depth_scale"):
        open_sequence(root, calibration_overrides=calib)
    seq = open_sequence(root, calibration_overrides={**calib, "depth_scale": 1000, "fx": 49})
    c = seq.calibration
    assert (c.width, c.height, c.fx, c.fy, c.depth_scale) == (64, 48, 49.0, 51.0, 1000.0)
    assert seq[0].depth_m[0, 0] == pytest.approx(5.0)  # 5000 / 1000


def test_tum_defaults_by_folder_name(tmp_path):
    seq = open_sequence(
        _write_seq(tmp_path / "rgbd_dataset_freiburg1_xyz", [0.0], [0.0], calib=False)
    )
    assert seq.calibration.fx == 517.3 and seq.calibration.depth_scale == 5000.0


def test_calibration_override(tmp_path):
    seq = open_sequence(
        _write_seq(tmp_path / "s", [0.0], [0.0]), calibration_overrides={"fx": 99.0}
    )
    assert seq.calibration.fx == 99.0 and seq.calibration.fy == 50.0


def test_unknown_layout(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(DatasetError, match="unknown sequence layout"):
        open_sequence(tmp_path / "x")
    with pytest.raises(DatasetError, match="not found"):
        open_sequence(tmp_path / "missing")


def test_corrupt_frame_raises_frame_error(tmp_path):
    root = _write_seq(tmp_path / "s", [0.0, 0.033], [0.0, 0.033])
    (root / "depth/1.png").write_bytes(b"not a png")
    seq = open_sequence(root)
    seq[0]
    with pytest.raises(FrameReadError, match="frame 1"):
        seq[1]


def test_depth_only_sequence(tmp_path):
    root = _write_seq(tmp_path / "s", [0.0], [0.0])
    (root / "rgb.txt").unlink()
    seq = open_sequence(root)
    assert not seq.has_color and seq[0].color is None
    assert not seq.color_registered  # no colour: nothing to register



def _write_calib(root, text):
    (root / "calibration.yaml").write_text(text)
    return root


FR1_YAML = (
    "width: 640\nheight: 480\nfx: 517.3\nfy: 516.5\ncx: 318.6\ncy: 255.3\ndepth_scale: 5000\n"
)


def test_tum_fr1_intrinsics_come_with_their_published_distortion(tmp_path):
    """TUM's calibrated fr1 intrinsics were estimated with fr1's distortion, and fr1 images are
    distributed as recorded: a calibration stating those intrinsics and no distortion gets it;
    one stating its own distortion, or an override, keeps what it says."""
    root = _write_calib(_write_seq(tmp_path / "a", [0.0], [0.0]), FR1_YAML)
    c = open_sequence(root).calibration
    assert (c.k1, c.k2, c.p1, c.p2, c.k3) == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    root = _write_calib(_write_seq(tmp_path / "b", [0.0], [0.0]), FR1_YAML + "k1: 0.1\n")
    assert open_sequence(root).calibration.distortion.tolist() == [0.1, 0, 0, 0, 0]
    off = dict.fromkeys(("k1", "k2", "p1", "p2", "k3"), 0.0)
    assert not open_sequence(root, calibration_overrides=off).calibration.has_distortion
    root = _write_calib(_write_seq(tmp_path / "c", [0.0], [0.0]), FR1_YAML.replace("517.3", "520"))
    assert not open_sequence(root).calibration.has_distortion


def test_tum_fr1_colour_is_taken_later_than_stamped(tmp_path):
    """fr1's Kinect took its colour images 12 ms later, relative to depth, than the stamps say
    (slam.data.calibration.TUM_COLOUR_DELAY_S): its intrinsics bring that delay, which every
    frame's colour instant includes; a calibration or an override stating its own keeps it,
    other intrinsics and depth-only sequences have none, and a delay of 0.1 s or more is no
    timing offset."""
    rgb, depth = [0.000, 0.033], [0.010, 0.043]  # colour stamped 10 ms before depth

    def write(name, yaml):
        return _write_calib(_write_seq(tmp_path / name, rgb, depth, size=(640, 480)), yaml)

    root = write("a", FR1_YAML)
    seq = open_sequence(root)
    assert seq.calibration.colour_delay_s == 0.012
    assert seq[1].color_dt_s == pytest.approx(-0.010 + 0.012)
    stated = write("b", FR1_YAML + "colour_delay_s: 0\n")
    assert open_sequence(stated)[1].color_dt_s == pytest.approx(-0.010)
    override = open_sequence(root, calibration_overrides={"colour_delay_s": 0.004})
    assert override[1].color_dt_s == pytest.approx(-0.006)
    other = write("c", FR1_YAML.replace("517.3", "520"))
    assert open_sequence(other)[1].color_dt_s == pytest.approx(-0.010)
    with pytest.raises(CalibrationError, match="colour_delay_s"):
        open_sequence(root, calibration_overrides={"colour_delay_s": 0.5})


def test_frames_are_undistorted(tmp_path):
    root = _write_seq(tmp_path / "s", [0.0], [0.0])
    depth = np.tile(5000 + 100 * np.arange(64), (48, 1)).astype(np.uint16)
    cv2.imwrite(str(root / "depth/0.png"), depth)
    plain = open_sequence(root)[0].depth_m
    _write_calib(
        root,
        "width: 64\nheight: 48\nfx: 50.0\nfy: 50.0\ncx: 31.5\ncy: 23.5\ndepth_scale: 5000.0\n"
        "k1: 0.3\n",
    )
    und = open_sequence(root)[0].depth_m
    assert und[24, 32] == plain[24, 32]  # the principal point stays
    # k1 > 0: a pixel of the pinhole image lies farther out in the recorded one
    assert und[24, 60] > plain[24, 60] and und[24, 4] < plain[24, 4]


def test_the_calibration_says_where_it_came_from(tmp_path):
    """Shown after every run (metrics.json calibration_source), not only with -v."""
    seq = open_sequence(_write_seq(tmp_path / "own", [0.0], [0.0]))
    assert seq.calibration_source == "the folder's calibration.yaml"
    folder = _write_seq(tmp_path / "rgbd_dataset_freiburg1_x", [0.0], [0.0], calib=False,
                        size=(640, 480))  # fmt: skip
    assert open_sequence(folder).calibration_source == "the TUM defaults for the folder's name"
