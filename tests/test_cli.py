import json

import numpy as np
import yaml
from typer.testing import CliRunner

from slam.cli import app
from slam.data.calibration import read_calibration_yaml
from slam.geometry import exp_se3
from slam.tools import eval as slam_eval
from slam.trajectory import Trajectory, read_tum, write_tum

runner = CliRunner()


def flat(text: str) -> str:
    """CLI output with rich's line wrapping undone."""
    return " ".join(text.split())


def test_eval_json_matches_library(tmp_path):
    rng = np.random.default_rng(0)
    t = np.arange(100) / 30.0
    gt = Trajectory(
        t,
        np.stack(
            [exp_se3(np.r_[0.0, 0.01 * i, 0.0, 0.02 * i, 0.0, 0.001 * i**1.5]) for i in range(100)]
        ),
    )
    est = Trajectory(t, np.stack([p @ exp_se3(rng.normal(0, 0.003, 6)) for p in gt.poses]))
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    res = runner.invoke(
        app,
        [
            "eval",
            str(tmp_path / "gt.txt"),
            str(tmp_path / "est.txt"),
            "--json",
            "--plot",
            str(tmp_path / "p.png"),
        ],
    )
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    lib = slam_eval.evaluate(read_tum(tmp_path / "gt.txt"), read_tum(tmp_path / "est.txt"))
    for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "matched_poses"):
        assert out[key] == lib[key]
    assert (tmp_path / "p.png").stat().st_size > 1000
    assert f"wrote {tmp_path / 'p.png'}" in res.stderr  # stdout holds the JSON alone


def test_eval_reports_unassociated_timestamps(tmp_path):
    gt = Trajectory(np.arange(10.0), np.tile(np.eye(4), (10, 1, 1)))
    est = Trajectory(np.arange(10.0) + 100.0, np.tile(np.eye(4), (10, 1, 1)))
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    res = runner.invoke(app, ["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt")])
    assert res.exit_code == 2
    assert "--t-max-diff" in res.output


def test_run_on_missing_folder_is_a_clear_error(tmp_path):
    res = runner.invoke(app, ["run", str(tmp_path / "nope"), "--out", str(tmp_path / "run")])
    assert res.exit_code == 2
    assert "not found" in res.output


def test_synth_writes_a_sequence(tmp_path):
    seq = tmp_path / "seq"
    res = runner.invoke(app, ["synth", str(seq), "--frames", "3", "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert len(list((seq / "depth").iterdir())) == 3
    assert (seq / "calibration.yaml").is_file() and (seq / "groundtruth.txt").is_file()


def test_synth_renders_the_scene_kinds_at_a_speed(tmp_path):
    from slam.trajectory import read_tum

    steps = {}
    for speed in ("1", "2"):
        seq = tmp_path / f"corridor-{speed}"
        args = ["synth", str(seq), "--frames", "3", "--scene", "corridor", "--speed", speed]
        res = runner.invoke(app, args)
        assert res.exit_code == 0, res.output
        P = read_tum(seq / "groundtruth.txt").poses
        steps[speed] = P[1][0, 3] - P[0][0, 3]  # along the corridor
    # the corridor walked at twice the rate: twice the first step along it
    np.testing.assert_allclose(steps["2"], 2 * steps["1"], rtol=0.05)
    res = runner.invoke(app, ["synth", str(tmp_path / "x"), "--scene", "garden"])
    assert res.exit_code != 0 and "scene" in res.output


def test_synth_takes_colour_off_the_depths_instant(tmp_path):
    seq = tmp_path / "seq"
    res = runner.invoke(app, ["synth", str(seq), "--frames", "3", "--color-offset-ms", "10"])
    assert res.exit_code == 0, res.output

    def stamps(name):
        lines = (seq / name).read_text().splitlines()
        return np.array([float(ln.split()[0]) for ln in lines if not ln.startswith("#")])

    offsets = stamps("rgb.txt") - stamps("depth.txt")
    assert np.all(np.abs(offsets) <= 0.010 + 1e-6) and np.any(offsets != 0)
    res = runner.invoke(app, ["synth", str(tmp_path / "x"), "--color-offset-ms", "30"])
    assert res.exit_code != 0 and "color_offset_ms" in res.output


def test_synth_records_a_handheld_kinect(tmp_path):
    seq = tmp_path / "seq"
    args = ["synth", str(seq), "--frames", "3", "--scene", "desk", "--handheld", "fr1_desk2"]
    res = runner.invoke(app, [*args, "--kinect"])
    assert res.exit_code == 0, res.output
    assert json.loads((seq / ".complete").read_text())["kinect"] is True
    res = runner.invoke(app, ["synth", str(tmp_path / "x"), "--handheld", "fr9_nowhere"])
    assert res.exit_code != 0 and "fr1_desk2" in res.output  # the recordings are named


def test_run_writes_the_run_folder(tmp_path):
    from slam.synthetic import SynthConfig, generate_sequence

    seq = generate_sequence(
        tmp_path / "seq",
        SynthConfig.half_resolution(frames=300, render_frames=8),
    )
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(seq), "--out", str(out), "--max-frames", "6"])
    assert res.exit_code == 0, res.output
    assert "ATE RMSE" in res.stdout
    assert len(read_tum(out / "trajectory.txt")) == 6
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 6 and metrics["tracking_failures"] == 0
    assert metrics["ate_rmse_m"] < 0.02
    for name in ("odometry.txt", "mesh.ply", "config.yaml", "tracking.csv"):
        assert (out / name).is_file()


