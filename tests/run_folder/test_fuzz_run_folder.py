"""Fuzzing a run folder's JSON: whatever value replaces any part of a checkpoint's state.json or
of a keyframe's document (a checkpoint damaged after it was written: refused by its digests), of
metrics.json or of loops.json, the commands that read them (``--resume``, ``slam eval``,
``slam report``, ``slam view``) end in a result or a SlamError (exit 0 or 2), never another
exception."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import slam
from slam.cli import app
from slam.run_folder import LOOPS_FILE, METRICS_FILE
from slam.run_folder.layout import CHECKPOINT_DIR

pytestmark = pytest.mark.slow

FRAMES = 12
SETTINGS = settings(
    max_examples=20,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

#: any JSON value, numbers from the ones a file holds to ones no file could mean
json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.text(max_size=8)
    | st.floats(allow_nan=False, allow_infinity=False) | st.sampled_from([-1, 0, 1, 1e30]),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                max_size=3),
    max_leaves=6,
)  # fmt: skip
#: where to put it: one index per level, taken modulo the level's length
paths = st.lists(st.integers(0, 2**16), min_size=0, max_size=6)


def replace_at(tree: Any, path: list[int], value: Any) -> Any:
    """``tree`` with the part that ``path`` leads to replaced by ``value`` (a path that meets a
    leaf early replaces that leaf)."""
    if not path or not isinstance(tree, (dict, list)) or not tree:
        return value
    keys = list(tree) if isinstance(tree, dict) else list(range(len(tree)))
    key = keys[path[0] % len(keys)]
    tree[key] = replace_at(tree[key], path[1:], value)
    return tree


@pytest.fixture(scope="module")
def stopped_run(tiny_seq, tmp_path_factory) -> Path:
    """A run of the tiny sequence stopped after 7 frames, with a checkpoint after 5."""

    class Stop(Exception):
        pass

    def stop_after(frame, result) -> None:
        if frame.index >= 6:
            raise Stop

    out = tmp_path_factory.mktemp("stopped") / "run"
    with pytest.raises(Stop):
        slam.run_sequence(tiny_seq, out, checkpoint_every=5, on_frame=stop_after)
    assert (out / CHECKPOINT_DIR / "state.json").is_file()
    return out


@pytest.fixture(scope="module")
def finished_run(tiny_seq, tmp_path_factory) -> Path:
    _, out = slam.run_sequence(tiny_seq, tmp_path_factory.mktemp("finished") / "run")
    return out


@pytest.fixture(scope="module")
def tiny_seq(tmp_path_factory) -> Path:
    from slam.synthetic import SynthConfig, generate_sequence

    cfg = SynthConfig.half_resolution(frames=300, render_frames=FRAMES, seed=5)
    return generate_sequence(tmp_path_factory.mktemp("tiny") / "seq", cfg)


def _damage_keyframe(path: Path, where: list[int], value: Any) -> None:
    with zipfile.ZipFile(path) as z:
        entries = {n: z.read(n) for n in z.namelist()}
    doc_name = next(n for n in entries if n.startswith("__doc__"))
    doc = np.load(path, allow_pickle=False)["__doc__"]
    tree = replace_at(json.loads(bytes(doc).decode() if doc.dtype == np.uint8 else str(doc)),
                      where, value)  # fmt: skip
    text = json.dumps(tree)
    arr = np.frombuffer(text.encode(), np.uint8) if doc.dtype == np.uint8 else np.array(text)
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    entries[doc_name] = buf.getvalue()
    with zipfile.ZipFile(path, "w") as z:
        for n, data in entries.items():
            z.writestr(n, data)


@SETTINGS
@given(st.sampled_from(["state", "keyframe"]), paths, json_values)
def test_a_damaged_checkpoint_resumes_or_is_a_slam_error(
    stopped_run, tmp_path_factory, which, where, value
):
    run = Path(shutil.copytree(stopped_run, tmp_path_factory.mktemp("fuzz") / "run"))
    folder = run / CHECKPOINT_DIR
    if which == "state":
        state = folder / "state.json"
        state.write_text(json.dumps(replace_at(json.loads(state.read_text()), where, value)))
    else:
        _damage_keyframe(sorted(folder.glob("kf_*.npz"))[0], where, value)
    try:
        result, _ = slam.resume_run(run)
    except slam.SlamError:
        return
    assert np.all(np.isfinite(result.trajectory.poses))


@SETTINGS
@given(st.sampled_from([METRICS_FILE, LOOPS_FILE]), paths, json_values)
def test_damaged_run_folder_json_is_read_or_refused(
    finished_run, tmp_path_factory, name, where, value
):
    run = Path(shutil.copytree(finished_run, tmp_path_factory.mktemp("fuzz") / "run"))
    path = run / name
    if not path.is_file():
        pytest.skip(f"the tiny run wrote no {name}")
    path.write_text(json.dumps(replace_at(json.loads(path.read_text()), where, value)))
    for cmd in (["eval", str(run)], ["report", str(run)], ["view", str(run), "--image-scale", "0"]):
        res = CliRunner().invoke(app, cmd)
        assert res.exit_code in (0, 2), (cmd, res.output, res.exception)
