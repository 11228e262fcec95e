"""Ctrl-C and SIGTERM: the run stops after the frame it is on, saves its state and says how to
resume; a resumed run finishes. Automatic checkpoints keep within their time budget."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from slam import pipeline
from slam.config import config_from_dict
from slam.data import open_sequence
from slam.errors import RunInterrupted
from slam.run_folder.checkpoint import has_checkpoint, read_checkpoint

SMALL = {"dataset": {"max_frames": 30}, "tracking": {"downsample": 1}}


def _signal_at(frame: int, signum: int):
    def progress(done, total, status):
        if done == frame:
            os.kill(os.getpid(), signum)

    return progress


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_after_the_frame_saves_and_the_run_resumes(
    synth_loop_320, tmp_path, signum
):
    seq = open_sequence(synth_loop_320)
    cfg = config_from_dict(SMALL)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    before = signal.getsignal(signum)
    with pytest.raises(RunInterrupted) as err:
        pipeline.run(seq, cfg, run_dir=run_dir, checkpoint_every=0, progress=_signal_at(12, signum))
    assert err.value.signal_number == signum
    msg = str(err.value)
    assert f"interrupted by {signal.Signals(signum).name} after frame 12 of 30" in msg
    assert f"slam run --resume {run_dir}" in msg
    assert signal.getsignal(signum) is before  # the handlers are put back
    # saved although checkpoints were off: the state after frame 12
    assert has_checkpoint(run_dir)
    state, position = read_checkpoint(run_dir)
    assert position == 12
    res = pipeline.run(seq, cfg, run_dir=run_dir, resume=True)
    assert len(res.trajectory) == 30 and res.metrics.resumed_at_frame == 12


def test_without_a_run_folder_nothing_is_saved_and_the_message_says_so(synth_loop_320):
    seq = open_sequence(synth_loop_320)
    with pytest.raises(RunInterrupted, match="nothing was saved .no run folder"):
        pipeline.run(seq, config_from_dict(SMALL), progress=_signal_at(5, signal.SIGINT))


def test_automatic_checkpoints_keep_within_their_budget(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(pipeline.time, "perf_counter", lambda: clock[0])
    s = pipeline.Checkpoints("run", None)
    assert not s.due(pipeline.FIRST_CHECKPOINT - 1, 0) and s.due(pipeline.FIRST_CHECKPOINT, 0)
    s.written(0.3)  # a checkpoint that took 0.3 s: the next one after 0.3 / 1.5% = 20 s
    clock[0] = 19.9
    assert not s.due(200, 0)
    clock[0] = 20.0
    assert s.due(200, 0)
    fixed = pipeline.Checkpoints("run", 20)
    assert fixed.due(40, 0) and not fixed.due(41, 0)
    assert not pipeline.Checkpoints("run", 0).due(100, 0)
    assert not pipeline.Checkpoints(None, None).due(100, 0)  # no run folder, no checkpoints


def test_a_resumed_automatic_run_stays_automatic(synth_loop_320, tmp_path):
    seq = open_sequence(synth_loop_320)
    run_dir = Path(tmp_path / "run")
    run_dir.mkdir()
    with pytest.raises(RunInterrupted):
        pipeline.run(
            seq, config_from_dict(SMALL), run_dir=run_dir, progress=_signal_at(4, signal.SIGINT)
        )
    state, _ = read_checkpoint(run_dir)
    assert state["checkpoint_every"] == -1  # automatic


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_the_command_line_stops_says_how_to_resume_and_resumes(synth_loop_320, tmp_path, signum):
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "slam", "run", str(synth_loop_320), "--out", str(out), "-q"]
    cmd += ["--max-frames", "150"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 120
    while not (out / "config.yaml").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(2.0)  # into the frame loop (150 frames take far longer)
    proc.send_signal(signum)
    text, _ = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signum, text
    name = signal.Signals(signum).name
    assert f"stopped: run interrupted by {name} after frame " in text
    assert f"continue with `slam run --resume {out}`" in text
    assert "Traceback" not in text
    done = subprocess.run(
        [sys.executable, "-m", "slam", "run", "--resume", str(out), "-q"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert (out / "metrics.json").exists() and not (out / "checkpoint").exists()


def test_a_signal_while_a_finished_run_is_written_lets_the_files_finish(
    synth_loop_320, tmp_path, monkeypatch, caplog
):
    """A signal during the final save (before any checkpoint) killed the process half way: the
    folder kept a lock, a mesh and trajectories, no metrics.json, no checkpoint, and a rerun
    needed --overwrite. The run is finished then: its files are written whole first."""
    import slam.api
    from slam.run_folder import METRICS_FILE
    from slam.run_folder.layout import LOCK_FILE

    real_save = slam.api.save_run

    def save_with_a_signal(result, out, overwrite=False):
        os.kill(os.getpid(), signal.SIGINT)  # arrives while the files are being written
        return real_save(result, out, overwrite=overwrite)

    monkeypatch.setattr(slam.api, "save_run", save_with_a_signal)
    before = signal.getsignal(signal.SIGINT)  # SIG_IGN when pytest runs in the background
    if before is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        before = signal.default_int_handler
    result, run_dir = slam.api.run_sequence(synth_loop_320, tmp_path / "run", max_frames=10)
    assert (run_dir / METRICS_FILE).is_file() and not (run_dir / LOCK_FILE).exists()
    assert "SIGINT: the run is finished; writing its results first" in caplog.text
    assert signal.getsignal(signal.SIGINT) is before  # put back


@pytest.mark.slow
def test_the_largest_counts_a_config_accepts_still_stop_on_sigterm(synth_loop_320, tmp_path):
    """`tracking.icp.iterations: [1e9, 1e9, 1e9]` made one frame last hours, and SIGTERM (twice)
    was ignored for 14 minutes. With the counts at their largest accepted values, a SIGTERM
    stops the run after the frame it is on, and a second one at once."""
    import subprocess
    import sys
    import time

    from slam.config_ranges import MAX_GN_ITERATIONS, MAX_RANSAC_ITERATIONS

    cfg = tmp_path / "max.yaml"
    most = [MAX_GN_ITERATIONS] * 3
    cfg.write_text(
        f"tracking:\n  icp: {{iterations: {most}, large_motion_iterations: {most}}}\n"
        f"  ransac: {{iterations: {MAX_RANSAC_ITERATIONS}}}\n"
    )
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "slam", "run", str(synth_loop_320), "--out", str(out), "-q",
           "-c", str(cfg), "--max-frames", "100"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 120
    while not (out / "config.yaml").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(3.0)  # inside the frame loop
    proc.send_signal(signal.SIGTERM)
    try:  # after the frame it is on: well within a minute
        text, _ = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signal.SIGTERM and "Traceback" not in text, text
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGTERM)  # a second one stops it at once
        proc.communicate(timeout=10)
        pytest.fail("one SIGTERM did not stop the run within a minute")
