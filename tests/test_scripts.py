"""The example evaluation scripts in scripts/ run (as a user would run them) and are right."""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from slam.tools.eval import evaluate_run
from tests.tools.test_report import make_run

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def run_script(name: str, *args, timeout: float = 240) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, str(SCRIPTS / name), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=SCRIPTS.parent,
    )
    return proc


def load_script(name: str):
    """Import a script as a module (to call its ``main(argv)`` in-process: faster)."""
    spec = importlib.util.spec_from_file_location(name.removesuffix(".py"), SCRIPTS / name)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_sweep_voxel_size(tmp_path):
    out_csv, out_png = tmp_path / "sweep.csv", tmp_path / "sweep.png"
    proc = run_script(
        "sweep_voxel_size.py", "--frames", 8, "--voxel", 0.01, 0.02, "--csv", out_csv,
        "--plot", out_png,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("| voxel [m] | frames | ATE rmse [m]")
    with out_csv.open() as f:
        rows = list(csv.DictReader(f))
    assert [float(r["voxel_size_m"]) for r in rows] == [0.01, 0.02]  # 0.02: the bound
    for r in rows:
        assert int(r["frames"]) == 8 and int(r["tracking_failures"]) == 0
        assert 0 < float(r["ate_rmse_m"]) < 0.03  # exact synthetic ground truth, 8 frames
        assert f"| {float(r['voxel_size_m']):.3f} | 8 | {float(r['ate_rmse_m']):.4f} |" in (
            proc.stdout
        )
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sweep_voxel_size_bad_sequence(tmp_path, capsys):
    main = load_script("sweep_voxel_size.py").main
    assert main(["--sequence", str(tmp_path / "nope"), "--frames", "3"]) == 2
    assert "sequence folder not found" in capsys.readouterr().err


def test_compare_runs(tmp_path, capsys):
    a = make_run(tmp_path / "a", with_loops=False)
    b = make_run(tmp_path / "b")
    (b / "trajectory.txt").write_text((b / "odometry.txt").read_text())  # no correction in b
    proc = run_script("compare_runs.py", a, b, "--labels", "lc", "nolc", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    for label, run in (("lc", a), ("nolc", b)):
        ev = evaluate_run(run, rpe_deltas=["1f", "1s"])
        assert out[label]["ate_rmse_m"] == ev.final.ate.rmse
        assert out[label]["rpe_1s_trans_rmse_m"] == ev.final.rpe[1].trans.rmse
        assert out[label]["drift_percent"] == ev.final.drift.percent
        assert out[label]["ate_rmse_odometry_m"] == ev.odometry.ate.rmse
    assert out["nolc"]["ate_rmse_m"] == out["nolc"]["ate_rmse_odometry_m"]
    assert out["lc"]["ate_rmse_m"] < out["nolc"]["ate_rmse_m"]
    main = load_script("compare_runs.py").main
    png = tmp_path / "cmp.png"
    assert main([str(a), str(b), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "| | run | run | run - run |" in text  # no --labels: the folder names
    delta = out["nolc"]["ate_rmse_m"] - out["lc"]["ate_rmse_m"]
    assert f"| ATE rmse final [m] | {out['lc']['ate_rmse_m']:.4f} | " in text
    assert f"| {delta:+.4f} |" in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main([str(a), str(tmp_path / "nope")]) == 2
    assert "run folder not found" in capsys.readouterr().err
    assert main([str(a), str(b), "--labels", "one"]) == 2
