"""Tests of slam.tools.eval: numbers must equal evo's (CLI and Python API) to 1e-9 relative."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from evo.core import metrics, sync
from evo.main_ape import ape as evo_ape
from evo.main_rpe import rpe as evo_rpe
from evo.tools import file_interface
from scipy.spatial.transform import Rotation

from slam.errors import TrajectoryError
from slam.tools.eval import (
    Stats,
    align_trajectory,
    ape_per_pose,
    associate,
    ate,
    drift,
    evaluate,
    evaluate_files,
    evaluate_full,
    evaluate_run,
    plot_trajectories,
    rpe,
)
from slam.trajectory import Trajectory, read_tum, write_tum

RTOL = 1e-9
STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")
DATASETS = Path(__file__).resolve().parents[2].parent / "shared" / "datasets"
SEVEN_SCENES_GT = DATASETS / "7scenes-300" / "groundtruth.txt"


# ----------------------------------------------------------------------------------------------
# helpers


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def smooth_gt(n: int = 600, rate: float = 100.0, t0: float = 1000.0) -> Trajectory:
    """A smooth hand-held-like path: an ellipse with bobbing height and turning, tilting camera."""
    t = t0 + np.arange(n) / rate
    s = t - t0
    pos = np.stack(
        [1.5 * np.cos(0.5 * s), 0.2 * np.sin(1.3 * s) + 0.05 * s, 1.0 * np.sin(0.5 * s)], axis=1
    )
    euler = np.stack([0.5 * s, 0.2 * np.sin(0.7 * s), 0.1 * np.cos(0.9 * s)], axis=1)
    R = Rotation.from_euler("yxz", euler).as_matrix()
    return Trajectory(t, np.stack([_pose(R[i], pos[i]) for i in range(n)]))


RIGID = _pose(Rotation.from_rotvec([0.1, -0.35, 0.2]).as_matrix(), [0.4, -0.25, 1.1])


def perturb(
    gt: Trajectory,
    seed: int = 0,
    step: int = 3,
    dt: float = 0.004,
    sigma_t: float = 0.01,
    sigma_r: float = 0.005,
    offset: np.ndarray = RIGID,
    drop: tuple[int, ...] = (7, 8, 9, 40),
) -> Trajectory:
    """Subsample, shift timestamps by ``dt``, add pose noise and a rigid offset, drop some poses."""
    rng = np.random.default_rng(seed)
    idx = np.delete(np.arange(0, len(gt), step), list(drop))
    poses = []
    for i in idx:
        noise = _pose(
            Rotation.from_rotvec(rng.normal(0, sigma_r, 3)).as_matrix(), rng.normal(0, sigma_t, 3)
        )
        poses.append(offset @ gt.poses[i] @ noise)
    return Trajectory(gt.timestamps[idx] + dt, np.stack(poses))


def transformed(traj: Trajectory, T: np.ndarray, scale: float = 1.0) -> Trajectory:
    poses = np.array(traj.poses)
    poses[:, :3, 3] *= scale
    return Trajectory(traj.timestamps.copy(), T @ poses)


def assert_stats_equal(ours: Stats, theirs: dict, rtol: float = RTOL) -> None:
    for k in STAT_KEYS:
        assert getattr(ours, k) == pytest.approx(float(theirs[k]), rel=rtol, abs=1e-15), k


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("traj")
    gt = smooth_gt()
    write_tum(d / "gt.txt", gt)
    write_tum(d / "est.txt", perturb(gt))
    return d / "gt.txt", d / "est.txt"


@pytest.fixture(scope="module")
def evo_cli(tmp_path_factory):
    """Run an evo CLI tool, return the stats of its --save_results zip."""
    bindir = Path(sys.executable).parent
    home = tmp_path_factory.mktemp("evo_home")  # evo writes ~/.evo/settings.json on first run
    out = tmp_path_factory.mktemp("evo_out")
    counter = [0]

    def run(tool: str, *args: str) -> dict:
        exe = bindir / tool
        if not exe.exists():
            pytest.skip(f"{tool} not found next to {sys.executable}")
        counter[0] += 1
        res_zip = out / f"res{counter[0]}.zip"
        env = {**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"}
        proc = subprocess.run(
            [str(exe), *map(str, args), "--save_results", str(res_zip), "--no_warnings"],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 0, f"{tool} failed:\n{proc.stdout}\n{proc.stderr}"
        with zipfile.ZipFile(res_zip) as z:
            return json.loads(z.read("stats.json"))

    return run


def _evo_load_synced(gt_path: Path, est_path: Path, max_diff: float = 0.01):
    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    return sync.associate_trajectories(ref, est, max_diff=max_diff)


# ----------------------------------------------------------------------------------------------
# (1)-(2) identical to the evo command line tools


def test_ate_matches_evo_ape_cli(files, evo_cli):
    gt_path, est_path = files
    gt, est = read_tum(gt_path), read_tum(est_path)
    theirs = evo_cli("evo_ape", "tum", gt_path, est_path, "-a")
    ours = ate(gt, est)
    assert_stats_equal(ours, theirs)
    assert 0.005 < ours.rmse < 0.05  # noise level, the rigid offset has been aligned away
    theirs_sim3 = evo_cli("evo_ape", "tum", gt_path, est_path, "-as")
    assert_stats_equal(ate(gt, est, correct_scale=True), theirs_sim3)


def test_rpe_matches_evo_rpe_cli(files, evo_cli):
    gt_path, est_path = files
    gt, est = read_tum(gt_path), read_tum(est_path)
    common = ("tum", gt_path, est_path, "-a", "--delta", "1", "--delta_unit", "f")
    theirs_t = evo_cli("evo_rpe", *common, "-r", "trans_part")
    theirs_r = evo_cli("evo_rpe", *common, "-r", "angle_deg")
    ours_t, ours_r = rpe(gt, est, delta=1, delta_unit="frames")
    assert_stats_equal(ours_t, theirs_t)
    assert_stats_equal(ours_r, theirs_r)
    assert ours_r.rmse > 0.1  # degrees, not radians (noise is ~0.5 deg per pair)


# ----------------------------------------------------------------------------------------------
# (3) identical to evo's Python API


@pytest.mark.parametrize(
    "align,correct_scale", [(True, False), (True, True), (False, False), (False, True)]
)
def test_ate_matches_evo_api(files, align, correct_scale):
    ref, est = _evo_load_synced(*files)
    res = evo_ape(
        ref, est, metrics.PoseRelation.translation_part, align=align, correct_scale=correct_scale
    )
    ours = ate(read_tum(files[0]), read_tum(files[1]), align=align, correct_scale=correct_scale)
    assert_stats_equal(ours, res.stats)


@pytest.mark.parametrize(
    "delta,unit,evo_unit,align",
    [
        (1, "frames", metrics.Unit.frames, True),
        (5, "frames", metrics.Unit.frames, True),
        (1, "frames", metrics.Unit.frames, False),
        (0.25, "meters", metrics.Unit.meters, True),
    ],
)
def test_rpe_matches_evo_api(files, delta, unit, evo_unit, align):
    gt, est = read_tum(files[0]), read_tum(files[1])
    ours_t, ours_r = rpe(gt, est, delta=delta, delta_unit=unit, align=align)
    for relation, ours in (
        (metrics.PoseRelation.translation_part, ours_t),
        (metrics.PoseRelation.rotation_angle_deg, ours_r),
    ):
        ref, est_e = _evo_load_synced(*files)
        res = evo_rpe(
            ref, est_e, relation, delta=delta, delta_unit=evo_unit, all_pairs=False, align=align
        )
        assert_stats_equal(ours, res.stats)


def test_associate_matches_evo(files):
    gt, est = read_tum(files[0]), read_tum(files[1])
    gt_before, est_before = copy.deepcopy(gt), copy.deepcopy(est)
    g, e = associate(gt, est)
    ref, est_e = _evo_load_synced(*files)
    assert len(g) == len(e) == ref.num_poses == len(est)  # every estimate pose finds its GT
    np.testing.assert_array_equal(g.timestamps, ref.timestamps)
    np.testing.assert_array_equal(e.timestamps, est_e.timestamps)
    np.testing.assert_allclose(g.poses, np.array(ref.poses_se3), atol=1e-12)
    assert np.all(np.abs(g.timestamps - e.timestamps) <= 0.01)
    # inputs untouched by association and alignment
    ate(gt, est, correct_scale=True)
    rpe(gt, est)
    evaluate(gt, est)
    np.testing.assert_array_equal(gt.poses, gt_before.poses)
    np.testing.assert_array_equal(est.poses, est_before.poses)
    np.testing.assert_array_equal(est.timestamps, est_before.timestamps)


def test_rpe_seconds_equals_frames_for_uniform_rate():
    gt = smooth_gt(n=300, rate=30.0, t0=0.0)
    est = perturb(gt, step=1, drop=(), dt=0.002, offset=np.eye(4))
    t_s, r_s = rpe(gt, est, delta=1.0, delta_unit="seconds")
    t_f, r_f = rpe(gt, est, delta=30, delta_unit="frames")
    assert t_s == t_f
    assert r_s == r_f
    t_s2, _ = rpe(gt, est, delta=0.5, delta_unit="s")
    assert t_s2 == rpe(gt, est, delta=15, delta_unit="f")[0]


def test_rpe_bad_arguments(files):
    gt, est = read_tum(files[0]), read_tum(files[1])
    with pytest.raises(TrajectoryError, match="delta_unit"):
        rpe(gt, est, delta_unit="furlongs")
    with pytest.raises(TrajectoryError, match="positive"):
        rpe(gt, est, delta=0)
    with pytest.raises(TrajectoryError, match="whole number"):
        rpe(gt, est, delta=1.5, delta_unit="frames")
    with pytest.raises(TrajectoryError, match="longer than"):
        rpe(gt, est, delta=1000.0, delta_unit="seconds")
    with pytest.raises(TrajectoryError, match="RPE failed"):
        rpe(gt, est, delta=10_000, delta_unit="frames")


# ----------------------------------------------------------------------------------------------
# (4) sanity: identical, rigidly moved, scaled


def test_identical_trajectory_gives_zero():
    gt = smooth_gt()
    for align in (True, False):
        s = ate(gt, gt, align=align)
        assert s.rmse < 1e-12 and s.max < 1e-12
        t, r = rpe(gt, gt, align=align)
        assert t.rmse < 1e-12 and r.rmse < 1e-5  # arccos near 1 -> ~1e-6 deg of round-off


def test_rigid_offset_aligned_away_or_measured():
    gt = smooth_gt()
    moved = transformed(gt, RIGID)
    assert ate(gt, moved, align=True).rmse < 1e-9
    assert rpe(gt, moved, align=False)[0].rmse < 1e-9  # RPE is invariant to a rigid offset
    offset = np.array([0.1, -0.2, 0.3])
    shifted = transformed(gt, _pose(np.eye(3), offset))
    s = ate(gt, shifted, align=False)
    expected = float(np.linalg.norm(offset))
    for k in STAT_KEYS:
        if k == "std":
            assert s.std < 1e-12
        else:
            assert getattr(s, k) == pytest.approx(expected, rel=1e-12)
    assert ate(gt, shifted, align=True).rmse < 1e-9


def test_scale_needs_sim3():
    gt = smooth_gt()
    scaled = transformed(gt, RIGID, scale=2.0)
    assert ate(gt, scaled, align=True).rmse > 0.1
    assert ate(gt, scaled, align=True, correct_scale=True).rmse < 1e-9


def test_align_trajectory_maps_whole_estimate():
    gt = smooth_gt()
    moved = transformed(gt, RIGID, scale=0.5)
    back = align_trajectory(gt, moved, correct_scale=True)
    assert len(back) == len(moved)
    np.testing.assert_allclose(back.poses, gt.poses, atol=1e-9)


# ----------------------------------------------------------------------------------------------
# evaluate


def test_evaluate_dict(files):
    gt, est = read_tum(files[0]), read_tum(files[1])
    res = evaluate(gt, est)
    assert set(res) == {
        "ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_std_m", "ate_max_m",
        "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "matched_poses", "drift_percent",
        "path_length_m",
    }  # fmt: skip
    a = ate(gt, est)
    t, r = rpe(gt, est)
    assert res["ate_rmse_m"] == a.rmse and res["ate_mean_m"] == a.mean
    assert res["ate_median_m"] == a.median and res["ate_std_m"] == a.std
    assert res["ate_max_m"] == a.max
    assert res["rpe_trans_rmse_m"] == t.rmse and res["rpe_rot_rmse_deg"] == r.rmse
    assert res["matched_poses"] == len(est) and isinstance(res["matched_poses"], int)
    g, _ = associate(gt, est)
    assert res["path_length_m"] == pytest.approx(g.path_length(), rel=1e-12)
    assert 0 < res["drift_percent"] < 5
    assert evaluate_files(files[0], files[1]) == res
    sim3 = evaluate_files(files[0], files[1], correct_scale=True, max_diff=0.02)
    assert sim3["ate_rmse_m"] == ate(gt, est, correct_scale=True, max_diff=0.02).rmse


def test_drift_percent():
    gt = smooth_gt()
    n = len(gt)
    poses = np.array(gt.poses)
    d = np.array([0.03, 0.0, -0.04])  # linearly growing error, 5 cm at the end
    poses[:, :3, 3] += np.linspace(0, 1, n)[:, None] * d
    est = Trajectory(gt.timestamps, poses)
    res = evaluate(gt, est, align=False)
    assert res["drift_percent"] == pytest.approx(0.05 / gt.path_length() * 100, rel=1e-9)
    assert res["path_length_m"] == pytest.approx(gt.path_length(), rel=1e-12)
    assert evaluate(gt, gt)["drift_percent"] < 1e-9


# ----------------------------------------------------------------------------------------------
# (5) association failures


def test_no_association_raises_with_counts():
    gt = smooth_gt()
    est = Trajectory(gt.timestamps + 500.0, gt.poses)
    with pytest.raises(TrajectoryError) as exc:
        ate(gt, est)
    msg = str(exc.value)
    assert "0 of 600" in msg
    assert "1000.000000" in msg and "1500.000000" in msg  # both timestamp ranges
    assert "max_diff" in msg and "--t-max-diff" in msg
    assert "do not overlap" in msg


def test_too_few_matches_raises():
    gt = smooth_gt(n=100)
    # two stamps match, the other five lie after the end of the ground truth
    est = Trajectory(gt.timestamps[:2].tolist() + [2000.0 + i for i in range(5)], gt.poses[:7])
    with pytest.raises(TrajectoryError, match=r"only 2 of 7 possible"):
        evaluate(gt, est)
    # clocks offset by 15 ms at 30 Hz: nothing within evo's default 10 ms, all within 20 ms
    gt30 = smooth_gt(n=100, rate=30.0)
    late = Trajectory(gt30.timestamps + 0.015, gt30.poses)
    with pytest.raises(TrajectoryError, match="0 of 100"):
        associate(gt30, late)
    g, e = associate(gt30, late, max_diff=0.02)
    assert len(g) == len(e) == 100


def test_invalid_inputs():
    gt = smooth_gt(n=50)
    bad = Trajectory(gt.timestamps, gt.poses.copy())
    bad.poses[10, 0, 3] = np.nan
    with pytest.raises(TrajectoryError, match="non-finite pose"):
        ate(gt, bad)
    with pytest.raises(TrajectoryError, match="empty"):
        ate(gt, Trajectory(np.zeros(0), np.zeros((0, 4, 4))))
    still = Trajectory(gt.timestamps, np.tile(np.eye(4), (50, 1, 1)))
    with pytest.raises(TrajectoryError, match="cannot align"):
        ate(gt, still)
    with pytest.raises(TrajectoryError, match="max_diff"):
        associate(gt, gt, max_diff=-1)


# ----------------------------------------------------------------------------------------------
# (6) plotting


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_plot_trajectories(tmp_path):
    gt = smooth_gt()
    est = perturb(gt)
    out = tmp_path / "plots" / "traj.png"
    plot_trajectories(
        out, gt, {"estimate": est, "aligned": align_trajectory(gt, est)}, title="test"
    )
    assert out.stat().st_size > 1000
    w, h = _png_size(out)
    assert w > 100 and h > 100
    assert [p.name for p in out.parent.iterdir()] == ["traj.png"]  # no temp file left
    plot_trajectories(tmp_path / "no_gt.png", None, {"estimate": est})
    assert (tmp_path / "no_gt.png").stat().st_size > 1000
    with pytest.raises(TrajectoryError, match="nothing to plot"):
        plot_trajectories(tmp_path / "empty.png", None, {})


# ----------------------------------------------------------------------------------------------
# real ground truth


@pytest.mark.realdata
def test_real_7scenes_gt_matches_evo_cli(tmp_path, evo_cli):
    if not SEVEN_SCENES_GT.is_file():
        pytest.skip(f"real dataset not available: {SEVEN_SCENES_GT} is missing")
    gt = read_tum(SEVEN_SCENES_GT)
    est = perturb(gt, seed=3, step=1, dt=0.003, sigma_t=0.005, sigma_r=0.003, drop=(100, 250))
    est_path = tmp_path / "est.txt"
    write_tum(est_path, est)
    est = read_tum(est_path)
    ours_ate = ate(gt, est)
    assert_stats_equal(ours_ate, evo_cli("evo_ape", "tum", SEVEN_SCENES_GT, est_path, "-a"))
    ours_t, ours_r = rpe(gt, est)
    common = ("tum", SEVEN_SCENES_GT, est_path, "-a", "--delta", "1", "--delta_unit", "f")
    assert_stats_equal(ours_t, evo_cli("evo_rpe", *common, "-r", "trans_part"))
    assert_stats_equal(ours_r, evo_cli("evo_rpe", *common, "-r", "angle_deg"))
    assert evaluate(gt, est)["matched_poses"] == len(gt) - 2


# ----------------------------------------------------------------------------------------------
# (7) drift, RPE per second / per metre, evaluate_full: equal to evo's library


def _evo_ape_errors(ref, est, align: bool = True, correct_scale: bool = False) -> np.ndarray:
    res = evo_ape(
        ref, est, metrics.PoseRelation.translation_part, align=align, correct_scale=correct_scale
    )
    return np.asarray(res.np_arrays["error_array"])


@pytest.mark.parametrize(
    "alignment,align,correct_scale",
    [("se3", True, False), ("sim3", True, True), ("scale", False, True), ("none", False, False)],
)
def test_drift_matches_evo(files, alignment, align, correct_scale):
    gt, est = read_tum(files[0]), read_tum(files[1])
    d = drift(gt, est, alignment=alignment)
    ref, est_e = _evo_load_synced(*files)
    errors = _evo_ape_errors(ref, est_e, align, correct_scale)
    assert d.final_error_m == pytest.approx(errors[-1], rel=RTOL)
    assert d.path_length_m == pytest.approx(ref.path_length, rel=RTOL)
    assert d.percent == pytest.approx(100 * errors[-1] / ref.path_length, rel=RTOL)
    assert d.final_timestamp == est_e.timestamps[-1] and d.alignment == alignment


def test_drift_origin_matches_evo_align_origin(files):
    gt, est = read_tum(files[0]), read_tum(files[1])
    d = drift(gt, est, alignment="origin")
    ref, est_e = _evo_load_synced(*files)
    est_e.align_origin(ref)
    res = evo_ape(ref, est_e, metrics.PoseRelation.translation_part, align=False)
    err = np.asarray(res.np_arrays["error_array"])
    assert err[0] < 1e-12  # first poses made identical
    assert d.final_error_m == pytest.approx(err[-1], rel=RTOL)
    # a pure drift that grows linearly: origin alignment sees all of it
    g = smooth_gt()
    poses = np.array(g.poses)
    poses[:, :3, 3] += np.linspace(0, 1, len(g))[:, None] * np.array([0.0, 0.06, 0.08])
    dr = drift(g, Trajectory(g.timestamps, poses), alignment="origin")
    assert dr.final_error_m == pytest.approx(0.1, rel=1e-9)
    assert dr.percent == pytest.approx(10.0 / g.path_length(), rel=1e-9)
    with pytest.raises(TrajectoryError, match="unknown drift alignment"):
        drift(g, g, alignment="umeyama")


def _ids_at_least(stamps: np.ndarray, delta: float) -> list[int]:
    ids = [0]
    for i in range(1, len(stamps)):
        if stamps[i] - stamps[ids[-1]] >= delta - 1e-6:
            ids.append(i)
    return ids


@pytest.mark.parametrize("delta", [0.25, 1.0])
def test_rpe_seconds_matches_evo_on_selected_pairs(files, delta):
    """evo has no time delta: the pairs are consecutive poses >= delta s apart (on the estimate's
    timestamps, which here are irregular: subsampled, with dropped poses), then evo's RPE."""
    gt, est = read_tum(files[0]), read_tum(files[1])
    ours_t, ours_r = rpe(gt, est, delta=delta, delta_unit="seconds")
    ref, est_e = _evo_load_synced(*files)
    ids = _ids_at_least(np.asarray(est_e.timestamps), delta)
    gaps = np.diff(np.asarray(est_e.timestamps)[ids])
    assert np.all(gaps >= delta - 1e-6) and np.all(gaps < delta + 0.05)
    ref.reduce_to_ids(ids)
    est_e.reduce_to_ids(ids)
    for relation, ours in (
        (metrics.PoseRelation.translation_part, ours_t),
        (metrics.PoseRelation.rotation_angle_deg, ours_r),
    ):
        res = evo_rpe(
            copy.deepcopy(ref),
            copy.deepcopy(est_e),
            relation,
            delta=1,
            delta_unit=metrics.Unit.frames,
            all_pairs=False,
            align=True,
        )
        assert_stats_equal(ours, res.stats)


