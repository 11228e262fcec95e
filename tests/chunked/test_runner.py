"""`slam run --workers N`: chunks tracked in worker processes (Ray or local processes), joined
into one run folder; killed workers are run again, a stopped run resumes without redoing the
chunks that finished."""

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from slam.api import resume_run, run_sequence
from slam.chunked import runner
from slam.chunked.worker import CHUNK_FILE, chunk_dir
from slam.run_folder import RunFolder
from slam.tools.eval import evaluate, sequence_ground_truth

FRAMES = 160


def _ate(run_dir: Path, seq: Path) -> float:
    gt, _ = sequence_ground_truth(seq)
    return evaluate(gt, RunFolder(run_dir).trajectory())["ate_rmse_m"]


@pytest.fixture(scope="module")
def sequential(synth_loop_320, tmp_path_factory) -> tuple[Path, float]:
    _, out = run_sequence(synth_loop_320, tmp_path_factory.mktemp("seq") / "run",
                          max_frames=FRAMES)  # fmt: skip
    return out, _ate(out, synth_loop_320)


def _check_joined(out: Path, seq: Path, sequential: tuple[Path, float], workers: int) -> dict:
    m = json.loads((out / "metrics.json").read_text())
    assert m["workers"] == workers and m["frames"] == FRAMES and m["frames_in_trajectory"] == FRAMES
    traj = RunFolder(out).trajectory()
    assert len(traj) == FRAMES and np.all(np.diff(traj.timestamps) > 0)  # each frame once
    _, ate_seq = sequential
    ate = _ate(out, seq)
    assert ate <= 1.1 * ate_seq + 1e-3, (ate, ate_seq)
    chunks = json.loads((out / "chunks.json").read_text())
    assert len(chunks["chunks"]) == workers
    assert all(j["joined"] and j["how"] == "overlap" for j in chunks["joins"])
    assert all(j["overlap_fit"]["median_mm"] < 5 for j in chunks["joins"])
    assert (out / "mesh.ply").stat().st_size > 0 and not (out / "chunks").exists()
    return chunks


def test_two_worker_processes_match_the_sequential_run(synth_loop_320, sequential, tmp_path):
    calls = []
    _, out = run_sequence(synth_loop_320, tmp_path / "run", max_frames=FRAMES, workers=2,
                          executor="processes", progress=lambda *a: calls.append(a))  # fmt: skip
    chunks = _check_joined(out, synth_loop_320, sequential, 2)
    # the progress bar follows the workers' frames (the overlap counted once), then the join
    done = [d for d, total, status in calls]
    assert calls[-1] == (FRAMES, FRAMES, None) and all(t == FRAMES for _, t, _ in calls)
    assert any(0 < d < FRAMES for d in done) and done == sorted(done)
    assert all(
        c["worker"]["threads"] == max(1, (os.cpu_count() or 1) // 2) for c in chunks["chunks"]
    )


def _kill_when_started(run_dir: Path, number: int, after_s: float, killed: list[int]) -> None:
    """Kill chunk ``number``'s worker ``after_s`` seconds after it started tracking."""
    pid_file = chunk_dir(run_dir, number) / "worker.pid"
    deadline = time.monotonic() + 120
    while not pid_file.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(after_s)
    pid = int(pid_file.read_text())
    os.kill(pid, signal.SIGKILL)
    killed.append(pid)


@pytest.mark.parametrize("executor", ["ray", "processes"])
def test_a_worker_killed_mid_chunk_is_run_again(synth_loop_320, sequential, tmp_path, executor):
    if executor == "ray":
        pytest.importorskip("ray", reason="Ray is not installed (no wheel for this platform)")
    out, killed = tmp_path / "run", []
    killer = threading.Thread(target=_kill_when_started, args=(out, 1, 1.0, killed))
    killer.start()
    run_sequence(synth_loop_320, out, max_frames=FRAMES, workers=2, executor=executor)
    killer.join()
    chunks = _check_joined(out, synth_loop_320, sequential, 2)
    assert killed and chunks["chunks"][1]["worker"]["worker_pid"] != killed[0]


def test_chunks_run_on_an_existing_ray_cluster(synth_loop_320, sequential, tmp_path, monkeypatch):
    """``--ray ADDRESS``: the chunks run as tasks of a cluster this process did not start (a
    head node in its own processes, as ``ray start --head`` makes one) and join as locally."""
    pytest.importorskip("ray", reason="Ray is not installed (no wheel for this platform)")
    from ray.cluster_utils import Cluster

    if len(os.environ.get("TMPDIR", "")) > 40 and "RAY_TMPDIR" not in os.environ:
        monkeypatch.setenv("RAY_TMPDIR", "/tmp")  # Unix socket paths must stay under 108 bytes
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 2})
    try:
        _, out = run_sequence(synth_loop_320, tmp_path / "run", max_frames=FRAMES, workers=2,
                              ray_address=cluster.address)  # fmt: skip
    finally:
        cluster.shutdown()
    chunks = _check_joined(out, synth_loop_320, sequential, 2)
    pids = {c["worker"]["worker_pid"] for c in chunks["chunks"]}
    assert os.getpid() not in pids and len(pids) == 2


