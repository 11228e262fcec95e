"""The run folder holds one run, checked before the first frame; checkpoints survive kill -9."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from typer.testing import CliRunner

import slam
from slam.cli import app
from slam.run_folder import prepare_run_dir, require_complete
from slam.trajectory import read_tum

runner = CliRunner()


def flat(text: str) -> str:
    """CLI output with rich's line wrapping undone."""
    return " ".join(text.split())


def test_out_naming_a_file_is_refused_before_any_work(tmp_path):
    f = tmp_path / "results.txt"
    f.write_text("x")
    res = runner.invoke(app, ["run", str(tmp_path / "nope"), "--out", str(f)])
    assert res.exit_code == 2
    assert "is a file, not a folder" in flat(res.output)


def test_unwritable_out_is_refused_before_any_work(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root can write into read-only folders")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    with pytest.raises(slam.RunFolderError, match="not writable|cannot create"):
        prepare_run_dir(ro / "run")


def test_unwritable_out_as_root_is_refused(tmp_path):
    """/proc is not writable even for root: the check runs before the first frame."""
    with pytest.raises(slam.RunFolderError, match="cannot create|not writable"):
        prepare_run_dir("/proc/slam-run")


def test_existing_run_is_refused_unless_overwrite(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for name in ("metrics.json", "mesh.ply", "report.md", "report_topview.png"):
        (run / name).write_text("old")
    (run / "notes.txt").write_text("mine")
    with pytest.raises(slam.RunFolderError, match="already holds a run .*--overwrite"):
        prepare_run_dir(run)
    prepare_run_dir(run, overwrite=True)
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt"]  # only the run's files go


def test_eval_and_report_refuse_an_incomplete_run(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.txt").write_text("0 0 0 0 0 0 0 1\n")
    (run / "checkpoint").mkdir()
    for cmd in (["eval", str(run)], ["report", str(run)]):
        res = runner.invoke(app, cmd)
        assert res.exit_code == 2, res.output
        assert "no metrics.json" in flat(res.output) and "--resume" in flat(res.output)
    with pytest.raises(slam.RunFolderError, match="no metrics.json"):
        require_complete(run)


def test_cli_run_overwrite_replaces_the_old_run(synth_loop_320, tmp_path):
    out = tmp_path / "run"
    args = ["run", str(synth_loop_320), "--out", str(out), "--max-frames", "10"]
    assert runner.invoke(app, args).exit_code == 0
    (out / "report.md").write_text("stale")
    res = runner.invoke(app, args)
    assert res.exit_code == 2 and "already holds a run" in flat(res.output)
    res = runner.invoke(app, args + ["--overwrite"])
    assert res.exit_code == 0, res.output
    assert not (out / "report.md").exists()
    assert not (out / "submaps").exists() and not (out / "checkpoint").exists()
    assert "0 lost, 0 skipped" in flat(res.output)


@pytest.mark.parametrize("n", ["-1", "0"])
def test_max_frames_must_be_positive(tmp_path, n):
    """-1 used to drop the last frame silently (a Python slice); 0 and -1 are refused, naming
    the flag, before any work."""
    res = runner.invoke(app, ["run", "--max-frames", n, "--out", str(tmp_path / "r")])
    assert res.exit_code == 2
    assert "--max-frames" in flat(res.output) and "greater than or equal to 1" in flat(res.output)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("n", [-1, 0])
def test_api_max_frames_must_be_positive(tmp_path, n):
    from slam.api import run_sequence
    from slam.errors import ConfigError

    with pytest.raises(ConfigError, match=rf"max_frames must be >= 1 .*got {n}"):
        run_sequence(tmp_path, tmp_path / "r", max_frames=n)
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_kill_after_first_checkpoint_then_resume(synth_loop_320, tmp_path):
    """kill -9 a run after its first checkpoint, resume it: every frame is in the outputs and
    the ATE is within 1.2x an uninterrupted run's + 1 mm."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("dataset: {max_frames: 150}\n")
    whole = tmp_path / "whole"
    res = runner.invoke(app, ["run", str(synth_loop_320), "--out", str(whole), "-c", str(cfg)])
    assert res.exit_code == 0, res.output
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "slam.cli", "run", str(synth_loop_320), "--out", str(out)]
    proc = subprocess.Popen(
        cmd + ["-c", str(cfg), "--checkpoint-every", "40"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    state = out / "checkpoint" / "state.json"
    t0 = time.time()
    while not state.exists() and proc.poll() is None and time.time() - t0 < 300:
        time.sleep(0.1)
    assert proc.poll() is None, "the run ended before its first checkpoint"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (out / "metrics.json").exists()
    assert (out / "config.yaml").is_file()  # written before the first frame
    assert (out / "submaps").is_dir()  # spilled submaps live in the run folder
    res = runner.invoke(app, ["eval", str(out)])
    assert res.exit_code == 2 and "--resume" in flat(res.output)
    res = runner.invoke(app, ["run", "--resume", str(out)])
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    m_whole = json.loads((whole / "metrics.json").read_text())
    assert m["resumed_at_frame"] in (40, 80, 120)
    assert m["frames"] == 150 and m["frames_tracked"] == 150
    assert len(read_tum(out / "trajectory.txt")) == 150
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in whole.iterdir())
    assert m["ate_rmse_m"] <= 1.2 * m_whole["ate_rmse_m"] + 0.001, (m, m_whole)
    np.testing.assert_allclose(
        read_tum(out / "trajectory.txt").timestamps, read_tum(whole / "trajectory.txt").timestamps
    )
    res = runner.invoke(app, ["run", "--resume", str(out)])
    assert res.exit_code == 2 and "complete" in flat(res.output)


def test_resume_without_checkpoint_says_so(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    res = runner.invoke(app, ["run", "--resume", str(run)])
    assert res.exit_code == 2
    assert "no checkpoint to resume from" in flat(res.output)


def test_save_run_twice_is_refused_unless_overwrite(tmp_path):
    """`slam.save_run(result, dir)` into a folder holding a complete run replaced it without a
    word; now it says so, and overwrite=True replaces it. A Python caller of run_sequence is
    told the keyword, not only the CLI flag."""
    from slam.run_folder import METRICS_FILE
    from tests.tools.test_report import make_run

    run_dir = make_run(tmp_path / "a")
    assert (run_dir / METRICS_FILE).is_file()
    with pytest.raises(slam.RunFolderError, match="already holds a complete run.*overwrite=True"):
        slam.save_run(_FakeResult(), run_dir)
    with pytest.raises(slam.RunFolderError, match=r"overwrite=True"):
        slam.run_sequence(run_dir, run_dir)


class _FakeResult:
    """Never written: the refusal comes first."""
