"""Damaged recordings (slam.synthetic.damage) on a synthetic loop: every run ends with honest
poses, the damage is reported, and accuracy stays within the robustness issue's bounds
(ATE over the written poses <= 1.5x the clean run's + 3 mm)."""

import numpy as np
import pytest

import slam
from slam.synthetic.damage import Damage, damage_sequence
from slam.tools.eval import ate

pytestmark = pytest.mark.slow


def bound(clean_ate: float) -> float:
    return 1.5 * clean_ate + 0.003


@pytest.fixture(scope="module")
def clean(synth_loop_320):
    """The undamaged 300-frame loop (measured ATE 0.0035-0.0045 m, 2-3 loops)."""
    return slam.run(slam.open_sequence(synth_loop_320)).metrics


def run_damaged(src, tmp_path, damage: Damage):
    seq = slam.open_sequence(damage_sequence(src, tmp_path / "damaged", damage))
    return seq, slam.run(seq)


def test_blackout_frames_are_lost_and_tracking_comes_back(synth_loop_320, tmp_path, clean):
    """15 frames with zero depth and black colour mid-loop: they are lost (not fused, not in
    trajectory.txt); tracking comes back in the same map (at 320x240 the view after the
    blackout has few ORB matches to the model, so tracking may need a new map segment that
    the loop then joins: then the frames until it started are lost too)."""
    blackout = list(range(143, 158))
    _, res = run_damaged(synth_loop_320, tmp_path, Damage(blackout=blackout))
    m = res.metrics
    assert set(blackout) <= set(m["lost_frames"])
    assert len(m["lost_frames"]) <= len(blackout) + slam.SlamConfig().tracking.recovery.new_segment_after_lost
    assert not set(blackout) & set(np.round(res.trajectory.timestamps * 30).astype(int))
    assert len(m["map_segments"]) == 1  # one map in the end: relocalised or joined
    assert m["relocalisations"] + len(m["segment_joins"]) >= 1
    assert m["ate_rmse_m"] <= bound(clean["ate_rmse_m"]), (m["ate_rmse_m"], clean["ate_rmse_m"])


def test_teleport_back_is_relocalised(synth_loop_320, tmp_path, clean):
    """At frame 250 the camera jumps back to where it was 200 frames before (no time gap):
    the first frame there fails tracking and is relocalised against the keyframes of that
    place; no frame stays lost and the trajectory stays accurate."""
    frames = [*range(250), *range(50, 300)]
    seq, res = run_damaged(synth_loop_320, tmp_path, Damage(frames=frames, retime=True))
    m = res.metrics
    assert m["relocalisations"] >= 1
    reloc = [s for s in res.tracking if s.path == "reloc"]
    assert reloc and reloc[0].index == 250, [(s.index, s.reason) for s in reloc]
    assert len(m["lost_frames"]) <= 2, m["lost_frames"]
    assert m["ate_rmse_m"] <= bound(clean["ate_rmse_m"]), (m["ate_rmse_m"], clean["ate_rmse_m"])


def test_corrupt_frames_are_skipped(synth_loop_320, tmp_path, clean):
    corrupt = {
        40: "truncate",
        90: "random",
        140: "empty",
        190: "wrong_size",
        240: "color:truncate",
        241: "missing",
    }
    _, res = run_damaged(synth_loop_320, tmp_path, Damage(corrupt=corrupt))
    m = res.metrics
    assert m["frames_skipped"] == 6
    assert [s["index"] for s in m["skipped"]] == sorted(corrupt)
    errors = {s["index"]: s["error"] for s in m["skipped"]}
    assert "cannot decode depth image" in errors[40]
    assert "depth image is 160x120 but the calibration says 320x240" in errors[190]
    assert "cannot decode colour image" in errors[240]
    assert m["lost_frames"] == []
    assert m["ate_rmse_m"] <= bound(clean["ate_rmse_m"]), (m["ate_rmse_m"], clean["ate_rmse_m"])


def test_jump_into_unmapped_space_starts_a_segment_joined_at_the_revisit(
    synth_loop_320, tmp_path
):
    """100 frames removed (a 1.2 m / 117 deg jump with a time gap): the view after the jump
    is nowhere in the map, so after a few lost frames a new map segment starts; when the loop
    comes back to the start, verified revisits join it to the first segment, and the whole
    trajectory is in one frame again."""
    frames = [*range(100), *range(200, 300)]
    seq, res = run_damaged(synth_loop_320, tmp_path, Damage(frames=frames))
    m = res.metrics
    assert len(m["segment_joins"]) == 1, m["segment_joins"]
    assert len(m["map_segments"]) == 1 and m["map_segments"][0]["segments"] == [0, 1]
    n_lost = slam.SlamConfig().tracking.recovery.new_segment_after_lost - 1
    assert m["lost_frames"] == list(range(100, 100 + n_lost))
    assert m["frames_in_trajectory"] == 200 - n_lost
    # odometry alone cannot place the second segment; the joined trajectory can
    assert m["ate_rmse_odometry_m"] > 0.1
    assert m["ate_rmse_m"] < 0.015, m["ate_rmse_m"]  # measured 0.0068 m
    second = res.trajectory.timestamps >= seq.timestamp(110)
    assert ate(seq.ground_truth, slam.Trajectory(
        res.trajectory.timestamps[second], res.trajectory.poses[second]
    )).rmse < 0.02


def test_gap_in_the_lists_is_verified_not_trusted(synth_loop_320, tmp_path):
    """10 frames missing from the lists (a time gap): the frame after it is tracked in
    verification mode (gap flag), and its pose, when accepted, is right."""
    frames = [*range(100), *range(110, 160)]
    seq, res = run_damaged(synth_loop_320, tmp_path, Damage(frames=frames))
    after = next(s for s in res.tracking if s.index == 100)
    assert after.gap
    gt = seq.ground_truth
    e = ate(gt, res.trajectory)
    assert e.rmse < 0.01, e.rmse


def test_wrong_depth_scale_is_refused_with_the_fix(synth_loop_320, tmp_path):
    seq = slam.open_sequence(
        damage_sequence(synth_loop_320, tmp_path / "scale", Damage(depth_scale_factor=1000.0))
    )
    with pytest.raises(slam.CalibrationError, match="depth_scale 5000 would give"):
        slam.run(seq)
