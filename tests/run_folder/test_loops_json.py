"""A damaged ``loops.json`` (issue 19): `slam view` crashed with a traceback on candidates
whose fields had the wrong type; every reader now gets a RunFolderError naming the file, the
candidate and the value."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from slam.errors import RunFolderError
from slam.records import TrackingStatus
from slam.run_folder import LOOPS_FILE, METRICS_FILE, TRACKING_FILE, TRAJECTORY_FILE, RunFolder
from slam.run_folder.tracking_csv import format_rows
from slam.trajectory import Trajectory, write_tum

GOOD = {
    "query_kf": 5, "match_kf": 0, "query_frame": 50, "match_frame": 0,
    "query_timestamp": 1.5, "match_timestamp": 0.0, "score": 0.2, "accepted": True,
    "reason": "", "matches": 80, "inliers": 40, "inlier_ratio": 0.5, "icp_fitness": 0.9,
    "overlap": 0.8, "T_match_query": np.eye(4).tolist(),
}  # fmt: skip


def run_folder(tmp_path, loops) -> RunFolder:
    """A complete run folder of 3 frames whose loops.json holds ``loops`` (text or data)."""
    run = tmp_path / "run"
    run.mkdir(parents=True)
    (run / METRICS_FILE).write_text(json.dumps({"frames": 3}))
    statuses = [TrackingStatus(i, "icp", True, timestamp=i / 30) for i in range(3)]
    (run / TRACKING_FILE).write_text(format_rows(statuses))
    write_tum(run / TRAJECTORY_FILE, Trajectory(np.arange(3) / 30, np.tile(np.eye(4), (3, 1, 1))))
    text = loops if isinstance(loops, str) else json.dumps(loops)
    (run / LOOPS_FILE).write_text(text)
    return RunFolder(run)


@pytest.mark.parametrize(
    "change, problem",
    [
        ({"query_frame": "x"}, "'query_frame' must be an integer, got 'x'"),
        ({"match_frame": None}, "'match_frame' must be an integer, got None"),
        ({"accepted": "yes"}, "'accepted' must be true or false, got 'yes'"),
        ({"query_frame": True}, "'query_frame' must be an integer, got True"),
        ({"query_timestamp": "soon"}, "'query_timestamp' must be a finite number, got 'soon'"),
        ({"score": float("nan")}, "'score' must be a finite number, got nan"),
        ({"reason": 7}, "'reason' must be a string, got 7"),
        ({"T_match_query": [[1, 0], [0, 1]]}, "'T_match_query' must be a 4x4 list of numbers"),
    ],
)
def test_damaged_candidate_is_an_error_naming_file_and_value(tmp_path, change, problem):
    run = run_folder(tmp_path, {"candidates": [GOOD, {**GOOD, **change}]})
    with pytest.raises(RunFolderError) as info:
        run.loops()
    msg = str(info.value)
    assert msg.startswith(f"{run.file(LOOPS_FILE)}: loop candidate 1 (of 2) is damaged: {problem}")
    assert "delete it to go on without the loop details" in msg
    with pytest.raises(RunFolderError):
        run.accepted_loops()


def test_other_damage(tmp_path):
    run = run_folder(tmp_path, {"candidates": [GOOD, [1, 2]]})
    with pytest.raises(
        RunFolderError, match=r"candidate 1 \(of 2\) is damaged: expected an object"
    ):
        run.loops()
    run = run_folder(tmp_path / "b", '{"candidates": [')
    with pytest.raises(RunFolderError, match="loops.json: not valid JSON"):
        run.loops()
    run = run_folder(tmp_path / "c", {"candidates": [GOOD, {"accepted": False}]})
    assert len(run.loops()) == 2 and len(run.accepted_loops()) == 1  # fields may be absent


@pytest.mark.parametrize("loops", ['{"candidates": [{"accepted": true, "query_frame": "x"}]}',
                                   "\x00\x01garbage", '{"candidates": 3}'])  # fmt: skip
def test_slam_view_on_a_damaged_loops_json_is_a_clear_error(tmp_path, loops):
    from slam.cli import app

    run = run_folder(tmp_path, loops)
    result = CliRunner().invoke(app, ["view", str(run.path), "--image-scale", "0"])
    out = " ".join(result.output.split())
    assert result.exit_code == 2, (result.output, result.exception)
    assert "error:" in out and "loops.json" in out and "Traceback" not in out
