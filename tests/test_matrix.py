"""The scene matrix's CI version (benchmarks/matrix.py --small): two tiny synthetic rows where
depth alone is blind along a direction (a textured wall filling the view, a corridor) run in
fresh processes and land in one table and a JSON."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name: str):
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


@pytest.mark.slow
def test_the_small_matrix_runs_and_the_wall_does_not_slide(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SLAM_CACHE_DIR", str(tmp_path / "cache"))
    matrix = _load("matrix")
    out = tmp_path / "matrix.json"
    assert matrix.main(["--small", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert set(rows) == {"wall-x1-s0-half", "corridor-x1-s0-half"}
    wall = rows["wall-x1-s0-half"]
    assert "error" not in wall and wall["tracking_failures"] == 0
    # 40 frames of a 40 deg/s pan 1.3-2.8 m from a bare textured wall (2.3 cm a frame):
    # depth alone slid 4.7 cm a frame (median; odometry ATE 0.21 m); colour holds it
    assert wall["ate_rmse_odometry_m"] < 0.1  # 0.044 m: the first frames, from rest, still slip
    assert wall["step_err_median_m"] < 0.005
    assert wall["colour_frames"] > 20  # depth is blind along the wall: colour holds it
    assert "| wall-x1-s0-half |" in capsys.readouterr().out
    # --compare reads two result files and counts the rows that got worse
    text, worse = matrix.compare(json.loads(out.read_text()), json.loads(out.read_text()))
    assert worse == 0 and "wall-x1-s0-half" in text


def test_a_video_rate_real_sequence_runs_again_on_every_third_frame(tmp_path, monkeypatch):
    monkeypatch.setenv("SLAM_CACHE_DIR", str(tmp_path / "cache"))
    matrix = _load("matrix")
    seq = tmp_path / "shared" / "seq"
    (seq / "rgb").mkdir(parents=True)
    for name in ("rgb", "depth"):
        entries = [f"{i / 30:.6f} {name}/{i}.png" for i in range(10)]
        (seq / f"{name}.txt").write_text("# a comment\n" + "\n".join(entries) + "\n")
    (seq / "groundtruth.txt").write_text("0 0 0 0 0 0 0 1\n")
    assert matrix._median_interval_s(seq / "depth.txt") == pytest.approx(1 / 30, abs=1e-5)
    out = matrix.strided_copy(seq, 3)
    assert out.parent == tmp_path / "cache" / "matrix" / "real" and out.name == "seq-x3"
    depth = (out / "depth.txt").read_text().splitlines()
    # the comments, then frames 0, 3, 6 and 9
    assert depth == ["# a comment"] + [f"{i / 30:.6f} depth/{i}.png" for i in (0, 3, 6, 9)]
    assert (out / "rgb").is_symlink() and (out / "rgb").resolve() == (seq / "rgb").resolve()
    assert (out / "groundtruth.txt").read_text() == "0 0 0 0 0 0 0 1\n"
    assert matrix.strided_copy(seq, 3) == out  # made once
    # a sequence already far apart in time (the cabinet's keyframes) gets no faster copy
    monkeypatch.setattr(matrix, "SHARED", tmp_path / "shared")
    assert [r.name for r in matrix.real_rows()] == ["seq", "seq-x3"]
    slow = tmp_path / "shared" / "slow"
    slow.mkdir()
    (slow / "depth.txt").write_text("\n".join(f"{i * 0.66:.2f} d/{i}.png" for i in range(5)))
    (slow / "groundtruth.txt").write_text("0 0 0 0 0 0 0 1\n")
    assert [r.name for r in matrix.real_rows()] == ["seq", "slow", "seq-x3"]


def test_compare_judges_a_change_by_the_spread_measured_in_other_runs():
    matrix = _load("matrix")
    old = {"rows": {"hall": {"ate_rmse_odometry_m": 0.0100, "step_err_max_m": 0.010}}}
    new = {"rows": {"hall": {"ate_rmse_odometry_m": 0.0120, "step_err_max_m": 0.014}}}
    # assumed spread (10% + 0.5 mm): both columns got worse
    assert matrix.compare(old, new)[1] == 1
    # three runs of the same code ranged 9 mm in odometry and 6 mm in worst step: spread
    runs = {"hall": {"ate_rmse_odometry_m_range": 0.009, "step_err_max_m_range": 0.006}}
    spreads = matrix.measured_spreads([{"rows": runs}])
    assert spreads == {"hall": {"ate_rmse_odometry_m": 0.009, "step_err_max_m": 0.006}}
    text, worse = matrix.compare(old, new, spreads)
    assert worse == 0 and "**worse**" not in text
    # a measured spread narrower than the change does not hide it (the largest range counts)
    narrow = {"hall": {"ate_rmse_odometry_m_range": 0.003, "step_err_max_m_range": 0.001}}
    spreads = matrix.measured_spreads([{"rows": narrow}, {"rows": runs}])
    assert spreads["hall"]["ate_rmse_odometry_m"] == 0.009
    text, worse = matrix.compare(old, new, matrix.measured_spreads([{"rows": narrow}]))
    assert worse == 1 and text.count("**worse**") == 1  # the worst step's 4 mm


def test_the_handheld_rows_are_recorded_as_a_handheld_kinect(tmp_path, monkeypatch):
    monkeypatch.setenv("SLAM_CACHE_DIR", str(tmp_path / "cache"))
    matrix = _load("matrix")
    rows = matrix.synthetic_rows(4, (), (), (), half=True, handheld=[("desk", 1)])
    assert [r.name for r in rows] == ["desk-hh-s1-half"]
    made = json.loads((rows[0].path / ".complete").read_text())
    assert made["handheld"] == matrix.HANDHELD["desk"] and made["kinect"] is True
    assert made["color_offset_ms"] == matrix.UNSYNCED_MS and made["seed"] == 1


def test_the_results_page_is_written_from_a_matrix_result(tmp_path, monkeypatch):
    """benchmarks/results_page.py: real rows first, then the synthetic ones, in millimetres."""
    page = _load("results_page")
    matrix = {
        "machine": {"cpus": 2, "platform": "Linux", "python": "3.11"},
        "rows": {
            "tum-fr1-xyz": {"frames": 792, "ate_rmse_odometry_m": 0.0109, "ate_rmse_m": 0.0085,
                            "step_err_max_m": 0.0138, "fps": 15.4, "colour_frames": 15,
                            "tracking_failures": 0, "peak_rss_mb": 1040.2},
            "wall-x1-s0": {"frames": 240, "ate_rmse_odometry_m": 0.004, "ate_rmse_m": 0.003},
        },
    }  # fmt: skip
    source = tmp_path / "matrix-x.json"
    source.write_text(json.dumps(matrix))
    monkeypatch.setattr(page, "ROOT", tmp_path)
    text = page.render(matrix, source)
    real, synthetic = text.split("## Synthetic scene matrix")
    assert "| `tum-fr1-xyz` | 792 | 10.9 / **8.5** | 13.8 | 15.4 | 1040 | 15 | 0 |" in real
    assert "| `wall-x1-s0` | 240 | 4.0 / **3.0** | - | - | - | - | - |" in synthetic
    # the README's table: the real recordings only, between its markers
    readme = f"intro\n{page.BEGIN}\nold table\n{page.END}\nafter\n"
    new = page.with_readme_table(readme, page.readme_table(matrix))
    assert new.startswith(f"intro\n{page.BEGIN}\n| sequence |") and new.endswith(
        f"{page.END}\nafter\n"
    )
    assert "| `tum-fr1-xyz` | 792 | 0.0109 / **0.0085 m** | 15.4 | 1040 | 0.0220 m |" in new
    assert "wall-x1-s0" not in new and "old table" not in new


def test_the_results_page_compares_with_the_reference_code(tmp_path, monkeypatch):
    """The page's table against the code of 2026-11-22: one row per alternating benchmark,
    the median time ratio and each arm's ATE ranges in millimetres."""
    page = _load("results_page")
    run = {"seconds": 1.0, "ate_rmse_m": 0.0093, "ate_rmse_odometry_m": 0.0112}
    faster = dict(run, ate_rmse_m=0.0085)
    result = {
        "sequence": "tum-fr1-xyz",
        "b": {"config": "benchmarks/motion_check_colour_off.yaml"},
        "pairs": [{"a": run, "b": faster}, {"a": run, "b": dict(faster, ate_rmse_m=0.0086)}],
        "median_seconds_ratio_b_over_a": 0.97,
    }
    monkeypatch.setattr(page, "RESULTS", tmp_path)
    assert page._reference_speed() == []  # none measured: no section
    (tmp_path / "alternate-vs-1122-xyz.json").write_text(json.dumps(result))
    lines = page._reference_speed()
    assert "## Against the code of 2026-11-22" in lines
    row = "| `tum-fr1-xyz` | motion_check_colour_off | 2 | 0.970 | 9.3 / 11.2 | 8.5-8.6 / 11.2 |"
    assert lines[-1] == row
