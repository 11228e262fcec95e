"""The rerun recording: `slam run --rerun FILE.rrd` and `slam view RUN_DIR` write files that
rerun's own reader loads, with the expected entities."""

from __future__ import annotations

import shutil
import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from slam.cli import app
from slam.errors import SlamError

rr = pytest.importorskip("rerun", reason="rerun-sdk (the viz extra) is not installed")
runner = CliRunner()

PER_FRAME = (
    "/world/camera",
    "/world/camera/image/rgb",
    "/world/camera/image/depth",
    "/tracking/overlap",
    "/tracking/icp_fitness",
    "/tracking/ms",
)
AT_THE_END = ("/world/mesh", "/world/trajectory", "/world/loops")


def load(path: Path) -> tuple[Counter, dict[str, list]]:
    """Rows per entity, and the timelines of each entity, as rerun's reader sees the file."""
    store = rr.chunk.RrdReader(path).stream().collect()
    rows: Counter = Counter()
    timelines: dict[str, list] = {}
    for chunk in store.stream():
        rows[chunk.entity_path] += chunk.num_rows
        timelines[chunk.entity_path] = chunk.timeline_names
    return rows, timelines


def frame_values(path: Path, entity: str, column: str) -> list:
    store = rr.chunk.RrdReader(path).stream().collect()
    out = []
    for chunk in store.stream():
        if chunk.entity_path == entity:
            out += chunk.to_record_batch().column(column).to_pylist()
    return sorted(out)


def check_recording(path: Path, frames: int) -> Counter:
    assert path.is_file() and not path.with_name(path.name + ".tmp").exists()
    rows, timelines = load(path)
    for entity in PER_FRAME:
        assert rows[entity] == frames, (entity, rows)
        assert {"frame", "time"} <= set(timelines[entity])
    assert rows["/tracking/status"] == frames + 1  # one per frame and the summary
    assert rows["/world/camera/image"] == 1  # the pinhole, logged when the intrinsics change
    assert rows["/world/odometry/000"] == frames  # the trajectory so far, every frame
    for entity in AT_THE_END:
        assert rows[entity] >= 1, (entity, rows)
    assert rows["/world/keyframes"] >= 2  # as they come, and the corrected ones at the end
    assert frame_values(path, "/world/camera", "frame") == list(range(frames))
    assert max(frame_values(path, "/world/mesh", "frame")) == frames  # after the last frame
    return rows


def test_run_records_a_rerun_file(recorded_run):
    run_dir, rrd = recorded_run
    check_recording(rrd, 30)
    exe = shutil.which("rerun")
    if exe:  # rerun's own command line check of the file
        proc = subprocess.run(
            [exe, "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120
        )
        assert proc.returncode == 0, proc.stderr[-2000:]


def test_view_writes_the_same_recording_from_the_run_folder(recorded_run, tmp_path):
    run_dir, live = recorded_run
    out = tmp_path / "view.rrd"
    res = runner.invoke(app, ["view", str(run_dir), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert f"wrote {out}" in res.stdout
    rows = check_recording(out, 30)
    live_rows, _ = load(live)
    # the same entities (loops may differ: the folder has their final decision)
    assert set(rows) == set(live_rows)
    res = runner.invoke(app, ["view", str(run_dir), "--image-scale", "0"])
    assert res.exit_code == 0, res.output
    rows, _ = load(run_dir / "recording.rrd")
    assert rows["/world/camera/image/rgb"] == 0 and rows["/world/camera"] == 30


def test_depth_is_logged_in_millimetres_at_quarter_resolution(recorded_run):
    _, rrd = recorded_run
    store = rr.chunk.RrdReader(rrd).stream().collect()
    for chunk in store.stream():
        if chunk.entity_path == "/world/camera/image/depth":
            batch = chunk.to_record_batch()
            fmt = batch.column("DepthImage:format").to_pylist()[0][0]
            meter = batch.column("DepthImage:meter").to_pylist()[0]
            break
    assert (fmt["width"], fmt["height"]) == (80, 60)  # 320x240 / 4
    assert np.ravel(meter)[0] == 1000.0


def test_view_refuses_an_incomplete_run_and_missing_rerun(tmp_path, monkeypatch):
    (tmp_path / "config.yaml").write_text("dataset: {}\n")
    res = runner.invoke(app, ["view", str(tmp_path)])
    assert res.exit_code == 2 and "no metrics.json" in " ".join(res.output.split())

    import builtins

    real_import = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("no rerun here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    from slam.tools.viewer import RerunRecorder

    with pytest.raises(SlamError, match=r"rgbd-slam\[viz\]"):
        RerunRecorder(tmp_path / "x.rrd")


def test_rerun_path_that_is_a_folder_is_refused_before_any_work(recorded_run, tmp_path):
    seq = recorded_run[0].parent / "seq"
    res = runner.invoke(
        app, ["run", str(seq), "--out", str(tmp_path / "r"), "--rerun", str(tmp_path)]
    )
    assert res.exit_code == 2
    assert "is a folder" in " ".join(res.output.split())
    assert not (tmp_path / "r").exists()
