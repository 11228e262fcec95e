"""Fuzzing a small sequence folder: whatever is damaged, a run ends in a result or a SlamError
(never another exception, never a hang)."""

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


KINDS = ("truncate", "flip", "delete_line", "swap_stamps", "resize", "zero_depth", "garbage_line")
mutation = st.tuples(
    st.sampled_from(KINDS),
    st.sampled_from(("rgb", "depth")),
    st.integers(0, N_FRAMES - 1),
    st.integers(0, N_FRAMES - 1),
    st.integers(0, 2**31 - 1),
)


def _list_lines(path: Path) -> tuple[list[str], list[int]]:
    lines = path.read_text().splitlines()
    return lines, [k for k, line in enumerate(lines) if line and not line.startswith("#")]


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
        ta, na = lines[a].split()
        tb, nb = lines[b].split()
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
