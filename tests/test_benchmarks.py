"""Smoke tests of the maintained benchmarks (listed in benchmarks/README.md): each runs end to
end on a tiny synthetic sequence and writes its JSON (into a temporary folder:
``SLAM_BENCH_RESULTS``). The scene matrix and the results page have their own tests
(tests/test_matrix.py). What they measure is not checked here: a benchmark that no longer
runs against today's code is what this catches."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """45 frames of the synthetic loop at 160x120 (kernel_floors times frame 40)."""
    from slam.synthetic import SynthConfig, generate_sequence

    half = SynthConfig.half_resolution()
    cfg = SynthConfig(
        frames=300, render_frames=45, seed=4, width=160, height=120, fx=half.fx / 2,
        fy=half.fy / 2, cx=(half.cx + 0.5) / 2 - 0.5, cy=(half.cy + 0.5) / 2 - 0.5,
    )  # fmt: skip
    return generate_sequence(tmp_path_factory.mktemp("bench") / "tiny", cfg)


def _bench(script: str, args: list[str], results: Path) -> list[dict]:
    env = dict(os.environ, SLAM_BENCH_RESULTS=str(results), PYTHONPATH=str(ROOT))
    proc = subprocess.run(
        [sys.executable, str(BENCH / script), *args],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    written = sorted(results.glob("*.json"))
    assert written, f"{script} wrote no result"
    return [json.loads(p.read_text()) for p in written]


@pytest.mark.parametrize(
    "script, args",
    [
        ("run_slam.py", ["--max-frames", "10"]),
        ("open3d_baseline.py", ["--max-frames", "10"]),
        ("profile_stages.py", ["--top", "3"]),
        ("alternate.py", ["--repeats", "1"]),
        ("chunked.py", ["--workers", "1"]),
        ("robustness.py", ["--only", "clean"]),
        ("kernel_floors.py", ["--reps", "1"]),
    ],
)
def test_a_maintained_benchmark_runs_on_tiny_data(tiny, tmp_path, script, args):
    args = [str(tiny), *args]
    if script == "chunked.py":  # sequences first, then options
        args = [str(tiny), "--workers", "1"]
    (result,) = _bench(script, args, tmp_path / "results")
    assert result


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="revisions.py checks out git revisions: needs git and a clone")  # fmt: skip
def test_revisions_runs_a_revision_in_its_own_worktree(tiny, tmp_path):
    (result,) = _bench("revisions.py", [str(tiny), "--revs", "HEAD"], tmp_path / "results")
    assert result
