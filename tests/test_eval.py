"""Tests of slam.eval: numbers must equal evo's (CLI and Python API) to 1e-9 relative."""

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
from slam.eval import (
    Stats,
    align_trajectory,
    associate,
    ate,
    evaluate,
    evaluate_files,
    plot_trajectories,
    rpe,
)
from slam.trajectory import Trajectory, read_tum, write_tum

RTOL = 1e-9
STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")
DATASETS = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"
SEVEN_SCENES_GT = DATASETS / "7scenes-1000" / "groundtruth.txt"


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


def test_plot_axes_choice():
    from slam.eval import _plot_axes

    rng = np.random.default_rng(1)
    pts = rng.normal(size=(100, 3)) * [3.0, 0.1, 2.0]
    assert _plot_axes(pts) == (0, 2)  # floor plane of a y-down camera
    assert _plot_axes(rng.normal(size=(100, 3)) * [0.1, 3.0, 2.0]) == (1, 2)
    assert _plot_axes(np.zeros((5, 3))) == (0, 2)
    assert _plot_axes(np.array([[0, 0, 0], [1, 1, 1.0]])) == (0, 2)  # tie -> x-z


# ----------------------------------------------------------------------------------------------
# real ground truth


@pytest.mark.realdata
def test_real_7scenes_gt_matches_evo_cli(tmp_path, evo_cli):
    if not SEVEN_SCENES_GT.is_file():
        pytest.skip(f"real dataset not available: {SEVEN_SCENES_GT} is missing")
    gt = read_tum(SEVEN_SCENES_GT)
    est = perturb(gt, seed=3, step=1, dt=0.003, sigma_t=0.005, sigma_r=0.003, drop=(100, 500))
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