def test_bad_config_is_a_clear_error(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("tracking:\n  no_such_key: 1\n")
    res = runner.invoke(
        app, ["run", str(tmp_path), "--config", str(cfg), "--out", str(tmp_path / "r")]
    )
    assert res.exit_code == 2
    assert "no_such_key" in res.output


def test_run_with_calibration_from_the_config(tmp_path):
    """A sequence folder with no calibration.yaml and no freiburg in its name runs when the
    config gives the intrinsics in dataset.calibration, as the error message says."""
    from slam.synthetic import SynthConfig, generate_sequence

    seq = generate_sequence(
        tmp_path / "mycam", SynthConfig.half_resolution(frames=300, render_frames=5)
    )
    calib = read_calibration_yaml(seq / "calibration.yaml")
    (seq / "calibration.yaml").unlink()
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(seq), "--out", str(out), "--max-frames", "4"])
    assert res.exit_code == 2
    assert "dataset.calibration" in flat(res.output)
    cfg = tmp_path / "calib.yaml"
    cfg.write_text(yaml.safe_dump({"dataset": {"calibration": calib.to_dict()}}))
    res = runner.invoke(
        app, ["run", str(seq), "--out", str(out), "--max-frames", "4", "--config", str(cfg)]
    )
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 4 and metrics["tracking_failures"] == 0


def test_console_is_quiet_by_default_verbose_and_quiet(tmp_path):
    """Default: the summary line, no INFO lines (a real run printed ~440: one per loop and
    graph update); -v: the per-event lines; -q: nothing at all."""
    from slam.synthetic import SynthConfig, generate_sequence

    seq = generate_sequence(
        tmp_path / "seq", SynthConfig.half_resolution(frames=300, render_frames=6)
    )
    args = ["run", str(seq), "--max-frames", "5", "--overwrite", "--out", str(tmp_path / "r")]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "INFO" not in res.output
    assert "5 frames" in res.stdout and "ATE RMSE" in res.stdout
    res = runner.invoke(app, [*args, "-v"])
    assert res.exit_code == 0, res.output
    assert "INFO" in res.output and "DEBUG" not in res.output
    res = runner.invoke(app, [*args, "--quiet"])
    assert res.exit_code == 0, res.output
    assert res.output == ""
    res = runner.invoke(app, ["eval", str(tmp_path / "r")])
    assert res.exit_code == 0 and "INFO" not in res.output


def test_demo_generation_is_its_own_step(tmp_path, monkeypatch):
    """`slam run` with no sequence generates the demo once, as a step of its own that says so
    (its progress bar used to sit at 0/? while the sequence was generated)."""
    from slam import demo
    from slam.synthetic import SynthConfig

    monkeypatch.setenv("SLAM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setitem(
        demo.BUILTIN, "demo", SynthConfig.half_resolution(frames=300, render_frames=5)
    )
    args = ["run", "--max-frames", "4", "--overwrite", "--out", str(tmp_path / "r")]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    text = flat(res.output)
    assert "generating the synthetic demo sequence" in text and "generating" in text
    assert demo.is_generated()
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "generating" not in res.output


def test_parallel_run_options_that_cannot_work_are_clear_errors(tmp_path):
    seq, out = str(tmp_path / "seq"), str(tmp_path / "run")
    res = runner.invoke(app, ["run", seq, "--out", out, "--ray", "auto"])
    assert res.exit_code != 0 and "give --workers N" in res.output
    res = runner.invoke(app, ["run", seq, "--out", out, "--workers", "2", "--rerun", "x.rrd"])
    assert res.exit_code != 0 and "no --rerun recording" in res.output
    res = runner.invoke(app, ["run", seq, "--out", out, "--workers", "0"])
    assert res.exit_code != 0
    assert not (tmp_path / "run").exists()
