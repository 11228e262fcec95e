"""The stepwise system object: frames in one at a time, and its state saved and restored."""

import json

import numpy as np
import pytest

import slam
from slam.config import config_from_dict
from slam.tools.eval import ate

FAST = {"tracking": {"downsample": 1}, "dataset": {"max_frames": 60}}


@pytest.fixture(scope="module")
def frames(synth_loop_320):
    seq = slam.open_sequence(synth_loop_320)
    return seq, [seq[i] for i in range(60)]


def test_step_and_finish_equal_run(frames):
    seq, fr = frames
    system = slam.Slam(config_from_dict(FAST), has_color=True)
    results = [system.step(f) for f in fr]
    assert all(r.ok for r in results)
    assert results[0].status.path == "init" and results[0].status.keyframe
    res = system.finish()
    assert len(res.trajectory) == 60
    # the frontend pose of each frame is what the trajectory holds (no loop in 60 frames)
    np.testing.assert_allclose(res.odometry.poses[-1], results[-1].T_world_cam)
    err = ate(seq.ground_truth, res.trajectory).rmse
    assert err < 0.005, err  # measured 0.001 m


def test_a_config_written_with_a_retired_key_still_loads(caplog):
    """A run folder's config.yaml written before ``mapping.raycast_refine`` or the colour step
    were retired has their keys: it loads, with a warning that each key is ignored."""
    tracking = {**FAST["tracking"], "colour": {"colour_step_weight": 1.0}}
    old = {**FAST, "mapping": {"raycast_refine": True}, "tracking": tracking}
    with caplog.at_level("WARNING"):
        cfg = config_from_dict(old)
    assert cfg.mapping == config_from_dict(FAST).mapping
    assert cfg.tracking.colour == config_from_dict(FAST).tracking.colour
    assert "mapping.raycast_refine' is ignored" in caplog.text
    assert "tracking.colour.colour_step_weight' is ignored" in caplog.text


def test_state_dict_round_trip_continues_the_run(frames, tmp_path):
    """Half the frames, state to a new object (through the checkpoint codec: JSON and arrays),
    the rest: the same trajectory as one uninterrupted object, to the run-to-run spread."""
    from slam.run_folder.checkpoint import decode, encode

    seq, fr = frames
    cfg = config_from_dict(FAST)
    whole = slam.Slam(cfg)
    for f in fr:
        whole.step(f)
    first = slam.Slam(cfg, spill_dir=str(tmp_path / "a"))
    for f in fr[:30]:
        first.step(f)
    tree, arrays = encode(first.state_dict())
    state = decode(json.loads(json.dumps(tree)), arrays)
    second = slam.Slam(cfg, spill_dir=str(tmp_path / "a"))
    second.load_state_dict(state)
    for f in fr[30:]:
        second.step(f)
    a, b = whole.finish(), second.finish()
    assert len(b.trajectory) == 60
    assert b.metrics["keyframes"] == a.metrics["keyframes"]
    diff = np.linalg.norm(a.trajectory.positions - b.trajectory.positions, axis=1).max()
    assert diff < 0.002, diff  # Open3D's CPU kernels are not bit-reproducible


def test_state_dict_rejects_another_version():
    state = slam.Slam().state_dict()
    state["version"] = -1
    with pytest.raises(slam.SlamError, match="version"):
        slam.Slam().load_state_dict(state)


def test_frame_without_depth_is_lost_not_fatal(frames):
    """A frame with no usable depth (covered lens) is lost, not fused, not in the trajectory;
    the first frame too (the map starts at the first frame with depth)."""
    _, fr = frames
    system = slam.Slam(config_from_dict(FAST))
    blank = slam.Frame(0, fr[0].timestamp, fr[0].color * 0, fr[0].depth_m * 0, fr[0].K)
    r0 = system.step(blank)
    assert not r0.ok and "no usable depth" in r0.status.reason
    for f in fr[1:20]:
        assert system.step(f).ok
    mid = fr[20]
    r = system.step(slam.Frame(20, mid.timestamp, mid.color, mid.depth_m * 0, mid.K))
    assert not r.ok and r.status.path == "lost"
    for f in fr[21:40]:
        assert system.step(f).ok
    res = system.finish()
    assert res.metrics["lost_frames"] == [0, 20]
    assert 20 not in res.trajectory.timestamps and len(res.trajectory) == 38
    assert res.metrics["relocalisations"] == 1


def test_depth_the_volume_cannot_use_is_lost_not_fatal(frames):
    """Depth with every other row NaN (Open3D samples every 4th pixel: it sees none) or all of
    it beyond the mapping range (a depth scale 5x off) after good frames: those frames fuse
    nothing, and the run goes on and finishes (Open3D raised "No block is touched")."""
    _, fr = frames
    system = slam.Slam(config_from_dict(FAST))
    for f in fr[:10]:
        assert system.step(f).ok
    striped = fr[10].depth_m.copy()
    striped[::2] = np.nan
    far = fr[11].depth_m * 5.0 + 10.0
    for f, depth in ((fr[10], striped), (fr[11], far)):
        system.step(slam.Frame(f.index, f.timestamp, f.color, depth, f.K))
    for f in fr[12:20]:
        system.step(f)
    res = system.finish()
    assert len(res.trajectory) >= 10 and res.mesh is not None


def test_loop_verification_trusts_features_only_where_colour_is_registered():
    """A feature's 3D point is where the feature is only where colour and depth are one camera;
    only then may the features veto ICP's loop pose (7-Scenes: two cameras)."""
    assert slam.Slam().closer.verifier.features_on_depth
    assert not slam.Slam(color_registered=False).closer.verifier.features_on_depth
    assert not slam.Slam(has_color=False).closer.verifier.features_on_depth


def test_a_state_of_another_configuration_is_refused_naming_the_difference(frames):
    """A state loaded into a Slam of another voxel size (or a run's config.yaml edited before
    --resume) went on without a word, frames lost and a segment never joined."""
    _, fr = frames
    system = slam.Slam(config_from_dict(FAST))
    for f in fr[:3]:
        system.step(f)
    state = system.state_dict()
    other = slam.Slam(config_from_dict({**FAST, "mapping": {"voxel_size_m": 0.02}}))
    with pytest.raises(slam.SlamError, match=r"mapping.voxel_size_m: 0.01 in the checkpoint, 0.02 now"):
        other.load_state_dict(state)
    same = slam.Slam(config_from_dict({**FAST, "dataset": {"max_frames": 5}}))  # where frames come from
    same.load_state_dict(state)


def test_step_of_no_frame_or_after_finish_is_a_clear_error(frames):
    """step(None) raised a TypeError about dataclasses; step() after finish() was accepted."""
    _, fr = frames
    system = slam.Slam(config_from_dict(FAST))
    with pytest.raises(slam.SlamError, match="step.. takes a slam.Frame.*got NoneType"):
        system.step(None)
    for f in fr[:3]:
        system.step(f)
    system.finish()
    with pytest.raises(slam.SlamError, match="step.. after finish.."):
        system.step(fr[3])