def test_parse_delta():
    from slam.tools.eval import parse_delta

    assert parse_delta("1f") == (1.0, "frames")
    assert parse_delta("10 frames") == (10.0, "frames")
    assert parse_delta("0.5s") == (0.5, "seconds")
    assert parse_delta("2 metres") == (2.0, "metres")
    assert parse_delta("1m") == (1.0, "metres")
    assert parse_delta("3") == (3.0, "frames")
    assert parse_delta(5) == (5.0, "frames")
    assert parse_delta((0.25, "meters")) == (0.25, "metres")
    with pytest.raises(TrajectoryError, match="e.g. '1f'"):
        parse_delta("one metre")
    with pytest.raises(TrajectoryError, match="delta_unit"):
        parse_delta("1 furlong")


def test_evaluate_full_equals_separate_metrics(files):
    gt, est = read_tum(files[0]), read_tum(files[1])
    for correct_scale in (False, True):
        res = evaluate_full(
            gt, est, correct_scale=correct_scale, rpe_deltas=["1f", "5f", "0.5s", "0.25m"]
        )
        assert res.alignment == ("sim3" if correct_scale else "se3")
        assert res.ate == ate(gt, est, correct_scale=correct_scale)
        expected = [(1, "frames"), (5, "frames"), (0.5, "seconds"), (0.25, "metres")]
        for r, (delta, unit) in zip(res.rpe, expected):
            assert (r.delta, r.unit) == (delta, unit)
            t, rot = rpe(gt, est, delta=delta, delta_unit=unit, correct_scale=correct_scale)
            assert r.trans == t and r.rot == rot and r.pairs > 0
        align = "sim3" if correct_scale else "se3"
        assert res.drift == drift(gt, est, alignment=align)
    assert res.rpe[0].pairs == len(est) - 1  # consecutive 1-frame pairs
    assert [r.label for r in res.rpe] == ["1 frame", "5 frames", "0.5 s", "0.25 m"]
    # origin drift on request, ATE untouched
    res_o = evaluate_full(gt, est, drift_alignment="origin")
    assert res_o.drift == drift(gt, est, alignment="origin")
    assert res_o.ate == ate(gt, est)
    # headline == evaluate(); as_dict is JSON with the detail
    assert evaluate_full(gt, est).headline() == evaluate(gt, est)
    d = json.loads(json.dumps(res.as_dict()))
    assert d["ate"]["rmse"] == res.ate.rmse and d["ate_min_m"] == res.ate.min
    assert d["rpe"][3]["unit"] == "metres" and d["rpe"][3]["trans_m"]["max"] == res.rpe[3].trans.max
    assert d["drift"]["percent"] == res.drift.percent and d["alignment"] == "sim3"
    assert d["scale"] != 1.0 and abs(d["scale"] - 1.0) < 0.05


