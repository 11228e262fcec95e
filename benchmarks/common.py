"""Shared helpers for the benchmark scripts: sequence lookup, runs in fresh processes, JSON
output."""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "datasets"
#: where results are written (``SLAM_BENCH_RESULTS`` overrides it: the smoke tests)
RESULTS = Path(os.environ.get("SLAM_BENCH_RESULTS") or ROOT / "benchmarks" / "results")


def sequence_path(name: str) -> Path:
    """``demo`` / ``demo-drift`` (built-in synthetic sequences) or a folder under
    ../shared/datasets."""
    from slam.demo import BUILTIN, demo_sequence_path

    if name in BUILTIN:
        return demo_sequence_path(name)
    path = Path(name)
    return path if path.is_dir() else SHARED / name


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict:
    return {
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def write_result(name: str, data: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / f"{name}.json"
    out.write_text(json.dumps(data, indent=2) + "\n")
    return out


_CHILD = """
import json, logging, sys
import slam
logging.basicConfig(level=logging.WARNING)
cfg = slam.load_config(sys.argv[2] or None)
seq = slam.open_sequence(sys.argv[1], cfg.dataset.layout, cfg.dataset.calibration)
m = slam.run(seq, cfg).metrics
print(json.dumps({k: m.get(k) for k in sys.argv[3].split(",")}))
"""


def run_in_child(
    path: Path,
    config: str,
    keys: tuple[str, ...],
    tree: Path | None = None,
    extra_env: dict[str, str] | None = None,
) -> dict:
    """One pipeline run (default config overridden by the YAML file ``config``, or none) in a
    fresh process, so runs do not share caches or memory; ``tree``: the source tree to import
    ``slam`` from (default this one); ``extra_env``: variables set for that process only.
    Returns the ``metrics.json`` values named by ``keys``."""
    env = dict(os.environ, **(extra_env or {}))
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path), config, ",".join(keys)],
        check=True,
        capture_output=True,
        text=True,
        env=env,
        cwd=tree,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])
