"""Localisation against a saved map (slam.saved_map, slam.localisation): a run's map is written
with it, loads whole or not at all, and a later recording is placed in it (or, of another
place, not placed at all)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import slam
from slam.api import run_sequence
from slam.config import config_from_dict
from slam.saved_map import Map, MapError
from slam.tools import eval as slam_eval

MAP_FRAMES = 120


@pytest.fixture(scope="module")
def mapped(synth_loop_320, tmp_path_factory) -> Path:
    """The first frames of the synthetic loop mapped into a run folder (with its map)."""
    out = tmp_path_factory.mktemp("mapped") / "run"
    run_sequence(synth_loop_320, out, max_frames=MAP_FRAMES)
    return out


@pytest.fixture(scope="module")
def localised(synth_loop_320, mapped, tmp_path_factory):
    """The odd frames among those mapped, localised in the map (never seen by the map run)."""
    cfg = config_from_dict({"dataset": {"first_frame": 1, "stride": 2, "max_frames": 50}})
    out = tmp_path_factory.mktemp("localised") / "run"
    return run_sequence(synth_loop_320, out, config=cfg, map_dir=mapped)


def test_a_run_writes_a_map_that_loads_whole(mapped):
    m = Map.load(mapped)
    assert m.source == mapped and len(m.keyframes) >= 3
    assert m.volume.n_blocks > 100
    doc = json.loads((mapped / "map" / "map.json").read_text())
    assert [kf["id"] for kf in doc["keyframes"]] == [kf.id for kf in m.keyframes]
    # the keyframes stand where the fused surface puts them: their submap's rigid correction,
    # within millimetres of the final trajectory (which bends inside a submap)
    traj = slam.read_tum(mapped / "trajectory.txt")
    apart = []
    for kf in m.keyframes:
        i = int(np.argmin(np.abs(traj.timestamps - kf.timestamp)))
        apart.append(np.linalg.norm(traj.poses[i][:3, 3] - kf.T_world_cam[:3, 3]))
    assert np.median(apart) < 0.015 and max(apart) < 0.03, np.round(apart, 4)


def test_the_saved_map_renders_as_the_run_fused_it(mapped, synth_loop_320):
    """The map's surface, rendered where the map run saw frame 60 from, lies on the scene's
    true depth there (float16 storage costs nothing measurable)."""
    from slam.localisation import MapModel

    m = Map.load(mapped)
    seq = slam.open_sequence(synth_loop_320)
    frame = seq[60]
    T = seq.ground_truth.poses[60]
    traj = slam.read_tum(mapped / "trajectory.txt")
    T_run = traj.poses[int(np.argmin(np.abs(traj.timestamps - frame.timestamp)))]
    h, w = frame.depth_m.shape
    r = MapModel(m).raycast(frame.K, w, h, T_run, frustum_depth_m=frame.depth_m)
    both = (r.depth_m > 0) & (frame.depth_m > 0)
    assert both.mean() > 0.5
    err = np.abs(r.depth_m[both] - frame.depth_m[both])
    assert np.median(err) < 0.01, np.median(err)
    assert T is not None


def test_frames_the_map_has_seen_are_all_localised_in_its_frame(localised, mapped):
    result, run_dir = localised
    m = result.metrics
    assert m["map"] == str(mapped)
    assert m["frames"] == 50 and m["frames_localised"] == 50 and m["frames_not_localised"] == 0
    assert m["first_localised_frame"] == 1
    # the map run's own alignment to the ground truth, none of the localisation's
    assert m["ate_rmse_map_frame_m"] < 0.01, m["ate_rmse_map_frame_m"]
    assert m["ate_rmse_m"] <= m["ate_rmse_map_frame_m"] + 1e-9
    assert not (run_dir / "map").exists() and not (run_dir / "mesh.ply").exists()


def test_the_map_frame_error_shows_a_map_that_is_off(localised, mapped, synth_loop_320):
    """Moved by 20 cm, a localisation that is right in itself reads 20 cm in the map frame."""
    result, _ = localised
    gt, _ = slam_eval.sequence_ground_truth(synth_loop_320)
    shift = np.eye(4)
    shift[0, 3] = 0.2
    moved = slam_eval.transformed(result.trajectory, shift)
    err = slam_eval.map_frame_ate(gt, moved, mapped)
    assert abs(err - 0.2) < 0.02, err


def test_a_recording_of_another_place_is_never_localised(mapped, tmp_path):
    from slam.synthetic import SynthConfig, generate_sequence

    other = generate_sequence(
        tmp_path / "corridor",
        SynthConfig.half_resolution(frames=300, render_frames=12, scene="corridor", seed=3),
    )
    result, run_dir = run_sequence(other, tmp_path / "run", map_dir=mapped)
    m = result.metrics
    assert m["frames_localised"] == 0 and m["frames_not_localised"] == m["frames"] == 12
    assert "first_localised_frame" not in m and "ate_rmse_m" not in m
    assert (run_dir / "metrics.json").is_file() and len(result.trajectory) == 0


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_a_damaged_map_is_refused_whole(mapped, tmp_path):
    run = _copy(mapped, tmp_path / "run")
    vol = run / "map" / "volume.npz"
    data = bytearray(vol.read_bytes())
    data[len(data) // 2] ^= 0xFF
    vol.write_bytes(bytes(data))
    with pytest.raises(MapError, match="damaged"):
        Map.load(run)


def test_a_map_of_another_format_version_is_refused(mapped, tmp_path):
    run = _copy(mapped, tmp_path / "run")
    path = run / "map" / "map.json"
    doc = json.loads(path.read_text())
    doc["version"] = 99
    path.write_text(json.dumps(doc))
    with pytest.raises(MapError, match="format version 99"):
        Map.load(run)


def test_an_unfinished_run_or_a_folder_without_a_map_is_refused(mapped, tmp_path):
    run = _copy(mapped, tmp_path / "run")
    (run / "metrics.json").unlink()
    with pytest.raises(MapError, match="has not finished"):
        Map.load(run)
    run2 = _copy(mapped, tmp_path / "run2")
    import shutil

    shutil.rmtree(run2 / "map")
    with pytest.raises(MapError, match="no map"):
        Map.load(run2)


def test_a_recording_from_another_camera_is_refused_before_the_first_frame(
    mapped, synth_loop_320, tmp_path
):
    cfg = config_from_dict({"dataset": {"calibration": {"fx": 300.0}}})
    with pytest.raises(MapError, match="is not the map's"):
        run_sequence(synth_loop_320, tmp_path / "run", config=cfg, map_dir=mapped)
    assert not (tmp_path / "run" / "metrics.json").exists()


def test_slam_run_map_and_slam_eval_report_the_frames_localised(mapped, synth_loop_320, tmp_path):
    """The CLI: `slam run SEQ --map RUN --first-frame N` localises, `slam eval` says how many
    frames were placed in the map and the error in its frame; a recording the map does not
    explain ends well too (exit 0), with 0 localised."""
    from typer.testing import CliRunner

    from slam.cli import app
    from slam.synthetic import SynthConfig, generate_sequence

    runner = CliRunner()
    out = tmp_path / "loc"
    args = ["run", str(synth_loop_320), "--map", str(mapped), "--out", str(out)]
    res = runner.invoke(app, [*args, "--first-frame", "31", "--max-frames", "12", "-q"])
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames_localised"] == 12 and m["first_localised_frame"] == 31
    res = runner.invoke(app, ["eval", str(out)])
    assert res.exit_code == 0, res.output
    assert "localised    12 of 12 frames, the first at frame 31; 0 not localised" in res.output
    assert "map frame    ATE rmse" in res.output

    other = generate_sequence(
        tmp_path / "wall",
        SynthConfig.half_resolution(frames=300, render_frames=6, scene="wall", seed=4),
    )
    out2 = tmp_path / "other"
    res = runner.invoke(app, ["run", str(other), "--map", str(mapped), "--out", str(out2), "-q"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["eval", str(out2)])
    assert res.exit_code == 0, res.output
    assert "localised    0 of 6 frames; 6 not localised" in res.output
    res = runner.invoke(app, ["run", str(other), "--map", str(tmp_path / "nope"), "--out",
                              str(tmp_path / "x")])  # fmt: skip
    assert res.exit_code != 0 and "no such run folder" in res.output


def test_first_frame_starts_a_run_inside_the_sequence(synth_loop_320):
    from slam.pipeline import frame_indices

    seq = slam.open_sequence(synth_loop_320)
    cfg = config_from_dict({"dataset": {"first_frame": 31, "stride": 2, "max_frames": 3}})
    assert frame_indices(seq, cfg) == [31, 33, 35]
    with pytest.raises(slam.ConfigError, match="dataset.first_frame"):
        config_from_dict({"dataset": {"first_frame": -1}})


def test_a_localisation_only_reads_its_map(mapped, synth_loop_320, tmp_path):
    """Nothing in the map's run folder changes (two localisations may share one map)."""

    def snapshot() -> dict[str, tuple[int, int]]:
        return {
            str(p.relative_to(mapped)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(mapped.rglob("*"))
        }

    before = snapshot()
    cfg = config_from_dict({"dataset": {"first_frame": 3, "max_frames": 4}})
    result, _ = run_sequence(synth_loop_320, tmp_path / "run", config=cfg, map_dir=mapped)
    assert result.metrics["frames_localised"] == 4
    assert snapshot() == before


def test_extend_joins_a_recording_that_meets_the_map(mapped, synth_loop_320, tmp_path):
    """`--extend`: the frames after the map's (overlapping its last ones) are mapped, linked to
    the old keyframes, placed in the map's frame; the new folder holds the merged map (old and
    new keyframes, one surface) and the old folder is left as it was."""
    cfg = config_from_dict({"dataset": {"first_frame": MAP_FRAMES - 20, "max_frames": 60}})
    before = sorted(p.name for p in (mapped / "map").iterdir())
    result, run_dir = run_sequence(
        synth_loop_320, tmp_path / "ext", config=cfg, map_dir=mapped, extend=True
    )
    m = result.metrics
    assert m["extended_map"] == str(mapped) and m["map_extension"]["joined"]
    assert m["map_extension"]["links"] >= 1 and m["map_extension"]["old_map_moved_m"] < 1e-3
    assert m["ate_rmse_map_frame_m"] < 0.02, m["ate_rmse_map_frame_m"]
    merged = Map.load(run_dir)
    old = Map.load(mapped)
    assert len(merged.keyframes) > len(old.keyframes)
    assert len({kf.id for kf in merged.keyframes}) == len(merged.keyframes)
    assert merged.volume.n_blocks >= old.volume.n_blocks * 0.8
    assert (run_dir / "mesh.ply").is_file()
    assert sorted(p.name for p in (mapped / "map").iterdir()) == before


def test_extend_with_a_recording_of_another_place_keeps_it_apart(mapped, tmp_path):
    from slam.synthetic import SynthConfig, generate_sequence

    other = generate_sequence(
        tmp_path / "hall",
        SynthConfig.half_resolution(frames=300, render_frames=20, scene="hall", seed=5),
    )
    result, run_dir = run_sequence(other, tmp_path / "ext", map_dir=mapped, extend=True)
    ext = result.metrics["map_extension"]
    assert not ext["joined"] and ext["links"] == 0 and ext["pairs_tried"] > 0
    # the new run as it was: its own frame, its own map
    assert len(Map.load(run_dir).keyframes) == result.metrics["keyframes"]