def test_a_run_stopped_between_chunks_resumes_without_redoing_them(
    synth_loop_320, sequential, tmp_path, monkeypatch
):
    real = runner.run_tasks

    def first_chunk_then_stop(tasks, *args, **kw):
        real(tasks[:1], *args, **kw)
        raise KeyboardInterrupt  # the run is stopped once chunk 0 is done

    monkeypatch.setattr(runner, "run_tasks", first_chunk_then_stop)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_sequence(synth_loop_320, out, max_frames=FRAMES, workers=2, executor="processes")
    first = json.loads((chunk_dir(out, 0) / CHUNK_FILE).read_text())
    assert not (out / "metrics.json").exists() and not (chunk_dir(out, 1) / CHUNK_FILE).exists()
    monkeypatch.setattr(runner, "run_tasks", real)
    resume_run(out)
    chunks = _check_joined(out, synth_loop_320, sequential, 2)
    assert chunks["chunks"][0]["worker"] == first  # chunk 0 was not run again


def test_a_chunk_lost_at_its_start_is_joined_or_reported_never_dropped(synth_loop_320, tmp_path):
    from slam.synthetic.damage import Damage, damage_sequence

    # no depth from frame 40 to 89: chunk 0 loses its last frames, chunk 1 its first 40
    seq = damage_sequence(synth_loop_320, tmp_path / "seq", Damage(blackout=range(40, 90)))
    _, out = run_sequence(seq, tmp_path / "run", max_frames=FRAMES, workers=2,
                          executor="processes")  # fmt: skip
    m = json.loads((out / "metrics.json").read_text())
    (join,) = json.loads((out / "chunks.json").read_text())["joins"]
    assert join["overlap_fit"]["pairs"] == 0  # nothing tracked by both chunks
    assert join["how"] in ("verified keyframes", "new map segment"), join
    assert m["frames"] == FRAMES and set(range(40, 90)) <= set(m["lost_frames"])
    segments = RunFolder(out).segments()
    in_files = len(RunFolder(out).trajectory()) + sum(len(t) for t in segments.values())
    assert in_files == m["frames_tracked"] == FRAMES - len(m["lost_frames"])
    if join["how"] == "new map segment":  # not joined: its frames are reported on their own
        assert len(m["map_segments"]) == 2 and segments


def test_one_chunk_replayed_is_the_sequential_run(synth_loop_320, sequential, tmp_path):
    """The join's replay (Slam.replay) of a single chunk rebuilds the sequential run: the same
    keyframes, loops and final poses (up to the kernels' run-to-run noise)."""
    from slam.config import SlamConfig
    from slam.data.loader import open_sequence

    cfg = SlamConfig()
    cfg.dataset.path, cfg.dataset.max_frames = str(synth_loop_320), FRAMES
    res = runner.run_chunked(open_sequence(synth_loop_320), cfg, tmp_path, 1, executor="processes")
    seq_dir, _ = sequential
    seq_m = json.loads((seq_dir / "metrics.json").read_text())
    m = res.metrics
    assert m.keyframes == seq_m["keyframes"] and m.loops_accepted == seq_m["loops_accepted"]
    ref = RunFolder(seq_dir).trajectory()
    np.testing.assert_array_equal(res.trajectory.timestamps, ref.timestamps)
    # 0.6 mm measured: the kernels' threads do not sum in a fixed order
    assert np.abs(res.trajectory.poses[:, :3, 3] - ref.poses[:, :3, 3]).max() < 2e-3


@pytest.mark.parametrize(
    "text",
    [
        "[" * 100000 + "]" * 100000,
        '{"workers": "abc", "overlap": 30, "frames": [0, 1], "chunks": []}',
        "[1, 2, 3]",
        '{"workers": 2, "overlap": 1, "frames": [0, 1, 2, 3],'
        ' "chunks": [{"number": 0, "start": 0, "stop": 99, "keep_stop": 2}]}',
        '{"workers": 1, "overlap": 1, "frames": [0, 1], "chunks": [{"number": "x"}]}',
    ],
    ids=["nested", "workers-abc", "a-list", "chunk-past-the-frames", "chunk-fields"],
)
def test_a_damaged_chunk_plan_is_a_run_folder_error(tmp_path, text):
    path = runner.plan_path(tmp_path)
    path.parent.mkdir()
    path.write_text(text)
    with pytest.raises(runner.RunFolderError, match="not a readable chunk plan.*--overwrite"):
        runner.read_plan(tmp_path)
