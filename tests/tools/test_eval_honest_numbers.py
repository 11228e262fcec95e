"""Issue 19, item 12: RPE rows say how many pose pairs they rest on and rows with too few are
left out with the reason (library, JSON, `slam eval`, `slam report`); too few poses to evaluate
advise what helps, not an option the command does not have. Item 15: `slam eval --plot` and
`slam report` draw one run in the same plane."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from slam.cli import app
from slam.errors import TrajectoryError
from slam.tools import eval as slam_eval
from slam.tools import plots, report
from slam.tools.eval import MIN_RPE_PAIRS, evaluate_full, rpe
from slam.trajectory import Trajectory, write_tum

runner = CliRunner()


def _line(n: int, rate: float = 30.0, seed: int = 0, noise: float = 0.0) -> Trajectory:
    """``n`` poses moving 2 cm a frame along x with a little y/z wiggle."""
    rng = np.random.default_rng(seed)
    t = 100.0 + np.arange(n) / rate
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = 0.02 * np.arange(n)
    poses[:, 1, 3] = 0.05 * np.sin(np.arange(n) / 5.0)
    poses[:, 2, 3] = 0.03 * np.cos(np.arange(n) / 7.0)
    poses[:, :3, 3] += rng.normal(0, noise, (n, 3))
    return Trajectory(t, poses)


def test_rpe_rows_with_too_few_pairs_are_left_out_with_the_reason():
    gt, est = _line(30), _line(30, seed=1, noise=0.002)
    res = evaluate_full(gt, est, rpe_deltas=["1f", "10f", "1s", "0.5m"])
    one, ten, sec, half = res.rpe
    assert one.pairs == 29 and one.trans is not None and one.left_out is None
    # 10 frames apart in 30 poses: 2 pairs, too few; evo's statistics are kept, the row is
    # left out with the reason
    assert ten.pairs == 2 and ten.left_out and (ten.trans, ten.rot) == rpe(gt, est, delta=10)
    assert "only 2 pose pairs 10 frames apart" in ten.left_out
    assert f"at least {MIN_RPE_PAIRS}" in ten.left_out and "smaller delta" in ten.left_out
    assert half.left_out and 0 < half.pairs < MIN_RPE_PAIRS
    # 1 s on a 1 s trajectory: no pair at all
    assert sec.trans is None and sec.pairs == 0 and sec.left_out == sec.error
    # JSON: the count and the reason, no numbers
    d = json.loads(json.dumps(res.as_dict()))
    assert d["rpe"][0]["pairs"] == 29 and d["rpe"][0]["trans_m"]["rmse"] == one.trans.rmse
    assert d["rpe"][0]["error"] is None
    assert d["rpe"][1] == {
        "delta": 10.0, "unit": "frames", "pairs": 2, "trans_m": None, "rot_deg": None,
        "error": ten.left_out,
    }  # fmt: skip
    # shown however few pairs on request (min_rpe_pairs=1)
    raw = evaluate_full(gt, est, rpe_deltas=["10f"], min_rpe_pairs=1)
    assert raw.rpe[0].left_out is None and raw.as_dict()["rpe"][0]["trans_m"] is not None


def test_headline_rpe_of_a_short_trajectory_is_none():
    """Fewer than 11 poses: fewer than 10 consecutive pairs, so no headline RPE."""
    gt, est = _line(10), _line(10, seed=1, noise=0.002)
    h = slam_eval.evaluate(gt, est)
    assert h["rpe_trans_rmse_m"] is None and h["rpe_rot_rmse_deg"] is None
    assert h["ate_rmse_m"] > 0
    assert slam_eval.evaluate(_line(11), _line(11, seed=1))["rpe_trans_rmse_m"] is not None


def test_eval_cli_prints_pair_counts_and_reasons(tmp_path):
    write_tum(tmp_path / "gt.txt", _line(30))
    write_tum(tmp_path / "est.txt", _line(30, seed=1, noise=0.002))
    res = runner.invoke(
        app,
        ["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"),
         "--rpe-delta", "1f", "--rpe-delta", "10f"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "(29 pairs)" in res.output
    assert "RPE 10 frames      n/a: only 2 pose pairs 10 frames apart" in res.output


def _fake_run(root: Path, gt: Trajectory, final: Trajectory, odometry: Trajectory) -> Path:
    """A complete run folder (as far as `slam eval` and `slam report` read one)."""
    seq, run = root / "seq", root / "run"
    seq.mkdir(parents=True)
    run.mkdir()
    write_tum(seq / "groundtruth.txt", gt)
    write_tum(run / "trajectory.txt", final)
    write_tum(run / "odometry.txt", odometry)
    (run / "config.yaml").write_text(f"dataset:\n  path: {seq}\n  layout: auto\n")
    (run / "metrics.json").write_text(json.dumps({"sequence": str(seq), "frames": len(final)}))
    return run


def test_run_folder_eval_and_report_show_pairs_and_reasons(tmp_path):
    gt = _line(60)
    run = _fake_run(tmp_path, gt, _line(60, seed=1, noise=0.002), _line(60, seed=2, noise=0.004))
    res = runner.invoke(app, ["eval", str(run), "--rpe-delta", "1f", "--rpe-delta", "10f"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert any(ln.split() == ["RPE", "1", "frame", "pose", "pairs", "59", "59"] for ln in lines)
    assert any(ln.split() == ["RPE", "10", "frames", "pose", "pairs", "5", "5"] for ln in lines)
    assert any(ln.split()[:7] == ["RPE", "10", "frames", "trans", "rmse", "[m]", "n/a"]
               for ln in lines)  # fmt: skip
    assert "RPE 10 frames n/a (final, odometry): only 5 pose pairs 10 frames apart" in res.output
    js = runner.invoke(app, ["eval", str(run), "--json", "--rpe-delta", "1f", "--rpe-delta", "10f"])
    d = json.loads(js.stdout)
    assert [r["pairs"] for r in d["final"]["rpe"]] == [59, 5]
    assert d["final"]["rpe"][1]["trans_m"] is None and "only 5" in d["final"]["rpe"][1]["error"]
    # the report: default deltas 1f, 1s (2 pairs in 2 s), 1 m (1.2 m of path: 1 pair)
    rep = report.write_report(run)
    md = rep.markdown.read_text()
    assert "| RPE 1 frame pose pairs | 59 | 59 |" in md
    assert "| RPE 1 s (1 / 1 pose pairs, see below) | n/a | n/a |" in md
    assert "- RPE 1 s (final, odometry) is left out: only 1 pose pair 1 s apart" in md


def test_too_few_poses_do_not_advise_a_larger_tolerance():
    """`slam run --max-frames 1` evaluated one pose: the advice was `--t-max-diff`, an option
    `slam run` does not have and that cannot help; now it says what is missing."""
    gt = _line(30)
    one = Trajectory(gt.timestamps[:1], gt.poses[:1])
    with pytest.raises(TrajectoryError) as exc:
        slam_eval.evaluate(gt, one)
    msg = str(exc.value)
    assert "the estimate has only 1 pose" in msg and "at least 3" in msg
    assert "t-max-diff" not in msg and "max_diff" not in msg
    with pytest.raises(TrajectoryError, match="the ground truth has only 2 poses"):
        slam_eval.ate(Trajectory(gt.timestamps[:2], gt.poses[:2]), gt)
    # timestamps that do not associate: the tolerance advice names the commands that have it
    far = Trajectory(gt.timestamps + 0.016, gt.poses)  # 16 ms off, frames 33 ms apart
    with pytest.raises(TrajectoryError, match=r"`slam eval` / `slam report` --t-max-diff"):
        slam_eval.ate(gt, far)


def test_run_of_one_frame_does_not_advise_t_max_diff(tmp_path):
    from slam.synthetic import SynthConfig, generate_sequence

    seq = generate_sequence(
        tmp_path / "seq", SynthConfig.half_resolution(frames=300, render_frames=2)
    )
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(seq), "--out", str(out), "--max-frames", "1"])
    assert res.exit_code == 0, res.output
    assert "--t-max-diff" not in res.output
    assert "the estimate has only 1 pose" in res.output
    m = json.loads((out / "metrics.json").read_text())
    assert "t-max-diff" not in m["evaluation_error"] and "only 1 pose" in m["evaluation_error"]


# ----------------------------------------------------------------------------------------------
# item 15: one projection for `slam eval --plot` and `slam report`


def _partial_run(root: Path) -> Path:
    """Ground truth that moves in x-z for the first 4 s (the run) and then 10 m along y: the
    whole ground truth extends most in x-y, the part that was run in x-z."""
    n1, n2 = 120, 120
    t = np.arange(n1 + n2) / 30.0
    pos = np.zeros((n1 + n2, 3))
    a = np.linspace(0, 2 * np.pi, n1)
    pos[:n1] = np.stack([1.0 * np.cos(a), 0.01 * np.sin(3 * a), 0.6 * np.sin(a)], 1)
    pos[n1:] = pos[n1 - 1] + np.outer(np.linspace(0, 1, n2), [0.5, 10.0, 0.0])
    poses = np.tile(np.eye(4), (n1 + n2, 1, 1))
    poses[:, :3, 3] = pos
    gt = Trajectory(t, poses)
    est = Trajectory(t[:n1].copy(), poses[:n1].copy())
    est.poses[:, :3, 3] += np.random.default_rng(0).normal(0, 0.003, (n1, 3))
    return _fake_run(root, gt, est, est)


def test_eval_plot_and_report_draw_a_run_in_the_same_plane(tmp_path, monkeypatch):
    run = _partial_run(tmp_path)
    planes: dict[str, plots.PlotPlane] = {}
    real = plots.plot_trajectories

    def spy(who):
        def plot(*args, **kw):
            planes[who] = real(*args, **kw)
            return planes[who]

        return plot

    monkeypatch.setattr(plots, "plot_trajectories", spy("eval"))  # `slam eval` imports it late
    res = runner.invoke(app, ["eval", str(run), "--plot", str(tmp_path / "eval.png")])
    assert res.exit_code == 0, res.output
    monkeypatch.setattr(report, "plot_trajectories", spy("report"))
    res = runner.invoke(app, ["report", str(run)])
    assert res.exit_code == 0, res.output
    ev, rep = planes["eval"], planes["report"]
    assert (ev.u_label, ev.v_label, ev.name) == (rep.u_label, rep.v_label, rep.name)
    np.testing.assert_array_equal(ev.u, rep.u)
    np.testing.assert_array_equal(ev.v, rep.v)
    # the plane of the run's time (x-z), not of the whole ground truth (x-y)
    assert rep.name == "x-z plane"
    assert "horizontal: x, vertical: z" in (run / "report.md").read_text()
    gt = slam_eval.load_run_ground_truth(run)[0]
    assert plots.plot_plane(gt.positions).name == "x-y plane"
    assert (tmp_path / "eval.png").stat().st_size > 1000


def test_trajectory_plane_uses_the_ground_truth_during_the_trajectories():
    gt = _line(100)
    part = Trajectory(gt.timestamps[10:20].copy(), gt.poses[10:20].copy())
    during = plots.ground_truth_during(gt, [part], tol=0.01)
    np.testing.assert_array_equal(during.timestamps, gt.timestamps[10:20])
    # no overlap (fewer than 2 poses in the span): the whole ground truth
    away = Trajectory(gt.timestamps[:3] + 1000.0, gt.poses[:3])
    assert len(plots.ground_truth_during(gt, [away])) == 100
    plane = plots.trajectory_plane(gt, {"part": part})
    assert plane.name == plots.plot_plane(during.positions).name
    assert (
        plots.trajectory_plane(None, {"part": part}).name == plots.plot_plane(part.positions).name
    )
