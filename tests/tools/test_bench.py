"""Tests of slam.tools.bench / `slam bench`: suites, the results table, failed runs, local vs Ray."""

from __future__ import annotations

import csv
import json
import math
import os
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from slam.cli import app
from slam.config import config_from_dict
from slam.errors import ConfigError, SlamError
from slam.tools.bench import (
    ACCURACY_COLUMNS,
    COLUMNS,
    load_suite,
    make_jobs,
    run_suite,
    suite_from_dict,
)
from slam.tools.eval import evaluate_run
from tests.conftest import SHARED_DATASETS

runner = CliRunner()
SEVEN_SCENES = SHARED_DATASETS / "7scenes-300"
FAST = {"output": {"save_mesh": False}}
BAD = {"tracking": {"no_such_key": 1}}


def _tiny_synthetic(path: Path) -> Path:
    from slam.synthetic import SynthConfig, generate_sequence

    cfg = SynthConfig.half_resolution(frames=300, render_frames=10)
    return generate_sequence(path, cfg)


@pytest.fixture(scope="module")
def suite_dict(tmp_path_factory):
    """The synthetic demo (a 10-frame stand-in in a private cache), 7scenes-300 when the shared
    datasets are there, and a missing folder; a valid config and one with a bad key."""
    from slam.demo import DEMO_VERSION

    cache = tmp_path_factory.mktemp("cache")
    _tiny_synthetic(cache / f"demo-v{DEMO_VERSION}")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SLAM_CACHE_DIR", str(cache))
        sequences: list = ["demo"]
        if SEVEN_SCENES.is_dir():
            sequences.append({"name": "7scenes", "path": str(SEVEN_SCENES), "max_frames": 5})
        sequences.append({"name": "missing", "path": "no/such/sequence"})
        yield {
            "name": "tiny",
            "max_frames": 8,
            "sequences": sequences,
            "configs": {"fast": FAST, "bad": BAD},
        }


