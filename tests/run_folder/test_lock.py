"""One writer per run folder (a lock naming its holder), and a run that fails before its first
checkpoint leaves nothing that blocks the corrected run."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import pytest

import slam
from slam.run_folder import CONFIG_FILE, METRICS_FILE, SUBMAPS_DIR
from slam.run_folder.layout import LOCK_FILE
from slam.run_folder.lock import RunLock
from slam.synthetic.damage import Damage, damage_sequence


def _write_lock(folder, pid):
    folder.mkdir(parents=True, exist_ok=True)
    holder = {"pid": pid, "host": socket.gethostname(), "started": time.time()}
    (folder / LOCK_FILE).write_text(json.dumps(holder))


def test_a_second_writer_is_refused_naming_the_holder(synth_loop_320, tmp_path):
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        _write_lock(out, holder.pid)
        with pytest.raises(
            slam.RunFolderError, match=rf"in use by another run \(pid {holder.pid} on"
        ):
            slam.run_sequence(synth_loop_320, out, max_frames=3)
        with pytest.raises(slam.RunFolderError, match=rf"pid {holder.pid}"):
            slam.resume_run(out)
        assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE]  # nothing written
    finally:
        holder.kill()
        holder.wait()


def test_a_stale_lock_is_taken_over_and_released(synth_loop_320, tmp_path):
    out = tmp_path / "run"
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    _write_lock(out, gone.pid)
    result, _ = slam.run_sequence(synth_loop_320, out, max_frames=3)
    assert result.metrics["frames"] == 3
    assert not (out / LOCK_FILE).exists()  # released after the run


def test_the_lock_is_exclusive_within_one_process(tmp_path):
    with RunLock(tmp_path):
        with pytest.raises(slam.RunFolderError, match=f"pid {os.getpid()}"):
            RunLock(tmp_path).acquire()
    with RunLock(tmp_path):  # released: free again
        pass


def test_a_run_failing_its_preflight_leaves_no_trace(synth_loop_320, tmp_path):
    bad = damage_sequence(synth_loop_320, tmp_path / "scaled", Damage(depth_scale_factor=1000.0))
    out = tmp_path / "new" / "run"
    with pytest.raises(slam.CalibrationError, match="depth_scale"):
        slam.run_sequence(bad, out, max_frames=5)
    assert not out.exists()  # the folder it created is gone again
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(slam.CalibrationError):
        slam.run_sequence(bad, existing, max_frames=5)
    assert list(existing.iterdir()) == []  # no config.yaml, no submaps, no lock
    # the corrected run needs no --overwrite
    result, _ = slam.run_sequence(synth_loop_320, existing, max_frames=3)
    assert (existing / CONFIG_FILE).is_file() and not (existing / SUBMAPS_DIR).exists()
    assert result.metrics["frames"] == 3
    # a finished run is protected; --overwrite replaces it (under the lock)
    with pytest.raises(slam.RunFolderError, match="already holds a run"):
        slam.run_sequence(synth_loop_320, existing, max_frames=3)
    slam.run_sequence(synth_loop_320, existing, max_frames=4, overwrite=True)
    assert json.loads((existing / METRICS_FILE).read_text())["frames"] == 4
