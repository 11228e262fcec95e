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


@pytest.mark.parametrize(
    "holder",
    [
        {"pid": 1099511627776, "host": socket.gethostname(), "started": 1.0},
        {"pid": -5, "host": socket.gethostname(), "started": 1.0},
        {"pid": 0, "host": socket.gethostname(), "started": "yesterday"},
        {"pid": True, "host": socket.gethostname(), "started": 1e30},
        {"pid": "abc", "started": float("nan")},
    ],
)
def test_a_lock_file_with_odd_contents_is_taken_over_without_a_traceback(tmp_path, holder):
    """A pid no process can have, a start time that is not one: no TypeError or
    OverflowError; no live holder, so the lock is free."""
    (tmp_path / LOCK_FILE).write_text(json.dumps(holder))
    with RunLock(tmp_path) as lock:
        assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == os.getpid()
        with pytest.raises(slam.RunFolderError, match=f"pid {os.getpid()} on"):
            RunLock(tmp_path).acquire()
        assert lock.held
    assert not (tmp_path / LOCK_FILE).exists()


_RACER = """
import json, os, sys, time
from slam.run_folder.lock import RunLock
import slam
start = float(sys.argv[2])
time.sleep(max(0.0, start - time.time()))
try:
    with RunLock(sys.argv[1]):
        t0 = time.time()
        time.sleep(0.3)
        print(json.dumps([t0, time.time()]))
except slam.RunFolderError:
    print("null")
"""


def test_processes_taking_over_a_stale_lock_at_once_never_hold_it_together(tmp_path):
    """Six processes find the same stale lock at the same instant: the intervals in which
    each held it never overlap (unlink-then-create let two hold it in 8 of 30 trials)."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    for trial in range(3):
        folder = tmp_path / f"t{trial}"
        _write_lock(folder, gone.pid)
        start = time.time() + 4.0  # after every racer has imported the package
        racers = [
            subprocess.Popen([sys.executable, "-c", _RACER, str(folder), str(start)],
                             stdout=subprocess.PIPE, text=True)  # fmt: skip
            for _ in range(6)
        ]
        held = [json.loads(p.communicate(timeout=120)[0].strip().splitlines()[-1]) for p in racers]
        spans = sorted(h for h in held if h is not None)
        assert spans, held
        for (_, end), (begin, _) in zip(spans, spans[1:]):
            assert begin >= end, spans
