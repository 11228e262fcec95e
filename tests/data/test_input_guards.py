"""Input guards of the sequence loaders (issue 19): repeated image names, byte-order marks,
file names with spaces, and image headers declaring a size the frame must not have (refused
before any pixel is decoded)."""

from __future__ import annotations

import logging
import struct
import zlib

import cv2
import numpy as np
import pytest

from slam.data import open_sequence
from slam.data.images import MAX_IMAGE_PIXELS, declared_size, read_color, read_depth
from slam.errors import DatasetError, FrameReadError, FrameSizeError
from slam.trajectory import read_tum

BOM = "\ufeff"
CALIB = "width: 64\nheight: 48\nfx: 50.0\nfy: 50.0\ncx: 31.5\ncy: 23.5\ndepth_scale: 5000.0\n"


def write_seq(root, n=6, depth_names=None, rgb_dir="rgb", prefix=""):
    """A 64x48 TUM-layout sequence of ``n`` frames; ``depth_names`` replaces the names listed in
    depth.txt; ``prefix`` starts each list (e.g. a byte-order mark)."""
    (root / rgb_dir).mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth = [f"{prefix}# rgb"], [f"{prefix}# depth"]
    for i in range(n):
        t = i / 30
        cv2.imwrite(str(root / rgb_dir / f"{i}.png"), np.full((48, 64, 3), i, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{i}.png"), np.full((48, 64), 5000 + i, np.uint16))
        rgb.append(f"{t:.6f} {rgb_dir}/{i}.png")
        depth.append(f"{t:.6f} {depth_names[i] if depth_names else f'depth/{i}.png'}")
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n", encoding="utf-8")
    (root / "depth.txt").write_text("\n".join(depth) + "\n", encoding="utf-8")
    (root / "calibration.yaml").write_text(CALIB)
    return root


def png_header(width: int, height: int, bit_depth: int = 16, colour_type: int = 0) -> bytes:
    """A small, well-formed PNG whose IHDR declares ``width`` x ``height`` (its one IDAT holds
    a few compressed bytes only: the file is ~100 bytes whatever size it declares)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    idat = zlib.compress(b"\0" * 64)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


# --- repeated names


def test_most_entries_naming_one_file_is_an_error(tmp_path):
    """Every depth line names one file: the camera would seem to stand still (no lost frame,
    no warning); opening the sequence says so instead, with the file, counts and a line."""
    root = write_seq(tmp_path / "s", n=6, depth_names=["depth/0.png"] * 6)
    with pytest.raises(DatasetError) as info:
        open_sequence(root)
    msg = str(info.value)
    assert "depth.txt: 5 of its 6 entries name an image an earlier entry already names" in msg
    assert "'depth/0.png' is named 6 times, first on line 2, again e.g. on line 3" in msg
    assert "'0.033333 depth/0.png'" in msg  # the example line as written
    assert "regenerate the list" in msg


def test_a_few_repeated_names_are_a_warning_naming_them(tmp_path, caplog):
    names = [f"depth/{i}.png" for i in range(6)]
    names[4] = "depth/2.png"
    root = write_seq(tmp_path / "s", n=6, depth_names=names)
    with caplog.at_level(logging.WARNING, logger="slam.data.tum"):
        seq = open_sequence(root)
    assert len(seq) == 6
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(
        "depth.txt: 1 of its 6 entries name an image an earlier entry already names: "
        "'depth/2.png' (lines 4, 6)" in m
        for m in warned
    ), warned


# --- byte-order marks, names with spaces


def test_byte_order_mark_in_lists_and_ground_truth(tmp_path):
    """Lists and groundtruth.txt saved with a UTF-8 BOM (Windows editors): read as without it
    (it gave "bad timestamp '\\ufeff#'" and, in groundtruth.txt, silently no ATE)."""
    root = write_seq(tmp_path / "s", n=3, prefix=BOM)
    gt = BOM + "# ground truth\n0.0 0 0 0 0 0 0 1\n0.05 1 0 0 0 0 0 1\n0.1 2 0 0 0 0 0 1\n"
    (root / "groundtruth.txt").write_text(gt, encoding="utf-8")
    seq = open_sequence(root)
    assert len(seq) == 3 and seq[2].depth_m[0, 0] == pytest.approx(5002 / 5000)
    assert seq.ground_truth is not None and len(seq.ground_truth) == 3
    assert len(read_tum(root / "groundtruth.txt")) == 3
    # a list whose first line is data, right after the mark
    (root / "depth.txt").write_text(BOM + "0.000000 depth/0.png\n", encoding="utf-8")
    assert len(open_sequence(root)) == 1


def test_file_names_with_spaces(tmp_path):
    root = write_seq(tmp_path / "s", n=3, rgb_dir="rgb images")
    seq = open_sequence(root)
    rgb, _ = seq.files(2)
    assert rgb == root / "rgb images" / "2.png"
    assert seq[2].color[0, 0, 0] == 2


# --- image headers


def test_declared_size_of_png_and_jpeg():
    img = np.zeros((48, 64, 3), np.uint8)
    assert declared_size(cv2.imencode(".png", img)[1].tobytes()) == (64, 48)
    assert declared_size(cv2.imencode(".jpg", img)[1].tobytes()) == (64, 48)
    assert declared_size(png_header(30000, 30000)) == (30000, 30000)
    assert declared_size(b"not an image") is None
    assert declared_size(b"\x89PNG\r\n\x1a\n") is None  # cut before its IHDR


def test_huge_png_header_is_refused_without_decoding(tmp_path, monkeypatch, caplog):
    """A ~100-byte PNG declaring 30000x30000 pixels as one depth frame (decoded, 1.8 GB of
    pixels and 6.7 GB peak): refused from its header, never handed to the decoder; the frame
    is skipped like other corrupt ones, the warning names the file and the declared size."""
    root = write_seq(tmp_path / "s", n=3)
    huge = root / "depth" / "1.png"
    huge.write_bytes(png_header(30000, 30000))
    assert huge.stat().st_size < 200
    seq = open_sequence(root)

    def no_decoding(*args, **kwargs):
        raise AssertionError("the image was handed to the decoder")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    with pytest.raises(FrameReadError) as info:
        seq[1]
    msg = str(info.value)
    assert not isinstance(info.value, FrameSizeError)  # damaged, not a calibration question
    assert f"frame 1: depth image {huge} declares 30000x30000 pixels in its header" in msg
    assert "not decoded" in msg
    with pytest.raises(FrameReadError, match="declares 30000x30000"):
        read_color(huge, 7)
    # a plausible size other than the calibration's: the same error as after decoding, earlier
    other = root / "depth" / "2.png"
    other.write_bytes(png_header(640, 480))
    with pytest.raises(FrameSizeError) as info:
        seq[2]
    assert "depth image is 640x480 but the calibration says 64x48" in str(info.value)
    assert str(other) in str(info.value)


def test_huge_png_frame_is_skipped_by_the_run(tmp_path, caplog):
    """Through the pipeline's reader: the frame is skipped with a warning naming the file."""
    import slam

    root = write_seq(tmp_path / "s", n=3)
    (root / "depth" / "1.png").write_bytes(png_header(30000, 30000))
    seq = open_sequence(root)
    system = slam.Slam(has_color=True)
    with caplog.at_level(logging.WARNING):
        for i in range(len(seq)):
            try:
                system.step(seq[i])
            except FrameReadError as exc:
                system.skip(i, seq.timestamp(i), str(exc))
    assert [s["index"] for s in system.skipped] == [1]
    assert any(
        "skipping frame 1" in r.getMessage()
        and "30000x30000" in r.getMessage()
        and "1.png" in r.getMessage()
        for r in caplog.records
    )


def test_huge_jpeg_header_is_refused_without_decoding(tmp_path):
    data = bytearray(cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes())
    sof = next(i for i in range(2, len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xC0)
    data[sof + 5 : sof + 9] = struct.pack(">HH", 60000, 60000)
    path = tmp_path / "big.jpg"
    path.write_bytes(bytes(data))
    assert declared_size(bytes(data)) == (60000, 60000)
    with pytest.raises(
        FrameReadError, match=r"frame 3: colour image .*big.jpg declares 60000x60000"
    ):
        read_color(path, 3)
    assert 60000 * 60000 > MAX_IMAGE_PIXELS


def test_depth_values_that_are_not_distances_are_no_depth(tmp_path):
    """A float depth image with NaN, infinite and negative values: those pixels have no depth."""
    raw = np.array([[1.0, np.nan], [np.inf, -2.0]], np.float32)
    path = tmp_path / "d.tiff"
    cv2.imwrite(str(path), raw)
    depth = read_depth(path, 0, 1.0)
    np.testing.assert_array_equal(depth, [[1.0, 0.0], [0.0, 0.0]])


def test_extra_columns_are_part_of_the_name_and_the_error_says_so(tmp_path):
    root = write_seq(tmp_path / "s", n=2)
    (root / "depth.txt").write_text("0.000000 depth/0.png 0.0\n0.033333 depth/1.png 0.0\n")
    with pytest.raises(DatasetError) as info:
        open_sequence(root)
    assert (
        "image listed but not found: 'depth/0.png 0.0' (a file name is everything after the "
        "timestamp; 'depth/0.png' exists: remove the extra columns from the list)"
        in str(info.value)
    )


@pytest.mark.parametrize("f", [1e-30, 1e-3, 1e30])
def test_a_focal_length_no_sensor_has_is_a_calibration_error(f):
    """fx = 1e-30 gave numpy's LinAlgError deep in the tracker: refused up front, with the
    field of view it implies."""
    from slam.camera import check_intrinsics
    from slam.errors import CalibrationError

    K = [[f, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]]
    with pytest.raises(CalibrationError, match="field of view"):
        check_intrinsics(K, 640, 480)
    check_intrinsics([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]], 640, 480)


@pytest.mark.parametrize("kind", ["dev-zero", "fifo", "huge"])
def test_a_depth_frame_that_is_not_a_regular_file_is_refused_at_once(tmp_path, kind):
    """A link to /dev/zero was read to 4.3 GB (MemoryError); a FIFO hung the run, SIGTERM
    ignored: only regular files of a bounded size are read, and the frame is skipped."""
    import os

    from slam.data import images
    from slam.errors import FrameReadError

    path = tmp_path / "d.png"
    if kind == "dev-zero":
        path.symlink_to("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(path)
    else:
        with open(path, "wb") as f:
            f.truncate(images.MAX_IMAGE_BYTES + 1)  # sparse: no disk used
    with pytest.raises(FrameReadError, match="not a regular file|more than any frame"):
        images.read_depth(path, 7, 5000.0)


def test_8_bit_depth_is_named_before_the_run(tmp_path):
    """Every frame's depth 8-bit: the run said only "no frame could be tracked ... see the
    log" (silent under -q); the pre-flight check now names the reason."""
    from tests.data.test_tum import _write_seq

    root = _write_seq(tmp_path / "s", [0.0, 0.033, 0.066], [0.0, 0.033, 0.066])
    for p in (root / "depth").iterdir():
        cv2.imwrite(str(p), np.full((48, 64), 200, np.uint8))
    from slam.data.checks import check_sequence

    seq = open_sequence(root)
    with pytest.raises(DatasetError, match="none of the first 3 frames can be read.*dtype uint8"):
        check_sequence(seq, list(range(len(seq))))


@pytest.mark.parametrize("size", [(1, 1), (64, 24), (128, 96)])
def test_a_colour_image_that_cannot_line_up_with_depth_is_reported_once(tmp_path, caplog, size):
    """A 1x1 colour image was stretched to the depth's size without a word; a scaled copy of the
    same view (twice the depth's size) still is, silently."""
    root = write_seq(tmp_path / "s")
    for i in range(6):
        cv2.imwrite(str(root / "rgb" / f"{i}.png"), np.full((size[1], size[0], 3), i, np.uint8))
    seq = open_sequence(root)
    with caplog.at_level(logging.WARNING):
        frames = [seq[i] for i in range(6)]
    assert all(f.color.shape == (48, 64, 3) for f in frames)
    warned = [r for r in caplog.records if "does not line up with depth" in r.getMessage()]
    if size == (128, 96):
        assert warned == []
    else:
        assert len(warned) == 1 and f"{size[0]}x{size[1]}" in warned[0].getMessage()