@pytest.fixture(scope="module")
def local(suite_dict, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_local")
    suite = suite_from_dict(suite_dict, base_dir=out)
    seen = []
    res = run_suite(suite, out, jobs=2, progress=lambda row, d, n: seen.append((d, n)))
    return res, out, seen


def _row(rows, seq, cfg):
    (row,) = [r for r in rows if r["sequence"] == seq and r["config"] == cfg]
    return row


@pytest.mark.slow
def test_local_suite_table(local, suite_dict):
    res, out, seen = local
    n_seq = len(suite_dict["sequences"])
    assert len(res.rows) == 2 * n_seq
    assert [d for d, _ in seen] == list(range(1, 2 * n_seq + 1))
    # suite order: sequences first, then configs
    names = [s if isinstance(s, str) else s["name"] for s in suite_dict["sequences"]]
    assert [(r["sequence"], r["config"]) for r in res.rows] == [
        (s, c) for s in names for c in ("fast", "bad")
    ]
    ok = [r for r in res.rows if r["status"] == "ok"]
    assert {r["sequence"] for r in ok} == set(names) - {"missing"}
    for r in ok:
        assert r["config"] == "fast" and r["error"] is None
        assert r["frames"] == (5 if r["sequence"] == "7scenes" else 8)
        assert 0 < r["ate_rmse_m"] < 0.05
        # 8 (or 5) frames: 7 (4) pose pairs 1 frame apart, too few for RPE: left out
        assert r["rpe_trans_rmse_m"] is None and r["rpe_rot_rmse_deg"] is None
        assert r["ate_rmse_odometry_m"] >= 0 and math.isfinite(r["drift_percent"])
        assert r["fps"] > 0 and r["peak_rss_mb"] > 100 and r["tracking_failures"] == 0
        assert r["loops_accepted"] in (0, None)
        # the row is exactly what `slam eval RUN_DIR` reports
        run_dir = Path(r["run_dir"])
        assert run_dir == out / "runs" / f"{r['sequence']}__fast"
        ev = evaluate_run(run_dir)
        assert r["ate_rmse_m"] == ev.final.ate.rmse
        assert r["rpe_trans_rmse_m"] == ev.final.headline()["rpe_trans_rmse_m"]
        assert ev.final.rpe[0].left_out and ev.final.rpe[0].pairs == r["frames"] - 1
        assert r["drift_percent"] == ev.final.drift.percent
        assert (run_dir / "trajectory.txt").is_file() and (run_dir / "log.txt").is_file()
    # failures are rows with their error; the suite went on
    for s in names:
        bad = _row(res.rows, s, "bad")
        assert bad["status"] == "failed" and "no_such_key" in bad["error"]
        assert bad["ate_rmse_m"] is None
    missing = _row(res.rows, "missing", "fast")
    assert missing["status"] == "failed" and "DatasetError" in missing["error"]
    assert "no/such/sequence: sequence folder not found" in missing["error"]
    assert "sequence folder not found" in (Path(missing["run_dir"]) / "log.txt").read_text()
    assert len(res.failed) == n_seq + 1


@pytest.mark.slow
def test_tables_agree(local):
    res, out, _ = local
    doc = json.loads((out / "bench.json").read_text())
    assert doc["suite"] == "tiny" and doc["executor"] == "local" and doc["columns"] == list(COLUMNS)
    assert doc["rows"] == res.rows
    with (out / "bench.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(res.rows)
    for got, want in zip(rows, res.rows):
        for k in COLUMNS:
            v = want[k]
            if v is None:
                assert got[k] == ""
            elif isinstance(v, float):
                assert float(got[k]) == v  # full precision
            else:
                assert got[k] == str(v)
    md = (out / "bench.md").read_text()
    assert f"{len(res.rows)} runs, {len(res.rows) - len(res.failed)} ok" in md
    demo = _row(res.rows, "demo", "fast")
    assert f"| demo | fast | ok | 8 | {demo['ate_rmse_m']:.4f} |" in md
    assert "| missing | fast | failed |" in md


#: Run-to-run spread of one pipeline run to the next on these 5-8 frame sequences: Open3D's
#: parallel kernels are not bit-reproducible and a frame-level threshold (e.g. whether a model
#: correction is trusted) can flip between runs; measured on the 8-frame demo stand-in, RPE
#: rotation came out 0.033 deg in 1 of 10 runs and 0.074-0.078 deg in the others.
RUN_TO_RUN = {
    "ate_rmse_m": 2e-3,
    "ate_rmse_odometry_m": 2e-3,
    "rpe_trans_rmse_m": 2e-3,
    "rpe_rot_rmse_deg": 0.06,
    # drift over 5 frames of 7-Scenes (a few cm of path) is the noisiest: 6 identical runs
    # gave 7.6-13.6% (code of 2c63699) and 7.9-15.0% (after the layout change of issue 16)
    "drift_percent": 8.0,
}


def _ray():
    try:
        import ray
    except ImportError:
        pytest.skip(
            "Ray is not installed (pip install 'rgbd-slam[ray]'; the dev extra has it where Ray "
            "publishes a wheel for this Python)"
        )
    return ray


@pytest.mark.slow
def test_ray_table_equals_local_table(local, suite_dict, tmp_path, monkeypatch):
    """The same suite as Ray tasks on a local Ray instance gives the same table.

    Accuracy columns agree to within the pipeline's run-to-run spread (``RUN_TO_RUN``); counts
    and errors agree exactly. Timing and memory columns are machine load, not compared.
    """
    ray = _ray()
    if len(os.environ.get("TMPDIR", "")) > 40 and "RAY_TMPDIR" not in os.environ:
        # Ray's session folder (under $TMPDIR) holds Unix sockets, whose paths may not exceed
        # 107 bytes: a deep $TMPDIR fails ray.init
        monkeypatch.setenv("RAY_TMPDIR", "/tmp")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        res = run_suite(
            suite_from_dict(suite_dict, base_dir=tmp_path), tmp_path, ray_address="auto"
        )
    finally:
        ray.shutdown()
    local_rows = local[0].rows
    assert json.loads((tmp_path / "bench.json").read_text())["executor"] == "ray:auto"
    assert len(res.rows) == len(local_rows)
    for got, want in zip(res.rows, local_rows):
        assert (got["sequence"], got["config"], got["status"]) == (
            want["sequence"],
            want["config"],
            want["status"],
        )
        if want["status"] != "ok":
            assert got["error"].replace(str(tmp_path), "OUT") == want["error"].replace(
                str(Path(local[1])), "OUT"
            )
            continue
        for k in ("frames", "loops_accepted", "tracking_failures"):
            assert got[k] == want[k], k
        for k in set(ACCURACY_COLUMNS) - {"frames", "loops_accepted", "tracking_failures"}:
            if want[k] is None:  # RPE of these short runs: too few pairs, left out in both
                assert got[k] is None, (got["sequence"], k)
                continue
            assert got[k] == pytest.approx(want[k], rel=0.05, abs=RUN_TO_RUN[k]), (
                got["sequence"],
                k,
            )
        assert got["fps"] > 0 and got["peak_rss_mb"] > 100


def test_missing_ray_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    suite = suite_from_dict({"sequences": ["x"]}, tmp_path)
    with pytest.raises(SlamError, match=r"pip install 'rgbd-slam\[ray\]'"):
        run_suite(suite, tmp_path / "out", ray_address="auto")
    assert not (tmp_path / "out").exists()  # failed before any work


def test_load_suite_resolves_paths_and_options(tmp_path):
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "coarse.yaml").write_text("mapping:\n  voxel_size_m: 0.02\n")
    (tmp_path / "configs" / "broken.yaml").write_text("mapping:\n  voxel_size: 0.02\n")
    (tmp_path / "suite.yaml").write_text(
        "max_frames: 50\n"
        "sequences:\n"
        "  - data/seq-a\n"
        "  - {name: b, path: /abs/seq-b, max_frames: 7}\n"
        "configs:\n"
        "  default: {}\n"
        "  coarse: configs/coarse.yaml\n"
        "  broken: configs/broken.yaml\n"
        "  gone: configs/nope.yaml\n"
        "  inline: {tracking: {downsample: 1}}\n"
    )
    suite = load_suite(tmp_path / "suite.yaml")
    assert suite.name == "suite" and suite.max_frames == 50
    assert [(s.name, s.path, s.max_frames) for s in suite.sequences] == [
        ("seq-a", "data/seq-a", None),
        ("b", "/abs/seq-b", 7),
    ]
    jobs = make_jobs(suite, tmp_path / "out")
    assert len(jobs) == 10
    j = {(x.sequence, x.config): x for x in jobs}
    assert j["seq-a", "default"].sequence_path == str(tmp_path / "data" / "seq-a")
    assert j["seq-a", "default"].max_frames == 50 and j["b", "default"].max_frames == 7
    assert j["b", "coarse"].config_overrides == {"mapping": {"voxel_size_m": 0.02}}
    assert j["b", "inline"].config_overrides == {"tracking": {"downsample": 1}}
    assert j["b", "inline"].run_dir == str(tmp_path / "out" / "runs" / "b__inline")
    assert "broken.yaml" in j["b", "broken"].error and "voxel_size" in j["b", "broken"].error
    assert "nope.yaml: cannot read config" in j["b", "gone"].error
    assert all(x.error is None for x in jobs if x.config in ("default", "coarse", "inline"))
    assert [x.index for x in jobs] == list(range(10))


@pytest.mark.parametrize(
    "data,match",
    [
        ({"configs": {"a": {}}}, "'sequences' must be a non-empty list"),
        ({"sequences": ["a"], "sequence": []}, r"unknown key\(s\) \['sequence'\]"),
        ({"sequences": ["x/a", "y/a"]}, r"duplicate sequence name\(s\) \['a'\]"),
        ({"sequences": ["a"], "max_frames": 0}, "max_frames must be a positive integer"),
        ({"sequences": [{"path": "a", "frames": 3}]}, r"unknown key\(s\) \['frames'\]"),
        ({"sequences": [3]}, "expected a path or a mapping"),
        ({"sequences": ["a"], "configs": {"c": 3}}, "expected overrides"),
        ([1, 2], "expected a mapping"),
    ],
)
def test_bad_suites(data, match):
    with pytest.raises(ConfigError, match=match):
        suite_from_dict(data)


def test_bench_cli_failed_runs_exit_code(tmp_path):
    (tmp_path / "s.yaml").write_text(
        "sequences: [some/seq]\nconfigs:\n  bad: {tracking: {no_such_key: 1}}\n"
    )
    res = runner.invoke(app, ["bench", str(tmp_path / "s.yaml"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1, res.output  # the suite ran; one run failed
    assert "| seq | bad | failed |" in res.stdout and "no_such_key" in res.stdout
    for name in ("bench.md", "bench.csv", "bench.json"):
        assert (tmp_path / "o" / name).is_file()
    res = runner.invoke(app, ["bench", str(tmp_path / "nope.yaml")])
    assert res.exit_code == 2 and "cannot read the suite" in res.output


def test_example_suite_parses():
    """The example runs for any user: the built-in demo, three valid configurations."""
    suite = load_suite(Path(__file__).resolve().parents[2] / "scripts" / "bench_suite_example.yaml")
    assert [s.name for s in suite.sequences] == ["demo"]
    assert list(suite.configs) == ["default", "voxel_2cm", "no_frame_to_frame"]
    assert suite.max_frames == 300
    for overrides in suite.configs.values():
        config_from_dict(overrides)  # every example configuration is valid


def test_missing_sequence_folders_are_named_before_any_run(tmp_path, caplog):
    """Each missing folder still fails as its rows, but the suite says so up front (a user
    without the CI data found 6 of 9 runs failed only after minutes)."""
    from slam.tools.bench import _warn_missing_sequences
    from slam.tools.bench_suite import suite_from_dict

    suite = suite_from_dict(
        {"sequences": ["demo", "no/such/a", "no/such/b"], "configs": {"x": {}, "y": {}}},
        tmp_path, name="s",
    )  # fmt: skip
    _warn_missing_sequences(suite)
    assert "2 sequence folder(s) not found, so 4 run(s) will fail: no/such/a, no/such/b" in caplog.text
