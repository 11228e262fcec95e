"""The built-in demo: a synthetic loop sequence generated once into a cache folder."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from slam.data.synthetic import SynthConfig, generate_sequence

log = logging.getLogger(__name__)

#: Bump when the generator's output changes so stale caches are regenerated.
DEMO_VERSION = 1
DEMO_CONFIG = SynthConfig(frames=300, loop=True, seed=0)
#: Built-in synthetic sequences by name: the demo, and the same loop with a depth distortion
#: that makes odometry drift (~5 deg of heading over the loop) for loop-closure benchmarks.
BUILTIN = {
    "demo": DEMO_CONFIG,
    "demo-drift": SynthConfig(frames=300, loop=True, seed=0, drift_bias=0.006),
}


def cache_dir() -> Path:
    """``$SLAM_CACHE_DIR``, else ``$XDG_CACHE_HOME/rgbd-slam``, else ``~/.cache/rgbd-slam``."""
    env = os.environ.get("SLAM_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rgbd-slam"


def demo_sequence_path(name: str = "demo") -> Path:
    """Path of a built-in synthetic sequence (:data:`BUILTIN`), generating it into the cache
    folder on first use (about half a minute)."""
    if name not in BUILTIN:
        raise KeyError(f"unknown built-in sequence {name!r}; choose one of {sorted(BUILTIN)}")
    path = cache_dir() / f"{name}-v{DEMO_VERSION}"
    if not (path / ".complete").is_file():
        log.info("generating the synthetic sequence %s into %s", name, path)
        generate_sequence(path, BUILTIN[name])
    return path
