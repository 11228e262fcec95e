"""slam.run_folder as the one owner of the run folder: RunFolder reads what save_run writes, and
tracking.csv converts both ways without loss."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam.config import SlamConfig
from slam.errors import ConfigError, RunFolderError, TrajectoryError
from slam.records import TrackingStatus
from slam.run_folder import (
    CONFIG_FILE,
    LOOPS_FILE,
    METRICS_FILE,
    RUN_FILES,
    TRACKING_FILE,
    TRAJECTORY_FILE,
    RunFolder,
    segment_file,
    segment_number,
)
from slam.run_folder.tracking_csv import columns, format_rows, parse_rows
from slam.trajectory import Trajectory, read_tum, write_tum


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """A 10-frame run of a 320x240 synthetic loop: (sequence folder, RunResult, run folder)."""
    from slam.api import run_sequence
    from slam.config import config_from_dict
    from slam.synthetic import SynthConfig, generate_sequence

    root = tmp_path_factory.mktemp("reader")
    seq = generate_sequence(
        root / "seq", SynthConfig.half_resolution(frames=300, render_frames=12, seed=3)
    )
    cfg = config_from_dict({"tracking": {"downsample": 1}, "dataset": {"max_frames": 10}})
    result, run_dir = run_sequence(seq, root / "run", config=cfg)
    return seq, result, run_dir


def test_run_folder_reads_a_real_run(small_run):
    seq, result, run_dir = small_run
    run = RunFolder(run_dir)
    assert run.complete and run.require_complete() is run
    metrics = run.metrics()
    assert metrics == json.loads((run_dir / METRICS_FILE).read_text())
    assert metrics["frames"] == 10
    cfg = run.config()
    assert isinstance(cfg, SlamConfig) and cfg.tracking.downsample == 1
    assert run.sequence_path() == str(seq.resolve()) and run.sequence_dir() == seq.resolve()
    traj = run.trajectory()
    assert len(traj) == 10
    np.testing.assert_array_equal(traj.poses, read_tum(run_dir / TRAJECTORY_FILE).poses)
    odo = run.odometry()
    assert odo is not None and len(odo) == 10
    assert run.segments() == {}
    assert run.tracking() == result.tracking  # the records the run made, read back equal
    assert (run_dir / TRACKING_FILE).read_bytes() == format_rows(result.tracking).encode()
    loops = run.loops()
    if (run_dir / LOOPS_FILE).is_file():
        assert loops == json.loads((run_dir / LOOPS_FILE).read_text())["candidates"]
        assert run.accepted_loops() == [c for c in loops if c.get("accepted")]
    else:
        assert loops is None and run.accepted_loops() == []
    mesh = run.mesh_path()
    assert mesh is not None and mesh.is_file()


def test_tracking_csv_round_trip():
    statuses = [
        TrackingStatus(0, "init", True, timestamp=1305031102.175304, keyframe=True, ms=12.5),
        TrackingStatus(
            1,
            "icp",
            True,
            1305031102.211214,
            icp_fitness=0.8125,
            icp_rmse_m=0.0031,
            overlap=0.93,
            f2f_fitness=0.71,
            ms=40.25,
        ),  # fmt: skip
        TrackingStatus(
            2,
            "lost",
            False,
            1305031102.243,
            reason='no estimate passed: overlap 0.2 < 0.5, "x"',
            gap=True,
            segment=1,
            ransac_inliers=6,
            ransac_matches=80,
            model_rejected=True,
        ),  # fmt: skip
        TrackingStatus(3, "ransac+icp", True, 2.0, icp_fitness=float("nan")),
    ]
    text = format_rows(statuses)
    assert text.splitlines()[0] == ",".join(statuses[0].as_row())
    back = parse_rows(text)
    assert back[:3] == statuses[:3]
    assert np.isnan(back[3].icp_fitness) and back[3].path == "ransac+icp"
    assert format_rows(back[:3]) == format_rows(statuses[:3])
    assert format_rows([]) == "" and parse_rows("") == []
    cols = columns(back)
    assert cols["ms"].dtype.kind == "f" and cols["ok"].tolist() == [1.0, 1.0, 0.0, 1.0]
    assert cols["path"].tolist() == ["init", "icp", "lost", "ransac+icp"]


def test_tracking_csv_partial_and_malformed():
    # other columns ignored, missing ones and empty cells take the defaults
    back = parse_rows("index,path,ok,extra,ms\n4,icp,True,zzz,\n5,lost,False,,7.5\n")
    assert back == [TrackingStatus(4, "icp", True), TrackingStatus(5, "lost", False, ms=7.5)]
    with pytest.raises(RunFolderError, match=r"line 2: column ms"):
        parse_rows("index,path,ok,ms\n1,icp,True,fast\n", "x.csv")
    with pytest.raises(RunFolderError, match="needs index, path and ok"):
        parse_rows("index,ms\n1,3.0\n")


def test_run_folder_missing_and_malformed_files(tmp_path):
    run = RunFolder(tmp_path / "run")
    with pytest.raises(RunFolderError, match="run folder not found"):
        run.require_complete()
    run.path.mkdir()
    (run.path / CONFIG_FILE).write_text("dataset: {}\n")
    with pytest.raises(RunFolderError, match="no metrics.json.*did not finish"):
        run.require_complete()
    assert not run.complete and run.metrics() == {}
    assert run.odometry() is None and run.tracking() is None and run.loops() is None
    assert run.mesh_path() is None and run.sequence_path() is None and run.sequence_dir() is None
    with pytest.raises(TrajectoryError, match="no trajectory.txt in the run folder"):
        run.trajectory()
    (run.path / METRICS_FILE).write_text("{not json")
    with pytest.raises(RunFolderError, match="metrics.json: not valid JSON"):
        run.metrics()
    (run.path / METRICS_FILE).write_text(json.dumps({"sequence": "seq"}))
    assert run.sequence_path() == "seq" and run.sequence_dir() is None
    (run.path / "seq").mkdir()
    assert run.sequence_dir() == run.path / "seq"  # relative: to the run folder too
    (run.path / LOOPS_FILE).write_text("[]")
    with pytest.raises(RunFolderError, match="'candidates' list"):
        run.loops()
    (run.path / CONFIG_FILE).write_text("tracking:\n  no_such_key: 1\n")
    with pytest.raises(ConfigError, match="no_such_key"):
        run.config()


def test_segments_and_names(tmp_path):
    traj = Trajectory(np.arange(3.0), np.tile(np.eye(4), (3, 1, 1)))
    for seg in (2, 10):
        write_tum(tmp_path / segment_file(seg), traj)
    (tmp_path / "segment_x.txt").write_text("")
    segs = RunFolder(tmp_path).segments()
    assert list(segs) == [2, 10] and len(segs[10]) == 3
    assert segment_file(7) == "segment_7.txt" and segment_number("segment_7.txt") == 7
    assert segment_number("segment_.txt") is None and segment_number("trajectory.txt") is None
    assert RUN_FILES == (
        "metrics.json", "trajectory.txt", "odometry.txt", "mesh.ply", "config.yaml",
        "tracking.csv", "loops.json", "pose_graph.g2o", "report.md", "recording.rrd",
        "chunks.json",
    )  # fmt: skip


def test_damaged_json_in_a_run_folder_is_a_clear_error_or_n_a(small_run, tmp_path):
    """metrics.json or loops.json of arrays nested 100,000 deep: a RunFolderError, not a
    RecursionError; metrics.json whose values are strings: `slam report` says which file
    holds a value of the wrong kind instead of a ValueError traceback."""
    import shutil

    from typer.testing import CliRunner

    from slam.cli import app
    from slam.errors import RunFolderError
    from slam.run_folder import LOOPS_FILE, METRICS_FILE

    _, _, run_dir = small_run
    for name in (METRICS_FILE, LOOPS_FILE):
        copy = Path(shutil.copytree(run_dir, tmp_path / f"deep-{name}"))
        (copy / name).write_text("[" * 100_000 + "]" * 100_000)
        with pytest.raises(RunFolderError, match="nested too deeply"):
            RunFolder(copy)._json(name)
        res = CliRunner().invoke(app, ["report", str(copy)])
        assert res.exit_code == 2 and "nested too deeply" in res.output, res.output
    copy = Path(shutil.copytree(run_dir, tmp_path / "strings"))
    metrics = json.loads((copy / METRICS_FILE).read_text())
    stringy = {k: (str(v) if isinstance(v, (int, float)) else v) for k, v in metrics.items()}
    (copy / METRICS_FILE).write_text(json.dumps(stringy))
    res = CliRunner().invoke(app, ["report", str(copy)])
    assert res.exit_code == 2 and "holds a value of the wrong kind" in res.output, res.output


@pytest.mark.parametrize("text", ["", "garbage", "[1, 2]", '"run"'])
def test_an_empty_or_garbage_metrics_json_is_not_a_complete_run(small_run, tmp_path, text):
    """`slam eval` and `slam view` returned 0 on them."""
    import shutil

    from typer.testing import CliRunner

    from slam.cli import app
    from slam.run_folder import METRICS_FILE

    _, _, run_dir = small_run
    copy = Path(shutil.copytree(run_dir, tmp_path / "copy"))
    (copy / METRICS_FILE).write_text(text)
    for cmd in (["eval", str(copy)], ["view", str(copy), "--image-scale", "0"]):
        res = CliRunner().invoke(app, cmd)
        assert res.exit_code == 2 and "not a run's metrics" in res.output, (cmd, res.output)


@pytest.mark.parametrize("damage", ["cut", "huge-header", "not-ply"])
def test_a_cut_or_overstated_mesh_is_refused_by_view_and_render(small_run, tmp_path, damage):
    """`slam view` returned 0 on a cut mesh (only an RPly line on stderr) and on one whose
    header declares 10^11 vertices."""
    import shutil

    from typer.testing import CliRunner

    from slam.cli import app
    from slam.run_folder import MESH_FILE
    from slam.tools.render import render_run

    _, _, run_dir = small_run
    assert len(RunFolder(run_dir).mesh().vertices) > 0  # the whole file reads
    copy = Path(shutil.copytree(run_dir, tmp_path / "copy"))
    mesh = copy / MESH_FILE
    data = mesh.read_bytes()
    if damage == "cut":
        mesh.write_bytes(data[: len(data) * 2 // 3])
    elif damage == "huge-header":
        head, body = data.split(b"end_header\n", 1)
        lines = [b"element vertex 100000000000" if ln.startswith(b"element vertex") else ln
                 for ln in head.split(b"\n")]  # fmt: skip
        mesh.write_bytes(b"\n".join(lines) + b"end_header\n" + body)
    else:
        mesh.write_bytes(b"solid cube\nendsolid\n")
    with pytest.raises(RunFolderError, match="PLY|cut short"):
        RunFolder(copy).mesh()
    with pytest.raises(RunFolderError):
        render_run(copy, tmp_path / "view.png")
    res = CliRunner().invoke(app, ["view", str(copy), "--image-scale", "0"])
    assert res.exit_code == 2 and str(mesh) in res.output.replace("\n", ""), res.output
