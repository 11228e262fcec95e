"""Fuzzing a small sequence folder: whatever is damaged, a run ends in a result or a SlamError
(never another exception, never a hang). The damage includes repeated image names, byte-order
marks, image headers declaring huge sizes; and frames handed to the API with NaN, infinite or
negative depth and bad intrinsics ``K``: a FrameResult or a SlamError, and the Slam goes on."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import slam
from slam.synthetic import SynthConfig, generate_sequence

pytestmark = pytest.mark.slow

N_FRAMES = 12


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """12 frames of the synthetic loop at 160x120."""
    half = SynthConfig.half_resolution()
    cfg = SynthConfig(
        frames=300,
        render_frames=N_FRAMES,
        seed=2,
        width=160,
        height=120,
        fx=half.fx / 2,
        fy=half.fy / 2,
        cx=(half.cx + 0.5) / 2 - 0.5,
        cy=(half.cy + 0.5) / 2 - 0.5,
    )
    return generate_sequence(tmp_path_factory.mktemp("tiny") / "seq", cfg)


KINDS = (
    "truncate", "flip", "delete_line", "swap_stamps", "resize", "zero_depth", "garbage_line",
    "duplicate_name", "bom", "bom_groundtruth", "huge_header",
)  # fmt: skip
mutation = st.tuples(
    st.sampled_from(KINDS),
    st.sampled_from(("rgb", "depth")),
    st.integers(0, N_FRAMES - 1),
    st.integers(0, N_FRAMES - 1),
    st.integers(0, 2**31 - 1),
)


def _list_lines(path: Path) -> tuple[list[str], list[int]]:
    lines = path.read_text(encoding="utf-8").splitlines()
    data = [k for k, line in enumerate(lines) if line and not line.lstrip("\ufeff").startswith("#")]
    return lines, data


def _png_header(width: int, height: int) -> bytes:
    """A ~100-byte PNG whose IHDR declares ``width`` x ``height`` 16-bit grey pixels."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


def mutate(root: Path, kind: str, which: str, i: int, j: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    image = root / which / f"{i:06d}.png"
    lst = root / f"{which}.txt"
    lines, data = _list_lines(lst)
    if kind == "truncate" and image.exists():
        b = image.read_bytes()
        image.write_bytes(b[: int(rng.integers(0, len(b)))])
    elif kind == "flip" and image.exists():
        b = bytearray(image.read_bytes())
        for k in rng.integers(0, len(b), 8):
            b[k] ^= 0xFF
        image.write_bytes(bytes(b))
    elif kind == "delete_line" and data:
        del lines[data[i % len(data)]]
        lst.write_text("\n".join(lines) + "\n")
    elif kind == "swap_stamps" and len(data) > 1:
        a, b = data[i % len(data)], data[j % len(data)]
        ta, na = lines[a].split(maxsplit=1)
        tb, nb = lines[b].split(maxsplit=1)
        lines[a], lines[b] = f"{tb} {na}", f"{ta} {nb}"
        lst.write_text("\n".join(lines) + "\n")
    elif kind == "resize" and image.exists():
        import cv2

        img = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
        if img is not None:
            cv2.imwrite(str(image), cv2.resize(img, (int(rng.integers(8, 200)), 90)))
    elif kind == "zero_depth":
        import cv2

        cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), np.zeros((120, 160), np.uint16))
    elif kind == "garbage_line":
        lines.insert(data[i % len(data)] if data else 0, "x" * int(rng.integers(1, 30)))
        lst.write_text("\n".join(lines) + "\n")
    elif kind == "duplicate_name" and len(data) > 1:
        # lines j.. name the image of line i: one repeat, or most of the list
        a = data[i % len(data)]
        name = lines[a].split(maxsplit=1)[1]
        count = 1 if seed % 2 else len(data)
        for b in [data[(j + k) % len(data)] for k in range(count)]:
            if b != a:
                lines[b] = f"{lines[b].split(maxsplit=1)[0]} {name}"
        lst.write_text("\n".join(lines) + "\n")
    elif kind in ("bom", "bom_groundtruth"):
        target = lst if kind == "bom" else root / "groundtruth.txt"
        if target.exists():
            target.write_bytes(b"\xef\xbb\xbf" + target.read_bytes().lstrip(b"\xef\xbb\xbf"))
    elif kind == "huge_header":
        side = int(rng.integers(100, 60000))
        (root / which / f"{i:06d}.png").write_bytes(_png_header(side, side))


@settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(st.lists(mutation, min_size=1, max_size=4))
def test_damaged_sequence_ends_in_result_or_slam_error(tiny, tmp_path_factory, mutations):
    root = tmp_path_factory.mktemp("fuzz") / "seq"
    shutil.copytree(tiny, root)
    for m in mutations:
        mutate(root, *m)
    try:
        result = slam.run(slam.open_sequence(root))
    except slam.SlamError:
        return
    m = result.metrics
    assert m["frames"] + m["frames_skipped"] <= N_FRAMES + 1
    assert len(result.trajectory) == m["frames_in_trajectory"]
    assert np.all(np.isfinite(result.trajectory.poses))


# --- the API: frames handed to Slam.step


FRAME_KINDS = ("clean", "nan", "inf", "negative", "all_nan", "bad_K", "bad_K_later")
BAD_K = {
    0: np.diag([0.0, 100.0, 1.0]),  # fx = 0
    1: np.array([[100.0, 0, np.nan], [0, 100.0, 59.5], [0, 0, 1]]),  # NaN cx
    2: np.eye(4),  # 4x4
    3: np.array([[100.0, 0, 900.0], [0, 100.0, 59.5], [0, 0, 1]]),  # cx outside the image
    4: np.array([[100.0, 0, 79.5], [0, -100.0, 59.5], [0, 0, 1]]),  # fy < 0
}
frame_damage = st.tuples(
    st.integers(0, N_FRAMES - 1),
    st.sampled_from(FRAME_KINDS),
    st.integers(0, len(BAD_K) - 1),
    # the damaged share of the rows: at most 90%, so what is left is never a few rows only
    # (that is test_frame_guards' xfail: Open3D reads depth at every 4th pixel when it picks the
    # blocks to fuse)
    st.floats(0.05, 0.9),
)


def damaged_frame(frame, kind: str, k: int, fraction: float):
    """``frame`` with depth values that are not distances over ``fraction`` of its rows, or a
    bad ``K`` (given to the Frame, or put in after it was made)."""
    import dataclasses

    if kind == "clean":
        return frame
    if kind in ("bad_K", "bad_K_later"):
        if kind == "bad_K":
            return dataclasses.replace(frame, K=BAD_K[k])  # raises: a Frame checks its K
        out = dataclasses.replace(frame)
        out.K = BAD_K[k]
        return out
    depth = frame.depth_m.copy()
    rows = max(1, int(fraction * depth.shape[0]))
    value = {"nan": np.nan, "inf": np.inf, "negative": -1.0, "all_nan": np.nan}[kind]
    if kind == "all_nan":
        depth[:] = value
    else:
        depth[:rows] = value
    return dataclasses.replace(frame, depth_m=depth)


@pytest.fixture(scope="module")
def tiny_frames(tiny):
    seq = slam.open_sequence(tiny)
    return [seq[i] for i in range(len(seq))]


@settings(
    max_examples=15,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(st.lists(frame_damage, min_size=1, max_size=4))
def test_damaged_frames_through_the_api(tiny_frames, damage):
    """Every frame either gives a FrameResult or raises a SlamError (a bad K), never another
    exception; the Slam goes on: the remaining frames step and finish() gives a result with a
    finite trajectory (or a SlamError when no frame was tracked)."""
    from slam.config import config_from_dict

    by_index = {i: (kind, k, fraction) for i, kind, k, fraction in damage}
    system = slam.Slam(config_from_dict({"tracking": {"downsample": 1}}))
    refused = 0
    for f in tiny_frames:
        try:
            frame = damaged_frame(f, *by_index.get(f.index, ("clean", 0, 0.0)))
            r = system.step(frame)
        except slam.SlamError:
            refused += 1
            continue
        assert r.T_world_cam is None or np.all(np.isfinite(r.T_world_cam))
    assert len(system.statuses) == len(tiny_frames) - refused
    try:
        result = system.finish()
    except slam.SlamError:
        return
    assert len(result.trajectory) >= 1
    assert np.all(np.isfinite(result.trajectory.poses))
