"""Shared helpers for the benchmark scripts: sequence lookup and JSON output."""

from __future__ import annotations

import json
import os
import platform
import resource
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "datasets"
RESULTS = ROOT / "benchmarks" / "results"


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
