"""Tests of slam.tools.report and `slam report`: files written, numbers in report.md, missing inputs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from slam.cli import app
from slam.errors import SlamError, TrajectoryError
from slam.tools import eval as slam_eval
from slam.tools.report import (
    ERROR_PNG,
    TIMING_PNG,
    TOPVIEW_PNG,
    load_run_folder,
    loop_edges,
    write_report,
)
from slam.trajectory import Trajectory, read_tum, write_tum
from tests.conftest import SHARED_DATASETS

runner = CliRunner()
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TRACKING_COLUMNS = (
    "index,path,ok,icp_fitness,icp_rmse_m,ransac_inliers,ransac_matches,overlap,f2f_fitness,"
    "model_rejected,keyframe,ms"
).split(",")


def _pose(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def loop_gt(n: int = 240, rate: float = 30.0) -> Trajectory:
    """A closed loop on the floor (x-y) with a camera looking outwards."""
    t = np.arange(n) / rate
    a = 2 * np.pi * np.arange(n) / (n - 1)
    pos = np.stack([1.5 * np.cos(a), 1.0 * np.sin(a), 1.2 + 0.05 * np.sin(3 * a)], 1)
    R = Rotation.from_euler("zx", np.stack([a, np.full(n, -1.6)], 1)).as_matrix()
    return Trajectory(t, np.stack([_pose(R[i], pos[i]) for i in range(n)]))


def drifting(gt: Trajectory, rate_m_per_s: float, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = np.array(gt.poses)
    s = gt.timestamps - gt.timestamps[0]
    poses[:, :3, 3] += np.outer(s, [rate_m_per_s, -0.5 * rate_m_per_s, 0.0])
    poses[:, :3, 3] += rng.normal(0, 0.002, (len(gt), 3))
    return Trajectory(gt.timestamps.copy(), poses)


def make_run(
    root: Path,
    with_gt: bool = True,
    with_loops: bool = True,
    with_metrics: bool = True,
    with_tracking: bool = True,
) -> Path:
    gt = loop_gt()
    seq = root / "seq"
    seq.mkdir(parents=True, exist_ok=True)
    if with_gt:
        write_tum(seq / "groundtruth.txt", gt)
    run = root / "run"
    run.mkdir(parents=True, exist_ok=True)
    odo = drifting(gt, 0.02, seed=0)
    write_tum(run / "odometry.txt", odo)
    write_tum(run / "trajectory.txt", drifting(gt, 0.004, seed=1))
    (run / "config.yaml").write_text(f"dataset:\n  path: {seq}\n  layout: auto\n")
    if with_metrics:
        metrics = {
            "sequence": str(seq),
            "frames": len(gt),
            "frames_skipped": 0,
            "seconds": 30.0,
            "fps": 8.0,
            "stage_ms_per_frame": {"load": 5.0, "tracking": 50.0, "integration": 20.0},
            "stage_ms_total": {
                "load": 1200.0,
                "tracking": 12000.0,
                "integration": 4800.0,
                "meshing": 300.0,
                "loop_detection": 900.0,
                "optimisation": 150.0,
                "reintegration": 2500.0,
            },
            "tracking_failures": 1,
            "tracking_paths": {"init": 1, "icp": 237, "lost": 1, "ransac+icp": 1},
            "keyframes": 12,
            "peak_rss_mb": 612.5,
            "loops_accepted": 2,
            "loops_rejected": 3,
        }
        (run / "metrics.json").write_text(json.dumps(metrics))
    if with_tracking:
        with (run / "tracking.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(TRACKING_COLUMNS)
            for i in range(len(gt)):
                ok = i != 100
                w.writerow(
                    [i, "icp" if ok else "lost", ok, 0.8, 1e-5, 0, 0, 0.9, 0.7, False,
                     i % 20 == 0, 40.0 + 10 * np.sin(i / 10)]
                )  # fmt: skip
    if with_loops:
        ts = gt.timestamps
        cands = [
            {"query_frame": 230, "match_frame": 5, "query_timestamp": ts[230],
             "match_timestamp": ts[5], "score": 0.41, "accepted": True, "reason": "accepted",
             "inliers": 120, "inlier_ratio": 0.7, "icp_fitness": 0.66,
             "T_match_query": np.eye(4).tolist()},
            {"query_frame": 235, "match_frame": 2, "query_timestamp": ts[235],
             "match_timestamp": ts[2], "score": 0.39, "accepted": True, "reason": "accepted",
             "inliers": 90, "inlier_ratio": 0.6, "icp_fitness": 0.61,
             "T_match_query": np.eye(4).tolist()},
            {"query_frame": 150, "match_frame": 20, "query_timestamp": ts[150],
             "match_timestamp": ts[20], "score": 0.3, "accepted": False,
             "reason": "18 RANSAC inliers < 25", "inliers": 18, "inlier_ratio": 0.2,
             "icp_fitness": 0.0, "T_match_query": np.eye(4).tolist()},
            {"query_frame": 160, "match_frame": 30, "query_timestamp": ts[160],
             "match_timestamp": ts[30], "score": 0.3, "accepted": False,
             "reason": "7 RANSAC inliers < 25", "inliers": 7, "inlier_ratio": 0.1,
             "icp_fitness": 0.0, "T_match_query": np.eye(4).tolist()},
            {"query_frame": 170, "match_frame": 40, "query_timestamp": ts[170],
             "match_timestamp": ts[40], "score": 0.3, "accepted": False,
             "reason": "overlap 0.45 < 0.5", "inliers": 40, "inlier_ratio": 0.5,
             "icp_fitness": 0.3, "T_match_query": np.eye(4).tolist()},
        ]  # fmt: skip
        (run / "loops.json").write_text(json.dumps({"candidates": cands}))
    return run


def assert_png(path: Path, min_w: int = 400, min_h: int = 300) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    w, h = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert w >= min_w and h >= min_h, (path, w, h)
    assert len(data) > 10_000  # real content, not an empty canvas


def test_full_report(tmp_path):
    run = make_run(tmp_path)
    rep = write_report(run)
    assert rep.markdown == run / "report.md"
    assert [p.name for p in rep.plots] == [TOPVIEW_PNG, ERROR_PNG, TIMING_PNG]
    for p in rep.plots:
        assert_png(p)
    assert not list(run.glob(".*.tmp"))  # atomic writes left no temporaries
    md = rep.markdown.read_text()
    ev = slam_eval.evaluate_run(run, rpe_deltas=("1f", "1s", "1m"))
    assert rep.evaluation is not None
    assert rep.evaluation.final.ate == ev.final.ate
    # the accuracy table has both columns with evo's numbers
    assert f"| ATE rmse [m] | {ev.final.ate.rmse:.4f} | {ev.odometry.ate.rmse:.4f} |" in md
    assert ev.final.ate.rmse < ev.odometry.ate.rmse  # the "loop closure" helped
    d_f, d_o = ev.final.drift.percent, ev.odometry.drift.percent
    assert f"| drift (final position error / path length) [%] | {d_f:.3f} | {d_o:.3f} |" in md
    origin = slam_eval.drift(read_tum(run.parent / "seq" / "groundtruth.txt"),
                             read_tum(run / "trajectory.txt"), "origin")  # fmt: skip
    assert f"| drift from the start (first poses aligned) [%] | {origin.percent:.3f} |" in md
    rp, rp_odo = ev.final.rpe[0], ev.odometry.rpe[0]
    assert f"| RPE 1 frame pose pairs | {rp.pairs} | {rp_odo.pairs} |" in md
    assert f"| RPE 1 frame translation rmse [m] | {rp.trans.rmse:.4f} |" in md
    # 1 s apart: only 7 pose pairs in these 8 s, so the row is left out with the reason
    assert ev.final.rpe[1].left_out and ev.final.rpe[1].pairs == 7
    assert "| RPE 1 s (7 / 7 pose pairs, see below) | n/a | n/a |" in md
    assert "- RPE 1 s (final, odometry) is left out: only 7 pose pairs 1 s apart" in md
    # loops: counts, grouped rejection reasons, accepted table
    assert "5 loop candidates verified: **2 accepted**, 3 rejected" in md
    assert "| 7–18 RANSAC inliers < 25 | 2 | 7, 18 |" in md  # values, not templates
    assert "| overlap 0.45 < 0.5 | 1 |  |" in md
    assert "| 230 | 5 | 7.5 | 0.410 | 120 | 0.70 | 0.66 |" in md
    # tracking and timing
    assert "tracking failures: 1" in md and "lost: 1" in md
    assert "| tracking | 12.00 | 50.0 | 40 % |" in md  # 12 s of 30 s wall time, 240 frames
    assert "| **wall time** | 30.00 | 125.0 | 100 % |" in md
    for name in (TOPVIEW_PNG, ERROR_PNG, TIMING_PNG):
        assert f"({name})" in md


def test_report_without_ground_truth_or_loops(tmp_path):
    run = make_run(tmp_path, with_gt=False, with_loops=False)
    rep = write_report(run, out_dir=tmp_path / "rep")
    assert rep.evaluation is None and "--gt FILE" in rep.ground_truth_error
    assert [p.name for p in rep.plots] == [TOPVIEW_PNG, TIMING_PNG]
    for p in rep.plots:
        assert_png(p)
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "No ground truth, so no accuracy numbers" in md and ERROR_PNG not in md
    assert "2 loop closures accepted, 3 rejected (no `loops.json`" in md
    assert not (run / "report.md").exists()  # written to out_dir only


def test_report_with_only_a_trajectory(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "trajectory.txt", loop_gt(60))
    with pytest.raises(SlamError, match="no metrics.json"):  # not a complete run
        write_report(run)
    (run / "metrics.json").write_text("{}")
    rep = write_report(run)
    assert [p.name for p in rep.plots] == [TOPVIEW_PNG]
    assert_png(rep.plots[0])
    md = rep.markdown.read_text()
    assert "No loop closure in this run" in md and "No run statistics or tracking.csv" in md


def test_report_gt_override_and_errors(tmp_path):
    run = make_run(tmp_path, with_gt=False)
    gt_file = tmp_path / "gt.txt"
    write_tum(gt_file, loop_gt())
    rep = write_report(run, gt_path=gt_file)
    assert rep.evaluation is not None and rep.evaluation.ground_truth == str(gt_file)
    assert len(rep.plots) == 3
    with pytest.raises(TrajectoryError, match="not found"):
        write_report(run, gt_path=tmp_path / "missing.txt")  # an explicit --gt must exist
    with pytest.raises(SlamError, match="run folder not found"):
        write_report(tmp_path / "nope")
    (run / "loops.json").write_text("{not json")
    with pytest.raises(SlamError, match="loops.json: not valid JSON"):
        write_report(run)


def test_loop_edges_by_timestamp(tmp_path):
    run = load_run_folder(make_run(tmp_path))
    assert run.loops is not None and len(run.accepted_loops) == 2
    edges = loop_edges(run.trajectory, run.accepted_loops)
    assert len(edges) == 2
    np.testing.assert_array_equal(edges[0][0], run.trajectory.positions[230])
    np.testing.assert_array_equal(edges[0][1], run.trajectory.positions[5])
    shifted = [dict(c, query_timestamp=c["query_timestamp"] + 5.0) for c in run.accepted_loops]
    assert loop_edges(run.trajectory, shifted) == []  # not in the trajectory: skipped
    assert loop_edges(run.trajectory, [{"query_frame": 1}]) == []  # no timestamps
    assert run.tracking is not None and run.tracking["ms"].shape == (240,)
    assert run.tracking["ok"][100] == 0 and run.tracking["path"][100] == "lost"


def test_report_cli(tmp_path):
    run = make_run(tmp_path)
    res = runner.invoke(app, ["report", str(run)])
    assert res.exit_code == 0, res.output
    assert f"wrote {run / 'report.md'}" in res.stdout
    assert (run / TOPVIEW_PNG).is_file() and (run / ERROR_PNG).is_file()
    res = runner.invoke(app, ["report", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "run folder not found" in res.output


@pytest.mark.realdata
def test_report_on_7scenes_ground_truth(tmp_path):
    seq = SHARED_DATASETS / "7scenes-300"
    if not (seq / "groundtruth.txt").is_file():
        pytest.skip(f"real dataset not available: {seq} is missing")
    gt = read_tum(seq / "groundtruth.txt")
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "odometry.txt", drifting(gt, 0.003, seed=3))
    write_tum(run / "trajectory.txt", drifting(gt, 0.0005, seed=4))
    (run / "config.yaml").write_text(f"dataset:\n  path: {seq}\n")
    (run / "metrics.json").write_text("{}")
    rep = write_report(run)
    assert rep.evaluation is not None and rep.evaluation.final.matched_poses == len(gt)
    assert rep.evaluation.ground_truth == str(seq / "groundtruth.txt")
    for p in rep.plots:
        assert_png(p)


def test_rejection_reasons_show_values():
    from slam.tools.report import rejection_reasons

    cands = [{"reason": f"{n} RANSAC inliers < 25"} for n in (6, 23, 12, 23)]
    cands += [{"reason": "ICP fitness 0.27 < 0.3"}, {"reason": "overlap 0.41 < 0.5"}]
    cands += [{"reason": "overlap 0.48 < 0.5"}, {"reason": "inconsistent with odometry: 0.12 m"}]
    rows = rejection_reasons(cands, max_values=3)
    assert rows[0] == ("6–23 RANSAC inliers < 25", 4, "6, 12, 23, ... (1 more)")
    assert ("overlap 0.41–0.48 < 0.5", 2, "0.41, 0.48") in rows
    assert ("ICP fitness 0.27 < 0.3", 1, "") in rows
    assert ("inconsistent with odometry: 0.12 m", 1, "") in rows


def test_trajectory_plot_names_its_plane(tmp_path):
    """TUM-like ground truth (z up, motion in x-y): the plot is the x-y plane and says so."""
    run = make_run(tmp_path)
    md = write_report(run).markdown.read_text()
    assert "Trajectories in the x-y plane of the ground truth (horizontal: x, vertical: y;" in md


def test_a_run_too_short_to_evaluate_is_not_said_to_have_no_ground_truth(tmp_path):
    """A 1-frame run of a sequence with ground truth: the report says the ground truth was
    found but cannot evaluate one pose (it said "no ground truth")."""
    from slam.trajectory import read_tum

    run = make_run(tmp_path, with_loops=False)
    for name in ("trajectory.txt", "odometry.txt"):
        t = read_tum(run / name)
        write_tum(run / name, Trajectory(t.timestamps[:1], t.poses[:1]))
    rep = write_report(run)
    assert rep.evaluation is None and "1 pose" in (rep.ground_truth_error or "")
    text = rep.markdown.read_text()
    assert "- ground truth: found, but no evaluation" in text and "No ground truth" not in text
    res = CliRunner().invoke(app, ["report", str(run)])
    assert res.exit_code == 0 and "no accuracy: " in res.output and "no ground truth" not in res.output
