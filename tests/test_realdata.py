"""Runs on the real sequences in ../shared/datasets (skipped with the reason when absent)."""

import pytest

import slam
from tests.conftest import shared_sequence

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


def test_7scenes_revisit_is_closed():
    """The whole 1000 frames: no tracking failure, the revisit of frames ~225-275 at ~925-950 is
    detected and accepted, and the corrected trajectory closes it.

    "Closes" is checked against the loop measurements themselves: the revisit's relative poses
    (RANSAC + ICP between the two keyframes' depth) are 5-10 cm away from odometry and within
    about a centimetre after correction. Against 7-Scenes' ground truth the corrected ATE came
    out 0.0511 vs 0.0536 m and 0.0545 vs 0.0540 m in two runs: the ground truth itself
    disagrees with these loop measurements by 2-12 cm (docs/benchmarks.md, "7-Scenes: what
    limits the ATE there"), so it cannot rank trajectories that differ by a few millimetres; the
    ATE is only held to not getting worse beyond that. Since ICP uses the near depth only
    (odometry 0.0375-0.0377 m), the pose graph reads 0.0396-0.0399 m and bundle adjustment
    0.0367-0.0379 m."""
    import numpy as np

    from slam.geometry import inv_T

    seq = slam.open_sequence(shared_sequence("7scenes-1000"))
    res = slam.run(seq)
    m = res.metrics
    assert m["tracking_failures"] == 0
    assert m["ate_rmse_odometry_m"] < 0.05, m["ate_rmse_odometry_m"]  # measured 0.0375-0.0377
    revisits = [
        c
        for c in res.loop_closer.loops_json()["candidates"]
        if c["accepted"] and 900 <= c["query_frame"] <= 1000 and 200 <= c["match_frame"] <= 320
    ]
    assert revisits, [
        (c["query_frame"], c["match_frame"], c["reason"]) for c in res.loop_closer.loops_json()["candidates"]
    ]

    def disagreement_m(poses: np.ndarray) -> np.ndarray:
        out = []
        for c in revisits:
            T_match_query = inv_T(poses[c["match_frame"]]) @ poses[c["query_frame"]]
            d = inv_T(np.asarray(c["T_match_query"])) @ T_match_query
            out.append(np.linalg.norm(d[:3, 3]))
        return np.array(out)

    before = disagreement_m(res.odometry.poses)  # frame index = row: every frame is tracked
    after = disagreement_m(res.pose_graph.poses)
    assert np.median(before) > 0.03, before  # measured 5-10 cm: odometry has drifted
    assert np.median(after) < 0.015, after  # measured 0.2-1.5 cm
    # the ground truth cannot rank trajectories a few millimetres apart (see above)
    assert m["ate_rmse_pose_graph_m"] < m["ate_rmse_odometry_m"] + 0.004, m
    # bundle adjustment then moves the keyframes by the ORB evidence (colour not registered to
    # depth here, so its depth term is weak): it must not make the trajectory worse
    assert m["ate_rmse_m"] <= m["ate_rmse_pose_graph_m"] + 0.001, m


def test_cabinet_keyframes_end_to_end():
    seq = slam.open_sequence(shared_sequence("tum-fr3-cabinet-kf58"))
    res = slam.run(seq)
    m = res.metrics
    assert m["frames"] == 58
    # large inter-frame motion: RANSAC must seed ICP on a good share of the frames
    assert m["tracking_paths"].get("ransac+icp", 0) >= 10
    # tracked end to end (the target: ATE <= 0.10 m); measured 0.065 m in 3 runs
    assert m["tracking_failures"] == 0
    assert m["ate_rmse_m"] <= 0.10, m["ate_rmse_m"]


def test_cabinet_teleport_is_relocalised_not_tracked_wrong(tmp_path):
    """The cabinet with the camera jumping back from frame 48 to frame 10 (no time gap): ICP
    finds a plausible wrong pose on the box's other side (overlap 0.42, against 0.8-0.95
    before), which was accepted 1.6 m off; its overlap falling below 0.6 of the recent frames'
    makes it verified, it fails, and the frame is relocalised against the map's keyframes."""
    from slam.synthetic.damage import Damage, damage_sequence

    src = shared_sequence("tum-fr3-cabinet-kf58")
    seq = slam.open_sequence(
        damage_sequence(src, tmp_path / "tp", Damage(frames=[*range(48), *range(10, 58)], retime=True))
    )
    m = slam.run(seq).metrics
    assert m["relocalisations"] >= 1, m
    assert m["ate_rmse_m"] <= 0.10, m["ate_rmse_m"]  # measured 0.056-0.058 (clean 0.059-0.063)


def test_fr1_xyz_metrics_equal_slam_eval(tmp_path):
    """On a real TUM recording (ground truth at 100 Hz from motion capture, starting 3.5 s
    before the first image), metrics.json and `slam eval RUN_DIR --json` report the same ATE,
    RPE, drift and matched poses: both associate groundtruth.txt by nearest timestamp within
    0.01 s, as evo_ape does (metrics.json used to interpolate it at the frame times: 691 vs
    690 matched poses, RPE rot 0.920 vs 1.015 deg on the full sequence)."""
    import json

    from typer.testing import CliRunner

    from slam.api import run_sequence
    from slam.cli import app

    _, out = run_sequence(shared_sequence("tum-fr1-xyz"), tmp_path / "run", max_frames=250)
    m = json.loads((out / "metrics.json").read_text())
    cli = CliRunner().invoke(app, ["eval", str(out), "--json"])
    assert cli.exit_code == 0, cli.output
    ev = json.loads(cli.stdout)
    keys = ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "matched_poses", "drift_percent")
    assert {k: m[k] for k in keys} == {k: ev["final"][k] for k in keys}
    assert m["ate_rmse_odometry_m"] == ev["odometry"]["ate_rmse_m"]
    assert 200 < m["matched_poses"] <= m["frames_in_trajectory"] <= 250
    assert m["ate_rmse_m"] < 0.05, m["ate_rmse_m"]


def test_fr1_xyz_tracking_accuracy():
    """The first 300 frames of tum-fr1-xyz (real, motion-capture ground truth): fr1's lens
    distortion is undistorted (TUM's published model for its calibrated intrinsics), frames are
    stamped at their depth image's time and bundle adjustment refines the loop-closed keyframes.
    ICP uses the depth nearer than 2.5 m. Measured odometry 0.0127 m, final 0.0111 m (the whole
    sequence: 0.0112 / 0.0093 m); with depth up to 4 m 0.0146 / 0.0123 m; stamped at the
    colour's time 0.0172 / 0.0132 m and without undistortion 0.0191 / 0.0147 m (those two with
    7 cm ICP gating; run-to-run spread about 2%)."""
    seq = slam.open_sequence(shared_sequence("tum-fr1-xyz"))
    assert seq.calibration.has_distortion and seq.calibration.k1 == 0.2624
    cfg = slam.SlamConfig()
    cfg.dataset.max_frames = 300
    m = slam.run(seq, cfg).metrics
    assert m["tracking_failures"] == 0
    assert m["ate_rmse_odometry_m"] < 0.0145, m["ate_rmse_odometry_m"]
    assert m["ate_rmse_m"] < 0.0125, m["ate_rmse_m"]
    assert m["ate_rmse_m"] <= m["ate_rmse_pose_graph_m"], m