def test_evaluate_full_records_impossible_rpe_delta(files):
    gt, est = read_tum(files[0]), read_tum(files[1])
    res = evaluate_full(gt, est, rpe_deltas=["1f", "1000s", "500m"])
    assert res.rpe[0].trans is not None
    for r in res.rpe[1:]:
        assert r.trans is None and r.rot is None and r.pairs == 0
    assert "longer than" in res.rpe[1].error
    assert "RPE failed" in res.rpe[2].error
    d = res.as_dict()
    assert d["rpe"][1]["trans_m"] is None and d["rpe"][1]["error"]


def test_ape_per_pose(files):
    gt, est = read_tum(files[0]), read_tum(files[1])
    t, err = ape_per_pose(gt, est)
    ref, est_e = _evo_load_synced(*files)
    np.testing.assert_array_equal(t, est_e.timestamps)
    np.testing.assert_allclose(err, _evo_ape_errors(ref, est_e), rtol=RTOL, atol=1e-15)
    assert float(np.sqrt(np.mean(err**2))) == pytest.approx(ate(gt, est).rmse, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# (8) run folders


def _make_run(run: Path, seq: Path | None, final: Trajectory, odometry: Trajectory | None):
    run.mkdir(parents=True, exist_ok=True)
    write_tum(run / "trajectory.txt", final)
    if odometry is not None:
        write_tum(run / "odometry.txt", odometry)
    if seq is not None:
        (run / "config.yaml").write_text(f"dataset:\n  path: {seq}\n  layout: auto\n")
    (run / "metrics.json").write_text(json.dumps({"frames": len(final), "loops_accepted": 3}))
    return run


def test_evaluate_run_reports_final_and_odometry(tmp_path):
    gt = smooth_gt(n=300, rate=30.0, t0=0.0)
    seq = tmp_path / "seq"
    seq.mkdir()
    write_tum(seq / "groundtruth.txt", gt)
    odo = perturb(gt, seed=1, step=1, drop=(), dt=0.0, sigma_t=0.01)
    final = perturb(gt, seed=2, step=1, drop=(), dt=0.0, sigma_t=0.003)
    run = _make_run(tmp_path / "run", seq, final, odo)
    ev = evaluate_run(run, rpe_deltas=["1f", "1s"])
    g = read_tum(seq / "groundtruth.txt")
    assert ev.ground_truth == str(seq / "groundtruth.txt")
    assert ev.final.ate == ate(g, read_tum(run / "trajectory.txt"))
    assert ev.odometry.ate == ate(g, read_tum(run / "odometry.txt"))
    assert ev.final.ate.rmse < ev.odometry.ate.rmse
    assert not ev.odometry_identical and ev.loops_accepted == 3
    assert ev.final.rpe[1].trans == rpe(g, read_tum(run / "trajectory.txt"), 1, "seconds")[0]
    d = json.loads(json.dumps(ev.as_dict()))
    assert d["ate_rmse_change_m"] == pytest.approx(ev.final.ate.rmse - ev.odometry.ate.rmse)
    assert d["final"]["ate_rmse_m"] == ev.final.ate.rmse
    # odometry identical to the final trajectory: evaluated once
    run2 = _make_run(tmp_path / "run2", seq, final, final)
    ev2 = evaluate_run(run2)
    assert ev2.odometry_identical and ev2.odometry is ev2.final
    # --gt wins over config; no odometry.txt
    run3 = _make_run(tmp_path / "run3", None, final, None)
    ev3 = evaluate_run(run3, gt_path=seq / "groundtruth.txt")
    assert ev3.odometry is None and ev3.final.ate == ev.final.ate


def test_evaluate_run_7scenes_ground_truth_from_loader(tmp_path):
    """No groundtruth.txt: the sequence loader's ground truth (7-Scenes *.pose.txt)."""
    gt = smooth_gt(n=40, rate=30.0, t0=0.0)
    seq = tmp_path / "seq-01"
    seq.mkdir()
    for i, T in enumerate(gt.poses):
        (seq / f"frame-{i:06d}.depth.png").write_bytes(b"")  # never decoded here
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", T)
    est = perturb(gt, seed=4, step=1, drop=(), dt=0.0)
    run = _make_run(tmp_path / "run", seq, est, est)
    ev = evaluate_run(run)
    assert "SevenScenesSequence" in ev.ground_truth
    assert ev.final.matched_poses == 40
    assert ev.final.ate.rmse == pytest.approx(ate(gt, read_tum(run / "trajectory.txt")).rmse)


def test_evaluate_run_errors(tmp_path):
    from slam.errors import RunFolderError

    with pytest.raises(RunFolderError, match="run folder not found"):
        evaluate_run(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunFolderError, match="no metrics.json"):
        evaluate_run(tmp_path / "empty")
    (tmp_path / "empty" / "metrics.json").write_text("{}")
    with pytest.raises(TrajectoryError, match="no trajectory.txt"):
        evaluate_run(tmp_path / "empty")
    gt = smooth_gt(n=50)
    run = _make_run(tmp_path / "run", None, gt, gt)
    (run / "metrics.json").write_text("{}")  # names no sequence either
    with pytest.raises(TrajectoryError, match="--gt FILE"):
        evaluate_run(run)
    (run / "config.yaml").write_text(f"dataset:\n  path: {tmp_path / 'moved'}\n")
    with pytest.raises(TrajectoryError, match=r"does not exist here.*--gt FILE"):
        evaluate_run(run)
    # timestamps that do not associate: counts and the CLI option in the message
    seq = tmp_path / "seq"
    seq.mkdir()
    write_tum(seq / "groundtruth.txt", Trajectory(gt.timestamps + 100.0, gt.poses))
    (run / "config.yaml").write_text(f"dataset:\n  path: {seq}\n")
    with pytest.raises(TrajectoryError, match=r"only 0 of 50 .*--t-max-diff"):
        evaluate_run(run)


@pytest.mark.realdata
def test_real_7scenes_drift_rpe_units_match_evo(tmp_path):
    if not SEVEN_SCENES_GT.is_file():
        pytest.skip(f"real dataset not available: {SEVEN_SCENES_GT} is missing")
    gt = read_tum(SEVEN_SCENES_GT)
    est = perturb(gt, seed=5, step=1, dt=0.002, sigma_t=0.004, sigma_r=0.002, drop=(10, 200))
    est_path = tmp_path / "est.txt"
    write_tum(est_path, est)
    est = read_tum(est_path)
    files = (SEVEN_SCENES_GT, est_path)
    res = evaluate_full(gt, est, correct_scale=True, rpe_deltas=["0.5m", "10f"])
    ref, est_e = _evo_load_synced(*files)
    sim3 = evo_ape(
        ref, est_e, metrics.PoseRelation.translation_part, align=True, correct_scale=True
    )
    assert_stats_equal(res.ate, sim3.stats)
    for r, unit in zip(res.rpe, (metrics.Unit.meters, metrics.Unit.frames)):
        ref, est_e = _evo_load_synced(*files)
        theirs = evo_rpe(
            ref, est_e, metrics.PoseRelation.translation_part, delta=r.delta, delta_unit=unit,
            all_pairs=False, align=True, correct_scale=True,
        )  # fmt: skip
        assert_stats_equal(r.trans, theirs.stats)
        assert r.pairs == len(theirs.np_arrays["error_array"])
    ref, est_e = _evo_load_synced(*files)
    errors = _evo_ape_errors(ref, est_e, True, True)
    assert res.drift.final_error_m == pytest.approx(errors[-1], rel=RTOL)
    assert res.drift.path_length_m == pytest.approx(ref.path_length, rel=RTOL)


@pytest.mark.realdata
def test_real_run_folder_eval_matches_evo_cli(tmp_path, evo_cli):
    """A run folder on 7scenes-300: `evaluate_run` == evo_ape / evo_rpe on the same files."""
    if not SEVEN_SCENES_GT.is_file():
        pytest.skip(f"real dataset not available: {SEVEN_SCENES_GT} is missing")
    gt = read_tum(SEVEN_SCENES_GT)
    odo = perturb(gt, seed=6, step=1, dt=0.0, sigma_t=0.006, sigma_r=0.003, drop=(), offset=RIGID)
    final = perturb(gt, seed=7, step=1, dt=0.0, sigma_t=0.002, sigma_r=0.001, drop=())
    run = _make_run(tmp_path / "run", SEVEN_SCENES_GT.parent, final, odo)
    ev = evaluate_run(run)
    for res, name in ((ev.final, "trajectory.txt"), (ev.odometry, "odometry.txt")):
        assert_stats_equal(res.ate, evo_cli("evo_ape", "tum", SEVEN_SCENES_GT, run / name, "-a"))
        theirs = evo_cli(
            "evo_rpe", "tum", SEVEN_SCENES_GT, run / name, "-a", "--delta", "1",
            "--delta_unit", "f", "-r", "trans_part",
        )  # fmt: skip
        assert_stats_equal(res.rpe[0].trans, theirs)


# ----------------------------------------------------------------------------------------------
# (9) `slam eval` command line


def _cli():
    from typer.testing import CliRunner

    from slam.cli import app

    return CliRunner(), app


def test_cli_eval_run_dir(tmp_path):
    runner, app = _cli()
    gt = smooth_gt(n=300, rate=30.0, t0=0.0)
    seq = tmp_path / "seq"
    seq.mkdir()
    write_tum(seq / "groundtruth.txt", gt)
    odo = perturb(gt, seed=1, step=1, drop=(), dt=0.0, sigma_t=0.01)
    final = perturb(gt, seed=2, step=1, drop=(), dt=0.0, sigma_t=0.003)
    run = _make_run(tmp_path / "run", seq, final, odo)
    res = runner.invoke(app, ["eval", str(run), "--json", "--plot", str(tmp_path / "p.png")])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    ev = evaluate_run(run, rpe_deltas=["1f", "1s", "1m"])
    assert out["final"]["ate_rmse_m"] == ev.final.ate.rmse
    assert out["odometry"]["ate_rmse_m"] == ev.odometry.ate.rmse
    assert out["final"]["ate"]["median"] == ev.final.ate.median
    assert [r["unit"] for r in out["final"]["rpe"]] == ["frames", "seconds", "metres"]
    assert out["odometry"]["rpe"][0]["trans_m"]["rmse"] == ev.odometry.rpe[0].trans.rmse
    # 1 s / 1 m apart: 9 / 7 pairs in these 10 s, too few: left out with the count and reason
    assert [r["pairs"] for r in out["odometry"]["rpe"]] == [r.pairs for r in ev.odometry.rpe]
    assert out["odometry"]["rpe"][2]["trans_m"] is None and out["odometry"]["rpe"][2]["error"]
    assert out["final"]["drift"]["percent"] == ev.final.drift.percent
    assert out["loops_accepted"] == 3 and out["odometry_identical"] is False
    assert (tmp_path / "p.png").stat().st_size > 1000
    # text: one table, final and odometry side by side
    res = runner.invoke(app, ["eval", str(run), "--rpe-delta", "2f", "--drift-align", "origin"])
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    assert any(line.split()[-2:] == ["final", "odometry"] for line in lines)
    ev2 = evaluate_run(run, rpe_deltas=["2f"], drift_alignment="origin")
    (ate_line,) = [line for line in lines if line.startswith("ATE rmse [m]")]
    assert ate_line.split()[-2:] == [f"{ev2.final.ate.rmse:.4f}", f"{ev2.odometry.ate.rmse:.4f}"]
    (drift_line,) = [line for line in lines if line.startswith("drift [%]")]
    assert drift_line.split()[-1] == f"{ev2.odometry.drift.percent:.3f}"
    assert any(line.startswith("RPE 2 frames trans rmse [m]") for line in lines)


def test_cli_eval_files_json_has_detail(files):
    runner, app = _cli()
    # 6 s of trajectory: 1 s / 1 m deltas would have too few pairs (left out)
    deltas = ["--rpe-delta", "1f", "--rpe-delta", "0.5s", "--rpe-delta", "0.25m"]
    res = runner.invoke(app, ["eval", str(files[0]), str(files[1]), "--json", *deltas])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    gt, est = read_tum(files[0]), read_tum(files[1])
    assert {k: out[k] for k in evaluate(gt, est)} == evaluate(gt, est)
    assert out["rpe"][1]["trans_m"]["rmse"] == rpe(gt, est, 0.5, "seconds")[0].rmse
    assert out["rpe"][2]["trans_m"]["rmse"] == rpe(gt, est, 0.25, "metres")[0].rmse
    res = runner.invoke(app, ["eval", str(files[0]), str(files[1]), "--correct-scale"])
    assert res.exit_code == 0 and "alignment sim3" in res.stdout
    assert f"rmse {ate(gt, est, correct_scale=True).rmse:.4f}" in res.stdout


def test_cli_eval_argument_errors(tmp_path, files):
    def _flat(text: str) -> str:  # rich wraps long error lines
        return " ".join(text.split())

    runner, app = _cli()
    res = runner.invoke(app, ["eval", str(files[0])])
    assert res.exit_code == 2 and "is not a folder" in _flat(res.output)
    res = runner.invoke(app, ["eval", str(tmp_path), str(files[1])])
    assert res.exit_code == 2 and "is a run folder" in _flat(res.output)
    res = runner.invoke(app, ["eval", str(tmp_path)])
    assert res.exit_code == 2 and "no metrics.json" in _flat(res.output)
    res = runner.invoke(app, ["eval", str(files[0]), str(files[1]), "--rpe-delta", "x"])
    assert res.exit_code == 2 and "cannot read RPE delta" in _flat(res.output)


def test_ground_truth_rows_with_nan_are_left_out_and_counted(tmp_path, caplog):
    """A motion-capture dropout written as NaN gave no ATE at all; ground truth is now
    evaluated on its finite rows, with a warning saying how many were left out. An estimate
    with NaN is still an error."""
    from slam.tools.ground_truth import sequence_ground_truth
    from slam.trajectory import TrajectoryError, read_tum

    lines = [f"{t:.2f} {0.01 * t:.4f} 0 0 0 0 0 1" for t in range(20)]
    lines[7] = "7.00 nan nan nan 0 0 0 1"
    lines[12] = "12.00 0 0 0 nan nan nan nan"
    (tmp_path / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    gt, _ = sequence_ground_truth(tmp_path)
    assert len(gt) == 18
    assert "2 rows with non-finite values left out (lines 8, 13)" in caplog.text
    with pytest.raises(TrajectoryError, match=":8: non-finite value"):
        read_tum(tmp_path / "groundtruth.txt")
